"""Steering: the thesis's "suitable window of advancement", chosen on the map.

1. A polar histogram of free range around the robot: along each of ``n_directions``
   rays from the robot's centre, the distance to the first cell that is occupied (grown
   by the robot's radius, so a ray's range is how far the *robot* can go) or unknown.
2. Open windows: runs of directions whose range is at least ``min_advance_m``.
3. The desired heading points at the frontier path ``lookahead_m`` ahead (or, with no
   goal, the robot scans in place). The chosen heading is the desired one if that aim
   point is reachable in a straight line or the direction lies in an open window
   (``window_margin_rad`` inside its edges), else the nearest point of the
   nearest window; with no open window at all, the robot turns in place towards the
   desired heading (it is blocked).
4. Speed: heading errors beyond ``turn_in_place_rad`` turn in place; otherwise the
   forward speed falls with the heading error and with the free range over the fan of
   directions from straight ahead to the heading (the robot drives an arc through them;
   ranges end where its body would touch), from ``slow_down_m`` above the minimum
   clearance down to zero at it. An open window whose range is already within the
   clearance leads nowhere: the robot turns towards the goal instead, to look.
5. Blocked ahead (the runtime says the safe zone in front is not floor): no forward
   motion, and a turn in place at ``turn_speed_rad_s`` towards the side with more free
   range, kept while the way ahead stays blocked, so the robot looks elsewhere.

`Steering` keeps only the smoothing state; `polar_free_range` and `choose_heading` are
pure functions on arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from app.config import SafetyConfig, SteeringConfig
from app.control.mux import Twist
from app.mapping.frames import GroundGrid, Pose2D
from app.mapping.occupancy import OCCUPIED, UNKNOWN


@dataclass(frozen=True)
class PolarRanges:
    """Free range per direction (robot frame, counter-clockwise from ahead).

    Attributes
    ----------
    angles_rad : (n,) float64 in [-pi, pi)
    ranges_m : (n,) float64, 0 where the robot cannot move at all
    """

    angles_rad: NDArray[np.float64]
    ranges_m: NDArray[np.float64]

    def range_towards(self, angle_rad: float, half_width_rad: float = 0.0) -> float:
        """The smallest range within ``half_width_rad`` of ``angle_rad``."""
        diff = np.abs(_wrap(self.angles_rad - angle_rad))
        near = diff <= max(half_width_rad, math.pi / len(self.angles_rad))
        return float(self.ranges_m[near].min())

    def range_sweeping_to(self, angle_rad: float) -> float:
        """The smallest range over the directions from straight ahead (0) to
        ``angle_rad``, both included: how far the robot can drive while it turns from its
        heading to ``angle_rad``. An arc that starts along 0 and ends along
        ``angle_rad`` stays within that fan (its chord's bearing is half the turn), so on
        a fan whose every ray is free for ``d`` the body touches nothing for ``d``."""
        lo, hi = sorted((0.0, float(wrap_angle(angle_rad))))
        half_step = math.pi / len(self.angles_rad)
        inside = (self.angles_rad >= lo - half_step) & (self.angles_rad <= hi + half_step)
        return float(self.ranges_m[inside].min())


def _wrap(angle: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.asarray((angle + np.pi) % (2 * np.pi) - np.pi, dtype=np.float64)


def wrap_angle(angle: float) -> float:
    return math.remainder(angle, math.tau)


def polar_free_range(
    cells: NDArray[np.int8],
    grid: GroundGrid,
    T_world_robot: Pose2D,
    *,
    body_radius_m: float,
    max_range_m: float,
    n_directions: int = 72,
) -> PolarRanges:
    """Free range along ``n_directions`` rays from the robot (see the module docstring).

    Parameters
    ----------
    cells : (rows, cols) int8 classes of ``grid`` (-1 unknown, 0 free, 1 occupied)
    grid : the raster of ``cells`` in the world frame
    T_world_robot : the robot's pose in that frame
    body_radius_m : occupied cells are grown by this much
    max_range_m : rays stop here (and off the raster)
    """
    if cells.shape != grid.shape:
        raise ValueError(f"cells {cells.shape} do not match the grid {grid.shape}")
    radius_cells = body_radius_m / grid.cell_m
    k = 2 * math.ceil(radius_cells) + 1
    disk = (
        (np.hypot(*np.meshgrid(np.arange(k) - k // 2, np.arange(k) - k // 2)) <= radius_cells)
        .astype(np.uint8)
        .reshape(k, k)
    )
    blocked_by_obstacle = cv2.dilate((cells == OCCUPIED).astype(np.uint8), disk) > 0
    blocked = blocked_by_obstacle | (cells == UNKNOWN)

    angles = -np.pi + np.arange(n_directions) * (2 * np.pi / n_directions)
    step = grid.cell_m / 2
    distances = np.arange(1, int(max_range_m / step) + 1) * step
    heading = T_world_robot.theta_rad + angles
    xs = T_world_robot.x_m + np.cos(heading)[:, None] * distances[None, :]
    ys = T_world_robot.y_m + np.sin(heading)[:, None] * distances[None, :]
    rc = grid.cell_of(np.column_stack((xs.ravel(), ys.ravel())))
    inside = grid.holds(rc)
    hit = np.ones(len(rc), dtype=bool)
    hit[inside] = blocked[rc[inside, 0], rc[inside, 1]]
    # The robot's own disk is never seen by the camera: rays start at its edge.
    hit = hit.reshape(len(angles), len(distances)) & (distances[None, :] > body_radius_m)
    first = np.where(hit.any(axis=1), hit.argmax(axis=1), len(distances))
    ranges = np.where(first > 0, distances[np.maximum(first - 1, 0)], 0.0)
    ranges = np.where(first >= len(distances), max_range_m, ranges)
    return PolarRanges(angles.astype(np.float64), ranges.astype(np.float64))


def open_windows(polar: PolarRanges, min_advance_m: float) -> list[tuple[float, float]]:
    """Runs of open directions as (start, end) angles, counter-clockwise, end >= start
    (``end`` may exceed pi when a window wraps round behind the robot)."""
    is_open = polar.ranges_m >= min_advance_m
    n = len(is_open)
    if not is_open.any():
        return []
    step = 2 * math.pi / n
    if is_open.all():
        return [(-math.pi, math.pi)]
    start = int(np.argmin(is_open))  # a closed direction: runs never wrap past it
    windows = []
    i = 0
    while i < n:
        j = (start + i) % n
        if is_open[j]:
            run = 0
            while i + run < n and is_open[(start + i + run) % n]:
                run += 1
            a0 = float(polar.angles_rad[j])
            windows.append((a0, a0 + (run - 1) * step))
            i += run
        else:
            i += 1
    return windows


def choose_heading(
    windows: list[tuple[float, float]], desired_rad: float, margin_rad: float
) -> float | None:
    """The heading closest to ``desired_rad`` inside an open window (``margin_rad``
    from its edges, or its middle if narrower); None if there is no window."""
    best: tuple[float, float] | None = None
    for a0, a1 in windows:
        lo, hi = a0 + margin_rad, a1 - margin_rad
        if lo > hi:
            lo = hi = (a0 + a1) / 2
        for d in (desired_rad - 2 * math.pi, desired_rad, desired_rad + 2 * math.pi):
            target = min(hi, max(lo, d))
            err = abs(target - d)
            if best is None or err < best[0]:
                best = (err, wrap_angle(target))
    return None if best is None else best[1]


def lookahead_point(
    path_xy: NDArray[np.float64], robot_xy: tuple[float, float], lookahead_m: float
) -> tuple[float, float] | None:
    """The first path point at least ``lookahead_m`` from the robot, searching onwards
    from the path point nearest the robot; the path's end if none is that far."""
    if len(path_xy) == 0:
        return None
    d = np.hypot(path_xy[:, 0] - robot_xy[0], path_xy[:, 1] - robot_xy[1])
    nearest = int(np.argmin(d))
    beyond = np.flatnonzero(d[nearest:] >= lookahead_m)
    i = nearest + int(beyond[0]) if len(beyond) else len(path_xy) - 1
    return float(path_xy[i, 0]), float(path_xy[i, 1])


@dataclass(frozen=True)
class SteeringDecision:
    """One steering step: the command and what it was based on (for display and logs).

    ``heading_rad`` and ``desired_rad`` are in the robot frame; ``reason`` is one of
    "goal", "window" (the desired heading was closed: steering round), "blocked" (no
    open window: turning in place), "scan" (no frontier goal: looking around),
    "not_floor" (the safe zone ahead is not floor: turning in place to look elsewhere).
    """

    twist: Twist
    heading_rad: float
    desired_rad: float
    range_ahead_m: float
    reason: str
    polar: PolarRanges = field(repr=False)


class Steering:
    """Turns the map around the robot and the frontier path into a `Twist`."""

    def __init__(
        self,
        steering: SteeringConfig,
        safety: SafetyConfig,
        *,
        robot_radius_m: float,
        body_margin_m: float = 0.05,
    ) -> None:
        self.config = steering
        self.safety = safety
        self.robot_radius_m = robot_radius_m
        self.body_radius_m = robot_radius_m + body_margin_m
        self._previous = Twist()
        self._scan_sign = 1.0
        self._blocked_sign: float | None = None
        """The turn direction chosen when the way ahead became blocked (kept until it
        clears, so the robot does not dither between sides)."""

    def reset(self) -> None:
        self._previous = Twist()
        self._blocked_sign = None

    def decide(
        self,
        cells: NDArray[np.int8],
        grid: GroundGrid,
        T_world_robot: Pose2D,
        path_xy: NDArray[np.float64] | None,
        *,
        blocked_ahead: bool = False,
    ) -> SteeringDecision:
        """The next command. ``blocked_ahead``: something the map does not show yet
        blocks the way (the safe zone is not floor): turn in place, see step 5."""
        cfg = self.config
        polar = polar_free_range(
            cells,
            grid,
            T_world_robot,
            body_radius_m=self.body_radius_m,
            max_range_m=min(cfg.local_window_m / 2, 3.0),
        )
        if blocked_ahead:
            if self._blocked_sign is None:
                self._blocked_sign = self._freer_side(polar)
            sign = self._blocked_sign
            return self._finish(
                Twist(0.0, sign * cfg.turn_speed_rad_s),
                sign * math.pi / 2,
                sign * math.pi / 2,
                polar,
                "not_floor",
                0.0,
            )
        self._blocked_sign = None
        windows = open_windows(polar, cfg.min_advance_m)
        point = (
            None
            if path_xy is None
            else lookahead_point(path_xy, (T_world_robot.x_m, T_world_robot.y_m), cfg.lookahead_m)
        )
        if point is None:
            # No goal: look around, turning in place.
            return self._finish(
                Twist(0.0, self._scan_sign * cfg.turn_speed_rad_s), 0.0, 0.0, polar, "scan"
            )
        desired = wrap_angle(
            math.atan2(point[1] - T_world_robot.y_m, point[0] - T_world_robot.x_m)
            - T_world_robot.theta_rad
        )
        self._scan_sign = 1.0 if desired >= 0 else -1.0
        to_point = math.hypot(point[0] - T_world_robot.x_m, point[1] - T_world_robot.y_m)
        heading: float | None
        if polar.range_towards(desired) >= min(cfg.min_advance_m, to_point):
            heading = desired  # the aim point itself is reachable in a straight line
        else:
            heading = choose_heading(windows, desired, cfg.window_margin_rad)
        if heading is None:
            omega = math.copysign(cfg.turn_speed_rad_s, desired)
            return self._finish(Twist(0.0, omega), desired, desired, polar, "blocked")
        reason = "goal" if abs(wrap_angle(heading - desired)) < 1e-6 else "window"
        # Obstacles are already grown by the body (plus margin): what is left is clearance.
        range_ahead = polar.range_towards(heading)
        stop_at = self.safety.min_clearance_m
        if range_ahead <= stop_at and abs(wrap_angle(heading - desired)) > cfg.window_margin_rad:
            # The open window leads nowhere yet: turn to look towards the goal instead
            # (turning in place is always possible for a round robot).
            omega = math.copysign(cfg.turn_speed_rad_s, desired)
            return self._finish(Twist(0.0, omega), desired, desired, polar, "blocked", range_ahead)
        omega = max(
            -cfg.turn_speed_rad_s, min(cfg.turn_speed_rad_s, cfg.heading_gain_per_s * heading)
        )
        if abs(heading) > cfg.turn_in_place_rad:
            return self._finish(Twist(0.0, omega), heading, desired, polar, reason, range_ahead)
        # The robot does not jump to the heading: it drives an arc from its own, so the
        # speed answers to every ray in between (turning alone needs no room).
        range_ahead = polar.range_sweeping_to(heading)
        room = max(0.0, min(1.0, (range_ahead - stop_at) / cfg.slow_down_m))
        v = cfg.cruise_speed_m_s * room * math.cos(heading) ** 2
        return self._finish(Twist(v, omega), heading, desired, polar, reason, range_ahead)

    def _freer_side(self, polar: PolarRanges) -> float:
        """+1 (turn left) if the directions on the left hold more free range than those
        on the right, -1 if fewer; on a tie, the way the robot last looked."""
        left = float(polar.ranges_m[(polar.angles_rad > 0) & (polar.angles_rad < math.pi)].sum())
        right = float(polar.ranges_m[(polar.angles_rad < 0) & (polar.angles_rad > -math.pi)].sum())
        if math.isclose(left, right, rel_tol=1e-9, abs_tol=1e-9):
            return self._scan_sign
        return 1.0 if left > right else -1.0

    def _finish(
        self,
        twist: Twist,
        heading: float,
        desired: float,
        polar: PolarRanges,
        reason: str,
        range_ahead: float | None = None,
    ) -> SteeringDecision:
        s = self.config.smoothing
        prev = self._previous
        # Smooth turning; never smooth a slow-down (it would delay a stop).
        v = twist.v_m_s if twist.v_m_s <= prev.v_m_s else s * prev.v_m_s + (1 - s) * twist.v_m_s
        omega = s * prev.omega_rad_s + (1 - s) * twist.omega_rad_s
        smoothed = Twist(v, omega)
        self._previous = smoothed
        ahead = polar.range_towards(0.0) if range_ahead is None else range_ahead
        return SteeringDecision(smoothed, heading, desired, ahead, reason, polar)
