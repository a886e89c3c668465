"""Virtual range scans from bird's-eye patches, and correlative scan matching."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from app.config import FloornavConfig, MappingConfig
from app.mapping.frames import FLOOR, NOT_FLOOR, UNSEEN, GroundGrid, Pose2D
from app.mapping.ground_map import GroundMapper
from app.mapping.scan_match import (
    LikelihoodField,
    LocalizerParams,
    MatchParams,
    ScanLocalizer,
    blend,
    likelihood_field,
    match_scan,
    view_bearings,
    virtual_scan,
)
from app.sim.setup import camera_model, sim_floor_calibration

FreeFn = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.bool_]]

WORLD = GroundGrid.covering(x_min_m=-6.0, x_max_m=6.0, y_min_m=-6.0, y_max_m=6.0, cell_m=0.05)
PATCH = GroundGrid.covering(x_min_m=0.1, x_max_m=3.0, y_min_m=-1.5, y_max_m=1.5, cell_m=0.01)
CAMERA = (0.1, 0.0)
HALF_FOV_RAD = math.radians(32.0)
MAX_RANGE_M = 3.0
OCCUPIED_THRESHOLD = 0.5
THRESHOLDS = (-0.5, OCCUPIED_THRESHOLD)
OFFSET = (0.1, -0.08, math.radians(3.0))
"""The prior's error in the brief: (x_m, y_m, theta_rad)."""


def room(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.bool_]:
    """A 4.5 x 3.3 m room with a box in it (walls off the map's cell edges, as walls are)."""
    inside = (x > -1.98) & (x < 2.53) & (y > -1.47) & (y < 1.81)
    box = (x > 1.22) & (x < 1.61) & (y > -0.88) & (y < -0.41)
    return np.asarray(inside & ~box)


def l_corridor(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.bool_]:
    """A 1 m wide corridor along x that turns left at its end."""
    along_x = (x > -3.02) & (x < 2.03) & (y > -0.51) & (y < 0.48)
    along_y = (x > 1.03) & (x < 2.03) & (y > -0.51) & (y < 4.01)
    return np.asarray(along_x | along_y)


def one_wall(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Open floor up to a straight wall at x = 2.02 (nothing else to see)."""
    return np.asarray(x < 2.02)


def map_of(free: FreeFn) -> NDArray[np.float32]:
    """Log-odds as the mapper leaves them: occupied where a 1 cm raster's not-free cells
    lie within the 3 cm obstacle band beyond the floor, free where the floor is."""
    fine = 5
    x, y = GroundGrid(
        WORLD.x_max_m, WORLD.y_max_m, WORLD.cell_m / fine, WORLD.rows * fine, WORLD.cols * fine
    ).cell_centers()
    is_free = free(x, y)
    to_floor_cells = cv2.distanceTransform(
        np.where(is_free, 0, 255).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE
    )
    band = ~is_free & (to_floor_cells <= 3.0)
    occupied = band.reshape(WORLD.rows, fine, WORLD.cols, fine).any(axis=(1, 3))
    floor = is_free.reshape(WORLD.rows, fine, WORLD.cols, fine).all(axis=(1, 3))
    log_odds = np.zeros(WORLD.shape, np.float32)
    log_odds[floor] = -1.5
    log_odds[occupied] = 2.0
    return log_odds


def patch_of(free: FreeFn, T_world_robot: Pose2D) -> NDArray[np.uint8]:
    """What the camera at ``T_world_robot`` sees: floor / not floor inside its wedge."""
    x, y = PATCH.cell_centers()
    bearing = np.arctan2(y - CAMERA[1], x - CAMERA[0])
    distance = np.hypot(x - CAMERA[0], y - CAMERA[1])
    visible = (np.abs(bearing) <= HALF_FOV_RAD) & (distance <= MAX_RANGE_M)
    world = T_world_robot.apply(np.column_stack((x.ravel(), y.ravel())))
    is_free = free(world[:, 0], world[:, 1]).reshape(PATCH.shape)
    patch = np.full(PATCH.shape, UNSEEN, np.uint8)
    patch[visible & is_free] = FLOOR
    patch[visible & ~is_free] = NOT_FLOOR
    return patch


def bearings() -> NDArray[np.float64]:
    x, y = PATCH.cell_centers()
    visible = np.abs(np.arctan2(y - CAMERA[1], x - CAMERA[0])) <= HALF_FOV_RAD
    return view_bearings(visible & (np.hypot(x - CAMERA[0], y) <= MAX_RANGE_M), PATCH, CAMERA)


def scan_points(free: FreeFn, T_world_robot: Pose2D) -> NDArray[np.float64]:
    scan = virtual_scan(
        patch_of(free, T_world_robot),
        PATCH,
        CAMERA,
        bearings(),
        max_range_m=MAX_RANGE_M,
        endpoint_depth_m=LocalizerParams().endpoint_depth_m,
    )
    return scan.points_robot


def offset(pose: Pose2D) -> Pose2D:
    dx, dy, dtheta = OFFSET
    return Pose2D(pose.x_m + dx, pose.y_m + dy, pose.theta_rad + dtheta)


def field_around(free: FreeFn, pose: Pose2D) -> LikelihoodField:
    return likelihood_field(
        map_of(free),
        WORLD,
        (pose.x_m, pose.y_m),
        3.6,
        occupied_threshold=OCCUPIED_THRESHOLD,
        sigma_m=0.05,
    )


# ------------------------------------------------------------------------ virtual scan


def test_virtual_scan_ranges_are_exact_to_a_wall_ahead_and_beside() -> None:
    # Floor up to a wall at x = 1.0 ahead, and up to one at y = 0.5 on the left.
    x, y = PATCH.cell_centers()
    patch = np.where((x < 1.0) & (y < 0.5), FLOOR, NOT_FLOOR).astype(np.uint8)
    angles = np.radians([0.0, 10.0, -20.0, 40.0, 70.0])
    scan = virtual_scan(patch, PATCH, CAMERA, angles, max_range_m=MAX_RANGE_M)
    ahead = 0.9 / np.cos(angles)
    with np.errstate(divide="ignore"):
        left = 0.5 / np.sin(angles)
    expected = np.where((angles > 0) & (left < ahead), left, ahead)
    assert scan.hit.all()
    np.testing.assert_allclose(scan.ranges_m, expected, atol=1e-9)
    np.testing.assert_allclose(
        scan.points_robot[:, 0], CAMERA[0] + expected * np.cos(angles), atol=1e-9
    )


def test_virtual_scan_gives_no_return_without_a_floor_boundary() -> None:
    x, y = PATCH.cell_centers()
    patch = np.full(PATCH.shape, FLOOR, np.uint8)
    patch[x > 1.5] = UNSEEN  # floor runs out of view: no return
    patch[(x > 1.0) & (x < 1.03)] = UNSEEN  # a 3 cm unseen seam is passed over
    patch[(y < -0.5) & (x > 2.0)] = FLOOR
    patch[(y < -0.5) & (x > 2.5)] = NOT_FLOOR  # the floor ends at 2.5 on the right
    # Not floor from the camera on (bearings above 30 degrees): its foot is out of view.
    patch[np.arctan2(y - CAMERA[1], x - CAMERA[0]) > math.radians(30.0)] = NOT_FLOOR
    angles = np.array([0.0, -math.atan2(1.0, 2.6), math.radians(60.0)])
    scan = virtual_scan(patch, PATCH, CAMERA, angles, max_range_m=MAX_RANGE_M, max_gap_m=0.1)
    assert scan.hit.tolist() == [False, False, False]
    # Without the 2 m of unseen floor, the ray to the right reaches the boundary.
    patch[(y < -0.5) & (x > 1.5) & (x < 2.0)] = FLOOR
    scan = virtual_scan(patch, PATCH, CAMERA, angles[1:2], max_range_m=MAX_RANGE_M)
    assert scan.hit.tolist() == [True]
    x_hit = CAMERA[0] + scan.ranges_m[0] * math.cos(angles[1])
    assert x_hit == pytest.approx(2.5, abs=1e-9)


def test_virtual_scan_stops_at_max_range() -> None:
    x, _ = PATCH.cell_centers()
    patch = np.where(x < 2.5, FLOOR, NOT_FLOOR).astype(np.uint8)
    angles = np.zeros(1)
    assert virtual_scan(patch, PATCH, CAMERA, angles, max_range_m=2.0).hit.tolist() == [False]
    assert virtual_scan(patch, PATCH, CAMERA, angles, max_range_m=2.5).hit.tolist() == [True]


def test_view_bearings_span_the_visible_wedge() -> None:
    b = bearings()
    assert b[0] == pytest.approx(-HALF_FOV_RAD, abs=math.radians(1.0))
    assert b[-1] == pytest.approx(HALF_FOV_RAD, abs=math.radians(1.0))
    np.testing.assert_allclose(np.diff(b), math.radians(1.0))


# ---------------------------------------------------------------------------- matching


@pytest.mark.parametrize(
    ("free", "truth"),
    [
        (room, Pose2D(0.3, 0.2, math.radians(-25.0))),
        (room, Pose2D(-1.0, 1.0, math.radians(150.0))),
        (l_corridor, Pose2D(-0.5, 0.05, math.radians(4.0))),
    ],
    ids=["room-corner", "room-back", "l-corridor"],
)
def test_a_scan_from_a_known_pose_is_matched_back(free: FreeFn, truth: Pose2D) -> None:
    """Within one map cell and one degree (5 cm cells resolve no finer a heading than
    that: a cell at the scan's 3 m range), from a prior 13 cm and 3 degrees off."""
    points = scan_points(free, truth)
    assert len(points) >= 40
    prior = offset(truth)
    params = MatchParams()
    match = match_scan(field_around(free, prior), points, prior, params)
    error = math.hypot(match.T_world_robot.x_m - truth.x_m, match.T_world_robot.y_m - truth.y_m)
    assert error <= WORLD.cell_m
    turn = math.remainder(match.T_world_robot.theta_rad - truth.theta_rad, math.tau)
    assert abs(turn) <= math.radians(1.0) + 1e-9
    assert match.score > match.prior_score + 0.2
    assert match.confident(params), (match.xy_std_m, match.theta_std_rad, match.score)


def test_a_straight_wall_is_uncertain_along_the_wall_and_not_confident() -> None:
    truth = Pose2D(0.0, 0.0, 0.0)
    points = scan_points(one_wall, truth)
    prior = offset(truth)
    params = MatchParams()
    match = match_scan(field_around(one_wall, prior), points, prior, params)
    # Across the wall (x) the match is sharp and right; along it (y) anything goes.
    assert abs(match.T_world_robot.x_m - truth.x_m) <= WORLD.cell_m
    assert math.sqrt(match.covariance[0, 0]) < 0.02
    assert math.sqrt(match.covariance[1, 1]) > params.max_xy_std_m
    assert match.xy_std_m > params.max_xy_std_m
    assert not match.confident(params)


def test_a_scan_that_does_not_fit_the_map_is_not_confident() -> None:
    truth = Pose2D(0.3, 0.2, math.radians(-25.0))
    points = scan_points(room, truth)
    prior = offset(truth)
    match = match_scan(field_around(l_corridor, prior), points, prior)
    assert not match.confident(MatchParams())


def test_too_few_points_return_the_prior() -> None:
    prior = Pose2D(1.0, 2.0, 0.3)
    match = match_scan(field_around(room, prior), np.zeros((3, 2)), prior)
    assert match.T_world_robot == prior
    assert not match.confident(MatchParams())


def test_matching_is_fast() -> None:
    """Few milliseconds for ~60 points and the default +-0.15 m, +-6 degree window
    (the first calls compile or load the kernels)."""
    truth = Pose2D(0.3, 0.2, math.radians(-25.0))
    points = scan_points(room, truth)
    prior = offset(truth)
    field_ = field_around(room, prior)
    match_scan(field_, points, prior)
    durations = []
    for _ in range(5):
        start = time.perf_counter()
        match_scan(field_, points, prior)
        durations.append(time.perf_counter() - start)
    assert min(durations) < 0.02


# --------------------------------------------------------------------------- localizer


def localizer(period_s: float = 0.25) -> ScanLocalizer:
    return ScanLocalizer(LocalizerParams(period_s=period_s), PATCH, CAMERA, bearings())


def test_localizer_corrects_part_of_the_way_capped() -> None:
    truth = Pose2D(0.3, 0.2, math.radians(-25.0))
    prior = offset(truth)
    loc = localizer()
    found = loc.localize(patch_of(room, truth), map_of(room), WORLD, THRESHOLDS, prior, now_s=0.0)
    assert found is not None and found.T_corrected_odom is not None
    assert found.seconds > 0
    corrected = found.T_corrected_odom.compose(prior)
    params = loc.params
    # Half the way, capped: 0.03 m towards the truth, 0.02 rad of the 3 degrees.
    assert math.hypot(corrected.x_m - prior.x_m, corrected.y_m - prior.y_m) == pytest.approx(
        params.max_step_m
    )
    before = math.hypot(prior.x_m - truth.x_m, prior.y_m - truth.y_m)
    after = math.hypot(corrected.x_m - truth.x_m, corrected.y_m - truth.y_m)
    assert after == pytest.approx(before - params.max_step_m, abs=0.01)
    assert corrected.theta_rad - prior.theta_rad == pytest.approx(-params.max_step_rad)
    # Not due again within the period; a featureless view corrects nothing.
    assert loc.localize(patch_of(room, truth), map_of(room), WORLD, THRESHOLDS, prior, 0.1) is None
    wall = Pose2D(0.0, 0.0, 0.0)
    featureless = loc.localize(
        patch_of(one_wall, wall), map_of(one_wall), WORLD, THRESHOLDS, offset(wall), 1.0
    )
    assert featureless is not None and featureless.T_corrected_odom is None
    assert (loc.attempts, loc.applied) == (2, 1)


def test_localizer_needs_a_map() -> None:
    truth = Pose2D(0.3, 0.2, 0.0)
    loc = localizer()
    empty = np.zeros(WORLD.shape, np.float32)
    assert loc.localize(patch_of(room, truth), empty, WORLD, THRESHOLDS, truth, 0.0) is None
    assert loc.attempts == 0


def test_blend_moves_about_the_robot_not_the_world_origin() -> None:
    params = LocalizerParams(gain_frac=0.5, max_step_m=1.0, max_step_rad=1.0)
    prior = Pose2D(5.0, 5.0, 0.0)
    blended = blend(prior, Pose2D(5.02, 5.0, 0.02), params)
    assert (blended.x_m, blended.y_m, blended.theta_rad) == pytest.approx((5.01, 5.0, 0.01))
    again = blended.compose(prior.inverse()).compose(prior)
    assert (again.x_m, again.y_m, again.theta_rad) == pytest.approx((5.01, 5.0, 0.01))


# ------------------------------------------------------------------------ in the mapper


def room_mask(mapper: GroundMapper, T_world_robot: Pose2D) -> NDArray[np.bool_]:
    """Perfect perception in a convex room (nothing hides floor): a pixel is floor when
    the floor point it sees lies inside the room."""
    width, height = mapper.calibration.image_size
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack((u.ravel(), v.ravel(), np.ones(u.size)))
    ground = mapper.calibration.H_ground_from_image @ pixels
    ahead = ground[2] > 1e-9
    xy = np.zeros((u.size, 2))
    xy[ahead] = (ground[:2, ahead] / ground[2, ahead]).T
    world = T_world_robot.apply(xy)
    inside = (world[:, 0] > -1.98) & (world[:, 0] < 2.53) & (world[:, 1] > -1.47)
    inside &= world[:, 1] < 1.81
    return np.asarray((ahead & inside).reshape(height, width))


def sim_mapper() -> GroundMapper:
    # The walls are mapped from the whole view (3 m), as the matcher's scans see them.
    mapping = MappingConfig(
        scan_matching=True, free_evidence_range_m=3.0, obstacle_evidence_range_m=3.0
    )
    config = FloornavConfig(mapping=mapping)
    return GroundMapper(sim_floor_calibration(camera_model(config)), config.mapping, config.camera)


def test_the_mapper_corrects_a_drifted_pose_and_leaves_a_right_one() -> None:
    mapper = sim_mapper()
    assert mapper.localizer is not None
    # Map the room by turning on the spot twice with perfect odometry: the matches that
    # run meanwhile have next to nothing to correct. (Scan points on a wall the robot is
    # just turning to see, left in, pulled matches 2-3.5 cm along the mapped walls.)
    now_s = 0.0
    moved_m, turned_rad = [], []
    for k in range(72):
        truth = Pose2D(0.4, 0.2, math.radians(10.0 * k))
        update = mapper.update(room_mask(mapper, truth), truth, now_s)
        now_s += 0.1
        if update.correction is not None:
            c = update.correction.compose(truth)
            moved_m.append(math.hypot(c.x_m - truth.x_m, c.y_m - truth.y_m))
            turned_rad.append(abs(math.remainder(c.theta_rad - truth.theta_rad, math.tau)))
    assert mapper.localizer.attempts >= 10 and len(moved_m) >= 5
    # The floor boundary 3 m away is found to a pixel row, ~8 cm of floor: that noise.
    assert max(moved_m) < 0.03 and float(np.mean(moved_m)) < 0.012
    assert max(turned_rad) < math.radians(0.75)
    assert float(np.mean(turned_rad)) < math.radians(0.3)
    # Odometry off by (6 cm, -4 cm, 2 degrees): each due frame moves it part of the
    # way, and the mapping stage left-multiplies the correction onto odometry.
    truth = Pose2D(0.4, 0.2, math.radians(35.0))
    odometry = Pose2D(0.46, 0.16, truth.theta_rad + math.radians(2.0))
    corrections = 0
    for _ in range(12):
        update = mapper.update(room_mask(mapper, truth), odometry, now_s)
        assert update.match_s is not None and update.match_s > 0
        if update.correction is not None:
            corrections += 1
            odometry = update.correction.compose(odometry)
        now_s += mapper.localizer.params.period_s
    assert corrections >= 2
    # From 7.2 cm and 2 degrees off to what 5 cm map cells resolve (the score is flat
    # within ~2.5 cm and ~0.7 degrees of the truth).
    assert math.hypot(odometry.x_m - truth.x_m, odometry.y_m - truth.y_m) < 0.035
    assert abs(math.remainder(odometry.theta_rad - truth.theta_rad, math.tau)) < math.radians(1.0)


def test_scan_matching_can_be_turned_off() -> None:
    config = FloornavConfig(mapping=MappingConfig(scan_matching=False))
    mapper = GroundMapper(
        sim_floor_calibration(camera_model(config)), config.mapping, config.camera
    )
    assert mapper.localizer is None
    truth = Pose2D(0.4, 0.2, 0.3)
    update = mapper.update(room_mask(mapper, truth), truth, 0.0)
    assert update.correction is None and update.match_s is None
