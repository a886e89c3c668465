"""``PATCH /api/config``: which keys the network may change, their schema, and the merge.

The documented body is generated from `FloornavConfig` (only the live keys, with their
types and bounds, and the bounds the running configuration sets: the clearance floor,
the wheels' top speed), so a client learns every rule a single value must meet from the
schema. A patch whose values are each fine but conflict with each other or with the
running configuration (a safe zone turned inside out) is refused with 409.
"""

from __future__ import annotations

import fnmatch
from typing import Annotated, Any

from annotated_types import Ge, Le
from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model

from app.config import FloornavConfig

# What the network may change. Whoever holds the token can start and stop autonomy
# anyway, but must not be able to switch a stop layer off or raise a limit past what the
# hardware does, so of the safety keys only these are live:
# - min_clearance_m: never below safety.min_clearance_floor_m (a validator; the floor
#   itself is set in config.toml only);
# - auto_resume, resume_after_clear_s: they only decide when autonomy goes on after a
#   protective stop's cause has cleared (no more than POST /api/start does); the stop
#   itself still holds while its cause lasts.
# Not live: perception_max_age_s, camera_max_age_s, teleop_timeout_s and
# autonomy_timeout_s (raised, the robot would move for seconds on stale perception or a
# vanished driver's command); fault_latch_repeats, fault_latch_window_s and
# device_lost_latch_s (they could switch fault latching off); min_clearance_floor_m.
# drive.max_wheel_speed_m_s is the motors' measured response, not a limit: lowered, it
# would make every command faster than its limit says, so only the max_linear_* and
# max_angular_* limits are live (and bounded by it, see `app.config.DriveConfig`).
LIVE_KEYS = (
    "steering.*",
    "drive.max_linear_*",
    "drive.max_angular_*",
    "safety.min_clearance_m",
    "safety.auto_resume",
    "safety.resume_after_clear_s",
    "perception.method",
    "perception.safe_zone.*",
    "perception.smoothing_sigma_px",
)
"""Dotted configuration keys (``fnmatch`` patterns) that `Runtime.update_config`
applies while running; everything else needs a restart."""


class ConfigPatchError(ValueError):
    """A configuration patch names a key that does not exist or is not live."""


def is_live_key(key: str) -> bool:
    """True if the dotted ``key`` may be changed through ``PATCH /api/config``."""
    return any(fnmatch.fnmatchcase(key, pattern) for pattern in LIVE_KEYS)


class ConfigConflictError(ConfigPatchError):
    """Each value is valid alone but the new configuration as a whole is not."""


def _extra_bounds(config: FloornavConfig) -> dict[str, dict[str, float]]:
    """Bounds of live keys that the running (not live) configuration sets."""
    drive = config.drive
    return {
        "safety.min_clearance_m": {"ge": config.safety.min_clearance_floor_m},
        "drive.max_linear_speed_m_s": {"le": drive.max_wheel_speed_m_s},
        "drive.max_angular_speed_rad_s": {"le": 2 * drive.max_wheel_speed_m_s / drive.wheel_base_m},
    }


def _tightened(info: Any, extra: dict[str, float]) -> list[Any]:
    """The field's constraints with ``extra`` applied (the tighter bound wins)."""
    metadata = list(info.metadata)
    for name, bound in extra.items():
        for item in metadata:
            current = getattr(item, name, None)
            if current is not None:
                bound = max(bound, current) if name == "ge" else min(bound, current)
        metadata = [m for m in metadata if getattr(m, name, None) is None]
        metadata.append(Ge(bound) if name == "ge" else Le(bound))
    return metadata


def _patch_model(
    model: type[BaseModel], prefix: str, bounds: dict[str, dict[str, float]]
) -> type[BaseModel] | None:
    fields: dict[str, Any] = {}
    for name, info in model.model_fields.items():
        dotted = f"{prefix}{name}"
        annotation = info.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            section = _patch_model(annotation, dotted + ".", bounds)
            if section is not None:
                fields[name] = (section, Field(default=None))
        elif is_live_key(dotted):
            metadata = _tightened(info, bounds.get(dotted, {}))
            typed = Annotated[annotation, *metadata] if metadata else annotation
            fields[name] = (typed, Field(default=None, description=info.description))
    if not fields:
        return None
    return create_model(
        f"{model.__name__.removesuffix('Config') or 'Floornav'}Patch",
        __config__=ConfigDict(extra="forbid", strict=True),
        __doc__=f"Live keys of [{prefix.rstrip('.')}]" if prefix else "Live keys",
        **fields,
    )


def config_patch_model(config: FloornavConfig) -> type[BaseModel]:
    """The body of ``PATCH /api/config`` for ``config``: every live key optional, typed
    strictly, bounded (also by `_extra_bounds`), unknown keys refused."""
    model = _patch_model(FloornavConfig, "", _extra_bounds(config))
    assert model is not None
    return model


def _merge(current: dict[str, Any], patch: dict[str, Any], path: str) -> None:
    for key, value in patch.items():
        dotted = f"{path}{key}"
        if key not in current:
            raise ConfigPatchError(f"{dotted}: not a configuration key")
        if value is None:
            raise ConfigPatchError(f"{dotted}: null is not a value (keys cannot be removed)")
        if isinstance(current[key], dict):
            if not isinstance(value, dict):
                raise ConfigPatchError(f"{dotted}: expected an object of this section's keys")
            _merge(current[key], value, dotted + ".")
            continue
        if not is_live_key(dotted):
            raise ConfigPatchError(
                f"{dotted}: cannot be changed while running (set it in config.toml and "
                f"restart); live keys: {', '.join(LIVE_KEYS)}"
            )
        current[key] = value


def _problems(exc: ValidationError) -> str:
    problems = []
    for error in exc.errors(include_url=False):
        key = ".".join(str(part) for part in error["loc"]) or "<root>"
        problems.append(f"{key}: {error['msg']}")
    return "; ".join(problems)


def apply_config_patch(config: FloornavConfig, patch: dict[str, Any]) -> FloornavConfig:
    """A new configuration: ``patch`` (nested sections, like the TOML) merged into
    ``config``.

    Raises
    ------
    ConfigPatchError
        A key is unknown or not live, a value is null, of the wrong JSON type (a patch
        is JSON: ``"0.2"`` or ``true`` for a speed is a client's bug) or out of bounds;
        the message names the dotted key.
    ConfigConflictError
        The values are each valid but the configuration they make is not.
    """
    merged = config.model_dump(mode="python")
    _merge(merged, patch, "")
    try:
        config_patch_model(config).model_validate(patch)
    except ValidationError as exc:
        raise ConfigPatchError(_problems(exc)) from exc
    try:
        return FloornavConfig.model_validate(merged)
    except ValidationError as exc:
        raise ConfigConflictError(_problems(exc)) from exc


def _inline(node: Any, defs: dict[str, Any]) -> Any:
    if isinstance(node, dict):
        ref = node.get("$ref")
        if isinstance(ref, str) and ref.startswith("#/$defs/"):
            return _inline(defs[ref.removeprefix("#/$defs/")], defs)
        # "default": null only says the key may be left out; it is never a value.
        return {
            k: _inline(v, defs)
            for k, v in node.items()
            if k != "$defs" and not (k == "default" and v is None)
        }
    if isinstance(node, list):
        return [_inline(v, defs) for v in node]
    return node


def patch_openapi(model: type[BaseModel]) -> dict[str, Any]:
    """``openapi_extra`` documenting ``model`` as the request body, inlined (the route
    reads a plain object so that its refusals can say which key is not live)."""
    schema = model.model_json_schema()
    body = _inline(schema, schema.get("$defs", {}))
    return {
        "requestBody": {
            "required": True,
            "content": {"application/json": {"schema": body}},
        }
    }
