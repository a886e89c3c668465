"""The simulated floor plan: walls, boxes, textured floors, lighting and a start pose,
read from a small TOML file. The shipped worlds are ``app/sim/worlds/NAME.toml``, chosen
by name (`resolve_world_path`): ``two-rooms`` (the default, also called ``default``),
``home`` and ``office``.

Coordinates
-----------
Everything here is in the *plan* frame: metres on the floor, x/y as drawn in the TOML
file, z up. The mapping modules' ``world`` frame (``app.mapping.frames``) is fixed at the
robot's start pose, so ``T_world_plan = world.start_pose.inverse()``.

File format (every key optional unless said; unknown keys are errors)::

    name = "two rooms"
    [start]                     # robot start pose (required)
    x_m = 1.0
    y_m = 3.0
    theta_rad = 0.0
    [floor]                     # default floor everywhere
    pattern = "wood"            # plain | tiles | wood | carpet (+ its own keys)
    color = "#a87c50"
    gloss = 0.0                 # 0 matte .. 1 mirror-like (reflects walls, boxes, lights)
    [[floor_areas]]             # a rug, another room's tiles ... (later areas on top)
    rect_m = [x_min, y_min, x_max, y_max]
    surface = { pattern = "carpet", color = "#7a3b3b" }
    end_color = "#3b4a7a"       # optional: the colour fades to this along fade_axis
    fade_axis = "x"
    [[light_areas]]             # a dark hallway (gain < 1), a sunlit patch (gain > 1)
    rect_m = [x_min, y_min, x_max, y_max]
    gain = 0.45
    color = "#ffffff"           # tint (a warm sun: "#fff0d0")
    softness_m = 0.1            # width of the soft edge
    [[lights]]                  # ceiling lights, seen as reflections in a glossy floor
    position_m = [3.0, 2.0]
    height_m = 2.6
    [[rooms]]                   # a closed rectangle of walls
    rect_m = [0.0, 0.0, 8.0, 6.0]
    [[walls]]                   # an open polyline of walls
    points_m = [[4.5, 0.0], [4.5, 2.2]]
    finish = "floor"            # paint | floor: a panel looking like the floor
    [[boxes]]
    center_m = [2.0, 1.5]
    size_m = [0.4, 0.3]         # along the box's own x and y (before yaw)
    height_m = 0.3
    yaw_rad = 0.2
    color = "#c03020"
    [lighting]
    azimuth_rad = 0.8

Colours are ``"#rrggbb"`` (as a person writes them); `World` holds them as BGR.
"""

from __future__ import annotations

import itertools
import math
import re
import tomllib
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import AfterValidator, Field, ValidationError

from app.config import StrictModel
from app.mapping.frames import GroundGrid, Pose2D
from app.sim.worlds import DEFAULT_WORLD_PATH, resolve_world_path

DEFAULT_ROBOT_RADIUS_M = 0.15
"""Radius of the circle the simulated robot occupies (a 0.2 m wheel base plus bumpers)."""

_COLOR_RE = re.compile(r"^#[0-9a-fA-F]{6}$")


def _check_color(value: str) -> str:
    if not _COLOR_RE.match(value):
        raise ValueError(f"colour must be written '#rrggbb' (hex), got {value!r}")
    return value.lower()


Color = Annotated[str, AfterValidator(_check_color)]
PositiveLength = Annotated[float, Field(gt=0.0, le=1000.0)]
Coordinate = Annotated[float, Field(ge=-1000.0, le=1000.0)]
Point = tuple[Coordinate, Coordinate]
Variation = Annotated[float, Field(ge=0.0, le=0.5)]
Gloss = Annotated[float, Field(ge=0.0, le=1.0)]
"""How mirror-like a floor is: the weight of its reflection at grazing view (Schlick's
Fresnel falloff makes it weaker looking down); 0 is matte."""
Rect = tuple[Coordinate, Coordinate, Coordinate, Coordinate]


# -- floors ----------------------------------------------------------------------------


class PlainFloor(StrictModel):
    """One colour with a faint low-frequency mottling."""

    pattern: Literal["plain"] = "plain"
    color: Color = "#9a8f80"
    variation: Variation = 0.03
    seed: int = 0
    gloss: Gloss = 0.0


class TilesFloor(StrictModel):
    """Square tiles with joints (grout); each tile's brightness varies a little."""

    pattern: Literal["tiles"] = "tiles"
    color: Color = "#c8c0b0"
    joint_color: Color = "#8a8478"
    tile_size_m: Annotated[float, Field(gt=0.02, le=5.0)] = 0.30
    joint_width_m: Annotated[float, Field(ge=0.0, le=0.05)] = 0.006
    variation: Variation = 0.06
    seed: int = 0
    gloss: Gloss = 0.0


class WoodFloor(StrictModel):
    """Planks along x in staggered rows, with seams, grain and per-plank tint."""

    pattern: Literal["wood"] = "wood"
    color: Color = "#a87c50"
    seam_color: Color = "#5a4028"
    plank_width_m: Annotated[float, Field(gt=0.02, le=2.0)] = 0.14
    plank_length_m: Annotated[float, Field(gt=0.05, le=10.0)] = 1.2
    seam_width_m: Annotated[float, Field(ge=0.0, le=0.02)] = 0.003
    grain: Variation = 0.08
    variation: Variation = 0.10
    seed: int = 0
    gloss: Gloss = 0.0


class CarpetFloor(StrictModel):
    """Short-pile carpet: band-limited noise at ``grain_m`` plus sparse flecks."""

    pattern: Literal["carpet"] = "carpet"
    color: Color = "#6a6e78"
    fleck_color: Color = "#9a9ca4"
    grain_m: Annotated[float, Field(gt=0.0, le=0.5)] = 0.01
    fleck_fraction: Annotated[float, Field(ge=0.0, le=0.5)] = 0.04
    variation: Variation = 0.12
    seed: int = 0
    gloss: Gloss = 0.0


FloorSurface = Annotated[
    PlainFloor | TilesFloor | WoodFloor | CarpetFloor, Field(discriminator="pattern")
]
_PATTERN_NAMES = frozenset({"plain", "tiles", "wood", "carpet"})


class FloorArea(StrictModel):
    """A rectangle of floor with its own surface (a rug, a tiled room, a threshold strip).

    With ``end_color`` the surface's colour fades linearly along ``fade_axis``, from
    ``surface.color`` at the rectangle's low edge to ``end_color`` at its high edge (a
    rug whose two ends differ: one region whose colour statistics drift)."""

    rect_m: Rect
    surface: FloorSurface
    end_color: Color | None = None
    fade_axis: Literal["x", "y"] = "x"


class LightArea(StrictModel):
    """A rectangle of the plan lit differently: floor and faces whose ground point lies in
    it have their brightness multiplied by ``gain`` (tinted by ``color``, white = none),
    fading in over ``softness_m`` at its edges. A dim hallway, a patch of sun."""

    rect_m: Rect
    gain: Annotated[float, Field(ge=0.05, le=4.0)]
    color: Color = "#ffffff"
    softness_m: Annotated[float, Field(ge=0.0, le=2.0)] = 0.1


class CeilingLight(StrictModel):
    """A round ceiling light: it shows as a bright blurred spot where a glossy floor
    mirrors it (it lights nothing itself: `LightingSpec` does)."""

    position_m: Point
    height_m: Annotated[float, Field(gt=0.0, le=20.0)] = 2.6
    radius_m: Annotated[float, Field(gt=0.0, le=2.0)] = 0.25
    intensity: Annotated[float, Field(ge=0.0, le=10.0)] = 2.5
    """Spot brightness in units of full scale (255) before the floor's gloss weight."""
    color: Color = "#fff8ec"


# -- walls and boxes -------------------------------------------------------------------

WallFinish = Literal["paint", "floor"]
"""``paint``: plain ``color``. ``floor``: the default floor's texture and colour (the
thesis's trap: a wall that looks like floor)."""


class WallSpec(StrictModel):
    """An open polyline of vertical wall panels (zero thickness, both sides visible)."""

    points_m: list[Point] = Field(min_length=2, max_length=1000)
    height_m: PositiveLength = 1.0
    color: Color = "#d8d4cc"
    finish: WallFinish = "paint"


class RoomSpec(StrictModel):
    """A closed rectangle of walls ``[x_min, y_min, x_max, y_max]``."""

    rect_m: Rect
    height_m: PositiveLength = 1.0
    color: Color = "#d8d4cc"
    finish: WallFinish = "paint"


class BoxSpec(StrictModel):
    """An upright box: footprint ``size_m`` (its own x, y) centred at ``center_m``,
    turned by ``yaw_rad``."""

    center_m: Point
    size_m: tuple[PositiveLength, PositiveLength]
    height_m: PositiveLength = 0.3
    yaw_rad: Annotated[float, Field(ge=-10.0, le=10.0)] = 0.0
    color: Color = "#b03028"


class StartSpec(StrictModel):
    x_m: Coordinate
    y_m: Coordinate
    theta_rad: Annotated[float, Field(ge=-10.0, le=10.0)] = 0.0


class LightingSpec(StrictModel):
    """A directional light plus ambient light; brightness falls with distance from the
    camera as ``1 / (1 + (d / attenuation_distance_m)^2)``."""

    ambient: Annotated[float, Field(ge=0.0, le=2.0)] = 0.55
    diffuse: Annotated[float, Field(ge=0.0, le=2.0)] = 0.45
    azimuth_rad: Annotated[float, Field(ge=-10.0, le=10.0)] = 0.8
    elevation_rad: Annotated[float, Field(ge=0.0, le=1.5708)] = 0.9
    attenuation_distance_m: PositiveLength = 9.0
    background_color: Color = "#4a4c50"


class WorldSpec(StrictModel):
    """The whole floor plan as read from TOML."""

    name: str = "unnamed"
    description: str = ""
    start: StartSpec
    floor: FloorSurface = TilesFloor()
    floor_areas: list[FloorArea] = Field(default_factory=list)
    rooms: list[RoomSpec] = Field(default_factory=list)
    walls: list[WallSpec] = Field(default_factory=list)
    boxes: list[BoxSpec] = Field(default_factory=list)
    lighting: LightingSpec = LightingSpec()
    light_areas: list[LightArea] = Field(default_factory=list)
    lights: list[CeilingLight] = Field(default_factory=list)


# -- errors ----------------------------------------------------------------------------


@dataclass(frozen=True)
class WorldIssue:
    """One problem of a world file: the key path, what is wrong, and the line if known."""

    key: str
    message: str
    line: int | None = None

    def __str__(self) -> str:
        where = f" (line {self.line})" if self.line is not None else ""
        return f"{self.key}{where}: {self.message}"


class WorldError(ValueError):
    """A world file could not be loaded; ``issues`` names every bad key."""

    def __init__(self, source: str, issues: list[WorldIssue]) -> None:
        self.source = source
        self.issues = issues
        lines = "\n".join(f"  {issue}" for issue in issues)
        super().__init__(f"invalid world {source}:\n{lines}")


Loc = tuple[str | int, ...]


def _key_name(loc: Loc) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + part
    return out or "<root>"


_HEADER_RE = re.compile(r"^\s*(\[\[?)\s*([A-Za-z0-9_.\- ]+?)\s*\]\]?\s*(#.*)?$")
_KEY_RE = re.compile(r"^\s*([A-Za-z0-9_\-]+)\s*=")


def _line_index(text: str) -> list[tuple[Loc, int]]:
    """(path, 1-based line) of every table header and ``key =`` line of a TOML text
    written in the usual one-key-per-line style (inline tables are not looked into)."""
    entries: list[tuple[Loc, int]] = []
    counts: dict[str, int] = {}
    table: Loc = ()
    for number, line in enumerate(text.splitlines(), start=1):
        header = _HEADER_RE.match(line)
        if header:
            names = [n.strip() for n in header.group(2).split(".")]
            path: list[str | int] = []
            for depth, name in enumerate(names):
                path.append(name)
                dotted = ".".join(names[: depth + 1])
                is_last = depth == len(names) - 1
                if is_last and header.group(1) == "[[":
                    counts[dotted] = counts.get(dotted, -1) + 1
                    path.append(counts[dotted])
                elif not is_last and dotted in counts:
                    path.append(counts[dotted])
            table = tuple(path)
            entries.append((table, number))
            continue
        key = _KEY_RE.match(line)
        if key:
            entries.append(((*table, key.group(1)), number))
    return entries


def _find_line(entries: list[tuple[Loc, int]], loc: Loc) -> int | None:
    """The line of the entry sharing the longest prefix with ``loc``."""
    wanted = tuple(p for p in loc if not (isinstance(p, str) and p in _PATTERN_NAMES))
    best, best_len = None, 0
    for path, line in entries:
        n = 0
        while n < min(len(path), len(wanted)) and path[n] == wanted[n]:
            n += 1
        if n == len(path) and n > best_len:
            best, best_len = line, n
    return best


# -- loading ---------------------------------------------------------------------------


def load_world(
    path: Path | None = None, *, robot_radius_m: float = DEFAULT_ROBOT_RADIUS_M
) -> World:
    """Read and check a world file (``None``: the shipped default world).

    Raises
    ------
    WorldError
        Missing file, bad TOML (with its line), unknown keys, out-of-range values,
        degenerate walls, a start pose inside an obstacle: every issue names its key
        path (``boxes[3].size_m``) and, when it can be found, its line.
    """
    path = DEFAULT_WORLD_PATH if path is None else path
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise WorldError(str(path), [WorldIssue("<file>", f"cannot read: {exc}")]) from exc
    return parse_world(text, source=str(path), robot_radius_m=robot_radius_m)


def load_named_world(selector: str, *, robot_radius_m: float = DEFAULT_ROBOT_RADIUS_M) -> World:
    """`load_world` of `resolve_world_path` (what ``[sim] world_file`` and ``floornav run
    --world`` hold)."""
    return load_world(resolve_world_path(selector), robot_radius_m=robot_radius_m)


def parse_world(
    text: str, *, source: str = "<string>", robot_radius_m: float = DEFAULT_ROBOT_RADIUS_M
) -> World:
    """`load_world` on a TOML text."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        match = re.search(r"line (\d+)", str(exc))
        line = int(match.group(1)) if match else None
        raise WorldError(source, [WorldIssue("<file>", f"not valid TOML: {exc}", line)]) from exc
    entries = _line_index(text)
    try:
        spec = WorldSpec.model_validate(data)
    except ValidationError as exc:
        issues = []
        for item in exc.errors():
            loc: Loc = tuple(item["loc"])
            message = item["msg"]
            if item["type"] not in ("extra_forbidden", "missing") and "input" in item:
                message = f"{message} (got {item['input']!r})"
            if item["type"] == "extra_forbidden":
                message = "unknown key"
            issues.append(WorldIssue(_key_name(loc), message, _find_line(entries, loc)))
        raise WorldError(source, issues) from exc
    problems = check_world(spec, robot_radius_m=robot_radius_m)
    if problems:
        raise WorldError(
            source,
            [WorldIssue(_key_name(loc), msg, _find_line(entries, loc)) for loc, msg in problems],
        )
    return World(spec, robot_radius_m=robot_radius_m, _checked=True)


def check_world(spec: WorldSpec, *, robot_radius_m: float) -> list[tuple[Loc, str]]:
    """Geometric checks pydantic cannot express: (key path, message) of each problem."""
    problems: list[tuple[Loc, str]] = []
    for i, wall in enumerate(spec.walls):
        for j in range(len(wall.points_m) - 1):
            (x0, y0), (x1, y1) = wall.points_m[j], wall.points_m[j + 1]
            if math.hypot(x1 - x0, y1 - y0) < 1e-3:
                problems.append(
                    (
                        ("walls", i, "points_m", j + 1),
                        f"degenerate wall: point {j + 1} repeats point {j} "
                        f"({x0:g}, {y0:g}); segments must be longer than 1 mm",
                    )
                )
    rects = [("rooms", i, r.rect_m) for i, r in enumerate(spec.rooms)]
    rects += [("floor_areas", i, a.rect_m) for i, a in enumerate(spec.floor_areas)]
    rects += [("light_areas", i, a.rect_m) for i, a in enumerate(spec.light_areas)]
    for name, i, rect in rects:
        x_min, y_min, x_max, y_max = rect
        if not (x_max - x_min > 1e-3 and y_max - y_min > 1e-3):
            problems.append(
                ((name, i, "rect_m"), "need x_max > x_min and y_max > y_min (degenerate)")
            )
    if problems:
        return problems
    x, y = spec.start.x_m, spec.start.y_m
    for i, box in enumerate(spec.boxes):
        if _box_distance(box, x, y) < robot_radius_m:
            problems.append(
                (
                    ("start",),
                    f"start pose ({x:g}, {y:g}) is inside boxes[{i}] (or closer than the "
                    f"robot radius {robot_radius_m:g} m to it)",
                )
            )
    segments = _wall_segments(spec)[0]
    if len(segments):
        d = _point_segment_distance(np.array([x, y]), segments)
        for k in np.flatnonzero(d < robot_radius_m):
            problems.append(
                (
                    ("start",),
                    f"start pose ({x:g}, {y:g}) touches a wall: {d[k]:.3f} m from segment "
                    f"({segments[k, 0]:g}, {segments[k, 1]:g})-({segments[k, 2]:g}, "
                    f"{segments[k, 3]:g}), less than the robot radius {robot_radius_m:g} m",
                )
            )
    return problems


# -- geometry helpers ------------------------------------------------------------------


def _hex_to_bgr(color: str) -> tuple[float, float, float]:
    r, g, b = (int(color[i : i + 2], 16) for i in (1, 3, 5))
    return (float(b), float(g), float(r))


def _room_points(rect: tuple[float, float, float, float]) -> list[tuple[float, float]]:
    x0, y0, x1, y1 = rect
    return [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]


def _wall_segments(spec: WorldSpec) -> tuple[NDArray[np.float64], list[int]]:
    """(N, 4) wall segments x0, y0, x1, y1 and, per segment, the index of its wall in
    ``rooms + walls`` order."""
    segs: list[tuple[float, float, float, float]] = []
    owner: list[int] = []
    polylines = [_room_points(r.rect_m) for r in spec.rooms] + [
        list(w.points_m) for w in spec.walls
    ]
    for k, pts in enumerate(polylines):
        for (x0, y0), (x1, y1) in itertools.pairwise(pts):
            segs.append((x0, y0, x1, y1))
            owner.append(k)
    return np.array(segs, dtype=np.float64).reshape(-1, 4), owner


def box_corners(box: BoxSpec) -> NDArray[np.float64]:
    """(4, 2) footprint corners, counter-clockwise."""
    c, s = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
    hx, hy = box.size_m[0] / 2, box.size_m[1] / 2
    local = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
    rot = np.array([[c, -s], [s, c]])
    out: NDArray[np.float64] = local @ rot.T + np.array(box.center_m)
    return out


def _box_distance(box: BoxSpec, x: float, y: float) -> float:
    """Distance from a point to the box footprint (0 inside)."""
    c, s = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
    dx, dy = x - box.center_m[0], y - box.center_m[1]
    lx, ly = c * dx + s * dy, -s * dx + c * dy
    ex = max(abs(lx) - box.size_m[0] / 2, 0.0)
    ey = max(abs(ly) - box.size_m[1] / 2, 0.0)
    return math.hypot(ex, ey)


def _nearest_on_segments(
    point: NDArray[np.float64], segments: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(N, 2) nearest point of each of (N, 4) segments to one point."""
    p0, p1 = segments[:, :2], segments[:, 2:]
    e = p1 - p0
    length2 = np.maximum((e * e).sum(axis=1), 1e-18)
    t = np.clip(((point - p0) * e).sum(axis=1) / length2, 0.0, 1.0)
    nearest: NDArray[np.float64] = p0 + t[:, None] * e
    return nearest


def _point_segment_distance(
    point: NDArray[np.float64], segments: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Distance from one point to each of (N, 4) segments."""
    out: NDArray[np.float64] = np.hypot(*(point - _nearest_on_segments(point, segments)).T)
    return out


# -- floor textures --------------------------------------------------------------------


def _hash01(*keys: NDArray[np.int32], seed: int) -> NDArray[np.float32]:
    """A deterministic pseudo-random number in [0, 1) per integer key tuple."""
    with np.errstate(over="ignore"):
        h = np.full(keys[0].shape, (seed * 0x9E3779B1 + 0x7F4A7C15) & 0xFFFFFFFF, np.uint32)
        for key in keys:
            h ^= key.astype(np.uint32)
            h *= np.uint32(0x85EBCA6B)
            h ^= h >> np.uint32(13)
            h *= np.uint32(0xC2B2AE35)
            h ^= h >> np.uint32(16)
    out: NDArray[np.float32] = h.astype(np.float32) * np.float32(2.0**-32)
    return out


def _smooth_noise(
    shape: tuple[int, int], sigma_px: float, rng: np.random.Generator
) -> NDArray[np.float32]:
    """Zero-mean, unit-variance noise low-passed at ``sigma_px`` texels."""
    noise = rng.standard_normal(shape).astype(np.float32)
    if sigma_px > 0.3:
        noise = np.asarray(cv2.GaussianBlur(noise, (0, 0), sigma_px), np.float32)
    std = float(noise.std()) or 1.0
    out: NDArray[np.float32] = noise / std
    return out


def _line_coverage(
    distance_m: NDArray[np.float32], width_m: float, texel_m: float
) -> NDArray[np.float32]:
    """Fraction of a texel covered by a line ``width_m`` wide whose centre is
    ``distance_m`` from the texel centre (a box filter, so thin lines stay visible)."""
    if width_m <= 0.0:
        return np.zeros(distance_m.shape, np.float32)
    inner = width_m / 2 - texel_m / 2
    edge = min(width_m, texel_m)
    out: NDArray[np.float32] = np.clip((width_m / 2 + texel_m / 2 - distance_m) / edge, 0, 1)
    if inner > 0:
        out[distance_m <= inner] = 1.0
    return out * np.float32(min(1.0, width_m / texel_m) if inner <= 0 else 1.0)


def floor_texture(
    surface: PlainFloor | TilesFloor | WoodFloor | CarpetFloor,
    x_m: NDArray[np.floating],
    y_m: NDArray[np.floating],
    *,
    texel_m: float,
) -> NDArray[np.uint8]:
    """Colour (BGR uint8, shape ``x_m.shape + (3,)``) of a floor surface at the given
    plan-frame texel centres (2-D arrays of one raster)."""
    x_m = np.asarray(x_m, np.float32)
    y_m = np.asarray(y_m, np.float32)
    rng = np.random.default_rng(surface.seed)
    shape = x_m.shape
    base = np.array(_hex_to_bgr(surface.color), np.float32)
    gain = np.ones(shape, np.float32)
    accent_cover = np.zeros(shape, np.float32)
    accent = base
    if isinstance(surface, PlainFloor):
        gain += surface.variation * _smooth_noise(shape, 0.25 / texel_m, rng)
    elif isinstance(surface, TilesFloor):
        size = surface.tile_size_m
        i = np.floor(x_m / size).astype(np.int32)
        j = np.floor(y_m / size).astype(np.int32)
        fx = x_m - i.astype(np.float32) * size
        fy = y_m - j.astype(np.float32) * size
        d = np.minimum(np.minimum(fx, size - fx), np.minimum(fy, size - fy))
        accent_cover = _line_coverage(d, surface.joint_width_m, texel_m)
        gain += (surface.variation * 2 * (_hash01(i, j, seed=surface.seed) - 0.5)).astype(
            np.float32
        )
        gain += 0.02 * _smooth_noise(shape, 0.01 / texel_m, rng)
        accent = np.array(_hex_to_bgr(surface.joint_color), np.float32)
    elif isinstance(surface, WoodFloor):
        width, length = surface.plank_width_m, surface.plank_length_m
        row = np.floor(y_m / width).astype(np.int32)
        stagger = _hash01(row, seed=surface.seed + 1) * length
        shifted = x_m + stagger
        col = np.floor(shifted / length).astype(np.int32)
        rowf = row.astype(np.float32)
        fy = y_m - rowf * width
        fx = shifted - col.astype(np.float32) * length
        d = np.minimum(np.minimum(fx, length - fx), np.minimum(fy, width - fy))
        accent_cover = _line_coverage(d, surface.seam_width_m, texel_m)
        plank = _hash01(row, col, seed=surface.seed)
        gain += (surface.variation * 2 * (plank - 0.5)).astype(np.float32)
        wobble = 0.004 * np.sin(x_m * 2.1 + plank * 40.0) + 0.002 * np.sin(x_m * 7.3)
        period = max(0.006, 3.0 * texel_m)  # finer grain would alias on the raster
        grain = np.sin((fy + wobble) * np.float32(2 * np.pi / period) + plank * 17.0)
        gain += surface.grain * grain * (0.6 + 0.4 * np.sin(x_m * 3.0 + rowf))
        accent = np.array(_hex_to_bgr(surface.seam_color), np.float32)
    else:
        pile = _smooth_noise(shape, surface.grain_m / texel_m, rng)
        gain += surface.variation * pile
        gain += 0.5 * surface.variation * _smooth_noise(shape, 0.15 / texel_m, rng)
        flecks = _smooth_noise(shape, 0.5 * surface.grain_m / texel_m, rng)
        threshold = float(np.quantile(flecks, 1.0 - surface.fleck_fraction))
        accent_cover = (flecks > threshold).astype(np.float32)
        accent = np.array(_hex_to_bgr(surface.fleck_color), np.float32)
    cover = accent_cover[..., None]
    color = (base * (1.0 - cover) + accent * cover) * gain[..., None]
    out: NDArray[np.uint8] = np.clip(color + 0.5, 0, 255).astype(np.uint8)
    return out


def _area_texture(
    area: FloorArea, x_m: NDArray[np.floating], y_m: NDArray[np.floating], *, texel_m: float
) -> NDArray[np.uint8]:
    """`floor_texture` of a floor area, faded towards ``end_color`` along its axis (the
    same pattern in both colours, blended, so only the colour drifts)."""
    near = floor_texture(area.surface, x_m, y_m, texel_m=texel_m)
    if area.end_color is None:
        return near
    far = floor_texture(
        area.surface.model_copy(update={"color": area.end_color}), x_m, y_m, texel_m=texel_m
    )
    x0, y0, x1, y1 = area.rect_m
    along, low, high = (x_m, x0, x1) if area.fade_axis == "x" else (y_m, y0, y1)
    t = np.clip((np.asarray(along, np.float32) - low) / (high - low), 0.0, 1.0)[..., None]
    out: NDArray[np.uint8] = (near * (1.0 - t) + far * t + 0.5).astype(np.uint8)
    return out


def _soft_step(distance_inside_m: NDArray[np.float64], softness_m: float) -> NDArray[np.float64]:
    """0 outside an edge, 1 inside, a linear ramp ``softness_m`` wide centred on it."""
    if softness_m <= 0.0:
        return (distance_inside_m >= 0.0).astype(np.float64)
    out: NDArray[np.float64] = np.clip(distance_inside_m / softness_m + 0.5, 0.0, 1.0)
    return out


# -- the world -------------------------------------------------------------------------


@dataclass(frozen=True)
class Faces:
    """Vertical faces for rendering (walls both sides, boxes outward), as arrays.

    Attributes
    ----------
    segments : (N, 4) float64, x0, y0, x1, y1 in the plan frame
    height_m : (N,) float64
    color_bgr : (N, 3) float64, 0..255
    box : (N,) int64, index into the box arrays, -1 for walls
    floor_like : (N,) bool, textured like the default floor
    two_sided : (N,) bool, walls (boxes are seen from outside only)
    """

    segments: NDArray[np.float64]
    height_m: NDArray[np.float64]
    color_bgr: NDArray[np.float64]
    box: NDArray[np.int64]
    floor_like: NDArray[np.bool_]
    two_sided: NDArray[np.bool_]


@dataclass(frozen=True)
class Boxes:
    """Box footprints for top faces: (M, 2) centre, (M, 2) half size, (M,) yaw cos/sin,
    (M,) height, (M, 3) BGR colour."""

    center_m: NDArray[np.float64]
    half_size_m: NDArray[np.float64]
    cos_yaw: NDArray[np.float64]
    sin_yaw: NDArray[np.float64]
    height_m: NDArray[np.float64]
    color_bgr: NDArray[np.float64]


@dataclass(frozen=True)
class FloorTexture:
    """The floor's colour as a raster over the plan, in `GroundGrid` layout (row 0 at
    ``x_max``, column 0 at ``y_max``), with a mip pyramid (level k halves the size,
    `mip_levels`) and which floor surface each texel of level 0 is (0: the ``[floor]``,
    k: the k-th ``[[floor_areas]]`` entry)."""

    grid: GroundGrid
    levels: list[NDArray[np.uint8]]
    surfaces: NDArray[np.int16]


def mip_levels(
    image: NDArray[np.uint8], surfaces: NDArray[np.int16], count: int | None = None
) -> list[NDArray[np.uint8]]:
    """``image`` and ``count - 1`` levels below it (None: down to about 16 texels a side,
    at most 10 levels), each ``cv2.pyrDown`` of the last, but
    each surface's texels averaged only with its own: a room's carpet does not bleed
    under the wall into the vinyl next to it. Blended, the band along every wall
    between two floors took the other room's colour a few centimetres deep, a dark line
    at the foot of a light wall seen from a metre or two, which a real camera does not
    see (and which put the wall's edge, as Canny finds it, a pixel nearer: a degree off
    on the floor). A threshold's two floors still blend where a level's texel straddles
    them (the renderer samples between texels)."""
    levels = [image]
    labels = surfaces
    present = np.unique(surfaces)
    while (
        len(levels) < count
        if count is not None
        else min(levels[-1].shape[:2]) > 16 and len(levels) < 10
    ):
        shrunk = np.asarray(cv2.pyrDown(levels[-1]), np.uint8)
        below = labels[::2, ::2]  # pyrDown's size: (n + 1) // 2
        if len(present) > 1:
            source = levels[-1].astype(np.float32)
            for surface in present:
                own = below == surface
                if not own.any():
                    continue
                mask = (labels == surface).astype(np.float32)
                # Never zero on its own texels: the kernel's centre is one of them.
                weight = np.asarray(cv2.pyrDown(mask), np.float32)
                summed = np.asarray(cv2.pyrDown(source * mask[:, :, None]), np.float32)
                mean = summed[own] / weight[own][:, None]
                shrunk[own] = np.clip(mean + 0.5, 0, 255).astype(np.uint8)
        levels.append(shrunk)
        labels = below
    return levels


class World:
    """A checked floor plan with the derived geometry the robot and renderer use.

    Build with `load_world` / `parse_world` (they report problems with lines), or
    ``World(spec)`` from code (raises `WorldError` without line numbers).
    """

    def __init__(
        self,
        spec: WorldSpec,
        *,
        robot_radius_m: float = DEFAULT_ROBOT_RADIUS_M,
        _checked: bool = False,
    ) -> None:
        if not _checked:
            problems = check_world(spec, robot_radius_m=robot_radius_m)
            if problems:
                raise WorldError(
                    spec.name, [WorldIssue(_key_name(loc), msg) for loc, msg in problems]
                )
        self.spec = spec
        self.robot_radius_m = robot_radius_m
        self.start_pose = Pose2D(spec.start.x_m, spec.start.y_m, spec.start.theta_rad)
        self._texture_cache: dict[float, FloorTexture] = {}
        self._occupancy_cache: dict[float, tuple[GroundGrid, NDArray[np.uint8]]] = {}

    @property
    def name(self) -> str:
        return self.spec.name

    @cached_property
    def wall_segments(self) -> NDArray[np.float64]:
        """(N, 4) wall segments x0, y0, x1, y1."""
        return _wall_segments(self.spec)[0]

    @cached_property
    def box_polygons(self) -> list[NDArray[np.float64]]:
        """(4, 2) corner arrays, one per box."""
        return [box_corners(b) for b in self.spec.boxes]

    @cached_property
    def obstacle_segments(self) -> NDArray[np.float64]:
        """(N, 4) every wall segment and box edge: what the robot can bump into."""
        edges = [self.wall_segments]
        for corners in self.box_polygons:
            edges.append(np.hstack((corners, np.roll(corners, -1, axis=0))))
        return np.vstack(edges)

    @cached_property
    def bounds_m(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of all walls, boxes, floor areas and the start."""
        pts = [np.array([[self.spec.start.x_m, self.spec.start.y_m]])]
        if len(self.wall_segments):
            pts.append(self.wall_segments.reshape(-1, 2))
        pts.extend(self.box_polygons)
        for area in self.spec.floor_areas:
            x0, y0, x1, y1 = area.rect_m
            pts.append(np.array([[x0, y0], [x1, y1]]))
        allp = np.vstack(pts)
        x_min, y_min = allp.min(axis=0)
        x_max, y_max = allp.max(axis=0)
        if x_max - x_min < 1.0 and y_max - y_min < 1.0:
            x_min, y_min, x_max, y_max = x_min - 5, y_min - 5, x_max + 5, y_max + 5
        return (float(x_min), float(y_min), float(x_max), float(y_max))

    @cached_property
    def faces(self) -> Faces:
        segs, owner = _wall_segments(self.spec)
        wall_specs: list[RoomSpec | WallSpec] = [*self.spec.rooms, *self.spec.walls]
        heights = [wall_specs[k].height_m for k in owner]
        colors = [_hex_to_bgr(wall_specs[k].color) for k in owner]
        floor_like = [wall_specs[k].finish == "floor" for k in owner]
        boxes = [-1] * len(owner)
        all_segs = [segs]
        for b, (box, corners) in enumerate(zip(self.spec.boxes, self.box_polygons, strict=True)):
            all_segs.append(np.hstack((corners, np.roll(corners, -1, axis=0))))
            heights += [box.height_m] * 4
            colors += [_hex_to_bgr(box.color)] * 4
            floor_like += [False] * 4
            boxes += [b] * 4
        n = len(heights)
        return Faces(
            segments=np.vstack(all_segs).reshape(n, 4),
            height_m=np.array(heights, np.float64),
            color_bgr=np.array(colors, np.float64).reshape(n, 3),
            box=np.array(boxes, np.int64),
            floor_like=np.array(floor_like, bool),
            two_sided=np.array([b < 0 for b in boxes], bool),
        )

    @cached_property
    def boxes(self) -> Boxes:
        specs = self.spec.boxes
        m = len(specs)
        return Boxes(
            center_m=np.array([b.center_m for b in specs], np.float64).reshape(m, 2),
            half_size_m=np.array([b.size_m for b in specs], np.float64).reshape(m, 2) / 2,
            cos_yaw=np.array([math.cos(b.yaw_rad) for b in specs], np.float64),
            sin_yaw=np.array([math.sin(b.yaw_rad) for b in specs], np.float64),
            height_m=np.array([b.height_m for b in specs], np.float64),
            color_bgr=np.array([_hex_to_bgr(b.color) for b in specs], np.float64).reshape(m, 3),
        )

    def clearance_m(self, x_m: float, y_m: float) -> float:
        """Distance from a point to the nearest wall or box edge (0 inside a box)."""
        point = np.array([x_m, y_m])
        best = math.inf
        if len(self.obstacle_segments):
            best = float(_point_segment_distance(point, self.obstacle_segments).min())
        for box in self.spec.boxes:
            if _box_distance(box, x_m, y_m) == 0.0:
                return 0.0
        return best

    def nearest_obstacle_xy(self, x_m: float, y_m: float) -> tuple[float, float] | None:
        """The nearest point of any wall or box edge to a point (None: nothing to hit)."""
        segments = self.obstacle_segments
        if not len(segments):
            return None
        point = np.array([x_m, y_m])
        nearest = _nearest_on_segments(point, segments)
        best = int(np.argmin(np.hypot(*(point - nearest).T)))
        return float(nearest[best, 0]), float(nearest[best, 1])

    def floor_raster(self, texel_m: float = 0.01, *, margin_m: float = 1.0) -> FloorTexture:
        """The floor's colour raster at ``texel_m`` (cached), covering the bounds plus
        ``margin_m``, with ``cv2.pyrDown`` mip levels down to about 8 texels."""
        cached = self._texture_cache.get(texel_m)
        if cached is not None:
            return cached
        x_min, y_min, x_max, y_max = self.bounds_m
        grid = GroundGrid.covering(
            x_min_m=x_min - margin_m,
            x_max_m=x_max + margin_m,
            y_min_m=y_min - margin_m,
            y_max_m=y_max + margin_m,
            cell_m=texel_m,
        )
        x, y = grid.cell_centers()
        image = floor_texture(self.spec.floor, x, y, texel_m=texel_m)
        surfaces = np.zeros(image.shape[:2], np.int16)
        for number, area in enumerate(self.spec.floor_areas, start=1):
            ax0, ay0, ax1, ay1 = area.rect_m
            rows = np.flatnonzero((x[:, 0] >= ax0) & (x[:, 0] < ax1))
            cols = np.flatnonzero((y[0, :] >= ay0) & (y[0, :] < ay1))
            if len(rows) and len(cols):
                sub = np.ix_(rows, cols)
                image[sub] = _area_texture(area, x[sub], y[sub], texel_m=texel_m)
                surfaces[sub] = number
        texture = FloorTexture(grid, mip_levels(image, surfaces), surfaces)
        self._texture_cache[texel_m] = texture
        return texture

    @cached_property
    def max_gloss(self) -> float:
        """The glossiest floor surface's gloss (0: the renderer skips reflections)."""
        return max([self.spec.floor.gloss] + [a.surface.gloss for a in self.spec.floor_areas])

    @cached_property
    def light_area_table(self) -> NDArray[np.float64]:
        """(L, 8) per light area: x_min, y_min, x_max, y_max, softness_m and the B, G, R
        gain (``gain`` times the tint): what the renderer's kernels evaluate."""
        rows = [
            (*a.rect_m, a.softness_m, *(a.gain * v / 255.0 for v in _hex_to_bgr(a.color)))
            for a in self.spec.light_areas
        ]
        return np.array(rows, np.float64).reshape(len(rows), 8)

    def light_gain(
        self, x_m: NDArray[np.floating], y_m: NDArray[np.floating]
    ) -> NDArray[np.float64]:
        """(..., 3) BGR brightness gain of the light areas at plan points: 1 outside
        every area, each area's gain inside it, ramping over ``softness_m`` centred on
        its edges; overlapping areas multiply."""
        x = np.asarray(x_m, np.float64)
        y = np.asarray(y_m, np.float64)
        out = np.ones((*x.shape, 3), np.float64)
        for x0, y0, x1, y1, soft, *gain in self.light_area_table:
            cover = _soft_step(x - x0, soft) * _soft_step(x1 - x, soft)
            cover *= _soft_step(y - y0, soft) * _soft_step(y1 - y, soft)
            out *= 1.0 + cover[..., None] * (np.array(gain) - 1.0)
        return out

    def gloss_raster(self, grid: GroundGrid) -> NDArray[np.float32]:
        """The floor's gloss at the centres of ``grid``'s cells, the floor areas laid as
        `floor_raster` lays their textures (later areas on top)."""
        x, y = grid.cell_centers()
        gloss = np.full(grid.shape, self.spec.floor.gloss, np.float32)
        for area in self.spec.floor_areas:
            ax0, ay0, ax1, ay1 = area.rect_m
            gloss[(x >= ax0) & (x < ax1) & (y >= ay0) & (y < ay1)] = area.surface.gloss
        return gloss

    def occupancy(
        self, cell_m: float = 0.05, *, margin_m: float = 0.5
    ) -> tuple[GroundGrid, NDArray[np.uint8]]:
        """Ground-truth occupancy over the plan (cached): 1 where a cell touches a wall
        or lies in a box footprint, 0 elsewhere. Returns the grid and its (rows, cols)
        uint8 raster."""
        cached = self._occupancy_cache.get(cell_m)
        if cached is not None:
            return cached
        x_min, y_min, x_max, y_max = self.bounds_m
        grid = GroundGrid.covering(
            x_min_m=x_min - margin_m,
            x_max_m=x_max + margin_m,
            y_min_m=y_min - margin_m,
            y_max_m=y_max + margin_m,
            cell_m=cell_m,
        )
        occ = np.zeros(grid.shape, np.uint8)
        x, y = grid.cell_centers()
        centers = np.column_stack((x.ravel(), y.ravel()))
        for box in self.spec.boxes:
            c, s = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
            dx, dy = centers[:, 0] - box.center_m[0], centers[:, 1] - box.center_m[1]
            inside = (np.abs(c * dx + s * dy) <= box.size_m[0] / 2) & (
                np.abs(-s * dx + c * dy) <= box.size_m[1] / 2
            )
            occ.ravel()[inside] = 1
        segs = self.obstacle_segments
        for x0, y0, x1, y1 in segs:
            n = max(2, math.ceil(math.hypot(x1 - x0, y1 - y0) / (cell_m / 4)) + 1)
            t = np.linspace(0.0, 1.0, n)
            pts = np.column_stack((x0 + t * (x1 - x0), y0 + t * (y1 - y0)))
            cells = grid.cell_of(pts)
            ok = grid.holds(cells)
            occ[cells[ok, 0], cells[ok, 1]] = 1
        occ.flags.writeable = False
        self._occupancy_cache[cell_m] = (grid, occ)
        return grid, occ
