"""SLIC kernel (app.perception.slic) and superpixel quality measures."""

from __future__ import annotations

from collections import deque
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from scipy import ndimage

from app.perception import slic
from app.perception.slic import slic_superpixels, warm_up
from app.perception.superpixel_quality import (
    boundary_map,
    boundary_recall,
    n_segments,
    undersegmentation_error,
)

PROJECT_ROOT = Path(__file__).resolve().parents[2]
HAND_FLOOR = PROJECT_ROOT.parent / "shared" / "datasets" / "robot-hand-floor"


# --------------------------------------------------------------------------- helpers


def two_halves(h: int = 20, w: int = 20) -> NDArray[np.float32]:
    """Lab-like image: dark grey left half, light bluish right half."""
    img = np.zeros((h, w, 3), np.float32)
    img[:, : w // 2] = (30.0, 0.0, 0.0)
    img[:, w // 2 :] = (70.0, -10.0, -20.0)
    return img


def smooth_random(h: int, w: int, seed: int = 0) -> NDArray[np.float32]:
    rng = np.random.default_rng(seed)
    img = rng.uniform(0.0, 100.0, size=(h, w, 3)).astype(np.float32)
    return np.asarray(cv2.GaussianBlur(img, (0, 0), 3.0), dtype=np.float32)


def assert_valid_labels(labels: NDArray[np.int32], shape: tuple[int, int]) -> None:
    assert labels.dtype == np.int32
    assert labels.shape == shape
    n = int(labels.max()) + 1
    assert np.array_equal(np.unique(labels), np.arange(n))


def assert_connected(labels: NDArray[np.int32]) -> None:
    for k in range(int(labels.max()) + 1):
        _, n_comp = ndimage.label(labels == k)  # default structure: 4-connectivity
        assert n_comp == 1, f"label {k} has {n_comp} components"


def reference_connectivity(labels: NDArray[np.int32], min_size: float) -> NDArray[np.int32]:
    """Pixel-by-pixel flood fill written like EnforceLabelConnectivity in the SLIC
    authors' code: raster scan; ``adjlabel`` is the last already relabelled pixel among
    the left, up, right and down neighbours of a component's first pixel (0 at the
    start); a component smaller than ``min_size`` takes ``adjlabel``."""
    h, w = labels.shape
    new = np.full((h, w), -1, np.int64)
    label = 0
    adjlabel = 0
    steps = ((0, -1), (-1, 0), (0, 1), (1, 0))
    for y in range(h):
        for x in range(w):
            if new[y, x] >= 0:
                continue
            new[y, x] = label
            for dy, dx in steps:
                yy, xx = y + dy, x + dx
                if 0 <= yy < h and 0 <= xx < w and new[yy, xx] >= 0:
                    adjlabel = int(new[yy, xx])
            comp = [(y, x)]
            queue = deque(comp)
            while queue:
                cy, cx = queue.popleft()
                for dy, dx in steps:
                    yy, xx = cy + dy, cx + dx
                    if (
                        0 <= yy < h
                        and 0 <= xx < w
                        and new[yy, xx] < 0
                        and labels[yy, xx] == labels[y, x]
                    ):
                        new[yy, xx] = label
                        comp.append((yy, xx))
                        queue.append((yy, xx))
            if len(comp) < min_size:
                for cy, cx in comp:
                    new[cy, cx] = adjlabel
                label -= 1
            label += 1
    return new.astype(np.int32)


def prepare_lab(bgr: NDArray[np.uint8]) -> NDArray[np.float32]:
    blur = cv2.GaussianBlur(bgr, (0, 0), 5.0)
    rgb = cv2.cvtColor(blur, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
    return np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab), dtype=np.float32)


# --------------------------------------------------------------------------- exact answers


@pytest.mark.parametrize("k", [2, 3, 4])
def test_two_flat_halves_boundary_recovered_exactly(k: int) -> None:
    img = two_halves()
    labels = slic_superpixels(img, n_segments=k)
    assert_valid_labels(labels, (20, 20))
    assert int(labels.max()) + 1 >= 2
    left, right = set(np.unique(labels[:, :10])), set(np.unique(labels[:, 10:]))
    assert left.isdisjoint(right)  # every superpixel lies within one half


def test_two_halves_skimage_backend_also_recovers_boundary() -> None:
    # Without the compactness correction skimage would see the halves as nearly equal
    # (it rescales the values to [0, 1]) and cut the image by position only.
    labels = slic_superpixels(two_halves(), n_segments=4, backend="skimage")
    assert_valid_labels(labels, (20, 20))
    assert set(np.unique(labels[:, :10])).isdisjoint(np.unique(labels[:, 10:]))


@pytest.mark.parametrize(
    ("h", "w", "k", "ny", "nx"), [(40, 40, 16, 4, 4), (40, 60, 6, 2, 3), (30, 90, 3, 1, 3)]
)
def test_flat_image_gives_regular_grid(h: int, w: int, k: int, ny: int, nx: int) -> None:
    img = np.full((h, w, 3), (50.0, 5.0, -5.0), np.float32)
    labels = slic_superpixels(img, n_segments=k)
    yy, xx = np.mgrid[:h, :w]
    expected = (yy * ny // h) * nx + xx * nx // w
    assert np.array_equal(labels, expected)


def test_grid_shape_close_to_requested_count() -> None:
    assert slic._grid_shape(480, 640, 200) == (12, 17)
    assert slic._grid_shape(240, 320, 200) == (12, 17)
    assert slic._grid_shape(20, 20, 2) == (1, 2)
    assert slic._grid_shape(20, 20, 1) == (1, 1)
    assert slic._grid_shape(2, 1000, 1) == (1, 1)
    assert slic._grid_shape(2, 1000, 10) == (1, 10)
    assert slic._grid_shape(5, 5, 100) == (5, 5)  # at most one seed per pixel


# --------------------------------------------------------------------------- properties


@pytest.mark.parametrize(("h", "w", "k"), [(64, 80, 20), (97, 131, 50), (2, 2, 1), (3, 50, 7)])
def test_labels_contiguous_connected_and_not_too_small(h: int, w: int, k: int) -> None:
    img = smooth_random(h, w, seed=h + w)
    labels = slic_superpixels(img, n_segments=k, compactness=5.0)
    assert_valid_labels(labels, (h, w))
    assert_connected(labels)
    # Fragments below min_size_factor * S^2 are merged into a neighbour.
    ny, nx = slic._grid_shape(h, w, k)
    min_size = 0.25 * h * w / (ny * nx)
    assert (np.bincount(labels.ravel()) >= min_size).all()


def test_without_connectivity_labels_are_contiguous() -> None:
    img = smooth_random(60, 70, seed=3)
    labels = slic_superpixels(img, n_segments=30, enforce_connectivity=False)
    assert_valid_labels(labels, (60, 70))
    for backend in ("numba", "skimage"):
        labels = slic_superpixels(img, n_segments=30, enforce_connectivity=False, backend=backend)
        assert_valid_labels(labels, (60, 70))


def test_deterministic_and_input_untouched() -> None:
    img = smooth_random(50, 60, seed=7)
    before = img.copy()
    a = slic_superpixels(img, n_segments=25)
    b = slic_superpixels(img, n_segments=25)
    assert np.array_equal(a, b)
    assert np.array_equal(img, before)


def test_other_dtypes_are_cast_to_float32() -> None:
    img = smooth_random(40, 40, seed=1)
    ref = slic_superpixels(img, n_segments=16)
    assert np.array_equal(slic_superpixels(img.astype(np.float64), n_segments=16), ref)
    u8 = np.clip(img, 0, 255).astype(np.uint8)
    assert_valid_labels(slic_superpixels(u8, n_segments=16), (40, 40))


def test_more_segments_than_pixels() -> None:
    img = smooth_random(6, 6, seed=2)
    labels = slic_superpixels(img, n_segments=100, enforce_connectivity=False)
    assert_valid_labels(labels, (6, 6))
    assert slic_superpixels(img, n_segments=100).shape == (6, 6)


def test_shapes_of_different_sizes_reuse_workspace_safely() -> None:
    for h, w in ((30, 40), (41, 33), (30, 40)):
        img = smooth_random(h, w, seed=h)
        labels = slic_superpixels(img, n_segments=12)
        assert_valid_labels(labels, (h, w))
        assert_connected(labels)


def test_warm_up_runs() -> None:
    warm_up()


def test_more_iterations_do_not_break_convergence_stop() -> None:
    img = smooth_random(48, 64, seed=5)
    _, n1 = slic._slic_numba(img, 12, 10.0, 1, True, 0.25)
    _, n50 = slic._slic_numba(img, 12, 10.0, 50, True, 0.25)
    assert n1 == 1
    assert 1 <= n50 < 50  # the residual criterion stops it long before 50


@pytest.mark.parametrize("seed", range(8))
def test_connectivity_pass_matches_flood_fill_reference(seed: int) -> None:
    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.integers(2, 25, size=2))
    if seed % 2:
        blocks = rng.integers(0, 4, size=(h // 3 + 1, w // 3 + 1))
        labels = np.kron(blocks, np.ones((3, 3), np.int64))[:h, :w].astype(np.int32)
    else:
        labels = rng.integers(0, 3, size=(h, w)).astype(np.int32)
    for min_size in (0.0, 3.0, 7.5, 1e9):
        expected = reference_connectivity(labels, min_size)
        got = slic._relabel_connected(labels, min_size)
        assert np.array_equal(got, expected)
        assert_valid_labels(got, (h, w))
        assert_connected(got)


def test_connectivity_merges_into_last_relabelled_neighbour() -> None:
    # The 1-pixel fragment of label 2 at (1, 1) has relabelled neighbours left and up
    # (segment of label 0) and right (label 1, which started earlier, in row 0); its
    # lower neighbour starts a later segment. The last relabelled one, right, wins.
    labels = np.array([[0, 0, 1, 1], [0, 2, 1, 1], [3, 3, 3, 3]], np.int32)
    got = slic._relabel_connected(labels, 2.0)
    assert np.array_equal(got, [[0, 0, 1, 1], [0, 1, 1, 1], [2, 2, 2, 2]])
    # With the lower neighbour relabelled before (same segment as the left one) it wins.
    labels[2] = 0
    got = slic._relabel_connected(labels, 2.0)
    assert np.array_equal(got, [[0, 0, 1, 1], [0, 0, 1, 1], [0, 0, 0, 0]])
    # A small first segment shares its label with the next one.
    labels = np.array([[5, 1, 1, 1], [1, 1, 1, 1]], np.int32)
    assert np.array_equal(slic._relabel_connected(labels, 2.0), np.zeros((2, 4)))


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    ("image", "kwargs", "match"),
    [
        (np.zeros((10, 10), np.float32), {}, r"shape \(H, W, 3\)"),
        (np.zeros((10, 10, 4), np.float32), {}, r"shape \(H, W, 3\)"),
        (np.zeros((1, 10, 3), np.float32), {}, "at least 2x2"),
        (np.zeros((10, 10, 3), np.complex64), {}, "real numeric"),
        (np.full((10, 10, 3), np.nan, np.float32), {}, "NaN or infinite"),
        (np.full((10, 10, 3), np.inf, np.float32), {}, "NaN or infinite"),
        (np.zeros((10, 10, 3), np.float32), {"n_segments": 0}, "n_segments must be >= 1"),
        (np.zeros((10, 10, 3), np.float32), {"n_segments": 2.5}, "n_segments must be an int"),
        (np.zeros((10, 10, 3), np.float32), {"compactness": 0.0}, "compactness"),
        (np.zeros((10, 10, 3), np.float32), {"compactness": float("nan")}, "compactness"),
        (np.zeros((10, 10, 3), np.float32), {"max_iter": 0}, "max_iter must be >= 1"),
        (np.zeros((10, 10, 3), np.float32), {"min_size_factor": -1.0}, "min_size_factor"),
        (np.zeros((10, 10, 3), np.float32), {"backend": "opencv"}, "backend"),
    ],
)
def test_invalid_input_raises(
    image: NDArray[np.float32], kwargs: dict[str, object], match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        slic_superpixels(image, **kwargs)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- quality measures


def test_boundary_map_marks_both_sides() -> None:
    a = np.array([[0, 0, 1], [0, 0, 1]])
    assert np.array_equal(boundary_map(a), [[False, True, True], [False, True, True]])


def test_boundary_recall_exact() -> None:
    labels = np.zeros((6, 6), np.int32)
    labels[:, 3:] = 1  # superpixel boundary pixels: columns 2 and 3
    gt = np.zeros((6, 6), bool)
    gt[:, :3] = True  # same edge
    assert boundary_recall(labels, gt, tolerance_px=0) == 1.0
    gt_shifted = np.zeros((6, 6), bool)
    gt_shifted[:, :2] = True  # gt boundary columns 1 and 2: only column 2 is hit exactly
    assert boundary_recall(labels, gt_shifted, tolerance_px=0) == 0.5
    assert boundary_recall(labels, gt_shifted, tolerance_px=1) == 1.0
    # chessboard tolerance: a far-away edge is not recalled
    far = np.zeros((6, 6), np.int32)
    far[:, 5:] = 1  # boundary columns 4, 5
    gt_left = np.zeros((6, 6), bool)
    gt_left[:, :1] = True  # boundary columns 0, 1
    assert boundary_recall(far, gt_left, tolerance_px=2) == 0.0  # distances 3 and 4
    assert boundary_recall(far, gt_left, tolerance_px=3) == 0.5
    assert boundary_recall(far, gt_left, tolerance_px=4) == 1.0


def test_boundary_recall_nan_without_gt_boundary() -> None:
    labels = np.arange(16, dtype=np.int32).reshape(4, 4)
    assert np.isnan(boundary_recall(labels, np.ones((4, 4), bool)))
    assert np.isnan(boundary_recall(labels, np.zeros((4, 4), bool)))


def test_undersegmentation_error_exact() -> None:
    labels = np.array([[0, 0, 1, 1], [0, 0, 1, 1]], np.int32)
    gt = np.array([[1, 1, 1, 0], [1, 1, 1, 0]], bool)
    assert undersegmentation_error(labels, gt) == 2 / 8  # segment 1 is half floor
    gt2 = np.array([[1, 1, 1, 1], [1, 1, 1, 0]], bool)
    assert undersegmentation_error(labels, gt2) == 1 / 8
    assert undersegmentation_error(labels, labels == 0) == 0.0
    sparse = np.where(labels == 0, 5, 9).astype(np.int32)  # non-contiguous labels
    assert undersegmentation_error(sparse, gt) == 2 / 8
    assert undersegmentation_error(np.zeros((2, 4), np.int32), gt) == 2 / 8


def test_n_segments_and_errors() -> None:
    assert n_segments(np.array([[3, 3], [7, 0]])) == 3
    with pytest.raises(ValueError, match="does not match"):
        undersegmentation_error(np.zeros((2, 2), np.int32), np.zeros((3, 2), bool))
    with pytest.raises(ValueError, match="integer"):
        boundary_recall(np.zeros((2, 2), np.float32), np.zeros((2, 2), bool))


# --------------------------------------------------------------------------- vs skimage


@pytest.mark.skipif(
    not HAND_FLOOR.is_dir(), reason=f"dataset {HAND_FLOOR} not present (needs ../shared)"
)
def test_numba_matches_skimage_quality_on_real_images() -> None:
    images = sorted(HAND_FLOOR.glob("*.jpg"))
    images = [p for p in images if p.with_name(p.stem + "_floor.png").is_file()]
    assert images, "no images with floor masks"
    picked = images[:: max(1, len(images) // 4)][:4]
    quality: dict[str, list[tuple[float, float]]] = {"numba": [], "skimage": []}
    for path in picked:
        bgr = cv2.imread(str(path))
        mask = cv2.imread(str(path.with_name(path.stem + "_floor.png")), cv2.IMREAD_GRAYSCALE)
        assert bgr is not None and mask is not None
        gt: NDArray[np.bool_] = np.asarray(mask) == 255
        lab = prepare_lab(np.asarray(bgr, dtype=np.uint8))
        counts = {}
        for backend in ("numba", "skimage"):
            labels = slic_superpixels(lab, n_segments=200, compactness=10.0, backend=backend)
            counts[backend] = n_segments(labels)
            quality[backend].append(
                (boundary_recall(labels, gt, tolerance_px=2), undersegmentation_error(labels, gt))
            )
        assert abs(counts["numba"] - counts["skimage"]) <= 0.25 * counts["skimage"]
    br = {b: float(np.nanmean([q[0] for q in v])) for b, v in quality.items()}
    ue = {b: float(np.mean([q[1] for q in v])) for b, v in quality.items()}
    assert abs(br["numba"] - br["skimage"]) <= 0.03, br
    assert abs(ue["numba"] - ue["skimage"]) <= 0.01, ue
