"""Occupancy grid: ray casting in the patch, world fusion, clamping, decay by travel,
snapshots and restore, bad inputs."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from numpy.typing import NDArray

from app.benchmarks.grid import bench_grid_update, format_grid_bench
from app.mapping.frames import FLOOR, NOT_FLOOR, UNSEEN, GroundGrid, Pose2D
from app.mapping.frontiers import FrontierParams, find_frontiers
from app.mapping.occupancy import (
    FREE,
    OCCUPIED,
    PATCH_FREE,
    PATCH_OCCUPIED,
    PATCH_UNTOUCHED,
    UNKNOWN,
    OccupancyGrid,
    OccupancyParams,
    SavedMap,
    build_polar_table,
    cast_rays,
    decay_factor,
    fuse_patch_labels,
    travel_m,
)

# A 1 m x 1 m patch of 1 cm cells in front of a camera at the robot's origin: row i
# covers x in [1 - (i + 1) / 100, 1 - i / 100).
PATCH = GroundGrid.covering(x_min_m=0.0, x_max_m=1.0, y_min_m=-0.5, y_max_m=0.5, cell_m=0.01)
CAMERA = (0.0, 0.0)
# World: x -1..2, y -1..1 in 5 cm cells; row r covers x in [2 - (r + 1) / 20, 2 - r / 20).
WORLD = GroundGrid.covering(x_min_m=-1.0, x_max_m=2.0, y_min_m=-1.0, y_max_m=1.0, cell_m=0.05)
NO_DECAY = OccupancyParams(obstacle_band_m=0.025, half_distance_m=math.inf)


def wall_patch(wall_x_m: float = 0.6) -> NDArray[np.uint8]:
    """Floor up to x = wall_x_m, not floor (a wall and its smear) from there on."""
    x, _ = PATCH.cell_centers()
    return np.where(x < wall_x_m, FLOOR, NOT_FLOOR).astype(np.uint8)


def test_wall_line_free_before_occupied_band_at_nothing_behind() -> None:
    labels = cast_rays(wall_patch(), build_polar_table(PATCH, CAMERA), obstacle_band_m=0.025)
    # Rows 40..99 are floor (x < 0.6), row 39 is the first wall row (x in [0.60, 0.61)).
    assert (labels[40:] == PATCH_FREE).all()
    assert (labels[38:40] == PATCH_OCCUPIED).all()
    assert np.isin(labels[37], [PATCH_OCCUPIED, PATCH_UNTOUCHED]).all()  # band edge, oblique
    assert (labels[:37] == PATCH_UNTOUCHED).all()


def test_wall_line_in_the_world_is_cell_exact() -> None:
    grid = OccupancyGrid(WORLD, NO_DECAY)
    summary = grid.update(wall_patch(), PATCH, Pose2D(), CAMERA)
    expected = np.zeros(WORLD.shape, np.float32)
    # Patch y in [-0.5, 0.5) -> world cols 10..29; x in [0.60, 0.65) -> row 27 (holds the
    # band and 2 cm of smear: occupied wins); x in [0, 0.6) -> rows 28..39.
    expected[27, 10:30] = np.float32(0.85)
    expected[28:40, 10:30] = np.float32(-0.4)
    np.testing.assert_array_equal(grid.log_odds, expected)
    assert (summary.world_free, summary.world_occupied) == (12 * 20, 20)
    assert summary.patch_free == 60 * 100 and summary.patch_occupied >= 200
    classes = grid.classify()
    assert classes.dtype == np.int8
    assert (classes[27, 10:30] == OCCUPIED).all() and (classes[28:40, 10:30] == UNKNOWN).all()
    grid.update(wall_patch(), PATCH, Pose2D(), CAMERA)
    assert (grid.classify()[28:40, 10:30] == FREE).all()  # two floor sightings make free


def test_evidence_only_within_its_ranges() -> None:
    table = build_polar_table(PATCH, CAMERA)
    # The wall at 0.6 m, past the obstacle range: the floor before it is free, the wall
    # gives nothing, and nothing behind it is touched either.
    labels = cast_rays(wall_patch(), table, obstacle_band_m=0.025, occupied_max_range_m=0.5)
    np.testing.assert_array_equal(labels[40:] == PATCH_FREE, np.ones((60, 100), bool))
    assert (labels[:40] == PATCH_UNTOUCHED).all()
    # Inside both ranges: the same labels as without limits.
    unlimited = cast_rays(wall_patch(), table, obstacle_band_m=0.025)
    within = cast_rays(
        wall_patch(), table, obstacle_band_m=0.025, free_max_range_m=2.0, occupied_max_range_m=2.0
    )
    np.testing.assert_array_equal(within, unlimited)
    # Floor past the free range gives no evidence but hides nothing: the wall behind it
    # (straight ahead, rows 38-39 at x 0.60-0.62) is still occupied.
    labels = cast_rays(wall_patch(), table, obstacle_band_m=0.025, free_max_range_m=0.3)
    x, y = PATCH.cell_centers()
    near = np.hypot(x, y) < 0.29
    far = (np.hypot(x, y) > 0.31) & (x < 0.6)
    assert (labels[near] == PATCH_FREE).all() and (labels[far] == PATCH_UNTOUCHED).all()
    assert (labels[38:40, 45:55] == PATCH_OCCUPIED).all()
    # What geometry saw standing is mapped as far as floor is: the same wall, flagged
    # standing, gets its band back (here the free range is unlimited).
    standing = wall_patch() == NOT_FLOOR
    labels = cast_rays(
        wall_patch(), table, obstacle_band_m=0.025, occupied_max_range_m=0.5, standing=standing
    )
    np.testing.assert_array_equal(labels, unlimited)
    labels = cast_rays(
        wall_patch(),
        table,
        obstacle_band_m=0.025,
        free_max_range_m=0.55,
        occupied_max_range_m=0.5,
        standing=standing,
    )
    assert not (labels == PATCH_OCCUPIED).any()
    with pytest.raises(ValueError, match="standing"):
        cast_rays(wall_patch(), table, standing=standing[1:])
    # In the world: a wall seen from 0.6 m away with a 0.5 m obstacle range is no obstacle.
    grid = OccupancyGrid(WORLD, replace(NO_DECAY, occupied_max_range_m=0.5))
    summary = grid.update(wall_patch(), PATCH, Pose2D(), CAMERA)
    assert summary.world_occupied == 0 and summary.patch_occupied == 0
    assert not (grid.log_odds > 0).any() and (grid.log_odds[28:40, 10:30] < 0).all()
    summary = grid.update(wall_patch(), PATCH, Pose2D(), CAMERA, standing=standing)
    assert summary.world_occupied == 20 and (grid.log_odds[27, 10:30] > 0).all()
    for name in ("free_max_range_m", "occupied_max_range_m"):
        with pytest.raises(ValueError, match=name):
            OccupancyParams(**{name: 0.0})
        with pytest.raises(ValueError, match=name):
            cast_rays(wall_patch(), table, **{name: -1.0})
        assert getattr(OccupancyParams(**{name: math.inf}), name) == math.inf


def test_floor_just_before_an_unmapped_boundary_is_not_free() -> None:
    table = build_polar_table(PATCH, CAMERA)
    x, y = PATCH.cell_centers()
    # Along each ray the wall (x >= 0.6) starts at range 0.6 / cos(bearing).
    boundary_r = 0.6 * np.hypot(x, y) / np.maximum(x, 1e-9)
    # Rays that leave the patch's sides before the wall have no boundary: leave them out.
    reaches_wall = np.abs(y) * 0.6 / np.maximum(x, 1e-9) < 0.45
    # The wall at 0.6 m is past the 0.5 m obstacle range: floor within 0.1 m of it (along
    # the ray) gives no free label; nearer floor still does.
    labels = cast_rays(wall_patch(), table, occupied_max_range_m=0.5, far_boundary_margin_m=0.1)
    r = np.hypot(x, y)
    floor = x < 0.6
    # (A cell's range is where its ray enters it: up to a cell's diagonal off its centre.)
    sure_free = floor & (r < boundary_r - 0.1 - 0.015)
    sure_out = floor & reaches_wall & (r > boundary_r - 0.1 + 0.015)
    assert sure_free.sum() > 3000 and sure_out.sum() > 600
    assert (labels[sure_free] == PATCH_FREE).all()
    assert (labels[sure_out] == PATCH_UNTOUCHED).all() and (labels[~floor] == 0).all()
    # A boundary within the obstacle range is mapped: the margin changes nothing there.
    mapped = cast_rays(wall_patch(), table, obstacle_band_m=0.025, far_boundary_margin_m=0.1)
    np.testing.assert_array_equal(mapped, cast_rays(wall_patch(), table, obstacle_band_m=0.025))
    # Nor does it change rays that end without a boundary (floor to the patch's edge).
    open_floor = np.full(PATCH.shape, FLOOR, np.uint8)
    np.testing.assert_array_equal(
        cast_rays(open_floor, table, occupied_max_range_m=0.5, far_boundary_margin_m=0.1),
        np.full(PATCH.shape, PATCH_FREE, np.uint8),
    )
    with pytest.raises(ValueError, match="far_boundary_margin_m"):
        cast_rays(wall_patch(), table, far_boundary_margin_m=-0.1)
    with pytest.raises(ValueError, match="far_boundary_margin_m"):
        OccupancyParams(far_boundary_margin_m=-0.1)


def test_unseen_never_updates_and_does_not_stop_rays() -> None:
    grid = OccupancyGrid(WORLD, NO_DECAY)
    unseen = np.full(PATCH.shape, UNSEEN, np.uint8)
    summary = grid.update(unseen, PATCH, Pose2D(0.3, -0.2, 0.5), CAMERA)
    assert not grid.log_odds.any()
    assert (summary.patch_free, summary.world_free, summary.world_occupied) == (0, 0, 0)

    patch = wall_patch()
    patch[60:70] = UNSEEN  # a blind strip across the floor at x in [0.30, 0.40)
    patch[:, 50:] = UNSEEN  # and the whole right half (y < 0)
    labels = cast_rays(patch, build_polar_table(PATCH, CAMERA), obstacle_band_m=0.025)
    assert (labels[patch == UNSEEN] == PATCH_UNTOUCHED).all()
    assert (labels[70:, :50] == PATCH_FREE).all() and (labels[40:60, :50] == PATCH_FREE).all()
    assert (labels[38:40, :50] == PATCH_OCCUPIED).all()
    grid.update(patch, PATCH, Pose2D(), CAMERA)
    assert not grid.log_odds[:, 20:].any()  # world y < 0
    assert not grid.log_odds[32:34].any()  # world x in [0.30, 0.40)
    assert (grid.log_odds[34:40, 10:20] < 0).all() and (grid.log_odds[28:32, 10:20] < 0).all()


def test_fov_wedge_is_respected() -> None:
    x, y = PATCH.cell_centers()
    wedge = np.abs(np.arctan2(y - CAMERA[1], x - CAMERA[0])) < math.radians(30)
    patch = np.where(wedge, FLOOR, UNSEEN).astype(np.uint8)
    labels = cast_rays(patch, build_polar_table(PATCH, CAMERA))
    np.testing.assert_array_equal(labels == PATCH_FREE, wedge)
    assert not (labels == PATCH_OCCUPIED).any()

    grid = OccupancyGrid(WORLD, NO_DECAY)
    pose = Pose2D(0.2, 0.1, 0.3)
    grid.update(patch, PATCH, pose, CAMERA)
    hit = WORLD.cell_of(pose.apply(np.column_stack((x[wedge], y[wedge]))))
    expected = np.zeros(WORLD.shape, bool)
    expected[hit[:, 0], hit[:, 1]] = True
    np.testing.assert_array_equal(grid.log_odds != 0, expected)
    assert (grid.log_odds[expected] == np.float32(-0.4)).all()


def test_obstacle_without_floor_before_it_is_not_mapped() -> None:
    patch = wall_patch(wall_x_m=2.0)  # all floor ...
    patch[80:] = NOT_FLOOR  # ... but the first 20 cm in front of the camera are not
    labels = cast_rays(patch, build_polar_table(PATCH, CAMERA))
    # Rays from the camera meet not-floor first: the obstacle's foot is out of view, so
    # neither it nor anything behind it is mapped.
    assert (labels == PATCH_UNTOUCHED).all()


def test_pose_transform_is_cell_exact() -> None:
    world = GroundGrid.covering(x_min_m=-5, x_max_m=5, y_min_m=-5, y_max_m=5, cell_m=0.05)
    patch_grid = GroundGrid.covering(
        x_min_m=0.0, x_max_m=0.5, y_min_m=-0.25, y_max_m=0.25, cell_m=0.05
    )
    rng = np.random.default_rng(1)
    labels = rng.integers(0, 3, patch_grid.shape).astype(np.uint8)
    log_odds = np.zeros(world.shape, np.float32)
    pose = Pose2D(1.0, 2.0, math.pi / 2)
    fuse_patch_labels(log_odds, world, labels, patch_grid, pose, OccupancyParams())
    # Patch cell (i, j) has its centre at robot (0.475 - 0.05 i, 0.225 - 0.05 j), hence at
    # world (0.775 + 0.05 j, 2.475 - 0.05 i): world cell (84 - j, 50 + i).
    values = np.array([0.0, -0.4, 0.85], np.float32)[labels]
    expected = np.zeros(world.shape, np.float32)
    expected[75:85, 50:60] = np.rot90(values)
    np.testing.assert_array_equal(log_odds, expected)
    assert expected[84, 50] == values[0, 0] and expected[75, 59] == values[9, 9]

    # The same through update(): an all-floor patch seen from its near edge.
    grid = OccupancyGrid(world, NO_DECAY)
    grid.update(np.full(patch_grid.shape, FLOOR, np.uint8), patch_grid, pose, (0.0, 0.0))
    expected = np.zeros(world.shape, np.float32)
    expected[75:85, 50:60] = np.float32(-0.4)
    np.testing.assert_array_equal(grid.log_odds, expected)


def test_many_patch_cells_on_one_world_cell_give_one_update_occupied_wins() -> None:
    world = GroundGrid.covering(x_min_m=0, x_max_m=0.1, y_min_m=0, y_max_m=0.1, cell_m=0.05)
    patch_grid = GroundGrid.covering(x_min_m=0, x_max_m=0.1, y_min_m=0, y_max_m=0.1, cell_m=0.01)
    labels = np.full(patch_grid.shape, PATCH_FREE, np.uint8)
    labels[0, 0] = PATCH_OCCUPIED  # 1 of the 25 cells of world cell (0, 0)
    labels[5:, 5:] = PATCH_UNTOUCHED  # world cell (1, 1) gets nothing
    log_odds = np.zeros(world.shape, np.float32)
    counts = fuse_patch_labels(log_odds, world, labels, patch_grid, Pose2D(), OccupancyParams())
    np.testing.assert_array_equal(log_odds, np.array([[0.85, -0.4], [-0.4, 0.0]], np.float32))
    assert counts == (2, 1)


def test_log_odds_are_clamped() -> None:
    grid = OccupancyGrid(WORLD, NO_DECAY)
    for _ in range(12):
        grid.update(wall_patch(), PATCH, Pose2D(), CAMERA)
    assert grid.log_odds.max() == np.float32(3.5)
    assert grid.log_odds.min() == np.float32(-2.0)
    assert (grid.log_odds[28:40, 10:30] == np.float32(-2.0)).all()
    probabilities = grid.probabilities()
    assert probabilities.dtype == np.float32
    assert probabilities[0, 0] == 0.5 and probabilities[27, 10] > 0.97


def test_standing_still_for_ten_minutes_keeps_the_map_exactly() -> None:
    # The failure users saw: a robot waiting after a fault lost its map to the clock.
    # Frames keep coming (10 a second for 10 minutes) at the same pose.
    grid = OccupancyGrid(WORLD, OccupancyParams(obstacle_band_m=0.025))
    reference = OccupancyGrid(WORLD, NO_DECAY)
    pose = Pose2D(0.2, -0.1, 0.3)
    for target in (grid, reference):
        target.update(wall_patch(), PATCH, pose, CAMERA)
        target.update(wall_patch(), PATCH, pose, CAMERA)
    before = grid.log_odds.copy()
    classes = grid.classify()
    assert (classes == FREE).any() and (classes == OCCUPIED).any()
    unseen = np.full(PATCH.shape, UNSEEN, np.uint8)
    for _ in range(10 * 60 * 10):
        assert grid.update(unseen, PATCH, pose, CAMERA).decayed is False
    np.testing.assert_array_equal(grid.log_odds, before)
    assert grid.travelled_m == 0.0
    # Seeing the same scene again only adds evidence, exactly as without any decay.
    for target in (grid, reference):
        for _ in range(20):
            target.update(wall_patch(), PATCH, pose, CAMERA)
    np.testing.assert_array_equal(grid.log_odds, reference.log_odds)


def test_driving_n_half_distances_halves_the_evidence_n_times() -> None:
    params = OccupancyParams(obstacle_band_m=0.025, half_distance_m=1.0, decay_step_m=0.05)
    grid = OccupancyGrid(WORLD, params)
    grid.update(wall_patch(), PATCH, Pose2D(), CAMERA)
    before = grid.log_odds.copy()
    unseen = np.full(PATCH.shape, UNSEEN, np.uint8)
    # Whole half-distances at a time: the factor is exactly 0.5 per metre.
    for n in (1, 2, 3):
        assert grid.update(unseen, PATCH, Pose2D(float(n), 0.0, 0.0), CAMERA).decayed is True
        np.testing.assert_array_equal(grid.log_odds, before / 2**n)
    assert grid.travelled_m == 3.0

    # Small steps (below the lazy step, so decays are batched) give the same result. The
    # numbers are binary fractions, so every distance is exact: 1/64 m steps, 1/16 m decay
    # step, 1 m out along y and back.
    params = replace(params, decay_step_m=1 / 16)
    grid = OccupancyGrid(WORLD, params)
    grid.update(wall_patch(), PATCH, Pose2D(), CAMERA)
    assert grid.update(unseen, PATCH, Pose2D(0.0, 1 / 64, 0.0), CAMERA).decayed is False
    np.testing.assert_array_equal(grid.log_odds, before)  # pending, below the step
    np.testing.assert_allclose(grid.snapshot().log_odds, before * 0.5 ** (1 / 64), rtol=1e-6)
    decays = 0
    for k in [*range(2, 65), *range(63, -1, -1)]:
        decays += grid.update(unseen, PATCH, Pose2D(0.0, k / 64, 0.0), CAMERA).decayed
    assert decays == 32 and grid.travelled_m == 2.0  # path length, not displacement
    np.testing.assert_allclose(grid.log_odds, before / 4, rtol=1e-5)
    assert decay_factor(0.5, 1.0) == pytest.approx(math.sqrt(0.5))


def test_decay_forgets_evidence_but_remembers_what_the_cells_were() -> None:
    params = OccupancyParams(obstacle_band_m=0.025, half_distance_m=1.0, decay_step_m=0.05)
    grid = OccupancyGrid(WORLD, params)
    for _ in range(3):
        grid.update(wall_patch(), PATCH, Pose2D(), CAMERA)
    seen = grid.classify()
    assert (seen == FREE).sum() > 100 and (seen == OCCUPIED).sum() > 10
    assert (grid.remembered == UNKNOWN).all()  # nothing decayed yet
    np.testing.assert_array_equal(grid.remembered_classes(), seen)
    unseen = np.full(PATCH.shape, UNSEEN, np.uint8)
    grid.update(unseen, PATCH, Pose2D(-0.9, 0.0, 0.0), CAMERA)  # behind: sees nothing new
    grid.update(unseen, PATCH, Pose2D(0.0, 0.0, 0.0), CAMERA)  # 1.8 m: 0.29 of it is left
    faded = (seen != UNKNOWN) & (grid.classify() == UNKNOWN)
    assert faded.sum() > 50
    np.testing.assert_array_equal(grid.remembered, seen)
    np.testing.assert_array_equal(grid.remembered_classes(), seen)
    # Planned on, the faded room is still there, explored: its frontiers are the free
    # cells beside what was never seen. Without the memory it is a void.
    frontier_params = FrontierParams(min_cluster_cells=1, robot_radius_m=0.0)
    assert find_frontiers(grid.classify(), WORLD, (0.0, 0.0), frontier_params).clusters == ()
    remembered = find_frontiers(grid.remembered_classes(), WORLD, (0.0, 0.0), frontier_params)
    assert remembered.goal is not None
    never_seen = np.pad(seen == UNKNOWN, 1)
    for cluster in remembered.clusters:
        rows, cols = cluster.cells[:, 0] + 1, cluster.cells[:, 1] + 1
        beside = (
            never_seen[rows - 1, cols]
            | never_seen[rows + 1, cols]
            | never_seen[rows, cols - 1]
            | never_seen[rows, cols + 1]
        )
        assert (seen[rows - 1, cols - 1] == FREE).all() and beside.all()
    # New evidence wins over a memory: a person now stands where the floor was free.
    person = np.full(PATCH.shape, UNSEEN, np.uint8)
    person[60:, :] = FLOOR
    person[55:60, 45:55] = NOT_FLOOR
    for _ in range(3):
        grid.update(person, PATCH, Pose2D(), CAMERA)
    now_classes = grid.classify()
    standing = now_classes == OCCUPIED
    assert (standing & (seen == FREE)).any()
    np.testing.assert_array_equal(grid.remembered_classes()[standing], OCCUPIED)

    # The snapshot carries the layer, with the pending travel's decay remembered too.
    params = replace(params, decay_step_m=10.0)
    pending = OccupancyGrid(WORLD, params)
    for _ in range(3):
        pending.update(wall_patch(), PATCH, Pose2D(), CAMERA)
    pending.update(unseen, PATCH, Pose2D(3.0, 0.0, 0.0), CAMERA)  # below the decay step
    assert (pending.remembered == UNKNOWN).all()
    snapshot = pending.snapshot()
    assert snapshot.remembered is not None and not snapshot.remembered.flags.writeable
    np.testing.assert_array_equal(snapshot.remembered, seen)
    restored = OccupancyGrid(WORLD, params)
    restored.restore(snapshot)
    np.testing.assert_array_equal(restored.remembered_classes(), seen)
    restored.reset()
    assert (restored.remembered == UNKNOWN).all()
    # A map saved without the layer: what it knows now is what it remembers.
    restored.restore(replace(snapshot, remembered=None))
    np.testing.assert_array_equal(restored.remembered, snapshot.classify())
    with pytest.raises(ValueError, match=r"remembered: expected int8 -1/0/1 of shape \(60, 40\)"):
        replace(snapshot, remembered=np.full((60, 40), 2, np.int8))


def test_a_jittering_pose_never_adds_up_to_travel() -> None:
    # Encoder ticks of a vibrating robot, or estimator noise: the pose wanders within a
    # few centimetres and degrees of where the robot stands, 30 times a second.
    grid = OccupancyGrid(WORLD, OccupancyParams(obstacle_band_m=0.025))
    grid.update(wall_patch(), PATCH, Pose2D(), CAMERA)
    before = grid.log_odds.copy()
    unseen = np.full(PATCH.shape, UNSEEN, np.uint8)
    rng = np.random.default_rng(7)
    for dx, dy, dtheta in rng.uniform(-1, 1, (30 * 60, 3)) * (0.02, 0.02, 0.2):
        assert grid.update(unseen, PATCH, Pose2D(dx, dy, dtheta), CAMERA).decayed is False
    np.testing.assert_array_equal(grid.log_odds, before)
    assert grid.travelled_m == 0.0
    # Once the robot really moves off, the travel is counted from where it stood.
    assert grid.update(unseen, PATCH, Pose2D(1.0, 0.0, 0.0), CAMERA).decayed is True
    assert grid.travelled_m == pytest.approx(1.0)


def test_turning_in_place_counts_as_wheel_travel() -> None:
    assert travel_m(Pose2D(), Pose2D(0.3, 0.4, 0.0), 0.1) == pytest.approx(0.5)
    assert travel_m(Pose2D(), Pose2D(0.0, 0.0, math.pi / 2), 0.1) == pytest.approx(0.05 * math.pi)
    # An arc counts once: the larger of driving and turning.
    assert travel_m(Pose2D(), Pose2D(0.1, 0.0, 0.2), 0.1) == pytest.approx(0.1)
    # Heading differences wrap: 3.1 -> -3.1 rad is a 0.083 rad turn, not 6.2 rad.
    wrapped = travel_m(Pose2D(0, 0, 3.1), Pose2D(0, 0, -3.1), 1.0)
    assert wrapped == pytest.approx(2 * math.pi - 6.2)

    params = OccupancyParams(half_distance_m=1.0, turn_radius_m=0.1, decay_step_m=0.0)
    grid = OccupancyGrid(WORLD, params)
    grid.update(wall_patch(), PATCH, Pose2D(), CAMERA)
    before = grid.log_odds.copy()
    unseen = np.full(PATCH.shape, UNSEEN, np.uint8)
    for k in range(1, 5):  # one full spin turn in quarter turns
        grid.update(unseen, PATCH, Pose2D(0.0, 0.0, k * math.pi / 2), CAMERA)
    assert grid.travelled_m == pytest.approx(0.2 * math.pi)
    np.testing.assert_allclose(grid.log_odds, before * 0.5 ** (0.2 * math.pi), rtol=1e-5)

    spin_free = OccupancyGrid(WORLD, OccupancyParams(half_distance_m=1.0, turn_radius_m=0.0))
    spin_free.update(wall_patch(), PATCH, Pose2D(), CAMERA)
    for k in range(1, 5):
        spin_free.update(unseen, PATCH, Pose2D(0.0, 0.0, k * math.pi / 2), CAMERA)
    np.testing.assert_array_equal(spin_free.log_odds, before)


def test_snapshot_is_a_read_only_copy_with_the_pending_decay_applied() -> None:
    params = OccupancyParams(obstacle_band_m=0.025, half_distance_m=1.0, decay_step_m=0.5)
    grid = OccupancyGrid(WORLD, params)
    grid.update(wall_patch(), PATCH, Pose2D(), CAMERA)
    before = grid.log_odds.copy()
    unseen = np.full(PATCH.shape, UNSEEN, np.uint8)
    grid.update(unseen, PATCH, Pose2D(0.25, 0.0, 0.0), CAMERA)  # pending, below the step
    np.testing.assert_array_equal(grid.log_odds, before)
    snapshot = grid.snapshot()
    np.testing.assert_allclose(snapshot.log_odds, before * 0.5**0.25, rtol=1e-6)
    np.testing.assert_array_equal(grid.log_odds, before)  # the grid itself is unchanged
    assert snapshot.T_world_robot == Pose2D(0.25, 0.0, 0.0)
    assert snapshot.travelled_m == 0.25
    assert snapshot.world_grid == WORLD
    assert (snapshot.free_threshold, snapshot.occupied_threshold) == (-0.5, 0.5)
    assert not snapshot.log_odds.flags.writeable
    grid.update(wall_patch(), PATCH, Pose2D(0.25, 0.0, 0.0), CAMERA)
    np.testing.assert_allclose(snapshot.log_odds, before * 0.5**0.25, rtol=1e-6)  # a copy
    np.testing.assert_array_equal(snapshot.classify(), grid_classes(snapshot.log_odds))
    assert OccupancyGrid(WORLD).snapshot().T_world_robot == Pose2D()  # never updated


def grid_classes(log_odds: NDArray[np.float32]) -> NDArray[np.int8]:
    grid = OccupancyGrid(WORLD)
    grid.log_odds[:] = log_odds
    return grid.classify()


def test_restore_continues_the_map_and_its_travel() -> None:
    params = OccupancyParams(obstacle_band_m=0.025, half_distance_m=1.0, decay_step_m=0.0)
    grid = OccupancyGrid(WORLD, params)
    pose = Pose2D(0.1, 0.2, 0.3)
    grid.update(wall_patch(), PATCH, pose, CAMERA)
    snapshot = grid.snapshot()

    fresh = OccupancyGrid(WORLD, params)
    fresh.restore(snapshot)
    np.testing.assert_array_equal(fresh.log_odds, snapshot.log_odds)
    assert fresh.log_odds.flags.writeable
    unseen = np.full(PATCH.shape, UNSEEN, np.uint8)
    # Travel is counted from the saved pose: standing there decays nothing...
    assert fresh.update(unseen, PATCH, pose, CAMERA).decayed is False
    np.testing.assert_array_equal(fresh.log_odds, snapshot.log_odds)
    # ...and one half-distance from it halves the evidence.
    fresh.update(unseen, PATCH, Pose2D(1.1, 0.2, 0.3), CAMERA)
    np.testing.assert_array_equal(fresh.log_odds, snapshot.log_odds / 2)
    assert fresh.travelled_m == pytest.approx(1.0)

    # Evidence beyond this grid's clamp is clamped.
    tight_params = OccupancyParams(clamp_min=-0.3, clamp_max=0.6, free_threshold=-0.2)
    tight = OccupancyGrid(WORLD, tight_params)
    tight.restore(snapshot)
    assert tight.log_odds.max() == np.float32(0.6) and tight.log_odds.min() == np.float32(-0.3)

    # Another world grid is refused, naming both, and nothing changes.
    other = GroundGrid.covering(x_min_m=-1.0, x_max_m=2.0, y_min_m=-1.0, y_max_m=1.0, cell_m=0.1)
    target = OccupancyGrid(other)
    target.log_odds[3, 4] = 1.0
    with pytest.raises(ValueError, match=r"60 x 40 cells of 0.05 m.*30 x 20 cells of 0.1 m"):
        target.restore(snapshot)
    assert target.log_odds[3, 4] == 1.0 and np.count_nonzero(target.log_odds) == 1
    with pytest.raises(ValueError, match="SavedMap"):
        target.restore(grid)  # type: ignore[arg-type]

    grid.reset()
    assert grid.travelled_m == 0.0 and grid.snapshot().T_world_robot == Pose2D()
    assert not grid.log_odds.any()


def test_snapshots_refuse_bad_contents() -> None:
    good = OccupancyGrid(WORLD).snapshot()
    fields = dict(
        world_grid=WORLD, free_threshold=-0.5, occupied_threshold=0.5, T_world_robot=Pose2D()
    )
    with pytest.raises(ValueError, match="float32 of shape"):
        SavedMap(log_odds=np.zeros((2, 2), np.float32), travelled_m=0.0, **fields)
    nan = np.array(good.log_odds)
    nan[1, 1] = np.nan
    with pytest.raises(ValueError, match="1 cells are not finite"):
        SavedMap(log_odds=nan, travelled_m=0.0, **fields)
    with pytest.raises(ValueError, match="travelled_m"):
        SavedMap(log_odds=np.array(good.log_odds), travelled_m=-1.0, **fields)


def test_footprint_is_cleared_when_enabled() -> None:
    grid = OccupancyGrid(WORLD, OccupancyParams(footprint_free_radius_m=0.06))
    unseen = np.full(PATCH.shape, UNSEEN, np.uint8)
    summary = grid.update(unseen, PATCH, Pose2D(0.0, 0.0, 1.0), CAMERA)
    # World cells with centres within 6 cm of the origin: (+-0.025, +-0.025) only.
    assert summary.world_free == 4
    cleared = np.argwhere(grid.log_odds < 0).tolist()
    assert cleared == [[39, 19], [39, 20], [40, 19], [40, 20]]


def test_polar_table_covers_a_camera_patch_in_range_order() -> None:
    patch_grid = GroundGrid.covering(
        x_min_m=0.1, x_max_m=3.0, y_min_m=-1.5, y_max_m=1.5, cell_m=0.01
    )
    table = build_polar_table(patch_grid, (0.1, 0.0))
    covered = np.zeros(patch_grid.rows * patch_grid.cols, bool)
    covered[table.cells] = True
    assert covered.all()
    for k in range(0, table.n_rays, 97):
        ranges = table.range_m[table.offsets[k] : table.offsets[k + 1]]
        assert (np.diff(ranges) >= 0).all()


def test_bad_inputs_raise_clear_value_errors() -> None:
    grid = OccupancyGrid(WORLD)
    good = wall_patch()
    with pytest.raises(ValueError, match="shape"):
        grid.update(good[:, :-1], PATCH, Pose2D(), CAMERA)
    with pytest.raises(ValueError, match="uint8"):
        grid.update(good.astype(np.float32), PATCH, Pose2D(), CAMERA)
    bad_values = good.copy()
    bad_values[0, 0] = 7
    with pytest.raises(ValueError, match="1 cells are not FLOOR"):
        grid.update(bad_values, PATCH, Pose2D(), CAMERA)
    with pytest.raises(ValueError, match="T_world_robot"):
        grid.update(good, PATCH, Pose2D(float("nan"), 0.0, 0.0), CAMERA)
    with pytest.raises(ValueError, match="camera_xy_robot"):
        grid.update(good, PATCH, Pose2D(), (0.0, float("inf")))
    negative = GroundGrid(1.0, 0.5, -0.01, 100, 100)
    with pytest.raises(ValueError, match=r"patch_grid: cell size must be finite and > 0"):
        grid.update(good, negative, Pose2D(), CAMERA)
    with pytest.raises(ValueError, match=r"world_grid: cell size"):
        OccupancyGrid(GroundGrid(1.0, 1.0, -0.05, 10, 10))
    with pytest.raises(ValueError, match="larger than the world"):
        coarse = GroundGrid.covering(x_min_m=0, x_max_m=1, y_min_m=-0.5, y_max_m=0.5, cell_m=0.1)
        grid.update(np.full(coarse.shape, FLOOR, np.uint8), coarse, Pose2D(), CAMERA)
    with pytest.raises(ValueError, match="log_odds_free"):
        OccupancyParams(log_odds_free=0.4)
    with pytest.raises(ValueError, match="half_distance_m"):
        OccupancyParams(half_distance_m=0.0)
    with pytest.raises(ValueError, match="turn_radius_m"):
        OccupancyParams(turn_radius_m=-0.1)
    with pytest.raises(ValueError, match="obstacle_band_m"):
        OccupancyParams(obstacle_band_m=float("nan"))
    with pytest.raises(ValueError, match="size_m"):
        OccupancyGrid.square(20.0, -0.05)
    assert not grid.log_odds.any()  # nothing was half-applied


@pytest.mark.slow
def test_grid_bench_smoke() -> None:
    result = bench_grid_update(1)
    assert result["updates"] == 12
    ms = {key: result[key] for key in ("median", "min", "max", "open_floor_median")}
    assert all(isinstance(v, float) and v > 0 for v in ms.values())
    assert float(ms["min"]) <= float(ms["median"]) <= float(ms["max"])
    assert "occupancy grid update" in format_grid_bench(result)


def test_a_grid_holds_exactly_its_own_cells() -> None:
    grid = GroundGrid(2.0, 1.0, 0.5, 4, 3)  # rows 0-3, cols 0-2
    rc = np.array([[0, 0], [3, 2], [-1, 0], [4, 0], [0, -1], [0, 3], [2, 1]])
    assert grid.holds(rc).tolist() == [True, True, False, False, False, False, True]
    # The points of cell_of: the corner (x_max, y_max) is on it, past it is not.
    points = np.array([[2.0, 1.0], [2.01, 1.0], [0.01, -0.49], [-0.01, 0.0]])
    assert grid.holds(grid.cell_of(points)).tolist() == [True, False, True, False]


def test_the_footprint_wipes_out_an_earlier_wall_unless_this_frame_sees_one() -> None:
    params = OccupancyParams(footprint_free_radius_m=0.06, half_distance_m=float("inf"))
    grid = OccupancyGrid(WORLD, params)
    grid.log_odds[39:41, 19:21] = params.clamp_max  # a threshold seen as a wall for seconds
    unseen = np.full(PATCH.shape, UNSEEN, np.uint8)
    # The robot stands on it: its cells are free in one frame, one sighting past the
    # threshold, then free updates as usual.
    grid.update(unseen, PATCH, Pose2D(0.0, 0.0, 1.0), CAMERA)
    once = params.free_threshold + params.log_odds_free
    np.testing.assert_allclose(grid.log_odds[39:41, 19:21], once)
    assert (grid.classify()[39:41, 19:21] == FREE).all()
    grid.update(unseen, PATCH, Pose2D(0.0, 0.0, 1.0), CAMERA)
    np.testing.assert_allclose(grid.log_odds[39:41, 19:21], once + params.log_odds_free)
    # Two occupied sightings bring a wall back (the pose may have been a cell off).
    assert once + 2 * params.log_odds_occupied > params.occupied_threshold
    # An obstacle this frame marks inside the footprint's radius keeps its occupied update.
    labels = np.zeros(PATCH.shape, np.uint8)
    r, c = PATCH.cell_of(np.array([[0.02, 0.02]]))[0]
    labels[r, c] = PATCH_OCCUPIED
    log_odds = np.zeros(WORLD.shape, np.float32)
    n_free, n_occ = fuse_patch_labels(log_odds, WORLD, labels, PATCH, Pose2D(), params)
    assert (n_free, n_occ) == (3, 1)
    assert log_odds[39, 19] == pytest.approx(params.log_odds_occupied)
    assert sorted(log_odds[39:41, 19:21].ravel().tolist()) == [
        pytest.approx(once),
        pytest.approx(once),
        pytest.approx(once),
        pytest.approx(params.log_odds_occupied),
    ]
