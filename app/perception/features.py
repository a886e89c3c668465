"""Stage 3: per-superpixel features and the superpixel adjacency graph.

Each function makes one or two compiled passes over the label image; nothing loops over
pixels in Python. Feature definitions follow the thesis ("Calculation of independent
variables"): mean colour, area, and the width, height and diagonal extents measured as
runs of same-label pixels through the superpixel's centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class SuperpixelFeatures:
    """Features of ``n`` superpixels labelled 0..n-1.

    Attributes
    ----------
    mean_color : (n, 3) float32
        Mean of the colour image (L, a, b or R, G, B) over the superpixel.
    std_color : (n, 3) float32
        Standard deviation of the colour image over the superpixel (texture).
    area_px : (n,) float32
        Number of pixels.
    centroid_xy : (n, 2) float32
        Mean pixel position (x = column, y = row).
    center_xy : (n, 2) int32
        The superpixel's own pixel nearest to its centroid (the centre the runs start at;
        a concave superpixel's centroid may lie outside it).
    width_px, height_px, diagonal_px : (n,) float32
        Lengths of the same-label runs through the centre: horizontal, vertical, and the
        mean of the two 45-degree diagonals (the thesis's "diagonal measure").
    bbox_xyxy : (n, 4) int32
        Inclusive bounding box x0, y0, x1, y1.
    """

    mean_color: NDArray[np.float32]
    std_color: NDArray[np.float32]
    area_px: NDArray[np.float32]
    centroid_xy: NDArray[np.float32]
    center_xy: NDArray[np.int32]
    width_px: NDArray[np.float32]
    height_px: NDArray[np.float32]
    diagonal_px: NDArray[np.float32]
    bbox_xyxy: NDArray[np.int32]

    @property
    def n(self) -> int:
        return int(self.area_px.shape[0])

    def thesis_vector(self) -> NDArray[np.float32]:
        """(n, 7) float32 in the thesis's order: width, height, diagonal, L, a, b, area."""
        return np.column_stack(
            (self.width_px, self.height_px, self.diagonal_px, self.mean_color, self.area_px)
        ).astype(np.float32)


@numba.njit(cache=True, nogil=True)
def _moments_kernel(
    labels: NDArray[np.int32], image: NDArray[np.float32], n: int
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    # sums: count, x, y, c0, c1, c2, c0^2, c1^2, c2^2 ; bbox: x0, y0, x1, y1.
    # Superpixels cover runs of ~S pixels per row, so sums are accumulated per run in
    # registers and flushed once per run: far fewer scattered writes than per pixel.
    sums = np.zeros((n, 9), dtype=np.float64)
    bbox = np.empty((n, 4), dtype=np.int64)
    bbox[:, 0] = 1 << 30
    bbox[:, 1] = 1 << 30
    bbox[:, 2] = -1
    bbox[:, 3] = -1
    height, width = labels.shape
    for y in range(height):
        x = 0
        while x < width:
            k = labels[y, x]
            start = x
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            q0 = 0.0
            q1 = 0.0
            q2 = 0.0
            while x < width and labels[y, x] == k:
                c0 = image[y, x, 0]
                c1 = image[y, x, 1]
                c2 = image[y, x, 2]
                s0 += c0
                s1 += c1
                s2 += c2
                q0 += c0 * c0
                q1 += c1 * c1
                q2 += c2 * c2
                x += 1
            run = x - start
            sums[k, 0] += run
            sums[k, 1] += 0.5 * run * (start + x - 1)
            sums[k, 2] += run * y
            sums[k, 3] += s0
            sums[k, 4] += s1
            sums[k, 5] += s2
            sums[k, 6] += q0
            sums[k, 7] += q1
            sums[k, 8] += q2
            if start < bbox[k, 0]:
                bbox[k, 0] = start
            if x - 1 > bbox[k, 2]:
                bbox[k, 2] = x - 1
            if y < bbox[k, 1]:
                bbox[k, 1] = y
            if y > bbox[k, 3]:
                bbox[k, 3] = y
    return sums, bbox


@numba.njit(cache=True, nogil=True)
def _centers_kernel(
    labels: NDArray[np.int32], centroid_xy: NDArray[np.float64], bbox: NDArray[np.int64]
) -> NDArray[np.int64]:
    n = centroid_xy.shape[0]
    center = np.zeros((n, 2), dtype=np.int64)
    for k in range(n):
        if bbox[k, 2] < 0:
            continue
        cx = centroid_xy[k, 0]
        cy = centroid_xy[k, 1]
        rx = int(cx + 0.5)
        ry = int(cy + 0.5)
        if labels[ry, rx] == k:
            # The usual case for compact superpixels: the rounded centroid is inside.
            center[k, 0] = rx
            center[k, 1] = ry
            continue
        best = np.inf
        # A concave superpixel: nearest own pixel, searched within its bounding box.
        for y in range(bbox[k, 1], bbox[k, 3] + 1):
            for x in range(bbox[k, 0], bbox[k, 2] + 1):
                if labels[y, x] == k:
                    d = (x - cx) * (x - cx) + (y - cy) * (y - cy)
                    if d < best:
                        best = d
                        center[k, 0] = x
                        center[k, 1] = y
    return center


@numba.njit(cache=True, nogil=True)
def _run_length(labels: NDArray[np.int32], x: int, y: int, dx: int, dy: int) -> int:
    """Same-label pixels on the line through (x, y) along +-(dx, dy), centre included."""
    height, width = labels.shape
    k = labels[y, x]
    count = 1
    for sign in (1, -1):
        xx = x + sign * dx
        yy = y + sign * dy
        while 0 <= xx < width and 0 <= yy < height and labels[yy, xx] == k:
            count += 1
            xx += sign * dx
            yy += sign * dy
    return count


@numba.njit(cache=True, nogil=True)
def _extents_kernel(labels: NDArray[np.int32], center: NDArray[np.int64]) -> NDArray[np.float64]:
    n = center.shape[0]
    out = np.zeros((n, 3), dtype=np.float64)
    for k in range(n):
        x = center[k, 0]
        y = center[k, 1]
        if labels[y, x] != k:
            continue
        out[k, 0] = _run_length(labels, x, y, 1, 0)
        out[k, 1] = _run_length(labels, x, y, 0, 1)
        out[k, 2] = 0.5 * (_run_length(labels, x, y, 1, 1) + _run_length(labels, x, y, 1, -1))
    return out


def _check_labels(labels: NDArray[np.integer]) -> NDArray[np.int32]:
    if labels.ndim != 2 or labels.size == 0:
        raise ValueError(f"labels: expected a non-empty (H, W) array, got shape {labels.shape}")
    if not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"labels: expected an integer array, got {labels.dtype}")
    out = np.ascontiguousarray(labels, dtype=np.int32)
    if int(out.min()) < 0:
        raise ValueError("labels: negative labels are not allowed")
    return out


def superpixel_features(
    labels: NDArray[np.integer], image: NDArray[np.float32]
) -> SuperpixelFeatures:
    """Compute the thesis's per-superpixel features.

    Parameters
    ----------
    labels : (H, W) int
        Superpixel labels 0..n-1 (every label should occur; an absent label gets zero
        area, zero extents and zero colour).
    image : (H, W, 3) float32
        The colour image the means are taken of (Lab or RGB from `to_color_space`).

    Returns
    -------
    SuperpixelFeatures

    Examples
    --------
    >>> labels = np.array([[0, 0, 1], [0, 0, 1]], dtype=np.int32)
    >>> image = np.zeros((2, 3, 3), np.float32)
    >>> superpixel_features(labels, image).width_px.tolist()
    [2.0, 1.0]
    """
    labels32 = _check_labels(labels)
    if image.shape[:2] != labels32.shape or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(
            f"image: expected shape {(*labels32.shape, 3)} to match labels, got {image.shape}"
        )
    n = int(labels32.max()) + 1
    sums, bbox = _moments_kernel(labels32, np.ascontiguousarray(image, dtype=np.float32), n)
    count = sums[:, 0]
    safe_count = np.maximum(count, 1.0)[:, None]
    centroid = sums[:, 1:3] / safe_count
    mean = sums[:, 3:6] / safe_count
    var = np.maximum(sums[:, 6:9] / safe_count - mean * mean, 0.0)
    center = _centers_kernel(labels32, centroid, bbox)
    extents = _extents_kernel(labels32, center)
    present = count > 0
    bbox = np.where(present[:, None], bbox, 0)
    return SuperpixelFeatures(
        mean_color=mean.astype(np.float32),
        std_color=np.sqrt(var).astype(np.float32),
        area_px=count.astype(np.float32),
        centroid_xy=centroid.astype(np.float32),
        center_xy=center.astype(np.int32),
        width_px=extents[:, 0].astype(np.float32),
        height_px=extents[:, 1].astype(np.float32),
        diagonal_px=extents[:, 2].astype(np.float32),
        bbox_xyxy=bbox.astype(np.int32),
    )


@numba.njit(cache=True, nogil=True)
def _adjacency_kernel(labels: NDArray[np.int32], n: int) -> NDArray[np.int64]:
    # Boundary-pixel counts between label pairs; n is about 200, so a dense matrix is small.
    counts = np.zeros((n, n), dtype=np.int64)
    height, width = labels.shape
    for y in range(height):
        for x in range(width):
            k = labels[y, x]
            if x + 1 < width:
                j = labels[y, x + 1]
                if j != k:
                    counts[k, j] += 1
                    counts[j, k] += 1
            if y + 1 < height:
                j = labels[y + 1, x]
                if j != k:
                    counts[k, j] += 1
                    counts[j, k] += 1
    return counts


@dataclass(frozen=True)
class AdjacencyGraph:
    """Undirected 4-neighbour adjacency of superpixels in CSR form.

    The neighbours of superpixel ``k`` are ``indices[indptr[k]:indptr[k + 1]]`` (sorted),
    and ``shared_px`` gives, for each of them, how many 4-neighbour pixel pairs the two
    superpixels share (the length of their common border).
    """

    indptr: NDArray[np.int64]
    indices: NDArray[np.int32]
    shared_px: NDArray[np.int32]

    @property
    def n(self) -> int:
        return int(self.indptr.shape[0] - 1)

    def neighbors(self, k: int) -> NDArray[np.int32]:
        return self.indices[self.indptr[k] : self.indptr[k + 1]]

    def edges(self) -> NDArray[np.int32]:
        """(E, 2) int32 undirected edges (i < j)."""
        rows = np.repeat(np.arange(self.n, dtype=np.int32), np.diff(self.indptr))
        keep = rows < self.indices
        return np.column_stack((rows[keep], self.indices[keep]))


def adjacency_graph(labels: NDArray[np.integer], n: int | None = None) -> AdjacencyGraph:
    """4-neighbour adjacency graph of a label image.

    Parameters
    ----------
    labels : (H, W) int
        Labels 0..n-1.
    n : int, optional
        Number of labels (default ``labels.max() + 1``).

    Returns
    -------
    AdjacencyGraph

    Examples
    --------
    >>> g = adjacency_graph(np.array([[0, 1, 2]], dtype=np.int32))
    >>> g.neighbors(1).tolist()
    [0, 2]
    """
    labels32 = _check_labels(labels)
    n_labels = int(labels32.max()) + 1 if n is None else n
    counts = _adjacency_kernel(labels32, n_labels)
    rows, cols = np.nonzero(counts)
    indptr = np.zeros(n_labels + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=n_labels), out=indptr[1:])
    return AdjacencyGraph(
        indptr=indptr,
        indices=cols.astype(np.int32),
        shared_px=counts[rows, cols].astype(np.int32),
    )
