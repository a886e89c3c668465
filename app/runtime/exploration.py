"""When exploration is finished, and the way home.

A run explores (frontier goals) until the map has no reachable frontier left; that
must hold for ``steering.explored_after_s`` (a frontier search sees one map, and a
frame later a new one may open), then the robot drives back to where autonomy first
started and, within ``steering.home_tolerance_m`` of it, stops: exploration is
finished (state ``explored``) and the daemon saves the map. A frontier that opens on
the way home (the robot sees a corner it missed) sends it exploring again.

`Exploration` holds the phase and decides the transitions from the frontier searches
it is shown; the mapping stage replaces the frontier goal by the path home while
returning. Pure logic on poses, times and searches: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

from app.mapping.frames import Pose2D
from app.mapping.frontiers import REASON_NO_FRONTIER, REASON_NO_REACHABLE, FrontierSearch

FINISHED_REASONS = frozenset({REASON_NO_FRONTIER, REASON_NO_REACHABLE})
"""Frontier search reasons that mean nothing is left to explore from here."""


HOME_STOPPING_MARGIN_M = 0.05
"""Arrival is judged this far inside ``home_tolerance_m`` (at most half of it): the robot
is checked twice a second while it drives, and where it comes to rest after the stop
must still be within the tolerance (a test once saw 0.312 m)."""


SAME_GOAL_M = 0.3
"""A goal within this of the one patience is counting for is the same goal (a frontier's
nearest cell shifts as the robot sees more of it)."""
GOAL_PROGRESS_M = 0.1
"""Coming this much closer to the goal (by path) restarts its patience."""


class GoalPatience:
    """When to give up a goal: when the robot has come no closer to it, by path, for the
    patience (explore_lite's ``progress_timeout``). A goal that merely stays the goal is
    not a failure: one across a room takes longer to reach than any fixed patience (the
    home's kitchen doorway, 4.8 m away, was given up after 8 s while the robot drove
    straight at it, and with it the look at the threshold there).

    Pure: `observe` is shown each new goal with its path length, the time and the
    patience (``steering.goal_patience_s``, read each time: the API may change it live)."""

    def __init__(self) -> None:
        self._goal_xy: tuple[float, float] | None = None
        self._closest_m = math.inf
        self._since_s = 0.0

    def reset(self) -> None:
        """Forget the goal (none now, or exploring paused): patience starts anew."""
        self._goal_xy = None

    def observe(
        self, goal_xy: tuple[float, float], path_length_m: float, now_s: float, patience_s: float
    ) -> bool:
        """Whether the goal at ``goal_xy``, ``path_length_m`` from the robot at
        ``now_s``, has come no closer for more than ``patience_s`` (then it is forgotten,
        as by `reset`)."""
        if self._goal_xy is None or math.dist(goal_xy, self._goal_xy) > SAME_GOAL_M:
            self._goal_xy, self._closest_m, self._since_s = goal_xy, path_length_m, now_s
            return False
        if path_length_m <= self._closest_m - GOAL_PROGRESS_M:
            self._closest_m, self._since_s = path_length_m, now_s
            return False
        if now_s - self._since_s > patience_s:
            self.reset()
            return True
        return False


class Phase(StrEnum):
    EXPLORING = "exploring"
    RETURNING = "returning"  # no reachable frontier left: driving back to the start
    EXPLORED = "explored"  # back at the start (or home unreachable): finished


@dataclass(frozen=True)
class PhaseChange:
    """What `Exploration.observe` decided: the new phase and why (for the log, the
    state's reason and the dashboard)."""

    phase: Phase
    reason: str


class Exploration:
    """The exploration phase of one map.

    Parameters
    ----------
    explored_after_s : no reachable frontier for this long (of search time) ends the
        exploring phase.
    home_tolerance_m : the robot ends this close to home (arrival is judged
        `HOME_STOPPING_MARGIN_M` inside it, so the stop lands within it).
    return_home : False: finish where the robot stands when nothing is left.
    return_timeout_s : returning this long without arriving finishes where the robot is
        (a path home the map shows but the robot cannot drive).
    """

    def __init__(
        self,
        *,
        explored_after_s: float,
        home_tolerance_m: float,
        return_home: bool = True,
        return_timeout_s: float = 180.0,
    ) -> None:
        if not (explored_after_s >= 0 and home_tolerance_m > 0 and return_timeout_s > 0):
            raise ValueError(
                "Exploration: need explored_after_s >= 0, home_tolerance_m > 0 and "
                "return_timeout_s > 0"
            )
        self.explored_after_s = explored_after_s
        self.home_tolerance_m = home_tolerance_m
        self.arrival_m = max(home_tolerance_m - HOME_STOPPING_MARGIN_M, home_tolerance_m / 2)
        """Arriving this close finishes (`HOME_STOPPING_MARGIN_M` inside the tolerance)."""
        self.return_home = return_home
        self.return_timeout_s = return_timeout_s
        self.phase = Phase.EXPLORING
        self.home_xy: tuple[float, float] | None = None
        """Where autonomy first started on this map (world frame)."""
        self.reason = ""
        self._nothing_since_s: float | None = None
        self._no_way_home_since_s: float | None = None
        self.returning_since_s: float | None = None
        self.explored_at_s: float | None = None
        """Clock time exploration last finished (None: not yet)."""

    def set_home(self, pose: Pose2D) -> None:
        """Remember the start (the first call only; a later start keeps the first home)."""
        if self.home_xy is None:
            self.home_xy = (pose.x_m, pose.y_m)

    def restart(self) -> None:
        """Explore again (a new start after a finished exploration, or a new map)."""
        self.phase = Phase.EXPLORING
        self.reason = ""
        self._nothing_since_s = None
        self._no_way_home_since_s = None
        self.returning_since_s = None

    def home_distance_m(self, pose: Pose2D) -> float | None:
        if self.home_xy is None:
            return None
        return math.hypot(pose.x_m - self.home_xy[0], pose.y_m - self.home_xy[1])

    def observe(
        self, search: FrontierSearch, now_s: float, pose: Pose2D, *, home_reachable: bool
    ) -> PhaseChange | None:
        """Update the phase from a new frontier search (taken at ``pose``, ``now_s``).
        ``home_reachable``: the search found a path home (`path_to_point`). Returns the
        change, or None when the phase stays."""
        if self.phase is Phase.EXPLORED:
            return None
        if search.goal is not None and (self.phase is Phase.EXPLORING or not search.goal.probe):
            # (An edge probe does not call the robot back from its way home: only a
            # frontier the map shows does.)
            self._nothing_since_s = None
            if self.phase is Phase.RETURNING:
                return self._change(Phase.EXPLORING, "a new frontier opened on the way home", now_s)
            return None
        if self.phase is Phase.EXPLORING:
            if search.goal is None and search.reason not in FINISHED_REASONS:
                self._nothing_since_s = None  # e.g. outside the map: not an answer
                return None
            if self._nothing_since_s is None:
                self._nothing_since_s = now_s
            if now_s - self._nothing_since_s < self.explored_after_s:
                return None
            if not self.return_home or self.home_xy is None:
                return self._change(Phase.EXPLORED, f"{search.reason} left", now_s)
            self.returning_since_s = now_s
            return self._change(
                Phase.RETURNING, f"{search.reason} left: returning to the start", now_s
            )
        # Returning.
        distance = self.home_distance_m(pose)
        if distance is not None and distance <= self.arrival_m:
            return self._change(
                Phase.EXPLORED, f"explored; back at the start ({distance:.2f} m from it)", now_s
            )
        away = f"{distance or 0.0:.2f} m away"
        if home_reachable:
            self._no_way_home_since_s = None
        elif self._no_way_home_since_s is None:
            self._no_way_home_since_s = now_s
        if (
            self._no_way_home_since_s is not None
            and now_s - self._no_way_home_since_s >= self.explored_after_s
        ):
            return self._change(
                Phase.EXPLORED, f"explored; no path back to the start ({away})", now_s
            )
        assert self.returning_since_s is not None
        if now_s - self.returning_since_s >= self.return_timeout_s:
            return self._change(
                Phase.EXPLORED,
                f"explored; not back at the start after {self.return_timeout_s:.0f} s ({away})",
                now_s,
            )
        return None

    def _change(self, phase: Phase, reason: str, now_s: float) -> PhaseChange:
        self.phase = phase
        self.reason = reason
        if phase is Phase.EXPLORING:
            self._nothing_since_s = self._no_way_home_since_s = self.returning_since_s = None
        if phase is Phase.EXPLORED:
            self.explored_at_s = now_s
        return PhaseChange(phase, reason)


class CoverageClock:
    """When the coverage first reached each mark (seconds of run time): the report's
    ``time_to_coverage_s``."""

    MARKS = (0.5, 0.9)

    def __init__(self) -> None:
        self.reached_s: dict[float, float] = {}
        self.last: float | None = None

    def sample(self, coverage: float, elapsed_s: float) -> None:
        self.last = coverage
        for mark in self.MARKS:
            if coverage >= mark and mark not in self.reached_s:
                self.reached_s[mark] = elapsed_s

    def summary(self) -> dict[str, float | None]:
        """``{"50": s or None, "90": s or None}``."""
        return {
            f"{round(mark * 100)}": (
                round(self.reached_s[mark], 1) if mark in self.reached_s else None
            )
            for mark in self.MARKS
        }
