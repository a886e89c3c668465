"""Map files: floornav's own saved map, and the ROS map_server format for other tools.

floornav's map file (`save_map` / `load_map`) is one NumPy ``.npz`` archive (deflated,
no pickled objects), written atomically (a temporary file renamed over the target, so a
crash never leaves half a map). It holds a `SavedMap`:

=====================  ==========================================================
``kind``               ``"floornav-map"``
``version``            int, `FORMAT_VERSION`
``log_odds``           (rows, cols) float32, in the `GroundGrid` raster convention
                       (row 0 at the largest x, column 0 at the largest y)
``grid_corner_m``      (x_max_m, y_max_m) float64, the raster's top-left corner
``grid_cell_m``        float64, cell size
``grid_shape``         (rows, cols) int64
``thresholds``         (free_threshold, occupied_threshold) float64
``pose``               (x_m, y_m, theta_rad) float64, the robot in the map's frame
``travelled_m``        float64, the robot's travel fused into the map
``confirmed_floor``    optional (rows, cols) uint8, 1 = floor confirmed by driving or
                       parallax (`app.mapping.floor_memory`)
``floor_appearances``  optional (k, 4) float32, learned floor colours (scaled CIELAB)
                       and the cells behind each; both or neither
``standing_marks``     optional (rows, cols) uint8, geometric tests that saw something
                       standing on each cell, net of those that saw floor there
``seen_foot_marks``    optional (rows, cols) uint8, of those, the ones that saw its
                       foot there (`app.mapping.floor_memory`); both or neither, and
                       only beside ``confirmed_floor``
``driven_floor``       optional (rows, cols) uint8, the cells the robot drove over:
                       bit 1 its footprint, bit 2 its centre's track
                       (`app.mapping.floor_memory`); only beside ``confirmed_floor``
``remembered``         optional (rows, cols) int8, each cell's last known class
                       before decay faded it (`OccupancyGrid.remembered`: -1 never
                       known, 0 free, 1 occupied); absent: what the map knows now
=====================  ==========================================================

`load_map` checks everything it reads and raises `MapFileError` with the reason; it
reads nothing into a grid, so a refused file leaves the current map as it was.

The ROS export (`export_ros_map`) is what ``map_server`` / ``nav2_map_server`` load: a
binary PGM (P5, 8 bits; occupied 0, free 254, unknown 205, as ``map_saver`` writes) and
a YAML description. ROS maps have x to the right and y up with the image's bottom-left
pixel at ``origin``, so image row 0 holds the largest y and image column 0 the smallest
x; the cells are the map as the daemon knows and plans on it (its own thresholds, faded
evidence at its last class), so the image shows what the daemon calls free and
occupied. `read_ros_map` reads such a pair back (a small reader for this flat YAML:
PyYAML is not a dependency).
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.fileio import write_bytes_atomic
from app.mapping.floor_memory import DRIVEN_FOOTPRINT, DRIVEN_TRACK, FloorMemoryState
from app.mapping.frames import GroundGrid, Pose2D, describe_grid, same_geometry
from app.mapping.occupancy import CLASSES, FREE, OCCUPIED, UNKNOWN, SavedMap

MAP_KIND = "floornav-map"
FORMAT_VERSION = 1
MAX_MAP_FILE_BYTES = 256 * 2**20
"""Files (and archive members, uncompressed) larger than this are refused unread: a
200 m x 200 m grid of 5 cm cells is 64 MB of float32."""

ROS_OCCUPIED = 0
ROS_FREE = 254
ROS_UNKNOWN = 205
"""Pixel values of `export_ros_map` (``map_saver``'s): black, white, grey."""
ROS_OCCUPIED_THRESH = 0.65
ROS_FREE_THRESH = 0.196

_PLAIN_YAML_NAME = re.compile(r"[A-Za-z0-9_./-]+")


class MapFileError(ValueError):
    """A map file that cannot be used; the message names the file and says why."""


# ------------------------------------------------------------------ floornav map files


def map_arrays(snapshot: SavedMap) -> dict[str, NDArray[np.generic]]:
    """The arrays of a map file (see the module docstring)."""
    grid = snapshot.world_grid
    pose = snapshot.T_world_robot
    arrays: dict[str, NDArray[np.generic]] = {
        "kind": np.array(MAP_KIND),
        "version": np.array(FORMAT_VERSION, dtype=np.int64),
        "log_odds": np.asarray(snapshot.log_odds, dtype=np.float32),
        "grid_corner_m": np.array([grid.x_max_m, grid.y_max_m], dtype=np.float64),
        "grid_cell_m": np.array(grid.cell_m, dtype=np.float64),
        "grid_shape": np.array(grid.shape, dtype=np.int64),
        "thresholds": np.array(
            [snapshot.free_threshold, snapshot.occupied_threshold], dtype=np.float64
        ),
        "pose": np.array([pose.x_m, pose.y_m, pose.theta_rad], dtype=np.float64),
        "travelled_m": np.array(snapshot.travelled_m, dtype=np.float64),
    }
    memory = snapshot.floor_memory
    if memory is not None:
        arrays["confirmed_floor"] = np.asarray(memory.confirmed, dtype=np.uint8)
        arrays["floor_appearances"] = np.asarray(memory.appearances, dtype=np.float32)
        if memory.standing_marks is not None and memory.seen_foot_marks is not None:
            arrays["standing_marks"] = np.asarray(memory.standing_marks, dtype=np.uint8)
            arrays["seen_foot_marks"] = np.asarray(memory.seen_foot_marks, dtype=np.uint8)
        if memory.driven is not None:
            arrays["driven_floor"] = np.asarray(memory.driven, dtype=np.uint8)
    if snapshot.remembered is not None:
        arrays["remembered"] = np.asarray(snapshot.remembered, dtype=np.int8)
    return arrays


def save_map(path: Path, snapshot: SavedMap) -> None:
    """Write ``snapshot`` (from `OccupancyGrid.snapshot` / `GroundMapper.snapshot`) to
    ``path`` atomically; `load_map` reads it back exactly."""
    if not isinstance(snapshot, SavedMap):
        raise ValueError(f"snapshot: expected a SavedMap, got {type(snapshot).__name__}")
    buffer = io.BytesIO()
    # Any: numpy's stub would check every array against savez's allow_pickle flag.
    arrays: dict[str, Any] = map_arrays(snapshot)
    np.savez_compressed(buffer, allow_pickle=False, **arrays)
    write_bytes_atomic(path, buffer.getvalue())


def load_map(
    path: Path, *, expected_grid: GroundGrid | None = None, max_bytes: int = MAX_MAP_FILE_BYTES
) -> SavedMap:
    """Read a map written by `save_map`.

    Parameters
    ----------
    path : the ``.npz`` file.
    expected_grid : the configured world grid; a map of another cell size or extent is
        refused before its cells are read.
    max_bytes : bound on the file's size (checked before reading) and on every array's
        uncompressed size.

    Raises
    ------
    MapFileError
        Missing or oversized file, not a floornav map, another format version, missing,
        misshapen or non-finite arrays, or a grid other than ``expected_grid`` (the message
        names both).
    """
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise MapFileError(f"{path}: map file not found") from None
    except OSError as exc:
        raise MapFileError(f"{path}: cannot read the map file ({exc})") from exc
    if not path.is_file():
        raise MapFileError(f"{path}: not a file")
    if size > max_bytes:
        raise MapFileError(f"{path}: {size} bytes, over the {max_bytes}-byte bound of a map file")
    try:
        archive = zipfile.ZipFile(path)
    except zipfile.BadZipFile as exc:
        raise MapFileError(
            f"{path}: not a floornav map file (not an .npz archive, or truncated: {exc})"
        ) from exc
    except OSError as exc:
        raise MapFileError(f"{path}: cannot read the map file ({exc})") from exc
    with archive:
        try:
            return _read_map(archive, path, expected_grid, max_bytes)
        except MapFileError:
            raise
        except (zipfile.BadZipFile, OSError, EOFError, zlib.error, ValueError) as exc:
            raise MapFileError(f"{path}: corrupt map file ({exc})") from exc


def _read_map(
    archive: zipfile.ZipFile, path: Path, expected_grid: GroundGrid | None, max_bytes: int
) -> SavedMap:
    def read(name: str) -> NDArray[np.generic]:
        try:
            info = archive.getinfo(f"{name}.npy")
        except KeyError:
            raise MapFileError(f"{path}: not a floornav map file (no {name!r} array)") from None
        if info.file_size > max_bytes:
            raise MapFileError(
                f"{path}: array {name!r} is {info.file_size} bytes, over the {max_bytes}-byte bound"
            )
        with archive.open(info) as member:
            return np.asarray(np.lib.format.read_array(member, allow_pickle=False))

    def floats(name: str, shape: tuple[int, ...]) -> NDArray[np.float64]:
        value = read(name)
        if value.shape != shape or value.dtype.kind not in "fi":
            raise MapFileError(
                f"{path}: {name!r} must be numbers of shape {shape}, got {value.dtype}"
                f" {value.shape}"
            )
        number = value.astype(np.float64)
        if not np.isfinite(number).all():
            raise MapFileError(f"{path}: {name!r} is not finite ({number.tolist()})")
        return number

    kind = read("kind")
    if kind.shape != () or kind.dtype.kind != "U" or str(kind) != MAP_KIND:
        raise MapFileError(f"{path}: not a floornav map file (kind {kind!r})")
    version = read("version")
    if version.shape != () or version.dtype.kind not in "iu":
        raise MapFileError(f"{path}: map format version is not an integer ({version!r})")
    if int(version) != FORMAT_VERSION:
        raise MapFileError(
            f"{path}: map format version {int(version)}; this floornav reads version"
            f" {FORMAT_VERSION}"
        )
    corner = floats("grid_corner_m", (2,))
    cell_m = float(floats("grid_cell_m", ()))
    shape_array = read("grid_shape")
    if shape_array.shape != (2,) or shape_array.dtype.kind not in "iu":
        raise MapFileError(f"{path}: 'grid_shape' must be two integers, got {shape_array!r}")
    shape = [int(n) for n in shape_array]
    if min(shape) < 1:
        raise MapFileError(f"{path}: 'grid_shape' must be positive, got {shape}")
    if not cell_m > 0:
        raise MapFileError(f"{path}: cell size must be > 0, got {cell_m}")
    grid = GroundGrid(float(corner[0]), float(corner[1]), cell_m, shape[0], shape[1])
    if expected_grid is not None and not same_geometry(grid, expected_grid):
        raise MapFileError(
            f"{path}: the map's grid is {describe_grid(grid)} but the configured grid is"
            f" {describe_grid(expected_grid)}"
        )
    log_odds = read("log_odds")
    if log_odds.dtype != np.float32 or log_odds.shape != grid.shape:
        raise MapFileError(
            f"{path}: 'log_odds' must be float32 of shape {grid.shape} (the grid's), got"
            f" {log_odds.dtype} {log_odds.shape}"
        )
    if not np.isfinite(log_odds).all():
        bad = int(np.count_nonzero(~np.isfinite(log_odds)))
        raise MapFileError(f"{path}: 'log_odds' has {bad} cells that are not finite")
    free_threshold, occupied_threshold = floats("thresholds", (2,))
    x_m, y_m, theta_rad = floats("pose", (3,))
    travelled = float(floats("travelled_m", ()))
    memory = _read_floor_memory(archive, read, path, grid)
    remembered = None
    if "remembered.npy" in archive.namelist():
        remembered = np.asarray(read("remembered"))
        if (
            remembered.dtype != np.int8
            or remembered.shape != grid.shape
            or not np.isin(remembered, CLASSES).all()
        ):
            raise MapFileError(
                f"{path}: 'remembered' must be int8 -1/0/1 of shape {grid.shape}, got"
                f" {remembered.dtype} {remembered.shape}"
            )
    try:
        return SavedMap(
            log_odds=np.asarray(log_odds, dtype=np.float32),
            world_grid=grid,
            free_threshold=float(free_threshold),
            occupied_threshold=float(occupied_threshold),
            T_world_robot=Pose2D(float(x_m), float(y_m), float(theta_rad)),
            travelled_m=travelled,
            floor_memory=memory,
            remembered=remembered,
        )
    except ValueError as exc:
        raise MapFileError(f"{path}: not a usable map ({exc})") from exc


def _read_floor_memory(
    archive: zipfile.ZipFile,
    read: Callable[[str], NDArray[np.generic]],
    path: Path,
    grid: GroundGrid,
) -> FloorMemoryState | None:
    names = set(archive.namelist())
    if not _pair_present(names, path, "confirmed_floor", "floor_appearances"):
        return None  # a map saved before the floor memory existed
    confirmed = _uint8_layer(read, path, "confirmed_floor", grid)
    table = np.asarray(read("floor_appearances"))
    counts = (
        np.asarray(table[:, 3], dtype=np.float64)
        if table.ndim == 2 and table.shape[1:] == (4,)
        else None
    )
    if (
        table.dtype != np.float32
        or table.ndim != 2
        or table.shape[1] != 4
        or counts is None
        or not np.isfinite(table.astype(np.float64)).all()
        or bool((counts <= 0).any())
    ):
        raise MapFileError(
            f"{path}: 'floor_appearances' must be finite float32 (k, 4) with cell counts"
            f" > 0, got {table.dtype} {table.shape}"
        )
    marks: tuple[NDArray[np.uint8] | None, NDArray[np.uint8] | None] = (None, None)
    if _pair_present(names, path, "standing_marks", "seen_foot_marks"):
        marks = (
            _uint8_layer(read, path, "standing_marks", grid),
            _uint8_layer(read, path, "seen_foot_marks", grid),
        )
    driven = _uint8_layer(read, path, "driven_floor", grid) if "driven_floor.npy" in names else None
    if driven is not None and (driven & ~np.uint8(DRIVEN_FOOTPRINT | DRIVEN_TRACK)).any():
        raise MapFileError(f"{path}: 'driven_floor' holds values above 3 (two bits per cell)")
    return FloorMemoryState(confirmed, np.asarray(table, dtype=np.float32), *marks, driven)


def _pair_present(names: set[str], path: Path, first: str, second: str) -> bool:
    """Whether the archive holds both arrays of a pair (neither: False); one alone is
    refused."""
    present = [n for n in (first, second) if f"{n}.npy" in names]
    if len(present) == 1:
        raise MapFileError(f"{path}: {present[0]!r} without its partner array")
    return bool(present)


def _uint8_layer(
    read: Callable[[str], NDArray[np.generic]], path: Path, name: str, grid: GroundGrid
) -> NDArray[np.uint8]:
    """A (rows, cols) uint8 layer of the map file, checked."""
    layer = read(name)
    if layer.dtype != np.uint8 or layer.shape != grid.shape:
        raise MapFileError(
            f"{path}: {name!r} must be uint8 of shape {grid.shape}, got {layer.dtype} {layer.shape}"
        )
    return np.asarray(layer, dtype=np.uint8)


# ------------------------------------------------------------------ ROS map_server


@dataclass(frozen=True, eq=False)
class RosMap:
    """A ROS map read back by `read_ros_map`.

    Attributes
    ----------
    image : (height, width) uint8, the PGM as stored (row 0 at the top: the largest y).
    cells : (world_grid.rows, world_grid.cols) int8 ``UNKNOWN`` / ``FREE`` / ``OCCUPIED``
        in the `GroundGrid` convention, classified as ``map_server`` does in trinary mode.
    world_grid : GroundGrid the cells lie on.
    resolution_m : float, metres per cell.
    origin : (x, y, yaw), the image's bottom-left corner in the map frame.
    """

    image: NDArray[np.uint8] = field(repr=False)
    cells: NDArray[np.int8] = field(repr=False)
    world_grid: GroundGrid
    resolution_m: float
    origin: tuple[float, float, float]


def ros_image(cells: NDArray[np.int8]) -> NDArray[np.uint8]:
    """(rows, cols) `GroundGrid`-convention classes -> (cols, rows) ROS image pixels.

    Grid row r has x decreasing with r, column c has y decreasing with c; the image's
    column j has x increasing with j and row i has y decreasing with i, so pixel (i, j) is
    cell (rows - 1 - j, i).

    >>> ros_image(np.array([[OCCUPIED, FREE], [UNKNOWN, UNKNOWN]], np.int8)).tolist()
    [[205, 0], [205, 254]]
    """
    pixels = np.full(cells.shape, ROS_UNKNOWN, dtype=np.uint8)
    pixels[cells == FREE] = ROS_FREE
    pixels[cells == OCCUPIED] = ROS_OCCUPIED
    return np.ascontiguousarray(pixels.T[:, ::-1])


def ros_origin(grid: GroundGrid) -> tuple[float, float, float]:
    """The ROS ``origin`` of a grid: its lower-left corner (smallest x and y), yaw 0,
    rounded to the nanometre (so float noise like ``2 - 60 * 0.05`` does not reach the
    YAML)."""
    x0 = round(grid.x_max_m - grid.rows * grid.cell_m, 9)
    y0 = round(grid.y_max_m - grid.cols * grid.cell_m, 9)
    return (x0 + 0.0, y0 + 0.0, 0.0)  # + 0.0 turns -0.0 into 0.0


def ros_map_yaml(image_name: str, grid: GroundGrid) -> str:
    """The map_server YAML for an image of ``grid`` (floats written to round-trip)."""
    x0, y0, yaw = ros_origin(grid)
    name = image_name if _PLAIN_YAML_NAME.fullmatch(image_name) else json.dumps(image_name)
    return (
        f"image: {name}\n"
        f"resolution: {grid.cell_m!r}\n"
        f"origin: [{x0!r}, {y0!r}, {yaw!r}]\n"
        "negate: 0\n"
        f"occupied_thresh: {ROS_OCCUPIED_THRESH}\n"
        f"free_thresh: {ROS_FREE_THRESH}\n"
        "mode: trinary\n"
    )


def pgm_bytes(image: NDArray[np.uint8], comment: str = "") -> bytes:
    """A binary (P5) 8-bit PGM of ``image`` (row 0 at the top)."""
    height, width = image.shape
    header = "P5\n" + (f"# {comment}\n" if comment else "") + f"{width} {height}\n255\n"
    return header.encode("ascii") + np.ascontiguousarray(image, dtype=np.uint8).tobytes()


def export_ros_map(pgm_path: Path, yaml_path: Path, snapshot: SavedMap) -> None:
    """Write ``snapshot`` as a ROS map_server map: the PGM, then the YAML naming it
    (relative to the YAML's folder), each atomically.

    The cells are the map as the robot knows it (`SavedMap.remembered_classes`: its
    thresholds, faded cells at their last class, as the robot plans on them): occupied
    -> 0, free -> 254, unknown -> 205; with ``negate: 0`` and the YAML's
    ``occupied_thresh: 0.65`` / ``free_thresh: 0.196`` map_server reads the same classes.
    """
    if not isinstance(snapshot, SavedMap):
        raise ValueError(f"snapshot: expected a SavedMap, got {type(snapshot).__name__}")
    image = ros_image(snapshot.remembered_classes())
    pose = snapshot.T_world_robot
    comment = (
        f"floornav map; robot at x {pose.x_m:.3f} m, y {pose.y_m:.3f} m,"
        f" theta {pose.theta_rad:.3f} rad"
    )
    image_name = os.path.relpath(pgm_path.resolve(), yaml_path.resolve().parent)
    write_bytes_atomic(pgm_path, pgm_bytes(image, comment))
    write_bytes_atomic(yaml_path, ros_map_yaml(image_name, snapshot.world_grid).encode())


def read_ros_map(yaml_path: Path, *, max_bytes: int = MAX_MAP_FILE_BYTES) -> RosMap:
    """Read a ROS map_server map (YAML and its PGM) and classify its cells as map_server
    does: occupancy ``p = (255 - v) / 255`` (``v / 255`` with ``negate: 1``), occupied
    when ``p > occupied_thresh``, free when ``p < free_thresh``, else unknown.

    Raises
    ------
    MapFileError
        Missing or oversized files, YAML without ``image`` / ``resolution`` / ``origin``,
        a rotated origin, ``mode: raw``, or an image that is not a binary 8-bit PGM.
    """
    doc = parse_flat_yaml(_read_bounded(yaml_path, max_bytes, "map YAML"), yaml_path)
    for key in ("image", "resolution", "origin"):
        if key not in doc:
            raise MapFileError(f"{yaml_path}: map YAML lacks {key!r}")
    image_name = doc["image"]
    if not isinstance(image_name, str) or not image_name:
        raise MapFileError(f"{yaml_path}: 'image' must name the image file, got {image_name!r}")
    resolution = _yaml_number(doc, "resolution", yaml_path)
    negate = _yaml_number(doc, "negate", yaml_path, default=0)
    occupied_thresh = _yaml_number(doc, "occupied_thresh", yaml_path, ROS_OCCUPIED_THRESH)
    free_thresh = _yaml_number(doc, "free_thresh", yaml_path, ROS_FREE_THRESH)
    origin = doc["origin"]
    if not (isinstance(origin, list) and len(origin) == 3):
        raise MapFileError(f"{yaml_path}: 'origin' must be [x, y, yaw], got {origin!r}")
    x0, y0, yaw = origin
    if not resolution > 0:
        raise MapFileError(f"{yaml_path}: 'resolution' must be > 0, got {resolution}")
    if not all(math.isfinite(v) for v in origin):
        raise MapFileError(f"{yaml_path}: 'origin' must be finite, got {origin}")
    if yaw != 0.0:
        raise MapFileError(f"{yaml_path}: a rotated origin (yaw {yaw}) is not supported")
    if doc.get("mode", "trinary") not in ("trinary", "scale"):
        raise MapFileError(f"{yaml_path}: mode {doc.get('mode')!r} is not supported")
    image_path = Path(image_name)
    if not image_path.is_absolute():
        image_path = yaml_path.parent / image_path
    image, maxval = parse_pgm(_read_bounded(image_path, max_bytes, "map image"), image_path)
    occupancy = image.astype(np.float64) / maxval
    if not negate:
        occupancy = 1.0 - occupancy
    classes = np.full(image.shape, UNKNOWN, dtype=np.int8)
    classes[occupancy < free_thresh] = FREE
    classes[occupancy > occupied_thresh] = OCCUPIED
    height, width = image.shape
    grid = GroundGrid(x0 + width * resolution, y0 + height * resolution, resolution, width, height)
    # Inverse of `ros_image`: cell (r, c) is pixel (c, rows - 1 - r).
    cells = np.ascontiguousarray(classes.T[::-1, :])
    return RosMap(image, cells, grid, resolution, (x0, y0, yaw))


def _yaml_number(
    doc: dict[str, YamlValue], key: str, source: Path, default: float | None = None
) -> float:
    value = doc.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise MapFileError(f"{source}: {key!r} must be a finite number, got {value!r}")
    return float(value)


def _read_bounded(path: Path, max_bytes: int, what: str) -> bytes:
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise MapFileError(f"{path}: {size} bytes, over the {max_bytes}-byte bound of a {what}")
        return path.read_bytes()
    except FileNotFoundError:
        raise MapFileError(f"{path}: {what} not found") from None
    except OSError as exc:
        raise MapFileError(f"{path}: cannot read the {what} ({exc})") from exc


YamlValue = str | int | float | list[float]


def parse_flat_yaml(data: bytes, source: Path) -> dict[str, YamlValue]:
    """``key: value`` lines (``#`` comments, blank lines) as map_server YAML files have
    them: numbers, flow lists of numbers (``[x, y, yaw]``), plain or quoted strings."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MapFileError(f"{source}: map YAML is not UTF-8 text") from exc
    doc: dict[str, YamlValue] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        key, sep, value = line.partition(":")
        if not sep or not key.strip():
            raise MapFileError(f"{source}:{number}: expected 'key: value', got {raw!r}")
        doc[key.strip()] = _yaml_value(value.strip(), source, number)
    return doc


def _yaml_value(text: str, source: Path, line: int) -> YamlValue:
    if text[:1] in ('"', "'"):
        quote = text[0]
        end = text.find(quote, 1)
        if end < 0:
            raise MapFileError(f"{source}:{line}: unterminated string {text!r}")
        if quote == '"':
            try:
                return str(json.loads(text[: end + 1]))
            except json.JSONDecodeError as exc:
                raise MapFileError(f"{source}:{line}: bad string {text!r}") from exc
        return text[1:end]
    text = text.split(" #", 1)[0].strip()
    if text.startswith("["):
        if not text.endswith("]"):
            raise MapFileError(f"{source}:{line}: unterminated list {text!r}")
        try:
            return [float(item) for item in text[1:-1].split(",") if item.strip()]
        except ValueError as exc:
            raise MapFileError(
                f"{source}:{line}: expected a list of numbers, got {text!r}"
            ) from exc
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def parse_pgm(data: bytes, source: Path) -> tuple[NDArray[np.uint8], int]:
    """A binary 8-bit PGM (P5, maxval <= 255) -> ((height, width) uint8, maxval)."""
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            end = data.find(b"\n", pos)
            pos = len(data) if end < 0 else end + 1
            continue
        start = pos
        while pos < len(data) and not data[pos : pos + 1].isspace() and data[pos : pos + 1] != b"#":
            pos += 1
        if start == pos:
            raise MapFileError(f"{source}: truncated PGM header")
        tokens.append(data[start:pos])
    if tokens[0] != b"P5":
        raise MapFileError(f"{source}: not a binary PGM (magic {tokens[0]!r}, expected b'P5')")
    try:
        width, height, maxval = (int(t) for t in tokens[1:])
    except ValueError as exc:
        raise MapFileError(f"{source}: bad PGM header ({exc})") from exc
    if width < 1 or height < 1 or not 1 <= maxval <= 255:
        raise MapFileError(
            f"{source}: PGM must be at least 1x1 with maxval 1..255, got {width}x{height}"
            f" maxval {maxval}"
        )
    pixels = data[pos + 1 :]  # exactly one whitespace byte ends the header
    if len(pixels) != width * height:
        raise MapFileError(
            f"{source}: PGM holds {len(pixels)} pixel bytes, expected {width}x{height}"
            f" = {width * height}"
        )
    image = np.frombuffer(pixels, dtype=np.uint8).reshape(height, width).copy()
    if int(image.max()) > maxval:
        raise MapFileError(f"{source}: PGM pixel {int(image.max())} exceeds maxval {maxval}")
    return image, maxval
