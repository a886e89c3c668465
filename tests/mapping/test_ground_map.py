"""Floor mask -> bird's-eye patch -> occupancy grid -> frontiers, end to end with a
synthetic calibrated camera."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from app.config import CameraConfig, MappingConfig
from app.mapping.calibration import apply_homography, homography_from_point_pairs
from app.mapping.frames import FLOOR, NOT_FLOOR, Pose2D
from app.mapping.ground_map import WALLS_PERIOD_S, GroundMapper, _FeetGeometry
from app.mapping.occupancy import FREE, OCCUPIED, UNKNOWN, OccupancyGrid

from .test_calibration import HEIGHT, WIDTH, camera_homography


def make_mapper(**mapping: float) -> GroundMapper:
    H_true = camera_homography()
    ground = np.array([[0.5, 0.3], [0.5, -0.3], [1.5, 0.5], [1.5, -0.5]])
    calibration = homography_from_point_pairs(
        apply_homography(H_true, ground), ground, (WIDTH, HEIGHT)
    )
    config = MappingConfig(max_range_m=2.5, **mapping)  # type: ignore[arg-type]
    return GroundMapper(calibration, config, CameraConfig(x_m=0.0))


def wall_mask(mapper: GroundMapper, wall_x_m: float) -> np.ndarray:
    """Floor up to a wall ``wall_x_m`` ahead (a straight line across the image)."""
    row = mapper.calibration.ground_to_image(np.array([[wall_x_m, 0.0]]))[0, 1]
    mask = np.zeros((HEIGHT, WIDTH), bool)
    mask[int(np.ceil(row)) :] = True
    return mask


def test_wall_ahead_becomes_free_floor_then_an_occupied_band() -> None:
    mapper = make_mapper()
    pose = Pose2D(0.0, 0.0, 0.0)
    # A wall within the obstacle evidence range (1 m by default).
    for t in range(3):
        update = mapper.update(wall_mask(mapper, 0.9), pose, now_s=0.1 * t)
    patch = update.patch
    assert (patch == FLOOR).any() and (patch == NOT_FLOOR).any()
    cells = mapper.grid.classify()
    grid = mapper.grid.world_grid
    row_col = grid.cell_of(np.array([[0.6, 0.0], [0.92, 0.0], [1.3, 0.0], [-0.5, 0.0]]))
    states = [int(cells[r, c]) for r, c in row_col]
    assert states == [FREE, OCCUPIED, UNKNOWN, UNKNOWN]  # behind the wall: not updated


def test_a_far_wall_is_no_obstacle_until_the_robot_is_near() -> None:
    mapper = make_mapper()
    for t in range(3):
        mapper.update(wall_mask(mapper, 1.4), Pose2D(0.0, 0.0, 0.0), now_s=0.1 * t)
    grid = mapper.grid.world_grid
    row_col = grid.cell_of(np.array([[0.8, 0.0], [1.42, 0.0]]))
    assert [int(mapper.grid.classify()[r, c]) for r, c in row_col] == [FREE, UNKNOWN]
    # From 0.9 m away the same wall is placed well enough to map.
    for t in range(3, 6):
        mapper.update(wall_mask(mapper, 0.9), Pose2D(0.5, 0.0, 0.0), now_s=0.1 * t)
    assert [int(mapper.grid.classify()[r, c]) for r, c in row_col] == [FREE, OCCUPIED]


def test_turned_robot_maps_into_the_world_frame() -> None:
    mapper = make_mapper()
    pose = Pose2D(1.0, 2.0, np.pi / 2)  # facing world +y
    for t in range(3):
        mapper.update(wall_mask(mapper, 0.9), pose, now_s=0.1 * t)
    cells = mapper.grid.classify()
    r, c = mapper.grid.world_grid.cell_of(np.array([[1.0, 2.6]]))[0]
    assert cells[r, c] == FREE
    r, c = mapper.grid.world_grid.cell_of(np.array([[1.0, 2.92]]))[0]
    assert cells[r, c] == OCCUPIED


def test_frontier_goal_lies_at_the_edge_of_what_was_seen() -> None:
    mapper = make_mapper()
    pose = Pose2D(0.0, 0.0, 0.0)
    open_floor = np.ones((HEIGHT, WIDTH), bool)
    for t in range(3):
        mapper.update(open_floor, pose, now_s=0.1 * t)
    search = mapper.frontiers(pose)
    assert search.goal is not None, search.reason
    assert search.clusters
    x, _ = search.goal.xy
    assert 0.0 < x <= 2.6  # at the far edge or the sides of the seen wedge


def sim_mapper(world: str | None = None, **mapping: object) -> tuple[GroundMapper, object, object]:
    from app.config import load_config
    from app.perception.pipeline import FloorSegmenter
    from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration

    sim = {} if world is None else {"world_file": world}
    config = load_config(
        Path(__file__).resolve().parents[2] / "config.toml", mapping=mapping, sim=sim
    )
    mapper = GroundMapper(
        sim_floor_calibration(camera_model(config)), config.mapping, config.camera
    )
    return mapper, renderer_from_config(config), FloorSegmenter(config.perception)


def test_parallax_confirms_floor_past_the_doorway_and_carries_it_between_tests() -> None:
    from app.mapping.ground_map import PARALLAX_CARRY_S, PARALLAX_PERIOD_S

    mapper, renderer, segmenter = sim_mapper(parallax_floor=True)
    plain, _, _ = sim_mapper(parallax_floor=False)
    assert mapper.parallax is not None and plain.parallax is None
    floor_cells = []
    for k, x in enumerate((3.83, 3.95, 3.96)):  # 0.12 m, then 0.01 m further on
        pose = Pose2D(x, 3.05, 0.0)
        frame = renderer.render(pose)  # type: ignore[attr-defined]
        mask = segmenter.segment(frame.image).floor_mask  # type: ignore[attr-defined]
        now = 0.05 * k  # the third frame comes before the next test is due
        update = mapper.update(mask, pose, now, frame.image)
        baseline = plain.update(mask, pose, now, frame.image)
        floor_cells.append(((update.patch == FLOOR).sum(), (baseline.patch == FLOOR).sum()))
    assert PARALLAX_PERIOD_S > 0.05 and PARALLAX_CARRY_S > 0.1
    assert mapper.parallax_frames == 1  # the first frame had no reference
    assert floor_cells[0][0] == floor_cells[0][1]
    # Confirmed: the tiles past the threshold add floor; carried to the next frame.
    assert floor_cells[1][0] > floor_cells[1][1] + 500
    assert floor_cells[2][0] > floor_cells[2][1] + 500


def _doorway_frames(
    renderer: object, segmenter: object, xs: tuple[float, ...]
) -> list[tuple[Pose2D, NDArray[np.bool_], NDArray[np.uint8]]]:
    frames = []
    for x in xs:
        pose = Pose2D(x, 3.05, 0.0)
        frame = renderer.render(pose)  # type: ignore[attr-defined]
        mask = segmenter.segment(frame.image).floor_mask  # type: ignore[attr-defined]
        frames.append((pose, mask, frame.image))
    return frames


def test_a_deferred_parallax_test_is_adopted_by_the_next_frame_as_inline_it_is_by_its_own() -> None:
    """`geometry="defer"` (the daemon: the test runs on another thread) hands the test
    out and the next frame adopts it: that frame's floor gains what the inline test gave
    its own frame (carried 1 cm on), and the floor memory ends the same."""
    from app.mapping.ground_map import run_geometry_job

    inline, renderer, segmenter = sim_mapper(parallax_floor=True)
    deferred, _, _ = sim_mapper(parallax_floor=True)
    frames = _doorway_frames(renderer, segmenter, (3.83, 3.95, 3.96))
    inline_floor, deferred_floor = [], []
    outcome = None
    for k, (pose, mask, image) in enumerate(frames):
        now = 0.05 * k
        inline_floor.append((inline.update(mask, pose, now, image).patch == FLOOR).sum())
        update = deferred.update(mask, pose, now, image, geometry="defer", geometry_outcome=outcome)
        deferred_floor.append((update.patch == FLOOR).sum())
        outcome = run_geometry_job(update.geometry_job) if update.geometry_job else None
        # The first frame has no reference view, but the walls test is due.
        assert (update.geometry_job is not None) == (k in (0, 1))
    assert outcome is None and deferred.parallax_frames == inline.parallax_frames == 1
    assert deferred_floor[0] == inline_floor[0]
    assert deferred_floor[1] < inline_floor[1] - 500  # not tested yet...
    assert deferred_floor[2] == pytest.approx(inline_floor[2], rel=0.02)  # ...now adopted
    for kind in ("confirmed", "standing"):
        a, b = getattr(inline.memory, kind) != 0, getattr(deferred.memory, kind) != 0
        assert (a & b).sum() >= 0.95 * max(a.sum(), b.sum()) > 0


def test_a_held_test_stays_due_and_a_test_from_a_replaced_map_is_dropped() -> None:
    from app.mapping.ground_map import run_geometry_job

    mapper, renderer, segmenter = sim_mapper(parallax_floor=True)
    frames = _doorway_frames(renderer, segmenter, (3.83, 3.95))
    (pose0, mask0, image0), (pose1, mask1, image1) = frames
    assert mapper.update(mask0, pose0, 0.0, image0, geometry="hold").geometry_job is None
    first = mapper.update(mask0, pose0, 0.01, image0, geometry="defer").geometry_job
    assert first is not None and first.walls and first.parallax is None  # no view yet
    job = mapper.update(mask1, pose1, 0.3, image1, geometry="defer").geometry_job
    assert job is not None and job.parallax is not None
    outcome = run_geometry_job(job)
    mapper.restore(mapper.snapshot())  # the same map, loaded again: a new generation
    mapper.update(mask1, pose1, 0.31, image1, geometry="hold", geometry_outcome=outcome)
    assert mapper.parallax_frames == 0


def test_an_adopted_test_moves_with_the_corrections_made_while_it_ran() -> None:
    """A correction that moved the kept views while the test ran moves the test's pose
    too (its confirmed floor is carried from there); one made before the job was cut
    does not."""
    from app.mapping.ground_map import run_geometry_job

    mapper, renderer, segmenter = sim_mapper(parallax_floor=True, scan_matching=False)
    frames = _doorway_frames(renderer, segmenter, (3.83, 3.95, 3.96))
    mapper.update(frames[0][1], frames[0][0], 0.0, frames[0][2])
    mapper._move_views(Pose2D(0.5, 0.0, 0.0))  # before the cut: already in the views
    pose, mask, image = frames[1]
    moved_pose = Pose2D(0.5, 0.0, 0.0).compose(pose)
    job = mapper.update(mask, moved_pose, 0.3, image, geometry="defer").geometry_job
    assert job is not None and job.parallax is not None
    correction = Pose2D(0.01, -0.02, 0.03)
    mapper._move_views(correction)
    mapper.update(mask, moved_pose, 0.31, image, geometry_outcome=run_geometry_job(job))
    assert mapper._confirmed is not None
    then = mapper._confirmed[1]
    expected = correction.compose(moved_pose)
    assert then == pytest.approx((expected.x_m, expected.y_m, expected.theta_rad))


def test_parallax_is_off_for_frames_with_lens_distortion() -> None:
    from dataclasses import replace

    from app.mapping.calibration import Intrinsics

    mapper, _, _ = sim_mapper(parallax_floor=True)
    assert mapper.parallax is not None
    intrinsics = Intrinsics(
        np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), np.zeros(5), (640, 480), 0.1
    )
    distorted = GroundMapper(
        replace(mapper.calibration, intrinsics=intrinsics), mapper.mapping, CameraConfig()
    )
    assert distorted.parallax is None


def test_a_standing_mapper_keeps_its_map_for_ten_minutes() -> None:
    mapper = make_mapper()  # the default configuration's decay
    reference = OccupancyGrid(
        mapper.grid.world_grid, replace(mapper.grid.params, half_distance_m=math.inf)
    )
    pose = Pose2D(0.3, -0.2, 0.4)
    mask = wall_mask(mapper, 1.2)
    for k in range(3):
        update = mapper.update(mask, pose, now_s=0.1 * k)
        reference.update(update.patch, mapper.birdseye.grid, pose, mapper.camera_xy_robot)
    classes = mapper.grid.classify()
    # The robot waits (stopped, faulted) while frames keep coming, one a second.
    for second in range(1, 601):
        update = mapper.update(mask, pose, now_s=float(second))
        assert update.summary.decayed is False
        reference.update(update.patch, mapper.birdseye.grid, pose, mapper.camera_xy_robot)
    np.testing.assert_array_equal(mapper.grid.log_odds, reference.log_odds)
    np.testing.assert_array_equal(mapper.grid.classify(), classes)
    assert mapper.grid.travelled_m == 0.0


def test_restore_puts_a_snapshot_into_a_fresh_mapper() -> None:
    mapper = make_mapper()
    for k in range(3):
        mapper.update(wall_mask(mapper, 1.2), Pose2D(0.1 * k, 0.0, 0.05 * k), now_s=0.1 * k)
    snapshot = mapper.snapshot()
    fresh = make_mapper()
    fresh.restore(snapshot)
    np.testing.assert_array_equal(fresh.grid.log_odds, mapper.grid.log_odds)
    assert fresh.snapshot().T_world_robot == Pose2D(0.2, 0.0, 0.1)
    assert fresh.grid.travelled_m == mapper.grid.travelled_m > 0
    pose = Pose2D(0.2, 0.0, 0.1)
    restored_goal, goal = fresh.frontiers(pose).goal, mapper.frontiers(pose).goal
    assert restored_goal is not None and goal is not None
    assert restored_goal.xy == goal.xy


def test_a_floor_coloured_box_the_mask_calls_floor_is_an_obstacle_by_the_horizon() -> None:
    """The shipped world's cardboard box (0.35 m, taller than the camera) 0.7 m ahead,
    under a mask that calls all of it floor: the horizon test stops the floor at its
    base, so the clearance ahead is the box's, not the camera's range."""
    from app.runtime.stages import clearance_ahead_m

    mapper, renderer, _ = sim_mapper(standing_by_horizon=True, parallax_floor=False)
    plain, _, _ = sim_mapper(standing_by_horizon=False, parallax_floor=False)
    box_xy, heading, distance = (2.4, 3.7), 2.982, 0.7
    pose = Pose2D(
        box_xy[0] - distance * math.cos(heading), box_xy[1] - distance * math.sin(heading), heading
    )
    frame = renderer.render(pose)  # type: ignore[attr-defined]
    red, blue = frame.image[..., 2].astype(int), frame.image[..., 0].astype(int)
    mask = frame.floor_mask | (red - blue > 30)  # the brown box called floor; walls grey
    radius, reach = mapper.mapping.robot_radius_m, mapper.mapping.max_range_m
    # Two frames: a cell joins the standing layer once two tests marked it.
    for now_s in (0.0, WALLS_PERIOD_S):
        found = mapper.update(mask, pose, now_s, frame.image)
        missed = plain.update(mask, pose, now_s, frame.image)
    clear_found = clearance_ahead_m(found.patch, mapper.birdseye.grid, radius, reach)
    clear_missed = clearance_ahead_m(missed.patch, plain.birdseye.grid, radius, reach)
    # The box's near face is 0.7 - 0.175 m from the robot's centre (its half depth).
    expected = distance - 0.175 - radius
    assert clear_found == pytest.approx(expected, abs=0.06)
    assert clear_missed > expected + 1.0
    assert mapper.standing_frames == 2 and plain.standing_frames == 0
    # The floor memory marks what stands where it stands (the box, and the brown things
    # beyond it the mask also called floor), not along the rays their faces project to
    # through the floor homography, up to the camera's range behind them.
    truth_grid, truth = renderer.world.occupancy(0.05)  # type: ignore[attr-defined]
    to_obstacle_m = cv2.distanceTransform((truth == 0).astype(np.uint8), cv2.DIST_L2, 5) * 0.05
    x, y = mapper.memory.world_grid.cell_centers()
    marked = mapper.memory.standing != 0
    at_box = np.hypot(x[marked] - box_xy[0], y[marked] - box_xy[1]) < 0.35
    assert at_box.sum() >= 5
    rc = truth_grid.cell_of(np.column_stack((x[marked], y[marked])))
    # Half at least lie at a true obstacle (marking whole rays: 200 of 1549 cells).
    assert (to_obstacle_m[rc[:, 0], rc[:, 1]] <= 0.15).mean() >= 0.5


def test_a_plain_walls_foot_is_remembered_standing_and_kept_from_edge_probes() -> None:
    """The left room's plain wall 1.5 m ahead: parallax sees nothing on it, but it runs
    from where the floor ends to past the horizon, so its foot is marked standing and
    the frontier search does not send the robot to probe it as an unproven edge."""
    # The wall is mapped from 1.5 m away (the default maps obstacles only within 1 m).
    far = {"obstacle_evidence_range_m": 2.0}
    mapper, renderer, segmenter = sim_mapper(standing_by_horizon=True, parallax_floor=False, **far)
    plain, _, _ = sim_mapper(standing_by_horizon=False, parallax_floor=False, **far)
    pose = Pose2D(1.5, 3.0, math.pi)  # facing the wall at x = 0
    frame = renderer.render(pose)  # type: ignore[attr-defined]
    mask = segmenter.segment(frame.image).floor_mask  # type: ignore[attr-defined]
    # Two frames a walls test apart: a cell joins the standing layer once two tests
    # marked it.
    for now_s in (0.0, WALLS_PERIOD_S):
        mapper.update(mask, pose, now_s, frame.image)
        plain.update(mask, pose, now_s, frame.image)
    assert not (plain.memory.standing != 0).any()
    x, y = mapper.memory.world_grid.cell_centers()
    marked = mapper.memory.standing != 0
    assert marked.sum() >= 10
    # All at the wall's foot (its inner face is at x = 0.05 m), across the view.
    assert np.all(x[marked] <= 0.2)
    assert y[marked].max() - y[marked].min() >= 0.8
    # The wall's occupied cells are no edge to probe (the mapper without the test sees
    # them as unproven edges).
    occupied = mapper.grid.classify() == OCCUPIED
    wall = occupied & (x <= 0.2)
    assert wall.sum() >= 10
    assert not (mapper.frontier_probe_cells() & wall).any()
    assert plain.frontier_probe_cells()[wall].all()
    # The report's share of probe-able edges says the same.
    assert plain.probe_edge_share() == 1.0
    assert mapper.probe_edge_share() is not None
    assert mapper.probe_edge_share() <= 1.0 - wall.sum() / occupied.sum() + 1e-9


def test_a_doorway_between_walls_seen_standing_is_probed_through_its_threshold() -> None:
    """A 1 m doorway whose threshold the map holds as an edge, on the line of two walls
    whose feet geometry saw: the walls are no edge to probe, the threshold is, and the
    probe search finds its way through the door to the unknown room past it (0.3 m kept
    from each jamb left it none: the home ended at its kitchen door)."""
    mapper, _, _ = sim_mapper()
    grid = mapper.grid.world_grid
    x, y = grid.cell_centers()
    room = (np.abs(x) < 1.0) & (np.abs(y) < 1.0)
    wall_line = (x >= 1.0) & (x < 1.1) & (np.abs(y) < 1.1)
    door = wall_line & (np.abs(y) < 0.5)
    walls = (wall_line & ~door) | ((np.abs(x) < 1.1) & (np.abs(y) >= 1.0) & (np.abs(y) < 1.1))
    walls |= (x <= -1.0) & (x > -1.1) & (np.abs(y) < 1.1)
    log_odds = np.zeros(grid.shape, np.float32)
    log_odds[room] = -2.0
    log_odds[walls | door] = 2.0
    mapper.grid.log_odds[...] = log_odds
    feet = np.flatnonzero(walls.reshape(-1)).astype(np.int64)
    for _ in range(2):  # two tests saw each foot where it stands
        mapper.memory.mark_standing(feet, seen_cells=feet)
    probe_cells = mapper.frontier_probe_cells()
    assert not (probe_cells & walls).any()
    threshold = door & (np.abs(y) < 0.3)
    assert probe_cells[threshold].all()
    goal = mapper.frontiers(Pose2D(0.0, 0.0, 0.0)).goal
    assert goal is not None and goal.probe and goal.edge_cells is not None
    rows, cols = goal.edge_cells.T
    assert door[rows, cols].all()
    # It looks from inside the room, before the door.
    assert 0.6 <= goal.xy[0] < 1.0 and abs(goal.xy[1]) < 0.5


def test_a_floor_coloured_box_side_the_mask_half_calls_floor_is_mapped_at_its_foot() -> None:
    """Driving north past the home's wood-coloured ottoman, 0.14 m from its east side:
    the shipped segmenter calls the lower half of that side floor, which the floor
    homography puts on and past the box. The walls test finds that half standing
    (`wall_surfaces`), and the frames between tests leave it out too, so the side is
    an obstacle in the map rather than floor (a robot once grazed its corner)."""
    found, renderer, segmenter = sim_mapper("home")
    plain, _, _ = sim_mapper("home", standing_by_horizon=False)
    for k, y in enumerate(np.arange(3.55, 3.96, 0.02)):
        pose = Pose2D(4.3, float(y), math.pi / 2)
        frame = renderer.render(pose)  # type: ignore[attr-defined]
        mask = segmenter.segment(frame.image).floor_mask  # type: ignore[attr-defined]
        for mapper in (found, plain):
            mapper.update(mask, pose, k / 15, frame.image)
    # The east side runs from (4.156, 4.111) to (4.089, 4.556): the cells within 5 cm.
    x, y = found.grid.world_grid.cell_centers()
    along = np.clip(((x - 4.156) * -0.067 + (y - 4.111) * 0.445) / (0.067**2 + 0.445**2), 0, 1)
    side = (np.hypot(x - (4.156 - 0.067 * along), y - (4.111 + 0.445 * along)) <= 0.05) & (x > 4.0)
    assert side.sum() == 22
    occupied_found = int((found.grid.remembered_classes()[side] == OCCUPIED).sum())
    occupied_plain = int((plain.grid.remembered_classes()[side] == OCCUPIED).sum())
    assert occupied_found >= 8 and occupied_plain <= 3


def test_unsure_pixels_give_no_evidence_and_the_rest_fuses_as_without() -> None:
    """A deferred learned-floor pass: where it could have found floor the first pass's
    "not floor" must not become a wall (the pass, later, may call it floor)."""
    # Obstacles mapped out to 2 m: the cabinets 1.6 m ahead count.
    plain, held_back = (
        make_mapper(obstacle_evidence_range_m=2.0),
        make_mapper(obstacle_evidence_range_m=2.0),
    )
    pose = Pose2D(0.0, 0.0, 0.0)
    mask = wall_mask(plain, 1.2)  # the first pass stops at 1.2 m: the kitchen threshold
    rows = plain.calibration.ground_to_image(np.array([[1.2, 0.0], [1.6, 0.0]]))[:, 1]
    unsure = np.zeros_like(mask)
    # 1.2-1.6 m: the kitchen's tiles, which a pass relative to their colour could call
    # floor; the cabinets beyond, 1.6 m ahead, are not unsure.
    unsure[int(np.ceil(rows[1])) : int(np.ceil(rows[0]))] = True
    for t in range(3):
        plain.update(mask, pose, now_s=0.1 * t)
        held_back.update(mask, pose, now_s=0.1 * t, unsure_mask=unsure)
    grid = plain.grid.world_grid
    row_col = grid.cell_of(np.array([[0.8, 0.0], [1.22, 0.0], [1.4, 0.0], [1.62, 0.0]]))
    states = [[int(m.grid.classify()[r, c]) for r, c in row_col] for m in (plain, held_back)]
    assert states == [[FREE, OCCUPIED, UNKNOWN, UNKNOWN], [FREE, UNKNOWN, UNKNOWN, OCCUPIED]]
    # Up to the unsure band the evidence is the same, cell for cell.
    near = grid.cell_of(np.array([[x, 0.0] for x in np.arange(0.3, 1.15, 0.05)]))
    for r, c in near:
        assert plain.grid.log_odds[r, c] == held_back.grid.log_odds[r, c]


def test_a_floor_finished_panel_parallax_saw_standing_ends_the_floor_at_its_foot() -> None:
    """The shipped world's wall panel with the floor's own finish (y = 0.05), driven at
    head-on: the colour mask calls most of it floor and the panel is too low for the
    horizon test, but parallax sees its planks stand up, so the floor of those columns
    ends at the panel's foot and the clearance ahead is the panel's, on the tested frame
    and on the next one (carried)."""
    from app.runtime.stages import clearance_ahead_m

    mapper, renderer, segmenter = sim_mapper(parallax_floor=True)
    heading, foot_y, radius = -math.pi / 2 - 0.26, 0.05, mapper.mapping.robot_radius_m
    reach = mapper.mapping.max_range_m
    clearances = []
    for k, distance in enumerate((0.62, 0.50, 0.49)):  # a 0.12 m baseline, then 1 cm on
        pose = Pose2D(
            1.97 - distance * math.cos(heading), foot_y - distance * math.sin(heading), heading
        )
        frame = renderer.render(pose)  # type: ignore[attr-defined]
        mask = segmenter.segment(frame.image).floor_mask  # type: ignore[attr-defined]
        assert (mask & ~frame.floor_mask).mean() > 0.1  # the mask takes the panel for floor
        update = mapper.update(mask, pose, 0.05 * k, frame.image)
        clearances.append(clearance_ahead_m(update.patch, mapper.birdseye.grid, radius, reach))
    assert mapper.parallax_frames == 1
    # Straight ahead the panel's foot is distance / cos(0.26) from the robot's centre.
    for distance, clearance in zip((0.50, 0.49), clearances[1:], strict=True):
        assert clearance == pytest.approx(distance / math.cos(0.26) - radius, abs=0.08)
    assert clearances[0] > clearances[1] + 0.3  # before any test: the floor ran on


def test_a_foot_marked_where_the_floor_ended_too_soon_leaves_once_floor_is_seen_past_it() -> None:
    """A plain view (a threshold, then a plain far wall): while the mask ends the floor
    0.8 m ahead, the walls test puts the foot there; once the floor is seen to 1.3 m
    (its material learned), tests that see floor on the old foot take its marks away.
    A mark needs two tests to stand and saturates at three."""
    mapper, _, _ = sim_mapper(standing_by_horizon=True, parallax_floor=False)
    pose = Pose2D(0.0, 0.0, 0.0)
    image = np.full((480, 640, 3), 120, np.uint8)
    x, _ = mapper.memory.world_grid.cell_centers()

    def floor_to(distance_m: float) -> np.ndarray:
        row = mapper.calibration.ground_to_image(np.array([[distance_m, 0.0]]))[0, 1]
        mask = np.zeros(image.shape[:2], bool)
        mask[int(row) :] = True
        return mask

    def standing_near(distance_m: float) -> int:
        return int(((mapper.memory.standing != 0) & (np.abs(x - distance_m) < 0.1)).sum())

    seen = []
    for k, distance_m in enumerate((0.8, 0.8, 0.8, 1.3, 1.3)):
        mapper.update(floor_to(distance_m), pose, k * WALLS_PERIOD_S, image)
        seen.append((standing_near(0.8) > 0, standing_near(1.3) > 0))
    assert seen == [
        (False, False),  # one test's foot
        (True, False),
        (True, False),  # three marks
        (True, False),  # floor seen on it once: two left; the new foot has one
        (False, True),
    ]


def test_the_map_says_how_much_of_the_safe_zone_it_knows_is_floor_and_none_with_a_foot_in_it() -> (
    None
):
    """`MapUpdate.zone_known_floor`: the share of the safe zone's ground the memory holds
    as confirmed floor, 0 when geometry sees something standing in the zone (a plain
    view whose floor ends inside the zone: the walls test finds a foot there)."""
    from app.config import load_config
    from app.perception.pipeline import trapezoid_from_config
    from app.perception.safe_zone import safe_zone_mask

    mapper, _, _ = sim_mapper(standing_by_horizon=True, parallax_floor=False)
    image = np.full((480, 640, 3), 120, np.uint8)
    zone = safe_zone_mask(
        image.shape[:2], trapezoid_from_config(load_config(None).perception.safe_zone)
    )
    rows = np.flatnonzero(zone.any(axis=1))
    near_m, far_m = mapper.calibration.image_to_ground(
        np.array([[320.0, rows[-1]], [320.0, rows[0]]])
    )[:, 0]
    assert 0.25 < near_m < far_m < near_m + 0.1 < 0.4  # the shipped zone, ~0.3 m ahead
    pose = Pose2D(0.0, 0.0, 0.0)

    def floor_to(distance_m: float) -> np.ndarray:
        row = mapper.calibration.ground_to_image(np.array([[distance_m, 0.0]]))[0, 1]
        mask = np.zeros(image.shape[:2], bool)
        mask[int(row) :] = True
        return mask

    def known(distance_m: float, k: int) -> float | None:
        update = mapper.update(
            floor_to(distance_m), pose, k * WALLS_PERIOD_S, image, safe_zone_px=zone
        )
        return update.zone_known_floor

    open_m = far_m + 0.6
    assert known(open_m, 0) == 0.0  # nothing confirmed yet
    x, y = mapper.memory.world_grid.cell_centers()
    # Confirmed floor on the left half of the way ahead: about half the zone is known.
    mapper.memory.confirm_cells(np.flatnonzero((x > 0) & (x < open_m) & (y >= 0) & (y < 1)))
    assert 0.3 < known(open_m, 1) < 0.7
    mapper.memory.confirm_cells(np.flatnonzero((x > 0) & (x < open_m) & (np.abs(y) < 1)))
    assert known(open_m, 2) == 1.0
    # The floor ends in the middle of the zone: a foot in the zone, nothing known there.
    assert known((near_m + far_m) / 2, 3) == 0.0
    # Back to the open view: the foot's cells (most of the zone: its ground is 8 cm deep,
    # two rows of cells) are no longer known floor until they are confirmed again.
    again = known(open_m, 4)
    assert again is not None and 0.0 < again < 0.5
    # Without the zone the mapper says nothing.
    assert mapper.update(floor_to(open_m), pose, 5 * WALLS_PERIOD_S, image).zone_known_floor is None


def test_feet_seen_standing_are_those_at_the_standing_things_own_base() -> None:
    """`_FeetGeometry.seen_feet`: a leg standing right on the floor has its foot seen;
    one beyond a not-floor gap (a threshold, tiles) has its foot placed where the floor
    ended, and that foot is not seen."""
    rows_m = np.array([np.nan, 3.0, 2.0, 1.2, 1.15, 1.1])
    feet_geometry = _FeetGeometry(None, rows_m)
    standing = np.zeros((6, 2), bool)
    standing[1:3, :] = True
    floor = np.zeros((6, 2), bool)
    floor[3:, 0] = True  # column 0: the floor reaches the leg
    floor[4:, 1] = True  # column 1: row 3 is a gap of not-floor below it
    feet = feet_geometry.feet(standing, floor)
    assert np.flatnonzero(feet[:, 0]).tolist() == [2]
    assert np.flatnonzero(feet[:, 1]).tolist() == [3]
    seen = feet_geometry.seen_feet(standing, feet)
    assert np.flatnonzero(seen[:, 0]).tolist() == [2]
    assert not seen[:, 1].any()
