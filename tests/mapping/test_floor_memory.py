"""The confirmed-floor layer and the learned floor appearances (exact answers on small
synthetic grids)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.mapping.floor_memory import (
    FloorMemory,
    FloorMemoryParams,
    FloorMemoryState,
    bgr_to_scaled_lab,
    patch_world_index,
)
from app.mapping.frames import FLOOR, NOT_FLOOR, UNSEEN, GroundGrid, Pose2D
from app.mapping.map_files import MapFileError, load_map, save_map
from app.mapping.occupancy import FREE, OCCUPIED, OccupancyGrid, OccupancyParams

WORLD = GroundGrid.covering(x_min_m=-2.0, x_max_m=2.0, y_min_m=-2.0, y_max_m=2.0, cell_m=0.05)
PATCH = GroundGrid.covering(x_min_m=0.1, x_max_m=1.6, y_min_m=-0.5, y_max_m=0.5, cell_m=0.01)
TILE_BGR = (190, 200, 207)


def patch_x() -> np.ndarray:
    return PATCH.cell_centers()[0]


def threshold_patch() -> np.ndarray:
    """Floor up to x = 0.8 m, a 10 cm strip the colour method calls not-floor, floor."""
    patch = np.full(PATCH.shape, FLOOR, np.uint8)
    x = patch_x()
    patch[(x >= 0.8) & (x < 0.9)] = NOT_FLOOR
    return patch


def world_cell(xy: tuple[float, float]) -> tuple[int, int]:
    r, c = WORLD.cell_of(np.array([xy]))[0]
    return int(r), int(c)


def test_patch_index_matches_the_grids_own_cell_lookup() -> None:
    pose = Pose2D(0.3, -0.2, 0.7)
    index = patch_world_index(PATCH, WORLD, pose)
    x, y = PATCH.cell_centers()
    world_xy = pose.apply(np.column_stack([x.ravel(), y.ravel()]))
    rc = WORLD.cell_of(world_xy)
    assert np.array_equal(index.ravel(), rc[:, 0] * WORLD.cols + rc[:, 1])


def test_a_threshold_crossed_becomes_free_and_stays_free() -> None:
    grid = OccupancyGrid(WORLD, OccupancyParams(half_distance_m=float("inf")))
    memory = FloorMemory(WORLD)
    start = Pose2D(-1.0, 0.0, 0.0)
    strip = world_cell((-1.0 + 0.81, 0.0))

    def look(pose: Pose2D) -> int:
        patch = threshold_patch()
        # The strip is fixed in the world: shift it in the robot frame as the robot moves.
        shift = pose.x_m - start.x_m
        x = patch_x()
        patch[:] = FLOOR
        patch[(x + shift >= 0.8) & (x + shift < 0.9)] = NOT_FLOOR
        changed = memory.correct_patch(patch, patch_world_index(PATCH, WORLD, pose))
        grid.update(patch, PATCH, pose, (0.0, 0.0))
        return changed

    assert look(start) == 0
    assert grid.classify()[strip] == OCCUPIED  # before: the colour edge is a wall
    # The robot drives across the strip; its footprint confirms the floor under it.
    for k in range(1, 21):
        pose = Pose2D(start.x_m + 0.05 * k, 0.0, 0.0)
        memory.drive_over(pose, 0.12)
    assert memory.confirmed[strip] == 1
    back = start
    for _ in range(6):
        assert look(back) > 0
    assert grid.classify()[strip] == FREE
    for _ in range(20):
        look(back)
    assert grid.classify()[strip] == FREE


def test_a_box_on_confirmed_floor_becomes_occupied_once_seen_standing() -> None:
    grid = OccupancyGrid(WORLD, OccupancyParams(half_distance_m=float("inf")))
    memory = FloorMemory(WORLD)
    pose = Pose2D(-1.0, 0.0, 0.0)
    index = patch_world_index(PATCH, WORLD, pose)
    memory.confirm_cells(index.ravel())
    box = world_cell((-1.0 + 1.0, 0.0))
    x, y = PATCH.cell_centers()
    box_cells = (np.abs(x - 1.0) < 0.05) & (np.abs(y) < 0.05)

    def look() -> None:
        patch = np.full(PATCH.shape, FLOOR, np.uint8)
        patch[(x >= 0.95) & (np.abs(y) < 0.05)] = NOT_FLOOR  # the box and its shadow
        memory.correct_patch(patch, index)
        grid.update(patch, PATCH, pose, (0.0, 0.0))

    for _ in range(3):
        look()
    assert grid.classify()[box] == FREE  # colour alone does not undo confirmed floor
    memory.mark_standing(index[box_cells])
    assert memory.confirmed[box] == 0
    for _ in range(8):
        look()
    assert grid.classify()[box] == OCCUPIED


def test_known_share_counts_confirmed_cells_and_not_marked_or_off_map_ones() -> None:
    memory = FloorMemory(WORLD, FloorMemoryParams(standing_min_marks=1))
    cells = np.arange(10, dtype=np.int64)
    memory.confirm_cells(cells[:6])
    assert memory.known_share(cells) == 0.6
    memory.mark_standing(cells[:1])  # seen standing: no longer known floor
    assert memory.known_share(cells) == 0.5
    # Off the map counts as not known; nothing asked, nothing known.
    assert memory.known_share(np.array([1, 2, -1, -1], dtype=np.int64)) == 0.5
    assert memory.known_share(np.zeros(0, dtype=np.int64)) == 0.0


def uniform_patch_bgr(bgr: tuple[int, int, int]) -> np.ndarray:
    return np.broadcast_to(np.array(bgr, np.uint8), (*PATCH.shape, 3)).copy()


def test_confirmed_floor_teaches_its_colour_and_a_standing_colour_is_unlearned() -> None:
    memory = FloorMemory(WORLD, FloorMemoryParams(min_cells=40))
    pose = Pose2D(-1.0, 0.0, 0.0)
    index = patch_world_index(PATCH, WORLD, pose)
    patch = np.full(PATCH.shape, NOT_FLOOR, np.uint8)
    near = np.ones(PATCH.shape, bool)
    memory.observe_colours(uniform_patch_bgr(TILE_BGR), patch, index, near)
    assert memory.appearances() == ()
    x, y = PATCH.cell_centers()
    few = index[(x < 0.3) & (np.abs(y) < 0.1)]
    memory.confirm_cells(few)
    assert memory.appearances() == ()  # 4 x 4 cells: not yet a material
    memory.confirm_cells(index.ravel())
    learned = memory.appearances()
    assert len(learned) == 1
    expected = bgr_to_scaled_lab(np.array([TILE_BGR], np.float32))[0]
    assert np.allclose(learned[0], expected, atol=0.04)
    # Confirming the same cells again teaches nothing more.
    cells_before = memory.appearance_cells().copy()
    memory.confirm_cells(index.ravel())
    assert np.array_equal(memory.appearance_cells(), cells_before)
    # A box of that colour is seen standing over enough cells: the colour is unlearned.
    memory.mark_standing(index.ravel())
    assert memory.appearances() == ()
    assert memory.unlearned == 1


def test_unseen_cells_teach_nothing() -> None:
    memory = FloorMemory(WORLD, FloorMemoryParams(min_cells=1))
    index = patch_world_index(PATCH, WORLD, Pose2D(-1.0, 0.0, 0.0))
    patch = np.full(PATCH.shape, UNSEEN, np.uint8)
    memory.observe_colours(uniform_patch_bgr(TILE_BGR), patch, index, np.ones(PATCH.shape, bool))
    memory.confirm_cells(index.ravel())
    assert memory.appearances() == ()


def test_the_memory_is_saved_with_the_map(tmp_path: Path) -> None:
    grid = OccupancyGrid(WORLD)
    memory = FloorMemory(WORLD, FloorMemoryParams(min_cells=1))
    index = patch_world_index(PATCH, WORLD, Pose2D())
    memory.observe_colours(
        uniform_patch_bgr(TILE_BGR),
        np.full(PATCH.shape, FLOOR, np.uint8),
        index,
        np.ones(PATCH.shape, bool),
    )
    memory.confirm_cells(index.ravel())
    from dataclasses import replace

    snapshot = replace(grid.snapshot(), floor_memory=memory.state())
    save_map(tmp_path / "m.npz", snapshot)
    loaded = load_map(tmp_path / "m.npz")
    assert loaded.floor_memory is not None
    again = FloorMemory(WORLD, FloorMemoryParams(min_cells=1))
    again.restore(loaded.floor_memory)
    assert np.array_equal(again.confirmed, memory.confirmed)
    assert again.appearances() == memory.appearances()


def test_what_stands_is_saved_with_the_map_and_a_map_without_it_still_loads(
    tmp_path: Path,
) -> None:
    # A wall's foot seen in two tests, and a foot placed once where a frame's floor ended.
    grid = OccupancyGrid(WORLD)
    memory = FloorMemory(WORLD)
    wall, once = np.array([5, 6, 7], np.int64), np.array([40], np.int64)
    for _ in range(2):
        memory.mark_standing(wall)
    memory.mark_standing(once, seen_cells=np.zeros(0, np.int64))
    assert memory.standing.reshape(-1)[[5, 6, 7, 40]].tolist() == [1, 1, 1, 0]
    from dataclasses import replace

    save_map(tmp_path / "m.npz", replace(grid.snapshot(), floor_memory=memory.state()))
    loaded = load_map(tmp_path / "m.npz").floor_memory
    assert loaded is not None
    again = FloorMemory(WORLD)
    again.restore(loaded)
    for layer in ("standing", "standing_marks", "seen_foot_marks"):
        np.testing.assert_array_equal(getattr(again, layer), getattr(memory, layer))
    np.testing.assert_array_equal(again.standing_seen(), memory.standing_seen())
    # One more test seeing floor there takes the wall out, as it would have before.
    again.see_floor(wall)
    memory.see_floor(wall)
    np.testing.assert_array_equal(again.standing, memory.standing)

    # A map from before the marks were saved loads with no standing layer; half the
    # pair is refused.
    from app.mapping.map_files import map_arrays

    arrays = map_arrays(replace(grid.snapshot(), floor_memory=memory.state()))
    del arrays["standing_marks"], arrays["seen_foot_marks"]
    np.savez(tmp_path / "old.npz", **arrays)  # type: ignore[arg-type]
    old = load_map(tmp_path / "old.npz").floor_memory
    assert old is not None and old.standing_marks is None
    again.restore(old)
    assert not again.standing.any() and not again.standing_marks.any()
    arrays = map_arrays(replace(grid.snapshot(), floor_memory=memory.state()))
    del arrays["seen_foot_marks"]
    np.savez(tmp_path / "half.npz", **arrays)  # type: ignore[arg-type]
    with pytest.raises(MapFileError, match="'standing_marks' without its partner"):
        load_map(tmp_path / "half.npz")
    arrays = map_arrays(replace(grid.snapshot(), floor_memory=memory.state()))
    arrays["seen_foot_marks"] = arrays["seen_foot_marks"].astype(np.int16)
    np.savez(tmp_path / "bad.npz", **arrays)  # type: ignore[arg-type]
    with pytest.raises(MapFileError, match="'seen_foot_marks' must be uint8"):
        load_map(tmp_path / "bad.npz")


def test_a_map_with_half_a_memory_is_refused(tmp_path: Path) -> None:
    from app.mapping.map_files import map_arrays

    grid = OccupancyGrid(WORLD)
    memory = FloorMemory(WORLD)
    from dataclasses import replace

    arrays = map_arrays(replace(grid.snapshot(), floor_memory=memory.state()))
    del arrays["floor_appearances"]
    np.savez(tmp_path / "half.npz", **arrays)  # type: ignore[arg-type]
    with pytest.raises(MapFileError, match="without its partner"):
        load_map(tmp_path / "half.npz")


def test_restore_refuses_another_grid() -> None:
    memory = FloorMemory(WORLD)
    state = FloorMemoryState(np.zeros((3, 3), np.uint8), np.zeros((0, 4), np.float32))
    with pytest.raises(ValueError, match="shape"):
        memory.restore(state)


def test_standing_pixels_unlearn_only_the_colour_most_of_them_have() -> None:
    memory = FloorMemory(WORLD, FloorMemoryParams(min_cells=40))
    index = patch_world_index(PATCH, WORLD, Pose2D(-1.0, 0.0, 0.0))
    patch = np.full(PATCH.shape, NOT_FLOOR, np.uint8)
    memory.observe_colours(uniform_patch_bgr(TILE_BGR), patch, index, np.ones(PATCH.shape, bool))
    memory.confirm_cells(index.ravel())
    assert len(memory.appearances()) == 1
    box = np.array([40.0, 40.0, 200.0], np.float32)  # a red box's edge...
    edge = np.vstack([np.tile(box, (70, 1)), np.tile(np.float32(TILE_BGR), (30, 1))])
    for _ in range(2):  # two tests: the layer's `standing_min_marks`
        memory.mark_standing(index.ravel()[:10], edge)  # ...with 30 % floor pixels beside it
    assert len(memory.appearances()) == 1 and memory.unlearned == 0
    assert memory.standing.reshape(-1)[index.ravel()[:10]].all()
    # A floor-coloured box: most of what stands has the floor's colour.
    floor_box = np.vstack([np.tile(np.float32(TILE_BGR), (80, 1)), np.tile(box, (20, 1))])
    for _ in range(20):
        memory.mark_standing(index.ravel()[:10], floor_box)
    assert memory.appearances() == () and memory.unlearned == 1


def test_observed_colours_are_each_cells_running_mean_of_its_pixels() -> None:
    """Exact answer from a per-cell loop: the first sighting sets the colour, the second
    blends at rate max(colour_rate, 1 / (sightings + 1)); cells not hit stay as they were."""
    memory = FloorMemory(WORLD)
    rng = np.random.default_rng(5)
    rate = memory.params.colour_rate
    expected: dict[int, np.ndarray] = {}
    sightings: dict[int, int] = {}
    for pose in (Pose2D(-1.0, 0.3, 0.2), Pose2D(-0.8, 0.2, 0.4)):
        index = patch_world_index(PATCH, WORLD, pose)
        patch_bgr = rng.integers(0, 256, (*PATCH.shape, 3), dtype=np.uint8)
        patch = np.where(rng.random(PATCH.shape) < 0.2, UNSEEN, FLOOR).astype(np.uint8)
        near = rng.random(PATCH.shape) < 0.8
        memory.observe_colours(patch_bgr, patch, index, near)
        use = near & (patch != UNSEEN) & (index >= 0)
        for cell in np.unique(index[use]):
            mean = patch_bgr[use & (index == cell)].astype(np.float64).mean(axis=0)
            seen = sightings.get(int(cell), 0)
            old = expected.get(int(cell), np.zeros(3))
            expected[int(cell)] = old + (mean - old) * max(rate, 1.0 / (seen + 1))
            sightings[int(cell)] = seen + 1
    cells = np.array(sorted(expected))
    assert np.allclose(memory.colour_of(cells), np.array([expected[c] for c in cells]), atol=1e-3)


def test_driving_marks_the_footprint_and_the_centres_track() -> None:
    from app.mapping.floor_memory import DRIVEN_FOOTPRINT, DRIVEN_TRACK

    memory = FloorMemory(WORLD)
    # At a cell's centre: the footprint is the cells within 0.12 m (2.4 cells), the track
    # the cell and its four neighbours (within one cell).
    here = WORLD.cell_centers()[0][40, 40], WORLD.cell_centers()[1][40, 40]
    assert memory.drive_over(Pose2D(float(here[0]), float(here[1]), 0.0), 0.12) == 21
    rows, cols = np.nonzero(memory.driven & DRIVEN_TRACK)
    assert sorted(zip(rows.tolist(), cols.tolist(), strict=True)) == [
        (39, 40),
        (40, 39),
        (40, 40),
        (40, 41),
        (41, 40),
    ]
    footprint = (memory.driven & DRIVEN_FOOTPRINT) != 0
    assert np.count_nonzero(footprint) == 21
    np.testing.assert_array_equal(footprint, memory.confirmed == 1)
    np.testing.assert_array_equal(memory.track(), (memory.driven & DRIVEN_TRACK) != 0)
    # A position off every cell centre still puts its own cell on the track.
    memory.reset()
    memory.drive_over(Pose2D(0.019, 0.019, 0.0), 0.0)
    assert memory.track()[world_cell((0.019, 0.019))]


def test_a_standing_mark_takes_a_driven_cell_out_of_the_known_floor_and_not_off_the_track() -> None:
    memory = FloorMemory(WORLD)
    memory.drive_over(Pose2D(0.0, 0.0, 0.0), 0.12)
    r, c = world_cell((0.0, 0.0))
    cell = np.array([r * WORLD.cols + c])
    # The pose a drive is marked at may be off: geometry's word still counts there.
    memory.mark_standing(cell)
    assert memory.confirmed[r, c] == 0
    assert memory.track()[r, c]  # where the robot went stays its history


def test_the_driven_layer_is_saved_with_the_map_and_checked(tmp_path: Path) -> None:
    from dataclasses import replace

    from app.mapping.map_files import map_arrays

    grid = OccupancyGrid(WORLD)
    memory = FloorMemory(WORLD)
    for k in range(10):
        memory.drive_over(Pose2D(-0.5 + 0.03 * k, 0.2, 0.0), 0.12)
    memory.mark_standing(np.flatnonzero(memory.track())[:3])
    memory.mark_standing(np.flatnonzero(memory.track())[:3])
    save_map(tmp_path / "m.npz", replace(grid.snapshot(), floor_memory=memory.state()))
    loaded = load_map(tmp_path / "m.npz").floor_memory
    assert loaded is not None
    again = FloorMemory(WORLD)
    again.restore(loaded)
    np.testing.assert_array_equal(again.driven, memory.driven)
    np.testing.assert_array_equal(again.standing, memory.standing)
    assert again.standing.sum() == 3
    # A map saved before the layer existed loads with nothing driven.
    arrays = map_arrays(replace(grid.snapshot(), floor_memory=memory.state()))
    del arrays["driven_floor"]
    np.savez(tmp_path / "old.npz", **arrays)  # type: ignore[arg-type]
    old = load_map(tmp_path / "old.npz").floor_memory
    assert old is not None and old.driven is None
    again.restore(old)
    assert not again.driven.any()
    arrays = map_arrays(replace(grid.snapshot(), floor_memory=memory.state()))
    arrays["driven_floor"][0, 0] = 4
    np.savez(tmp_path / "bad.npz", **arrays)  # type: ignore[arg-type]
    with pytest.raises(MapFileError, match="'driven_floor' holds values above 3"):
        load_map(tmp_path / "bad.npz")
