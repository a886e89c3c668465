"""Map files: floornav's saved map (exact round trip, refusals that leave the map alone)
and the ROS map_server export (read back cell for cell, in the right orientation)."""

from __future__ import annotations

import math
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.mapping.frames import FLOOR, NOT_FLOOR, UNSEEN, GroundGrid, Pose2D, same_geometry
from app.mapping.map_files import (
    FORMAT_VERSION,
    MAX_MAP_FILE_BYTES,
    ROS_FREE,
    ROS_OCCUPIED,
    ROS_UNKNOWN,
    MapFileError,
    export_ros_map,
    load_map,
    map_arrays,
    read_ros_map,
    ros_origin,
    save_map,
)
from app.mapping.occupancy import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    OccupancyGrid,
    OccupancyParams,
    SavedMap,
)

# A world that is neither square nor centred, so flips and swapped axes show:
# x -1..2 m (60 rows), y -0.5..1.5 m (40 columns), 5 cm cells.
WORLD = GroundGrid.covering(x_min_m=-1.0, x_max_m=2.0, y_min_m=-0.5, y_max_m=1.5, cell_m=0.05)
PATCH = GroundGrid.covering(x_min_m=0.0, x_max_m=1.0, y_min_m=-0.5, y_max_m=0.5, cell_m=0.01)
POSE = Pose2D(0.3, 0.4, 0.7)


def mapped_grid() -> OccupancyGrid:
    """A grid with free, occupied and unknown cells, seen from ``POSE`` after some travel."""
    grid = OccupancyGrid(WORLD, OccupancyParams(obstacle_band_m=0.025, half_distance_m=5.0))
    x, _ = PATCH.cell_centers()
    wall = np.where(x < 0.6, FLOOR, NOT_FLOOR).astype(np.uint8)
    for pose in (Pose2D(0.0, 0.4, 0.7), Pose2D(0.15, 0.4, 0.7), POSE):
        grid.update(wall, PATCH, pose, (0.0, 0.0))
    return grid


@pytest.fixture
def snapshot() -> SavedMap:
    return mapped_grid().snapshot()


def test_save_then_load_gives_the_same_map_exactly(tmp_path: Path, snapshot: SavedMap) -> None:
    path = tmp_path / "maps" / "home.npz"
    save_map(path, snapshot)
    assert [p.name for p in path.parent.iterdir()] == ["home.npz"]  # no temporary file left
    loaded = load_map(path, expected_grid=WORLD)
    assert loaded.log_odds.dtype == np.float32
    np.testing.assert_array_equal(loaded.log_odds, snapshot.log_odds)
    assert (loaded.log_odds != 0).sum() > 100 and (loaded.classify() == OCCUPIED).any()
    assert loaded.world_grid == WORLD
    assert loaded.T_world_robot == POSE
    assert loaded.travelled_m == snapshot.travelled_m == pytest.approx(0.3)
    assert (loaded.free_threshold, loaded.occupied_threshold) == (-0.5, 0.5)

    # Into a fresh grid, which then continues where the saved one stopped.
    fresh = OccupancyGrid(WORLD, OccupancyParams(obstacle_band_m=0.025, half_distance_m=5.0))
    fresh.restore(loaded)
    np.testing.assert_array_equal(fresh.log_odds, snapshot.log_odds)
    again = tmp_path / "again.npz"
    save_map(again, fresh.snapshot())
    np.testing.assert_array_equal(load_map(again).log_odds, snapshot.log_odds)


def test_the_remembered_classes_survive_a_save(tmp_path: Path, snapshot: SavedMap) -> None:
    assert snapshot.remembered is not None and (snapshot.remembered != UNKNOWN).any()
    path = tmp_path / "remembered.npz"
    save_map(path, snapshot)
    loaded = load_map(path)
    assert loaded.remembered is not None
    np.testing.assert_array_equal(loaded.remembered, snapshot.remembered)
    # A file from before the layer loads without it; a bad layer is refused.
    write_npz(tmp_path / "old.npz", with_changes(snapshot, remembered=None))
    assert load_map(tmp_path / "old.npz").remembered is None
    bad = np.full((60, 40), 2, np.int8)
    write_npz(tmp_path / "bad.npz", with_changes(snapshot, remembered=bad))
    with pytest.raises(MapFileError, match="'remembered' must be int8 -1/0/1"):
        load_map(tmp_path / "bad.npz")

    # Saving over an existing map replaces it.
    save_map(path, OccupancyGrid(WORLD).snapshot())
    assert not load_map(path).log_odds.any()


def write_npz(path: Path, arrays: dict[str, Any]) -> Path:
    np.savez_compressed(path, **arrays)
    return path


def write_text(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def with_changes(snapshot: SavedMap, **changes: Any) -> dict[str, Any]:
    arrays: dict[str, Any] = dict(map_arrays(snapshot))
    for key, value in changes.items():
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value
    return arrays


def nan_cell(snapshot: SavedMap) -> np.ndarray:
    log_odds = np.array(snapshot.log_odds)
    log_odds[5, 7] = np.nan
    return log_odds


BAD_FILES: dict[str, tuple[Callable[[Path, SavedMap], Path], str]] = {
    "missing": (lambda d, s: d / "nope.npz", "map file not found"),
    "a folder": (lambda d, s: d, "not a file"),
    "text": (lambda d, s: write_text(d / "notes.npz", "hello"), "not an .npz archive"),
    "another npz": (
        lambda d, s: write_npz(d / "other.npz", {"weights": np.zeros(3)}),
        "no 'kind' array",
    ),
    "wrong kind": (
        lambda d, s: write_npz(d / "k.npz", with_changes(s, kind=np.array("floornav-route"))),
        "not a floornav map file",
    ),
    "newer version": (
        lambda d, s: write_npz(d / "v.npz", with_changes(s, version=np.array(2))),
        f"map format version 2; this floornav reads version {FORMAT_VERSION}",
    ),
    "no log-odds": (
        lambda d, s: write_npz(d / "n.npz", with_changes(s, log_odds=None)),
        "no 'log_odds' array",
    ),
    "misshapen log-odds": (
        lambda d, s: write_npz(d / "m.npz", with_changes(s, log_odds=np.zeros((60, 39), "f4"))),
        r"'log_odds' must be float32 of shape \(60, 40\)",
    ),
    "float64 log-odds": (
        lambda d, s: write_npz(
            d / "f.npz", with_changes(s, log_odds=np.asarray(s.log_odds, np.float64))
        ),
        "must be float32",
    ),
    "NaN cell": (
        lambda d, s: write_npz(d / "nan.npz", with_changes(s, log_odds=nan_cell(s))),
        "1 cells that are not finite",
    ),
    "NaN pose": (
        lambda d, s: write_npz(d / "p.npz", with_changes(s, pose=np.array([0.0, np.nan, 0.0]))),
        "'pose' is not finite",
    ),
    "short pose": (
        lambda d, s: write_npz(d / "p2.npz", with_changes(s, pose=np.array([0.0, 1.0]))),
        r"'pose' must be numbers of shape \(3,\)",
    ),
    "crossed thresholds": (
        lambda d, s: write_npz(d / "t.npz", with_changes(s, thresholds=np.array([0.5, -0.5]))),
        "free_threshold <= occupied_threshold",
    ),
    "pickled array": (
        lambda d, s: write_npz(
            d / "o.npz", with_changes(s, log_odds=np.array([{"x": 1}], dtype=object))
        ),
        "corrupt map file",
    ),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_map_files_are_refused_with_the_reason_and_leave_the_map_alone(
    case: str, tmp_path: Path, snapshot: SavedMap
) -> None:
    make, reason = BAD_FILES[case]
    path = make(tmp_path, snapshot)
    current = mapped_grid()
    before = current.log_odds.copy()
    with pytest.raises(MapFileError, match=reason) as info:
        current.restore(load_map(path, expected_grid=WORLD))
    assert str(path) in str(info.value)
    np.testing.assert_array_equal(current.log_odds, before)
    assert current.snapshot().T_world_robot == POSE


def test_truncated_and_corrupted_files_are_refused(tmp_path: Path, snapshot: SavedMap) -> None:
    path = tmp_path / "map.npz"
    save_map(path, snapshot)
    data = path.read_bytes()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(MapFileError, match="truncated"):
        load_map(truncated)
    # Flip bytes inside the deflated log-odds: a CRC or inflate error, never a silent map.
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("log_odds.npy")
    data_start = info.header_offset + 100  # past the local header (with its zip64 extra)
    assert info.compress_size > 150
    corrupt = bytearray(data)
    for k in range(data_start, data_start + 50, 5):
        corrupt[k] ^= 0xFF
    damaged = tmp_path / "damaged.npz"
    damaged.write_bytes(bytes(corrupt))
    with pytest.raises(MapFileError, match="corrupt map file"):
        load_map(damaged)


def test_oversized_files_are_refused_before_reading(tmp_path: Path, snapshot: SavedMap) -> None:
    path = tmp_path / "map.npz"
    save_map(path, snapshot)
    size = path.stat().st_size
    with pytest.raises(MapFileError, match=f"{size} bytes, over the 100-byte bound"):
        load_map(path, max_bytes=100)
    # A small file whose arrays would inflate beyond the bound (60 x 40 float32 + header).
    assert size < 9000
    with pytest.raises(MapFileError, match="array 'log_odds' is 9728 bytes"):
        load_map(path, max_bytes=9000)
    # A huge (sparse) file is refused from its size alone.
    huge = tmp_path / "huge.npz"
    with huge.open("wb") as handle:
        handle.truncate(MAX_MAP_FILE_BYTES + 1)
    with pytest.raises(MapFileError, match=r"over the \d+-byte bound"):
        load_map(huge)


def test_a_map_of_another_grid_is_refused_naming_both(tmp_path: Path, snapshot: SavedMap) -> None:
    path = tmp_path / "map.npz"
    save_map(path, snapshot)
    finer = GroundGrid.covering(x_min_m=-1.0, x_max_m=2.0, y_min_m=-0.5, y_max_m=1.5, cell_m=0.025)
    with pytest.raises(MapFileError) as info:
        load_map(path, expected_grid=finer)
    message = str(info.value)
    assert "the map's grid is 60 x 40 cells of 0.05 m over x [-1, 2] m, y [-0.5, 1.5] m" in message
    assert "the configured grid is 120 x 80 cells of 0.025 m" in message
    bigger = OccupancyGrid.square(20.0, 0.05).world_grid
    with pytest.raises(MapFileError, match=r"configured grid is 400 x 400 cells of 0.05 m over"):
        load_map(path, expected_grid=bigger)
    shifted = GroundGrid(WORLD.x_max_m + 0.05, WORLD.y_max_m, 0.05, WORLD.rows, WORLD.cols)
    with pytest.raises(MapFileError, match=r"x \[-0.95, 2.05\] m"):
        load_map(path, expected_grid=shifted)


# ------------------------------------------------------------------------------ ROS


def test_ros_export_reads_back_as_the_grids_classification(
    tmp_path: Path, snapshot: SavedMap
) -> None:
    pgm, yaml = tmp_path / "home.pgm", tmp_path / "home.yaml"
    export_ros_map(pgm, yaml, snapshot)
    assert pgm.read_bytes().startswith(b"P5\n")
    assert yaml.read_text() == (
        "image: home.pgm\n"
        "resolution: 0.05\n"
        "origin: [-1.0, -0.5, 0.0]\n"
        "negate: 0\n"
        "occupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
        "mode: trinary\n"
    )
    ros = read_ros_map(yaml)
    classes = snapshot.remembered_classes()
    assert {FREE, OCCUPIED, UNKNOWN} <= set(np.unique(classes).tolist())
    np.testing.assert_array_equal(ros.cells, classes)
    assert same_geometry(ros.world_grid, WORLD)
    assert ros.resolution_m == 0.05 and ros.origin == ros_origin(WORLD) == (-1.0, -0.5, 0.0)
    assert ros.image.shape == (40, 60)  # height spans y, width spans x
    assert set(np.unique(ros.image).tolist()) == {ROS_OCCUPIED, ROS_UNKNOWN, ROS_FREE}
    assert (ros.image == ROS_OCCUPIED).sum() == (classes == OCCUPIED).sum()


def test_ros_export_keeps_the_floor_that_travel_faded(tmp_path: Path) -> None:
    # The robot saw the floor and the wall, then drove 20 m: the evidence faded to
    # unknown, and the exported map still shows what the robot explored.
    grid = mapped_grid()
    seen = grid.remembered_classes()
    grid.update(np.full(PATCH.shape, UNSEEN, np.uint8), PATCH, Pose2D(0.3, 20.4, 0.7), (0.0, 0.0))
    faded = grid.snapshot()
    assert (faded.classify() == UNKNOWN).all()
    export_ros_map(tmp_path / "m.pgm", tmp_path / "m.yaml", faded)
    ros = read_ros_map(tmp_path / "m.yaml")
    np.testing.assert_array_equal(ros.cells, seen)
    assert (seen == FREE).sum() > 100 and (seen == OCCUPIED).sum() > 10


def test_ros_export_puts_a_known_cell_at_the_right_pixel(tmp_path: Path) -> None:
    grid = OccupancyGrid(WORLD)
    occupied_xy, free_xy = (1.62, 1.13), (-0.88, -0.41)
    for (x, y), value in ((occupied_xy, 2.0), (free_xy, -2.0)):
        (row, col), *_ = WORLD.cell_of(np.array([[x, y]]))
        grid.log_odds[row, col] = value
    maps = tmp_path / "maps"
    maps.mkdir()
    yaml = tmp_path / "config" / "home.yaml"
    export_ros_map(maps / "home.pgm", yaml, grid.snapshot())
    assert "image: ../maps/home.pgm\n" in yaml.read_text()
    ros = read_ros_map(yaml)
    # The ROS convention, computed here without floornav's code: column j covers
    # x in origin_x + [j, j + 1) * resolution; the bottom image row covers the smallest y.
    ox, oy, _ = ros.origin
    height = ros.image.shape[0]
    pixels = []
    for x, y in (occupied_xy, free_xy):
        j = math.floor((x - ox) / ros.resolution_m)
        i = height - 1 - math.floor((y - oy) / ros.resolution_m)
        pixels.append((i, j))
    assert pixels == [(7, 52), (38, 2)]  # top right, bottom left
    assert ros.image[7, 52] == ROS_OCCUPIED and ros.image[38, 2] == ROS_FREE
    assert (ros.image != ROS_UNKNOWN).sum() == 2
    (row, col), *_ = WORLD.cell_of(np.array([occupied_xy]))
    assert ros.cells[row, col] == OCCUPIED


def test_read_ros_map_handles_map_saver_style_files(tmp_path: Path) -> None:
    pixels = np.array([[0, 254, 205], [100, 250, 0]], np.uint8)  # 3 wide, 2 high
    (tmp_path / "my map.pgm").write_bytes(
        b"P5\n# CREATOR: map_saver.cpp 0.050 m/pix\n3 2\n255\n" + pixels.tobytes()
    )
    yaml = tmp_path / "my map.yaml"
    yaml.write_text(
        '# saved by hand\nimage: "my map.pgm"\nresolution: 0.5  # metres\n'
        "origin: [1.0, 2.0, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    ros = read_ros_map(yaml)
    # Image (i, j) -> cell (rows - 1 - j, i): x grows along the image's width.
    assert ros.cells.tolist() == [[UNKNOWN, OCCUPIED], [FREE, FREE], [OCCUPIED, UNKNOWN]]
    assert ros.world_grid == GroundGrid(2.5, 3.0, 0.5, 3, 2)


@pytest.mark.parametrize(
    ("yaml_text", "pgm", "reason"),
    [
        ("resolution: 0.05\norigin: [0, 0, 0]\n", b"", "lacks 'image'"),
        ("image: m.pgm\norigin: [0, 0, 0]\n", b"", "lacks 'resolution'"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0]\n", b"", r"\[x, y, yaw\]"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0.5]\n", b"", "rotated origin"),
        ("image: m.pgm\nresolution: -1\norigin: [0, 0, 0]\n", b"", "must be > 0"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nmode: raw\n", b"", "mode 'raw'"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", b"P2\n1 1\n255\n0\n", "P5"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", b"P5\n2 2\n255\n\x00", "expected"),
        ("image: gone.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n", b"", "map image not found"),
        ("just words\n", b"", "expected 'key: value'"),
    ],
)
def test_bad_ros_maps_are_refused_with_the_reason(
    tmp_path: Path, yaml_text: str, pgm: bytes, reason: str
) -> None:
    yaml = tmp_path / "m.yaml"
    yaml.write_text(yaml_text)
    (tmp_path / "m.pgm").write_bytes(pgm)
    with pytest.raises(MapFileError, match=reason):
        read_ros_map(yaml)
    with pytest.raises(MapFileError, match="map YAML not found"):
        read_ros_map(tmp_path / "nope.yaml")
