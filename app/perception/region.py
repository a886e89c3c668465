"""Stage 6: breadth-first region growing over superpixels, and the pixel flood-fill
baseline the thesis compares it with."""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np
from numpy.typing import NDArray

from app.perception.features import AdjacencyGraph


def grow_region(
    graph: AdjacencyGraph, seeds: NDArray[np.bool_], accept: NDArray[np.bool_]
) -> NDArray[np.bool_]:
    """Breadth-first search over adjacent superpixels (thesis, "Region Growing").

    Starting from the seed superpixels (always part of the region), a neighbour joins
    the region if ``accept`` holds for it; the search continues from every superpixel that
    joined. The loop runs over superpixels (about 200), never over pixels.

    Parameters
    ----------
    graph : AdjacencyGraph with n nodes
    seeds : (n,) bool
    accept : (n,) bool, the membership criterion (e.g. ``ssd <= threshold``)

    Returns
    -------
    (n,) bool, the traversable set.

    Examples
    --------
    >>> from app.perception.features import adjacency_graph
    >>> g = adjacency_graph(np.array([[0, 1, 2, 3]], np.int32))
    >>> grow_region(g, np.array([1, 0, 0, 0], bool), np.array([1, 1, 0, 1], bool)).tolist()
    [True, True, False, False]
    """
    n = graph.n
    if seeds.shape != (n,) or accept.shape != (n,):
        raise ValueError(f"seeds {seeds.shape} and accept {accept.shape} must have shape ({n},)")
    region = seeds.copy()
    queue = deque(np.flatnonzero(seeds).tolist())
    indptr = graph.indptr
    indices = graph.indices
    while queue:
        k = queue.popleft()
        for j in indices[indptr[k] : indptr[k + 1]]:
            if not region[j] and accept[j]:
                region[j] = True
                queue.append(int(j))
    return region


def flood_fill_floor(
    image: NDArray[np.uint8],
    seed_xy: tuple[int, int],
    *,
    tolerance: float,
) -> NDArray[np.bool_]:
    """Pixel flood fill from a seed (the thesis's baseline, "Other floor segmentation
    methods").

    A 4-connected pixel joins when each channel differs from the seed pixel's colour by at
    most ``tolerance``: the thesis's "target colour" with a tolerance (a fixed range; a
    floating range compared with neighbours leaks across the gentle gradients of a
    smoothed image).

    Parameters
    ----------
    image : (H, W, 3) uint8, typically the smoothed frame in 8-bit Lab.
    seed_xy : (x, y) pixel inside the image.
    tolerance : float, per-channel difference in 8-bit units.

    Returns
    -------
    (H, W) bool, the filled region.
    """
    height, width = image.shape[:2]
    x, y = seed_xy
    if not (0 <= x < width and 0 <= y < height):
        raise ValueError(f"seed {seed_xy} lies outside the {width}x{height} image")
    mask = np.zeros((height + 2, width + 2), dtype=np.uint8)
    diff = (tolerance, tolerance, tolerance)
    flags = 4 | cv2.FLOODFILL_MASK_ONLY | cv2.FLOODFILL_FIXED_RANGE | (1 << 8)
    cv2.floodFill(image, mask, (x, y), (0, 0, 0), diff, diff, flags)
    return mask[1:-1, 1:-1].astype(bool)
