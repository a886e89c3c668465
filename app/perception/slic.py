"""SLIC superpixels (Achanta et al. 2012) as a single-threaded numba kernel.

The numba backend follows the paper (and the thesis that builds on it) step by step:

1. Seeds on a regular grid of about K cells of ``S x S`` pixels, ``S = sqrt(N / K)``
   (N pixels; S is recomputed from the actual number of cells), each moved to the
   lowest-gradient pixel of its 3x3 neighbourhood, with
   ``G(x, y) = ||I(x+1, y) - I(x-1, y)||^2 + ||I(x, y+1) - I(x, y-1)||^2``.
2. Local k-means: every centre only looks at the pixels of a ``2S x 2S`` window around
   itself, with the distance ``D^2 = d_c^2 + (d_s / S)^2 m^2`` (``d_c`` Euclidean colour
   distance, ``d_s`` Euclidean pixel distance, ``m`` the compactness).
3. Centre update (mean colour and position of the assigned pixels), repeated up to
   ``max_iter`` times or until the residual ``E``, the mean L1 displacement of the
   centres, drops below :data:`CONVERGENCE_TOL` times S.
4. Connectivity, O(N): the 4-connected components of equal label are found in raster
   order; a component smaller than ``min_size_factor * S^2`` pixels takes the label of
   the segment it touches at its first raster pixel (as ``EnforceLabelConnectivity`` in
   the authors' reference code), the others become superpixels of their own.

Implementation notes (what makes it fast, none of it changes the result): the image is
converted once to planar float32 rows; the assignment is evaluated row by row over the
windows that cover the row, so the distance and label buffers stay in L1 cache, with a
branch-free inner loop that LLVM vectorises (rows padded to whole 8-lane vectors); the
centre sums of the update are accumulated in the same pass per run of equal labels,
and the same runs feed a union-find connectivity pass. Scratch buffers are reused per
thread. Everything runs in one thread and releases the GIL.

The ``"skimage"`` backend calls :func:`skimage.segmentation.slic` as a reference; see
:func:`_slic_skimage` for how it is made to cluster the same values with the same meaning
of the compactness.
"""

from __future__ import annotations

import math
import threading
from typing import Any, Literal

import numpy as np
from numba import njit
from numpy.typing import NDArray

__all__ = [
    "CONVERGENCE_TOL",
    "SlicBackend",
    "slic_superpixels",
    "warm_up",
]

SlicBackend = Literal["numba", "skimage"]

CONVERGENCE_TOL = 0.02
"""k-means stops early once the mean L1 centre shift falls below this fraction of S.

The paper's residual ``E`` is the L1 distance between old and new centres; here only its
spatial part is used, averaged over the centres and divided by S so that the criterion
means the same at every resolution and K (0.02 S is about 0.8 px at 640x480 with K=200).
On the floor datasets this stops after about 8 iterations (640x480) or 7 (320x240) with
boundary recall and undersegmentation error within 0.001 of a full 10 iterations.
"""

# fastmath without the no-NaN / no-Inf assumptions: the inputs are checked to be finite
# and the distance buffer is initialised with a large finite value instead of +inf.
_FASTMATH = {"contract", "arcp", "nsz", "afn", "reassoc"}
_BIG = np.float32(3.0e38)
# Rows of the planar image and of the row buffers are padded by this many columns so
# that the distance loop always runs over whole 8-lane float32 vectors.
_PAD = 8


# --------------------------------------------------------------------------- kernels


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def _to_planar(image: Any, planes: Any) -> bool:  # pragma: no cover - numba
    """(H, W, 3) interleaved float32 -> (3, H, W + _PAD) planar (zero padding).

    Returns whether all values are finite, from the exponent bits (all ones for NaN and
    +-inf), checked by an integer max-reduction in the same pass.
    """
    h, w, _ = image.shape
    flat = image.reshape(h * w * 3)
    bits = flat.view(np.uint32)
    exp_mask = np.uint32(0x7F800000)
    top = np.uint32(0)
    for y in range(h):
        q0 = planes[0, y]
        q1 = planes[1, y]
        q2 = planes[2, y]
        r = flat[3 * w * y : 3 * w * (y + 1)]
        rb = bits[3 * w * y : 3 * w * (y + 1)]
        for x in range(w):
            q0[x] = r[3 * x]
            q1[x] = r[3 * x + 1]
            q2[x] = r[3 * x + 2]
            top = max(top, rb[3 * x] & exp_mask)
            top = max(top, rb[3 * x + 1] & exp_mask)
            top = max(top, rb[3 * x + 2] & exp_mask)
        for x in range(w, planes.shape[2]):
            q0[x] = 0.0
            q1[x] = 0.0
            q2[x] = 0.0
    return bool(top != exp_mask)


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def _gradient_at(planes: Any, y: int, x: int, h: int, w: int) -> float:  # pragma: no cover
    xm = max(x - 1, 0)
    xp = min(x + 1, w - 1)
    ym = max(y - 1, 0)
    yp = min(y + 1, h - 1)
    g = 0.0
    for c in range(3):
        dx = planes[c, y, xp] - planes[c, y, xm]
        dy = planes[c, yp, x] - planes[c, ym, x]
        g += dx * dx + dy * dy
    return g


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def _init_seeds(
    planes: Any, ny: int, nx: int, centres: Any, labels: Any
) -> None:  # pragma: no cover
    """Grid seeds moved to the 3x3 gradient minimum; ``labels`` = grid cell of each pixel.

    ``centres[k] = (y, x, c0, c1, c2)``. A seed starts at the exact centre of its grid
    cell and moves to the pixel of lowest gradient among the 3x3 pixels around it only
    if that gradient is *strictly* lower than at the pixel under the seed, so on flat
    regions the seeds stay exactly on the grid (and no tie depends on scan order).
    The seed colour is the colour of that pixel.
    """
    h, w = labels.shape
    for iy in range(ny):
        fy = (iy + 0.5) * h / ny - 0.5
        sy = math.floor(fy + 0.5)
        for ix in range(nx):
            fx = (ix + 0.5) * w / nx - 0.5
            sx = math.floor(fx + 0.5)
            best_y = sy
            best_x = sx
            best_g = _gradient_at(planes, sy, sx, h, w)
            for dy in range(-1, 2):
                yy = sy + dy
                if yy < 0 or yy >= h:
                    continue
                for dx in range(-1, 2):
                    xx = sx + dx
                    if xx < 0 or xx >= w:
                        continue
                    g = _gradient_at(planes, yy, xx, h, w)
                    if g < best_g:
                        best_g = g
                        best_y = yy
                        best_x = xx
            k = iy * nx + ix
            moved = best_y != sy or best_x != sx
            centres[k, 0] = best_y if moved else fy
            centres[k, 1] = best_x if moved else fx
            centres[k, 2] = planes[0, best_y, best_x]
            centres[k, 3] = planes[1, best_y, best_x]
            centres[k, 4] = planes[2, best_y, best_x]
    # Initial assignment = grid cell, so that every pixel has a valid label even if no
    # 2S x 2S window ever reaches it.
    col = np.empty(w, dtype=np.int32)
    for x in range(w):
        col[x] = min(x * nx // w, nx - 1)
    for y in range(h):
        row = np.int32(min(y * ny // h, ny - 1) * nx)
        rl = labels[y]
        for x in range(w):
            rl[x] = row + col[x]


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def _accumulate_row(
    r0: Any, r1: Any, r2: Any, rl: Any, y: int, sums: Any, runs: Any, n_runs: int
) -> int:  # pragma: no cover - numba
    """Add one row's pixels to the per-label sums ``(y, x, c0, c1, c2, count)``.

    Colours are summed in registers along runs of equal label and scattered once per
    run instead of once per pixel. The runs are also recorded in ``runs`` (rows y, x0,
    x1) from index ``n_runs`` on, for the connectivity pass; returns the new run count.
    """
    w = rl.shape[0]
    k = rl[0]
    x_start = 0
    s0 = np.float32(0.0)
    s1 = np.float32(0.0)
    s2 = np.float32(0.0)
    for x in range(w + 1):
        if x == w or rl[x] != k:
            n = x - x_start
            sums[k, 0] += n * y
            sums[k, 1] += 0.5 * n * (x_start + x - 1)
            sums[k, 2] += s0
            sums[k, 3] += s1
            sums[k, 4] += s2
            sums[k, 5] += n
            runs[0, n_runs] = y
            runs[1, n_runs] = x_start
            runs[2, n_runs] = x
            n_runs += 1
            if x == w:
                break
            k = rl[x]
            x_start = x
            s0 = np.float32(0.0)
            s1 = np.float32(0.0)
            s2 = np.float32(0.0)
        s0 += r0[x]
        s1 += r1[x]
        s2 += r2[x]
    return n_runs


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def _iterate(
    planes: Any,
    centres: Any,
    ny: int,
    nx: int,
    radius: float,
    weight: float,
    labels: Any,
    sums: Any,
    win: Any,
    cf: Any,
    band: Any,
    drow: Any,
    lrow: Any,
    runs: Any,
    row_start: Any,
) -> float:  # pragma: no cover - numba
    """One k-means iteration (assignment + centre update); returns the residual.

    The assignment is the paper's: pixel p goes to the centre k minimising
    ``D = d_c^2 + weight * d_s^2`` among the centres whose 2S x 2S window contains p
    (ties to the lowest k); a pixel inside no window keeps its previous label. It is
    evaluated row by row instead of centre by centre, which gives the same labels but
    keeps the distance and label buffers of the row in L1 cache, and lets the centre
    sums of the update be accumulated in the same pass while the row is still hot.
    The centres are then moved to the means; the return value is the mean L1 shift of
    the centres in pixels. The horizontal label runs of the new labels are left in
    ``runs`` / ``row_start`` for :func:`_enforce_connectivity`.
    """
    h, w = labels.shape
    n_k = centres.shape[0]
    p0 = planes[0]
    p1 = planes[1]
    p2 = planes[2]
    wt = np.float32(weight)
    # Windows [y0, y1) x [x0, x1) of the centres, and per grid row the union of the
    # y ranges, so that each image row only looks at the few grid rows that reach it.
    for iy in range(ny):
        band[iy, 0] = h
        band[iy, 1] = 0
        for ix in range(nx):
            k = iy * nx + ix
            cy = centres[k, 0]
            cx = centres[k, 1]
            y0 = max(math.ceil(cy - radius), 0)
            y1 = min(math.floor(cy + radius) + 1, h)
            win[k, 0] = y0
            win[k, 1] = y1
            win[k, 2] = max(math.ceil(cx - radius), 0)
            win[k, 3] = min(math.floor(cx + radius) + 1, w)
            band[iy, 0] = min(band[iy, 0], y0)
            band[iy, 1] = max(band[iy, 1], y1)
            for c in range(5):
                cf[k, c] = centres[k, c]
    sums[:, :] = 0.0
    n_runs = 0
    for y in range(h):
        row_start[y] = n_runs
        r0 = p0[y]
        r1 = p1[y]
        r2 = p2[y]
        rl_img = labels[y]
        for x in range(w):
            drow[x] = _BIG
            lrow[x] = rl_img[x]
        fy = np.float32(y)
        for iy in range(ny):
            if y < band[iy, 0] or y >= band[iy, 1]:
                continue
            for ix in range(nx):
                k = iy * nx + ix
                if y < win[k, 0] or y >= win[k, 1]:
                    continue
                x0 = win[k, 2]
                n = win[k, 3] - x0
                if n <= 0:
                    continue
                # The segment is rounded up to whole vectors (the rows are padded by
                # _PAD) and the extra lanes are masked out with _BIG: no scalar tail.
                m = (n + _PAD - 1) // _PAD * _PAD
                fn = np.float32(n)
                fdy = fy - cf[k, 0]
                dyw = wt * fdy * fdy
                fx0 = np.float32(x0) - cf[k, 1]
                c0 = cf[k, 2]
                c1 = cf[k, 3]
                c2 = cf[k, 4]
                k32 = np.int32(k)
                # Slices indexed from 0 + branch-free select: the form LLVM vectorises.
                a0 = r0[x0 : x0 + m]
                a1 = r1[x0 : x0 + m]
                a2 = r2[x0 : x0 + m]
                rd = drow[x0 : x0 + m]
                rl = lrow[x0 : x0 + m]
                for i in range(m):
                    fi = np.float32(i)
                    fdx = fi + fx0
                    d0 = a0[i] - c0
                    d1 = a1[i] - c1
                    d2 = a2[i] - c2
                    d = d0 * d0 + d1 * d1 + d2 * d2 + (wt * fdx * fdx + dyw)
                    d = d if fi < fn else _BIG
                    better = d < rd[i]
                    rd[i] = min(d, rd[i])
                    rl[i] = k32 if better else rl[i]
        for x in range(w):
            rl_img[x] = lrow[x]
        n_runs = _accumulate_row(r0, r1, r2, lrow[:w], y, sums, runs, n_runs)
    row_start[h] = n_runs
    shift = 0.0
    for k in range(n_k):
        cnt = sums[k, 5]
        if cnt > 0.0:
            new_y = sums[k, 0] / cnt
            new_x = sums[k, 1] / cnt
            shift += abs(new_y - centres[k, 0]) + abs(new_x - centres[k, 1])
            centres[k, 0] = new_y
            centres[k, 1] = new_x
            centres[k, 2] = sums[k, 2] / cnt
            centres[k, 3] = sums[k, 3] / cnt
            centres[k, 4] = sums[k, 4] / cnt
    return float(shift / n_k)


@njit(cache=True, nogil=True)
def _find_root(parent: Any, i: int) -> int:  # pragma: no cover - numba
    root = i
    while parent[root] != root:
        root = parent[root]
    while parent[i] != root:  # path compression
        nxt = parent[i]
        parent[i] = root
        i = nxt
    return root


@njit(cache=True, nogil=True)
def _run_at(run_x0: Any, row_start: Any, y: int, x: int) -> int:  # pragma: no cover
    """Index of the run of row ``y`` that contains column ``x`` (binary search)."""
    lo = row_start[y]
    hi = row_start[y + 1] - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if run_x0[mid] <= x:
            lo = mid
        else:
            hi = mid - 1
    return int(lo)


@njit(cache=True, nogil=True)
def _enforce_connectivity(
    labels: Any, min_size: float, out: Any, runs: Any, row_start: Any
) -> int:  # pragma: no cover - numba
    """Relabel ``labels`` into 4-connected segments ``0..n-1`` (returned ``n``) in O(N).

    Same result as the raster-scan flood fill of ``EnforceLabelConnectivity`` in the
    authors' reference code, computed on the horizontal runs of equal label that
    :func:`_iterate` recorded in ``runs`` / ``row_start`` for exactly these ``labels``:
    runs are joined by union-find to the overlapping runs of equal label in the row
    above, then the components are visited in raster order of their first pixel. A
    component smaller than ``min_size`` pixels takes the label of an already relabelled
    4-neighbour of its first pixel; that neighbour touches it, so every output label is
    one 4-connected region, and every output segment has at least ``min_size`` pixels
    (unless the whole image has fewer).
    """
    h, w = labels.shape
    # Workspace rows: y, x0, x1 (end, exclusive), union-find parent, size, final label.
    run_y = runs[0]
    run_x0 = runs[1]
    run_x1 = runs[2]
    n_runs = row_start[h]
    parent = runs[3]
    for i in range(n_runs):
        parent[i] = i
    for y in range(1, h):
        rl = labels[y]
        ru = labels[y - 1]
        j = row_start[y - 1]
        j_end = row_start[y]
        for i in range(row_start[y], row_start[y + 1]):
            x0 = run_x0[i]
            x1 = run_x1[i]
            k = rl[x0]
            while j < j_end and run_x1[j] <= x0:
                j += 1
            jj = j
            while jj < j_end and run_x0[jj] < x1:
                if ru[run_x0[jj]] == k:
                    a = _find_root(parent, i)
                    b = _find_root(parent, jj)
                    # Keep the raster-first run as root.
                    if a < b:
                        parent[b] = a
                    elif b < a:
                        parent[a] = b
                jj += 1

    # Component size, accumulated on the root (the raster-first run of the component).
    size = runs[4]
    size[:n_runs] = 0
    for i in range(n_runs):
        r = _find_root(parent, i)
        parent[i] = r
        size[r] += run_x1[i] - run_x0[i]

    final = runs[5]
    n_new = 0
    for i in range(n_runs):
        if parent[i] != i:
            final[i] = final[parent[i]]
            continue
        # i is the first run of its component, whose first pixel is (y, x). As in the
        # reference code, the merge target is the last already relabelled pixel among
        # its left, upper, right and lower neighbours. Left and upper ones are always
        # relabelled (earlier in raster order); a right or lower one only if its
        # component started earlier (root run < i).
        y = run_y[i]
        x = run_x0[i]
        adjacent = -1
        if x > 0:
            adjacent = final[parent[i - 1]]
        if y > 0:
            adjacent = final[parent[_run_at(run_x0, row_start, y - 1, x)]]
        if x + 1 < w and run_x1[i] == x + 1 and parent[i + 1] < i:
            adjacent = final[parent[i + 1]]
        if y + 1 < h:
            r = parent[_run_at(run_x0, row_start, y + 1, x)]
            if r < i:
                adjacent = final[r]
        if size[i] >= min_size:
            final[i] = n_new
            n_new += 1
        elif adjacent >= 0:
            final[i] = adjacent
        else:
            # Small component at pixel (0, 0): like the reference code, it shares its
            # label with the next component, which starts next to it.
            final[i] = n_new

    for i in range(n_runs):
        ro = out[run_y[i]]
        v = final[i]
        for x in range(run_x0[i], run_x1[i]):
            ro[x] = v
    return max(n_new, 1)


@njit(cache=True, nogil=True)
def _record_runs(labels: Any, runs: Any, row_start: Any) -> None:  # pragma: no cover
    """Horizontal runs of equal label, as :func:`_iterate` leaves them (for tests)."""
    h, w = labels.shape
    n_runs = 0
    for y in range(h):
        row_start[y] = n_runs
        rl = labels[y]
        x = 0
        while x < w:
            x_end = x + 1
            while x_end < w and rl[x_end] == rl[x]:
                x_end += 1
            runs[0, n_runs] = y
            runs[1, n_runs] = x
            runs[2, n_runs] = x_end
            n_runs += 1
            x = x_end
    row_start[h] = n_runs


def _relabel_connected(labels: NDArray[np.int32], min_size: float) -> NDArray[np.int32]:
    """Connectivity enforcement alone on any (H, W) int32 label image (for tests)."""
    lab = np.ascontiguousarray(labels, dtype=np.int32)
    h, w = lab.shape
    runs = np.empty((6, h * w), dtype=np.int32)
    row_start = np.empty(h + 1, dtype=np.int32)
    _record_runs(lab, runs, row_start)
    out = np.empty((h, w), dtype=np.int32)
    _enforce_connectivity(lab, float(min_size), out, runs, row_start)
    return out


@njit(cache=True, nogil=True)
def _compact_labels(labels: Any, n_labels: int, out: Any) -> int:  # pragma: no cover
    """Renumber the labels that occur to ``0..n-1`` in raster order of first appearance."""
    h, w = labels.shape
    remap = np.full(n_labels, -1, dtype=np.int32)
    n = 0
    for y in range(h):
        for x in range(w):
            k = labels[y, x]
            if remap[k] < 0:
                remap[k] = n
                n += 1
            out[y, x] = remap[k]
    return n


@njit(cache=True, nogil=True)
def _slic_kernel(
    image: Any,
    ny: int,
    nx: int,
    step: float,
    radius: float,
    compactness: float,
    max_iter: int,
    tol_px: float,
    enforce_connectivity: bool,
    min_size: float,
    planes: Any,
    labels: Any,
    runs: Any,
    row_start: Any,
    out: Any,
) -> int:  # pragma: no cover - numba
    """Whole SLIC into ``out``; returns the number of k-means iterations run, or -1
    (and leaves ``out`` undefined) if the image has a NaN or infinite value.

    ``planes`` (3, H, W + _PAD) float32, ``labels`` (H, W) int32, ``runs`` (6, H*W) int32 and
    ``row_start`` (H+1,) int32 are scratch buffers.
    """
    _h, w, _ = image.shape
    if not _to_planar(image, planes):
        return -1
    n_k = ny * nx
    centres = np.empty((n_k, 5), dtype=np.float64)
    sums = np.empty((n_k, 6), dtype=np.float64)
    win = np.empty((n_k, 4), dtype=np.int64)
    cf = np.empty((n_k, 5), dtype=np.float32)
    band = np.empty((ny, 2), dtype=np.int64)
    drow = np.full(w + _PAD, _BIG, dtype=np.float32)
    lrow = np.zeros(w + _PAD, dtype=np.int32)
    _init_seeds(planes, ny, nx, centres, labels)
    weight = (compactness / step) ** 2
    n_iter = 0
    for _ in range(max_iter):
        shift = _iterate(
            planes,
            centres,
            ny,
            nx,
            radius,
            weight,
            labels,
            sums,
            win,
            cf,
            band,
            drow,
            lrow,
            runs,
            row_start,
        )
        n_iter += 1
        if shift < tol_px:
            break
    if enforce_connectivity:
        _enforce_connectivity(labels, min_size, out, runs, row_start)
    else:
        _compact_labels(labels, n_k, out)
    return n_iter


# --------------------------------------------------------------------------- python side


def _grid_shape(height: int, width: int, n_segments: int) -> tuple[int, int]:
    """Rows and columns of the seed grid: cells close to ``S x S``, count close to K.

    Candidates are the floor/ceil of ``H / S`` and ``W / S`` (the paper's strips) plus
    the column/row counts that best complete the other axis to K; the winner minimises
    ``|ny * nx - K|``, then the cell aspect ratio, then prefers more columns. This keeps
    e.g. 204 seeds for K = 200 at 640x480 and, unlike pure rounding, still gives 2 seeds
    for K = 2 on a small square image.
    """
    step = math.sqrt(height * width / n_segments)

    def around(v: float, hi: int) -> set[int]:
        return {min(max(math.floor(v), 1), hi), min(max(math.ceil(v), 1), hi)}

    candidates: set[tuple[int, int]] = set()
    for ny in around(height / step, height):
        for nx in around(width / step, width) | around(n_segments / ny, width):
            candidates.add((ny, nx))
    for nx in around(width / step, width):
        for ny in around(n_segments / nx, height):
            candidates.add((ny, nx))

    def cost(c: tuple[int, int]) -> tuple[int, float, int, int]:
        ny, nx = c
        aspect = abs(math.log((width / nx) / (height / ny)))
        return (abs(ny * nx - n_segments), round(aspect, 9), -nx, ny)

    return min(candidates, key=cost)


_NOT_FINITE = "image contains NaN or infinite values (after casting to float32)"


def _validate(
    image: NDArray[Any],
    n_segments: int,
    compactness: float,
    max_iter: int,
    min_size_factor: float,
    backend: str,
) -> NDArray[np.float32]:
    if not isinstance(image, np.ndarray):
        raise ValueError(f"image must be a numpy array, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must have shape (H, W, 3), got {image.shape}")
    if image.shape[0] < 2 or image.shape[1] < 2:
        raise ValueError(f"image must be at least 2x2 pixels, got {image.shape[:2]}")
    if not (np.issubdtype(image.dtype, np.floating) or np.issubdtype(image.dtype, np.integer)):
        raise ValueError(f"image must have a real numeric dtype, got {image.dtype}")
    if isinstance(n_segments, bool) or not isinstance(n_segments, int | np.integer):
        raise ValueError(f"n_segments must be an int, got {n_segments!r}")
    if n_segments < 1:
        raise ValueError(f"n_segments must be >= 1, got {n_segments}")
    if not math.isfinite(compactness) or compactness <= 0:
        raise ValueError(f"compactness must be finite and > 0, got {compactness}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, int | np.integer):
        raise ValueError(f"max_iter must be an int, got {max_iter!r}")
    if max_iter < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    if not math.isfinite(min_size_factor) or min_size_factor < 0:
        raise ValueError(f"min_size_factor must be finite and >= 0, got {min_size_factor}")
    if backend not in ("numba", "skimage"):
        raise ValueError(f"backend must be 'numba' or 'skimage', got {backend!r}")
    # Finiteness is checked by the numba kernel on the fly (saves a pass over the image),
    # and here for the skimage backend.
    with np.errstate(over="ignore", invalid="ignore"):  # overflow -> inf, caught below
        img = np.ascontiguousarray(image, dtype=np.float32)
    if backend == "skimage" and not np.isfinite(img).all():
        raise ValueError(_NOT_FINITE)
    return img


class _Workspace:
    """Scratch buffers of one image size, kept per thread to avoid page faults per call."""

    __slots__ = ("labels", "planes", "row_start", "runs", "shape")

    def __init__(self, height: int, width: int) -> None:
        self.shape = (height, width)
        self.planes = np.empty((3, height, width + _PAD), dtype=np.float32)
        self.labels = np.empty((height, width), dtype=np.int32)
        self.runs = np.empty((6, height * width), dtype=np.int32)
        self.row_start = np.empty(height + 1, dtype=np.int32)


_local = threading.local()


def _workspace(height: int, width: int) -> _Workspace:
    ws: _Workspace | None = getattr(_local, "workspace", None)
    if ws is None or ws.shape != (height, width):
        ws = _Workspace(height, width)
        _local.workspace = ws
    return ws


def _slic_numba(
    image: NDArray[np.float32],
    n_segments: int,
    compactness: float,
    max_iter: int,
    enforce_connectivity: bool,
    min_size_factor: float,
    *,
    tol: float = CONVERGENCE_TOL,
) -> tuple[NDArray[np.int32], int]:
    """Run the numba kernel; returns ``(labels, iterations run)``."""
    h, w = image.shape[:2]
    ny, nx = _grid_shape(h, w, int(n_segments))
    # S from the actual seed count, so that S^2 is the expected superpixel area.
    step = math.sqrt(h * w / (ny * nx))
    # 2S x 2S search window; widened only for very elongated cells (thin images) so
    # that the window always covers the centre's own grid cell.
    radius = max(step, 0.5 * w / nx, 0.5 * h / ny)
    min_size = float(min_size_factor) * step * step
    ws = _workspace(h, w)
    out = np.empty((h, w), dtype=np.int32)
    n_iter = _slic_kernel(
        image,
        ny,
        nx,
        step,
        radius,
        float(compactness),
        int(max_iter),
        float(tol) * step,
        bool(enforce_connectivity),
        min_size,
        ws.planes,
        ws.labels,
        ws.runs,
        ws.row_start,
        out,
    )
    if n_iter < 0:
        raise ValueError(_NOT_FINITE)
    return out, int(n_iter)


def _slic_skimage(
    image: NDArray[np.float32],
    n_segments: int,
    compactness: float,
    max_iter: int,
    enforce_connectivity: bool,
    min_size_factor: float,
) -> NDArray[np.int32]:
    """Reference: :func:`skimage.segmentation.slic` on the same values.

    skimage always rescales the image by its global range ``r = max - min`` (over all
    channels) to [0, 1] before clustering, also with ``convert2lab=False``; on an image
    that already is Lab that shrinks the colour distances by ``r`` (about 100-200) and
    the result degenerates to a near-regular grid. Its distance is
    ``d_c'^2 / m'^2 + d_s^2 / S^2`` with ``d_c' = d_c / r``, so passing
    ``m' = m / r`` gives exactly the ordering of ``d_c^2 + (d_s / S)^2 m^2`` on the
    unscaled values. Differences that remain (skimage's choice, not the paper's): no
    seed perturbation, a 4S x 4S search window, always ``max_iter`` iterations, a
    slightly different seed grid, and components larger than 3 S^2 split by
    connectivity enforcement.
    """
    from skimage.segmentation import slic

    img = image.astype(np.float64)
    value_range = float(img.max() - img.min())
    m = compactness / value_range if value_range > 0 else compactness
    raw = slic(
        img,
        n_segments=int(n_segments),
        compactness=m,
        max_num_iter=int(max_iter),
        sigma=0,
        convert2lab=False,
        enforce_connectivity=bool(enforce_connectivity),
        min_size_factor=float(min_size_factor),
        start_label=0,
        channel_axis=-1,
    )
    _, inverse = np.unique(raw, return_inverse=True)
    return inverse.reshape(raw.shape).astype(np.int32)


def slic_superpixels(
    image: NDArray[Any],
    *,
    n_segments: int = 200,
    compactness: float = 10.0,
    max_iter: int = 10,
    enforce_connectivity: bool = True,
    min_size_factor: float = 0.25,
    backend: SlicBackend = "numba",
) -> NDArray[np.int32]:
    """Segment an image into SLIC superpixels.

    Parameters
    ----------
    image : (H, W, 3) ndarray, float32
        Image in the working colour space, e.g. CIELAB with L in [0, 100] and a, b in
        about [-128, 127] (as :func:`skimage.color.rgb2lab` gives), or RGB scaled to
        [0, 100]. It must already be smoothed; no smoothing is done here. Other real
        dtypes are cast to float32. H and W must be at least 2; values must be finite.
    n_segments : int, optional
        Desired number of superpixels K (>= 1). The seed grid has about K cells of
        ``S x S`` pixels, ``S = sqrt(H * W / K)``; the output count can differ
        somewhat (connectivity enforcement adds and removes segments).
    compactness : float, optional
        The paper's ``m`` (> 0): weight of the spatial distance in
        ``D^2 = d_c^2 + (d_s / S)^2 m^2``, in units of the colour values. Higher values
        give more square, grid-like superpixels.
    max_iter : int, optional
        Maximum number of k-means iterations (>= 1). The numba backend stops earlier once
        the mean L1 centre shift is below :data:`CONVERGENCE_TOL` times S.
    enforce_connectivity : bool, optional
        Make every superpixel one 4-connected region and merge fragments smaller than
        ``min_size_factor * S^2`` pixels into an adjacent superpixel.
    min_size_factor : float, optional
        Minimum fragment size relative to the expected superpixel area ``S^2``
        (the paper uses 1/4).
    backend : {"numba", "skimage"}, optional
        ``"numba"``: the kernel of this module (single-threaded, releases the GIL).
        ``"skimage"``: :func:`skimage.segmentation.slic` as a slow reference, made to use
        the same colour values and compactness meaning (see ``_slic_skimage``).

    Returns
    -------
    labels : (H, W) ndarray, int32
        Superpixel labels, contiguous ``0 .. n-1``. With ``enforce_connectivity`` each
        label is a single 4-connected region.

    Raises
    ------
    ValueError
        If the image is not (H, W, 3), smaller than 2x2, not real-valued or not finite,
        or if a parameter is out of range.

    References
    ----------
    .. [1] R. Achanta, A. Shaji, K. Smith, A. Lucchi, P. Fua and S. Süsstrunk, "SLIC
       Superpixels Compared to State-of-the-Art Superpixel Methods", IEEE TPAMI 34(11),
       pp. 2274-2282, 2012. :DOI:`10.1109/TPAMI.2012.120`

    Examples
    --------
    >>> import numpy as np
    >>> img = np.zeros((20, 20, 3), np.float32)
    >>> img[:, 10:] = 50.0
    >>> labels = slic_superpixels(img, n_segments=2)
    >>> labels.shape, labels.dtype, int(labels.max()) + 1
    ((20, 20), dtype('int32'), 2)
    """
    img = _validate(image, n_segments, compactness, max_iter, min_size_factor, backend)
    if backend == "skimage":
        return _slic_skimage(
            img, n_segments, compactness, max_iter, enforce_connectivity, min_size_factor
        )
    labels, _ = _slic_numba(
        img, n_segments, compactness, max_iter, enforce_connectivity, min_size_factor
    )
    return labels


def warm_up() -> None:
    """Compile (or load from the on-disk cache) every numba kernel on a tiny image."""
    rng = np.random.default_rng(0)
    img = rng.uniform(0.0, 100.0, size=(16, 16, 3)).astype(np.float32)
    slic_superpixels(img, n_segments=4, enforce_connectivity=True)
    slic_superpixels(img, n_segments=4, enforce_connectivity=False)
