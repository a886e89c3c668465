"""Request and response bodies of the REST API (they make the OpenAPI schema).

Request bodies are strict (`Body`): a number must be a JSON number (an integer is fine
where a float is expected), a flag must be ``true`` or ``false``, a text a string. No
``"0.1"`` for a speed, no ``true`` for a speed, no ``0`` for ``take_over``: a client
that sends those has a bug, and guessing what it meant is how a robot moves unasked.
"""

from __future__ import annotations

import json
from typing import Annotated, Any

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    field_validator,
)

from app.control.teleop_limits import TeleopAngularSpeed, TeleopLinearSpeed
from app.logs import escape_control
from app.messages import State

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
# A JSON array is a list once FastAPI has parsed the body, and strict mode takes only
# real tuples for a tuple: the pair itself is lax (a list of two), its numbers strict.
PixelPair = Annotated[
    tuple[
        Annotated[float, Field(allow_inf_nan=False, ge=-1e5, le=1e5)],
        Annotated[float, Field(allow_inf_nan=False, ge=-1e5, le=1e5)],
    ],
    Strict(False),
]
GroundPair = Annotated[
    tuple[
        Annotated[float, Field(allow_inf_nan=False, ge=-100.0, le=100.0)],
        Annotated[float, Field(allow_inf_nan=False, ge=-100.0, le=100.0)],
    ],
    Strict(False),
]
LABEL_MAX_CHARS = 64


PRINTABLE_PATTERN = r"^[^\x00-\x1f\x7f-\x9f\u2028\u2029]+$"
"""No control characters (what `app.logs.escape_control` escapes); in the schema, so a
client learns the rule from it and no request the schema allows is refused."""

DriverName = Annotated[
    str, Field(min_length=1, max_length=LABEL_MAX_CHARS, pattern=PRINTABLE_PATTERN)
]
"""Who drives by hand. It names the driver in the state log and in the "held by"
refusals and is compared between requests, so a name with control characters is refused
(422), not rewritten."""


BOARD_PATTERN_REGEX = r"^([3-9]|[1-9][0-9])x([3-9]|[1-9][0-9])$"
"""``COLSxROWS`` inner corners, each 3..99 (the schema says what `check_board_pattern`
accepts, so no request the schema allows is refused)."""


def check_board_pattern(pattern: str) -> tuple[int, int]:
    """(cols, rows) of a ``COLSxROWS`` pattern OpenCV can detect: at least 3x3 inner
    corners (its detector raises on fewer; `parse_pattern` allows 2). Raises ValueError."""
    cols, _, rows = pattern.lower().partition("x")
    if not (cols.isdigit() and rows.isdigit()) or min(int(cols), int(rows)) < 3:
        raise ValueError(f"pattern must be COLSxROWS inner corners, each >= 3, got {pattern!r}")
    return int(cols), int(rows)


class Body(BaseModel):
    """Request bodies reject unknown fields (a typo must not be silently ignored) and
    are strict about types (see the module's docstring)."""

    model_config = ConfigDict(extra="forbid", strict=True)


class TeleopRequest(Body):
    """One hand-driving command; repeat it at >= 10 Hz (the mux lets go after
    ``safety.teleop_timeout_s``, 0.5 s by default)."""

    v_m_s: TeleopLinearSpeed
    omega_rad_s: TeleopAngularSpeed
    driver: DriverName = "api"
    take_over: bool = False


class TeleopReleaseRequest(Body):
    driver: DriverName | None = None
    """Release only this driver's teleop; None releases whoever drives."""


class EstopRequest(Body):
    """The e-stop's optional body. Documentation only: an e-stop is never refused for
    its body (`estop_source` reads whatever came)."""

    source: Annotated[str, Field(min_length=1, max_length=LABEL_MAX_CHARS)] = "api"
    """Who pressed it, for the log and the status. Control characters are escaped and a
    longer label is cut to 64 characters."""


def estop_source(raw: bytes) -> str:
    """The label of an e-stop request body, whatever the body is: the ``source`` string
    with control characters escaped (it goes into the log and the status) and cut to
    `LABEL_MAX_CHARS`; ``"api"`` when there is none (no body, not JSON, not an object, no
    string ``source``). Never raises: refusing an e-stop because of its label would leave
    the robot moving over a typo."""
    try:
        document = json.loads(raw) if raw.strip() else None
    except (ValueError, RecursionError):  # not JSON or not UTF-8; nested too deep
        document = None
    source = document.get("source") if isinstance(document, dict) else None
    if not isinstance(source, str):
        return "api"
    label = escape_control(source).strip()[:LABEL_MAX_CHARS]
    return label or "api"


ESTOP_OPENAPI: dict[str, Any] = {
    "requestBody": {
        "required": False,
        "description": 'Optional `{"source": label}` (see `EstopRequest`). Any body is '
        "accepted, even one that is not JSON: an e-stop is never refused.",
        # Any value: a schema that rejected something would promise a 4xx the route
        # never gives (it latches first).
        "content": {"application/json": {"schema": {"examples": [{"source": "dashboard"}]}}},
    }
}
"""The e-stop route reads its body itself (`estop_source`); this documents it."""


class ChessboardCalibrationRequest(Body):
    """A chessboard lying flat on the floor, seen in the current frame."""

    pattern: Annotated[str, Field(pattern=BOARD_PATTERN_REGEX, examples=["9x6"])]
    """Inner corners, COLSxROWS."""
    square_m: Annotated[float, Field(ge=0.005, le=1.0, allow_inf_nan=False)]
    """Side of one board square; 5 mm is smaller than any board a camera resolves."""
    board_x_m: Annotated[float, Field(ge=-10.0, le=10.0, allow_inf_nan=False)] = 0.0
    board_y_m: Annotated[float, Field(ge=-10.0, le=10.0, allow_inf_nan=False)] = 0.0
    board_yaw_rad: Annotated[float, Field(ge=-0.8, le=0.8, allow_inf_nan=False)] = 0.0
    """The board frame in the robot frame (`app.mapping.calibration.BoardPlacement`)."""
    save: bool = True
    """Save the fit and make it the live calibration (the map starts afresh); false:
    only fit and return the errors (a preview: nothing live changes)."""

    @field_validator("pattern")
    @classmethod
    def _opencv_pattern(cls, pattern: str) -> str:
        check_board_pattern(pattern)
        return pattern


class PointPair(Body):
    """A pixel of the current frame and where it lies on the floor."""

    image_px: PixelPair
    ground_m: GroundPair
    """Robot frame: x forward, y left, metres."""


class PointPairCalibrationRequest(Body):
    """Four or more pixels of the current frame with their floor positions (one list of
    pairs, so a pixel can never lack its floor position)."""

    pairs: Annotated[list[PointPair], Field(min_length=4, max_length=500)]
    save: bool = True
    """As for the chessboard: false only fits and returns the errors."""


CalibrationRequest = ChessboardCalibrationRequest | PointPairCalibrationRequest


class CalibrationResponse(BaseModel):
    reprojection_rms_px: float
    ground_rms_m: float
    points: int
    inliers: int
    # Lists, not tuples: FastAPI writes tuples in response schemas in a form OpenAPI 3.1
    # validators reject.
    image_size: Annotated[list[int], Field(min_length=2, max_length=2)]
    board_origin_px: Annotated[list[float], Field(min_length=2, max_length=2)] | None
    corners_px: list[Annotated[list[float], Field(min_length=2, max_length=2)]] | None
    """The detected chessboard corners (chessboard requests), for the wizard to draw."""
    saved_to: str | None


class CommandResponse(BaseModel):
    ok: bool = True
    state: State
    detail: str = ""


class EstopResetResponse(CommandResponse):
    was_estopped: bool


class FaultResetResponse(CommandResponse):
    cleared: str | None
    """The latched fault's reason that was cleared, or null when none was latched."""


class ErrorResponse(BaseModel):
    detail: str
    errors: list[dict[str, Any]] | None = None


ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorResponse, "description": "missing or wrong bearer token"},
    422: {"model": ErrorResponse, "description": "malformed body or rejected value"},
}
REFUSED_RESPONSE: dict[int | str, dict[str, Any]] = {
    409: {"model": ErrorResponse, "description": "refused in the current state"}
}
STOP_RESPONSES: dict[int | str, dict[str, Any]] = {}
"""Stop and e-stop take no token and no required body: they answer 200 (a body over the
1 MiB limit gets 413 before any route runs)."""
