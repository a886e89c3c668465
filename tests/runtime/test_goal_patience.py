"""Goal patience (`app.runtime.exploration.GoalPatience`): a goal is given up when the
robot has come no closer to it for the patience, not when it has merely been the goal
that long."""

from __future__ import annotations

from app.runtime.exploration import GOAL_PROGRESS_M, SAME_GOAL_M, GoalPatience


def test_a_goal_the_robot_drives_at_is_never_given_up() -> None:
    """The home's kitchen doorway: 4.8 m away at 0.3 m/s, 16 s of driving."""
    patience = GoalPatience()
    goal = (5.67, 6.12)
    for step in range(33):  # a search every 0.5 s
        now = 0.5 * step
        assert patience.observe(goal, 4.8 - 0.3 * now, now, 8.0) is False


def test_a_goal_the_robot_comes_no_closer_to_is_given_up_after_the_patience() -> None:
    patience = GoalPatience()
    goal = (1.0, 2.0)
    assert patience.observe(goal, 3.0, 10.0, 8.0) is False
    # Driving closer until 12 s, then stuck (turning in place, path length unchanged or
    # slightly longer): 8 s from the last progress, not from the first sight.
    assert patience.observe(goal, 2.5, 12.0, 8.0) is False
    assert patience.observe(goal, 2.55, 16.0, 8.0) is False
    assert patience.observe(goal, 2.5 - GOAL_PROGRESS_M / 2, 20.0, 8.0) is False  # too little
    assert patience.observe(goal, 2.5, 20.01, 8.0) is True
    # Given up: forgotten, so the same goal again starts anew.
    assert patience.observe(goal, 2.5, 30.0, 8.0) is False
    assert patience.observe(goal, 2.5, 38.0, 8.0) is False
    assert patience.observe(goal, 2.5, 38.5, 8.0) is True


def test_a_goal_that_moves_on_is_a_new_goal_and_one_that_shifts_a_little_is_not() -> None:
    patience = GoalPatience()
    assert patience.observe((0.0, 0.0), 2.0, 0.0, 8.0) is False
    # Within SAME_GOAL_M of the first: the same goal, still no closer.
    assert patience.observe((SAME_GOAL_M - 0.01, 0.0), 2.0, 5.0, 8.0) is False
    assert patience.observe((0.0, SAME_GOAL_M - 0.01), 2.0, 8.5, 8.0) is True
    # A goal farther off than SAME_GOAL_M restarts the count.
    assert patience.observe((0.0, 0.0), 2.0, 10.0, 8.0) is False
    assert patience.observe((SAME_GOAL_M + 0.01, 0.0), 2.0, 17.0, 8.0) is False
    assert patience.observe((SAME_GOAL_M + 0.01, 0.0), 2.0, 25.5, 8.0) is True


def test_reset_forgets_the_goal() -> None:
    patience = GoalPatience()
    assert patience.observe((0.0, 0.0), 2.0, 0.0, 8.0) is False
    patience.reset()  # no goal for a while, or exploring paused
    assert patience.observe((0.0, 0.0), 2.0, 9.0, 8.0) is False
    assert patience.observe((0.0, 0.0), 2.0, 17.5, 8.0) is True


def test_a_patience_changed_live_applies_to_the_goal_at_hand() -> None:
    """`steering.*` is live over the API: the patience is read on every search."""
    patience = GoalPatience()
    assert patience.observe((0.0, 0.0), 2.0, 0.0, 8.0) is False
    assert patience.observe((0.0, 0.0), 2.0, 5.0, 8.0) is False
    assert patience.observe((0.0, 0.0), 2.0, 5.5, 4.0) is True
