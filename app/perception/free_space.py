"""Column-wise free-space boundary: the floor as a run from the image bottom up to an
obstacle, one boundary row per column, found exactly by dynamic programming.

Assumption (the thesis's): obstacles stand on the floor and the camera looks along it,
so in every image column the visible floor is the run of rows below the first obstacle.
Choosing the boundary row per column independently is noisy; a Viterbi pass over the
columns with a truncated-L1 smoothness cost gives the best boundary for the whole image.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray


@numba.njit(cache=True, nogil=True)
def _viterbi_truncated_l1(
    cost: NDArray[np.float64], smoothness: float, max_jump: int
) -> NDArray[np.int32]:
    n_cols, n_states = cost.shape
    total = cost[0].copy()
    previous = np.empty(n_states, dtype=np.float64)
    back = np.empty((n_cols, n_states), dtype=np.int32)
    for x in range(1, n_cols):
        previous[:] = total
        best_any = 0
        for s in range(1, n_states):
            if previous[s] < previous[best_any]:
                best_any = s
        # A jump larger than max_jump costs the same as max_jump (truncation), so any
        # state can be reached from the overall best one at that price.
        jump_cost = smoothness * max_jump
        for s in range(n_states):
            best_state = best_any
            best = previous[best_any] + jump_cost
            lo = max(0, s - max_jump)
            hi = min(n_states, s + max_jump + 1)
            for p in range(lo, hi):
                c = previous[p] + smoothness * abs(s - p)
                if c < best:
                    best = c
                    best_state = p
            total[s] = best + cost[x, s]
            back[x, s] = best_state
    path = np.empty(n_cols, dtype=np.int32)
    state = 0
    for s in range(1, n_states):
        if total[s] < total[state]:
            state = s
    path[n_cols - 1] = state
    for x in range(n_cols - 1, 0, -1):
        state = back[x, state]
        path[x - 1] = state
    return path


def free_space_boundary(
    floor_cost: NDArray[np.floating],
    *,
    edge_reward: NDArray[np.floating] | None = None,
    smoothness: float = 1.0,
    max_jump: int = 4,
) -> NDArray[np.int32]:
    """Best boundary row per column for a floor that runs from the bottom row up.

    Parameters
    ----------
    floor_cost : (H, W) float
        Cost of calling each cell floor (negative = floor-like); calling it non-floor
        costs 0.
    edge_reward : (H + 1, W) float, optional
        Reward for putting the boundary between rows ``b - 1`` and ``b`` of a column
        (e.g. image gradient there); row ``H`` means "no floor in this column".
    smoothness : float
        Cost per row of difference between neighbouring columns' boundaries ...
    max_jump : int
        ... up to this many rows; larger jumps (an obstacle's side) cost the same.

    Returns
    -------
    (W,) int32 boundary rows ``b`` in [0, H]: rows ``b..H-1`` of the column are floor.

    Examples
    --------
    >>> cost = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0]])
    >>> free_space_boundary(cost, smoothness=0.1).tolist()
    [1, 2]
    """
    if floor_cost.ndim != 2 or floor_cost.size == 0:
        raise ValueError(f"floor_cost: expected a non-empty (H, W) array, got {floor_cost.shape}")
    height, width = floor_cost.shape
    # below[b] = total cost of rows b..H-1 as floor; below[H] = 0 (no floor).
    below = np.zeros((height + 1, width), dtype=np.float64)
    np.cumsum(floor_cost[::-1], axis=0, out=below[height - 1 :: -1])
    if edge_reward is not None:
        if edge_reward.shape != (height + 1, width):
            raise ValueError(
                f"edge_reward: expected shape {(height + 1, width)}, got {edge_reward.shape}"
            )
        below -= edge_reward
    if smoothness < 0 or max_jump < 0:
        raise ValueError("smoothness and max_jump must be >= 0")
    path: NDArray[np.int32] = _viterbi_truncated_l1(
        np.ascontiguousarray(below.T), float(smoothness), int(max_jump)
    )
    return path


def boundary_to_mask(boundary: NDArray[np.int32], height: int) -> NDArray[np.bool_]:
    """(W,) boundary rows -> (height, W) bool mask, True on rows >= boundary."""
    rows = np.arange(height, dtype=np.int32)[:, None]
    return np.asarray(rows >= boundary[None, :], dtype=np.bool_)
