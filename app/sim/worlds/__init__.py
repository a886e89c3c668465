"""The shipped simulated worlds, one ``NAME.toml`` each, and how a world is named.

Kept apart from `app.sim.world` (which needs numpy and OpenCV) so that validating a
config can check a world's name without loading the simulator.
"""

from __future__ import annotations

import os
from pathlib import Path

WORLDS_DIR = Path(__file__).resolve().parent
"""The shipped worlds' folder."""
DEFAULT_WORLD_NAME = "two-rooms"
WORLD_ALIASES = {"default": DEFAULT_WORLD_NAME}
"""Other names of shipped worlds (``default``: what an empty ``[sim] world_file`` means)."""
DEFAULT_WORLD_PATH = WORLDS_DIR / f"{DEFAULT_WORLD_NAME}.toml"


class UnknownWorldError(ValueError):
    """A world selector that names no shipped world (and is not a path)."""


def world_names() -> list[str]:
    """The shipped worlds' names, sorted (aliases such as ``default`` not included)."""
    return sorted(path.stem for path in WORLDS_DIR.glob("*.toml"))


def is_world_path(selector: str) -> bool:
    """Whether a selector is a path (ends in ``.toml`` or holds a directory separator)
    rather than a shipped world's name."""
    return selector.endswith(".toml") or "/" in selector or os.sep in selector


def resolve_world_path(selector: str) -> Path:
    """The world file a selector means: ``""`` the default world, a shipped world's name
    (or alias), or a path (`is_world_path`; relative to the working directory, like
    every path of the config).

    Raises
    ------
    UnknownWorldError
        A bare name that is not shipped; the message lists the names.
    """
    if not selector:
        return DEFAULT_WORLD_PATH
    if is_world_path(selector):
        return Path(selector).expanduser()
    path = WORLDS_DIR / f"{WORLD_ALIASES.get(selector, selector)}.toml"
    if path.is_file():
        return path
    aliases = ", ".join(f"{alias!r} = {name}" for alias, name in sorted(WORLD_ALIASES.items()))
    raise UnknownWorldError(
        f"unknown world {selector!r}: the shipped worlds are {', '.join(world_names())} "
        f"({aliases}), or give the path of a .toml world file"
    )
