"""Steering: polar free range, open windows, heading choice and the speed rules, on
small synthetic maps with exact answers."""

import math

import numpy as np
import pytest

from app.config import SafetyConfig, SteeringConfig
from app.control.steering import (
    PolarRanges,
    Steering,
    choose_heading,
    lookahead_point,
    open_windows,
    polar_free_range,
)
from app.mapping.frames import GroundGrid, Pose2D
from app.mapping.occupancy import FREE, OCCUPIED, UNKNOWN

GRID = GroundGrid.covering(x_min_m=-3, x_max_m=3, y_min_m=-3, y_max_m=3, cell_m=0.05)


def free_map() -> np.ndarray:
    return np.full(GRID.shape, FREE, dtype=np.int8)


def wall_at_x(cells: np.ndarray, x_m: float) -> None:
    x, _ = GRID.cell_centers()
    cells[int(np.argmin(np.abs(x[:, 0] - x_m))), :] = OCCUPIED  # the cell row nearest x_m


def ranges(cells: np.ndarray, pose: Pose2D | None = None, body: float = 0.15) -> PolarRanges:
    return polar_free_range(
        cells, GRID, pose or Pose2D(), body_radius_m=body, max_range_m=2.5, n_directions=72
    )


def test_free_map_has_full_range_everywhere() -> None:
    assert np.all(ranges(free_map()).ranges_m == 2.5)


def test_wall_ahead_limits_range_by_the_body_radius() -> None:
    cells = free_map()
    wall_at_x(cells, 1.0)
    polar = ranges(cells)
    ahead = polar.range_towards(0.0)
    # The wall's cell spans 1.0..1.05 m; grown by 0.15 m (to whole cells) the robot can
    # go 0.85 m, give or take a cell.
    assert 0.82 <= ahead <= 0.92
    assert polar.range_towards(math.pi) == 2.5  # behind: free
    # 60 degrees off: the wall is 1/cos(60) farther.
    assert polar.range_towards(math.radians(60)) == pytest.approx(ahead * 2, abs=0.06)


def test_unknown_ends_rays_but_the_robot_disk_does_not() -> None:
    cells = np.full(GRID.shape, UNKNOWN, dtype=np.int8)
    polar = ranges(cells)
    assert np.all(polar.ranges_m <= 0.15)  # no farther than its own disk
    x, y = GRID.cell_centers()
    cells[(x > 0) & (np.abs(y) < 0.3)] = FREE  # a corridor ahead
    assert ranges(cells).range_towards(0.0) == 2.5


def test_rays_turn_with_the_pose() -> None:
    cells = free_map()
    wall_at_x(cells, 1.0)
    polar = ranges(cells, Pose2D(0.0, 0.0, math.pi / 2))  # facing +y: wall on the right
    assert polar.range_towards(0.0) == 2.5
    assert polar.range_towards(-math.pi / 2) < 0.95


def test_open_windows_wrap_round_behind() -> None:
    angles = -np.pi + np.arange(8) * (np.pi / 4)  # -180, -135, ..., 135
    polar = PolarRanges(angles, np.array([1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
    windows = open_windows(polar, 0.5)
    assert len(windows) == 1
    start, end = windows[0]
    assert start == pytest.approx(math.radians(135)) and end == pytest.approx(
        math.radians(135 + 90)
    )
    assert open_windows(PolarRanges(angles, np.zeros(8)), 0.5) == []
    assert open_windows(PolarRanges(angles, np.ones(8)), 0.5) == [(-math.pi, math.pi)]


def test_choose_heading_inside_or_nearest_edge() -> None:
    windows = [(-0.5, 0.5)]
    assert choose_heading(windows, 0.2, 0.1) == pytest.approx(0.2)
    assert choose_heading(windows, 1.0, 0.1) == pytest.approx(0.4)
    assert choose_heading(windows, -3.0, 0.1) == pytest.approx(-0.4)
    assert choose_heading([(2.8, 3.6)], -3.0, 0.1) == pytest.approx(-3.0)  # across +-pi
    assert choose_heading([], 0.0, 0.1) is None


def test_lookahead_point_searches_forward_from_the_nearest() -> None:
    path = np.column_stack((np.linspace(-0.5, 2.0, 26), np.zeros(26)))
    assert lookahead_point(path, (0.0, 0.0), 0.6) == pytest.approx((0.6, 0.0))
    assert lookahead_point(path, (1.8, 0.0), 0.6) == pytest.approx((2.0, 0.0))
    assert lookahead_point(np.empty((0, 2)), (0.0, 0.0), 0.6) is None


def steering() -> Steering:
    return Steering(SteeringConfig(smoothing=0.0), SafetyConfig(), robot_radius_m=0.12)


def path_to(x: float, y: float) -> np.ndarray:
    t = np.linspace(0, 1, 30)[:, None]
    return t * np.array([[x, y]])


def test_goal_ahead_on_free_floor_drives_straight() -> None:
    decision = steering().decide(free_map(), GRID, Pose2D(), path_to(2.0, 0.0))
    assert decision.reason == "goal"
    assert decision.twist.v_m_s == pytest.approx(SteeringConfig().cruise_speed_m_s)
    assert decision.twist.omega_rad_s == pytest.approx(0.0)


def test_goal_behind_turns_in_place() -> None:
    decision = steering().decide(free_map(), GRID, Pose2D(), path_to(-2.0, 0.3))
    assert decision.twist.v_m_s == 0.0
    assert decision.twist.omega_rad_s > 0  # the goal is behind on the left


def test_slows_down_near_an_obstacle_and_stops_at_the_clearance() -> None:
    far, near = free_map(), free_map()
    wall_at_x(far, 2.0)
    wall_at_x(near, 0.35)
    v_far = steering().decide(far, GRID, Pose2D(), path_to(2.5, 0.0)).twist.v_m_s
    v_near = steering().decide(near, GRID, Pose2D(), path_to(2.5, 0.0)).twist.v_m_s
    assert v_far > v_near
    assert v_near == 0.0


def test_turning_towards_a_free_heading_slows_for_what_stands_in_between() -> None:
    """A box straight ahead, the goal 35 degrees left and free: the robot turns towards
    it and, driving an arc from its own heading, must not run its front into the box; on
    the same map without the box it drives on at full turn-weighted speed."""
    goal = path_to(1.5 * math.cos(0.6), 1.5 * math.sin(0.6))
    clear = steering().decide(free_map(), GRID, Pose2D(), goal)
    cells = free_map()
    x, y = GRID.cell_centers()
    cells[(x > 0.45) & (x < 0.6) & (np.abs(y) < 0.1)] = OCCUPIED
    boxed = steering().decide(cells, GRID, Pose2D(), goal)
    assert clear.reason == boxed.reason == "goal"
    assert clear.twist.v_m_s == pytest.approx(
        SteeringConfig().cruise_speed_m_s * math.cos(0.6) ** 2
    )
    # The fan from 0 to 35 degrees ends at the grown box, 0.45 - 0.17 m ahead: within
    # the clearance plus a fifth of the slow-down distance.
    assert 0.0 < boxed.twist.v_m_s < 0.25 * clear.twist.v_m_s
    assert boxed.twist.omega_rad_s == pytest.approx(clear.twist.omega_rad_s)
    polar = boxed.polar
    assert polar.range_sweeping_to(0.6) == pytest.approx(polar.range_towards(0.0))
    assert polar.range_sweeping_to(-0.6) == pytest.approx(polar.range_towards(0.0))
    assert polar.range_towards(0.6) > 1.0


def test_closed_goal_direction_steers_through_the_open_window() -> None:
    cells = free_map()
    x, y = GRID.cell_centers()
    cells[(x > 0.4) & (x < 0.5) & (y > -0.2) & (y < 1.5)] = OCCUPIED  # ahead and left
    decision = steering().decide(cells, GRID, Pose2D(), path_to(2.0, -0.2))
    assert decision.reason == "window"
    assert decision.heading_rad < -0.9  # round the right end, the nearer window
    assert decision.twist.v_m_s == 0.0 and decision.twist.omega_rad_s < 0


def test_no_goal_scans_in_place() -> None:
    decision = steering().decide(free_map(), GRID, Pose2D(), None)
    assert (
        decision.reason == "scan"
        and decision.twist.v_m_s == 0.0
        and decision.twist.omega_rad_s != 0
    )


def test_boxed_in_turns_towards_the_goal_without_moving() -> None:
    cells = np.full(GRID.shape, UNKNOWN, dtype=np.int8)
    decision = steering().decide(cells, GRID, Pose2D(), path_to(0.0, -1.0))
    assert decision.reason == "blocked"
    assert decision.twist.v_m_s == 0.0 and decision.twist.omega_rad_s < 0


def test_blocked_ahead_turns_in_place_towards_the_freer_side_and_keeps_it() -> None:
    """The safe zone is not floor: no forward motion although the map shows free floor
    ahead, and a full-speed turn towards the side with more free range, kept while the
    way ahead stays blocked (no dithering), chosen afresh once it cleared."""
    turn = SteeringConfig().turn_speed_rad_s
    right_walled = free_map()
    _, y = GRID.cell_centers()
    right_walled[y < -0.4] = OCCUPIED  # the right side is closed: more room on the left
    left_walled = np.flip(right_walled, axis=1).copy()  # y decreases along columns
    robot = steering()
    decision = robot.decide(right_walled, GRID, Pose2D(), path_to(2.0, 0.0), blocked_ahead=True)
    assert decision.reason == "not_floor"
    assert decision.twist.v_m_s == 0.0
    assert decision.twist.omega_rad_s == pytest.approx(turn)  # left
    assert decision.range_ahead_m == 0.0
    # Still blocked, now the left looks freer: keep turning the way it started.
    again = robot.decide(left_walled, GRID, Pose2D(), path_to(2.0, 0.0), blocked_ahead=True)
    assert again.twist == decision.twist
    # Cleared: steering drives to the goal again; blocked anew, it picks the side afresh.
    clear = robot.decide(free_map(), GRID, Pose2D(), path_to(2.0, 0.0))
    assert clear.reason == "goal" and clear.twist.v_m_s > 0
    fresh = robot.decide(left_walled, GRID, Pose2D(), path_to(2.0, 0.0), blocked_ahead=True)
    assert fresh.twist.v_m_s == 0.0
    assert fresh.twist.omega_rad_s == pytest.approx(-turn)  # right
