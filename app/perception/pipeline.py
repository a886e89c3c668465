"""The floor segmentation pipeline: stages of the thesis wired together, by method name.

Methods (``PerceptionConfig.method``):

``thesis``
    Smoothing, Lab, SLIC, the 7 features, safe-zone sampling, the normalised SSD
    classifier and BFS region growing from the superpixel under the safe-zone centroid.
``thesis_junction``
    ``thesis`` ANDed with the floor-junction mask (the thesis's final result).
``flood_fill``
    The thesis's pixel baseline: flood fill of the smoothed Lab image from the seed.
``floornav``
    The same superpixels with what the thesis ignored: a robust self-supervised colour
    model of the safe zone, position and texture cues weighed by a fitted logistic model,
    the per-column free-space structure, and one self-training pass
    (`app.perception.floor_model`).
``floornet`` (default)
    A small convolutional network on the frame's colour, absolute and relative to the
    safe zone's, run by OpenCV's ``dnn`` (`app.perception.floor_net`). It also says how
    sure it is that the safe zone itself is floor, and calls an obstacle standing in the
    zone what it is.

Every method reports ``zone_floor_confidence``: for ``floornet`` the network's mean floor
probability inside the safe zone, for the others the share of the zone they call floor.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from app.config import PerceptionConfig, SafeZoneConfig
from app.perception.classify import ssd_classify
from app.perception.features import (
    AdjacencyGraph,
    SuperpixelFeatures,
    adjacency_graph,
    superpixel_features,
)
from app.perception.floor_model import boundary_to_image, floor_model_segment, grid_stats
from app.perception.floor_net import (
    DEFAULT_MODEL_PATH,
    INPUT_HEIGHT_PX,
    INPUT_WIDTH_PX,
    OUTPUT_HEIGHT_PX,
    OUTPUT_WIDTH_PX,
    FloorNet,
    blob_for_reference,
    floor_mask,
    learned_floor_pass,
    learned_floor_unsure,
    scaled_lab,
)
from app.perception.floor_weights import FIRST_PASS_WEIGHTS, SECOND_PASS_WEIGHTS
from app.perception.image_checks import check_bgr_image
from app.perception.junctions import JunctionResult, floor_junction_mask
from app.perception.preprocess import smooth, to_color_space, to_gray, to_lab_u8
from app.perception.region import flood_fill_floor, grow_region
from app.perception.safe_zone import Trapezoid, safe_zone_mask, safe_zone_superpixels
from app.perception.slic import slic_superpixels


@dataclass(frozen=True)
class FloorResult:
    """Output of `FloorSegmenter.segment`.

    Attributes
    ----------
    floor_mask : (H, W) bool
        True where the floor (free space) is, at the input image's size.
    labels : (H, W) int32 or None
        Superpixel labels 0..n-1 (None for pixel methods).
    superpixel_floor : (n,) bool or None
        Which superpixels were classified as floor.
    safe_zone_mask : (H, W) bool
    method : str
    timings_ms : dict
        Wall time of each stage in milliseconds, in pipeline order, plus ``"total"``.
    zone_floor_confidence : float in [0, 1]
        How sure the method is that the safe zone is floor (the thesis's premise):
        ``floornet``'s mean floor probability in the zone, else the share of the zone
        the method calls floor. Low means an obstacle stands right ahead.
    learned_floor_reference : (3,) floats or None
        The learned floor colour ``floornet`` ran its second pass relative to (twice the
        network time), or None when no second pass ran.
    learned_floor_added_share : float
        Share of the network's output cells that second pass made floor.
    unsure_mask : (H, W) bool or None
        On a frame whose second pass was deferred (`FloorSegmenter.learned_pass_due`):
        where that pass could have found floor; the map takes no evidence there.
    """

    floor_mask: NDArray[np.bool_]
    labels: NDArray[np.int32] | None
    superpixel_floor: NDArray[np.bool_] | None
    safe_zone_mask: NDArray[np.bool_]
    method: str
    timings_ms: dict[str, float] = field(default_factory=dict)
    zone_floor_confidence: float = 1.0
    learned_floor_reference: tuple[float, float, float] | None = None
    learned_floor_added_share: float = 0.0
    unsure_mask: NDArray[np.bool_] | None = None


def trapezoid_from_config(zone: SafeZoneConfig) -> Trapezoid:
    return Trapezoid(
        bottom_left_x_frac=zone.bottom_left_x_frac,
        bottom_right_x_frac=zone.bottom_right_x_frac,
        top_left_x_frac=zone.top_left_x_frac,
        top_right_x_frac=zone.top_right_x_frac,
        top_y_frac=zone.top_y_frac,
        bottom_y_frac=zone.bottom_y_frac,
    )


class _Stopwatch:
    """Records the wall time between successive ``lap`` calls, per stage name."""

    def __init__(self) -> None:
        self.timings_ms: dict[str, float] = {}
        self._start = self._last = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.timings_ms[stage] = self.timings_ms.get(stage, 0.0) + (now - self._last) * 1e3
        self._last = now

    def finish(self) -> dict[str, float]:
        self.timings_ms["total"] = (time.perf_counter() - self._start) * 1e3
        return self.timings_ms


@dataclass(frozen=True)
class _Superpixels:
    smoothed_bgr: NDArray[np.uint8]
    color: NDArray[np.float32]
    labels: NDArray[np.int32]
    zone_mask: NDArray[np.bool_]


@dataclass(frozen=True)
class _ThesisInputs:
    features: SuperpixelFeatures
    graph: AdjacencyGraph
    in_zone: NDArray[np.bool_]
    seeds: NDArray[np.bool_]


class FloorSegmenter:
    """Segments the floor in camera frames with one configured method.

    Holds the configuration and the buffers reused from frame to frame; not thread-safe
    (use one instance per thread). ``segment`` is a pure function of its input frame.
    """

    def __init__(self, config: PerceptionConfig, *, method: str | None = None) -> None:
        self.config = config
        self.method = method or config.method
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose one of {sorted(METHODS)}")
        self.zone = trapezoid_from_config(config.safe_zone)
        self._zone_cache: tuple[tuple[int, int], NDArray[np.bool_]] | None = None
        self._color_buffer: NDArray[np.float32] | None = None
        self._net: FloorNet | None = None
        self.learned_floor: tuple[tuple[float, float, float], ...] = ()
        """Floor colours learned on the way (scaled Lab, `app.mapping.floor_memory`):
        ``floornet`` runs a second pass relative to the one that explains the most of
        what its first pass left out. Set by the daemon before each frame."""
        self.learned_pass_due = True
        """False defers the second pass (the daemon's budget): the frame reports where
        it could have found floor as `FloorResult.unsure_mask` instead."""
        if self.method == "floornet":
            # Loaded here, not on the first frame: a missing model file fails at start-up.
            self._net = FloorNet(Path(config.floornet_model_path or DEFAULT_MODEL_PATH))
            self._net_zone_in = safe_zone_mask((INPUT_HEIGHT_PX, INPUT_WIDTH_PX), self.zone)
            out_shape = (OUTPUT_HEIGHT_PX, OUTPUT_WIDTH_PX)
            self._net_zone_out = safe_zone_mask(out_shape, self.zone)

    def zone_mask(self, shape: tuple[int, int]) -> NDArray[np.bool_]:
        if self._zone_cache is None or self._zone_cache[0] != shape:
            self._zone_cache = (shape, safe_zone_mask(shape, self.zone))
        return self._zone_cache[1]

    def segment(self, image: NDArray[np.uint8]) -> FloorResult:
        """Segment one frame.

        Parameters
        ----------
        image : (H, W, 3) uint8 BGR (grayscale and BGRA are accepted and converted).

        Raises
        ------
        app.perception.image_checks.ImageError
            Not an 8-bit image, or too small.
        app.perception.safe_zone.SafeZoneError
            The safe zone does not fit the image.
        """
        bgr = check_bgr_image(image)
        result = METHODS[self.method](self, bgr)
        if result.method != "floornet":
            zone_floor = result.floor_mask[result.safe_zone_mask]
            share = float(zone_floor.mean()) if zone_floor.size else 0.0
            result = replace(result, zone_floor_confidence=share)
        gap = self.config.fill_gaps_px
        if gap > 0:
            start = time.perf_counter()
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (gap, gap))
            closed = cv2.morphologyEx(result.floor_mask.view(np.uint8), cv2.MORPH_CLOSE, kernel)
            timings = dict(result.timings_ms)
            timings["fill_gaps"] = (time.perf_counter() - start) * 1000
            timings["total"] = timings.get("total", 0.0) + timings["fill_gaps"]
            result = replace(result, floor_mask=closed.astype(bool), timings_ms=timings)
        return result

    # -- shared front end ------------------------------------------------------------

    def _color(self, smoothed: NDArray[np.uint8]) -> NDArray[np.float32]:
        shape = smoothed.shape
        if self._color_buffer is None or self._color_buffer.shape != shape:
            self._color_buffer = np.empty(shape, dtype=np.float32)
        return to_color_space(smoothed, space=self.config.color_space, out=self._color_buffer)

    def superpixels(self, bgr: NDArray[np.uint8], watch: _Stopwatch) -> _Superpixels:
        cfg = self.config
        zone_mask = self.zone_mask(bgr.shape[:2])
        watch.lap("safe_zone")
        smoothed = smooth(bgr, sigma_px=cfg.smoothing_sigma_px)
        watch.lap("smooth")
        color = self._color(smoothed)
        watch.lap("color")
        labels = slic_superpixels(
            color,
            n_segments=cfg.n_superpixels,
            compactness=cfg.compactness,
            max_iter=cfg.slic_max_iter,
            backend=cfg.slic_backend,
        )
        watch.lap("slic")
        return _Superpixels(smoothed, color, labels, zone_mask)

    def thesis_inputs(self, sp: _Superpixels, watch: _Stopwatch) -> _ThesisInputs:
        """The thesis's 7 features, adjacency graph and safe-zone sampling."""
        features = superpixel_features(sp.labels, sp.color)
        graph = adjacency_graph(sp.labels, features.n)
        watch.lap("features")
        in_zone = safe_zone_superpixels(sp.labels, sp.zone_mask, features.n)
        height, width = sp.labels.shape
        seed_x, seed_y = self.zone.seed_xy(width, height)
        seeds = np.zeros(features.n, dtype=bool)
        seeds[sp.labels[seed_y, seed_x]] = True
        watch.lap("sampling")
        return _ThesisInputs(features, graph, in_zone, seeds)

    def junctions(self, smoothed: NDArray[np.uint8]) -> JunctionResult:
        j = self.config.junction
        height, width = smoothed.shape[:2]
        diagonal = float(np.hypot(width, height))
        return floor_junction_mask(
            to_gray(smoothed),
            canny_low=j.canny_low,
            canny_high=j.canny_high,
            hough_threshold=j.hough_threshold,
            min_line_length_px=max(2, round(j.min_line_length_frac * diagonal)),
            max_line_gap_px=j.max_line_gap_px,
            vertical_tolerance_rad=j.vertical_tolerance_rad,
            junction_radius_px=j.junction_radius_frac * diagonal,
        )


def _thesis_region(inputs: _ThesisInputs) -> NDArray[np.bool_]:
    classification = ssd_classify(inputs.features.thesis_vector(), inputs.in_zone)
    return grow_region(inputs.graph, inputs.seeds, classification.is_floor)


def _segment_thesis(seg: FloorSegmenter, bgr: NDArray[np.uint8]) -> FloorResult:
    watch = _Stopwatch()
    sp = seg.superpixels(bgr, watch)
    region = _thesis_region(seg.thesis_inputs(sp, watch))
    floor = region[sp.labels]
    watch.lap("classify")
    return FloorResult(floor, sp.labels, region, sp.zone_mask, "thesis", watch.finish())


def _segment_thesis_junction(seg: FloorSegmenter, bgr: NDArray[np.uint8]) -> FloorResult:
    watch = _Stopwatch()
    sp = seg.superpixels(bgr, watch)
    region = _thesis_region(seg.thesis_inputs(sp, watch))
    watch.lap("classify")
    junction = seg.junctions(sp.smoothed_bgr)
    watch.lap("junctions")
    floor = region[sp.labels] & junction.mask
    watch.lap("combine")
    return FloorResult(floor, sp.labels, region, sp.zone_mask, "thesis_junction", watch.finish())


def _segment_flood_fill(seg: FloorSegmenter, bgr: NDArray[np.uint8]) -> FloorResult:
    watch = _Stopwatch()
    zone_mask = seg.zone_mask(bgr.shape[:2])
    watch.lap("safe_zone")
    smoothed = smooth(bgr, sigma_px=seg.config.smoothing_sigma_px)
    watch.lap("smooth")
    lab_u8 = to_lab_u8(smoothed)
    watch.lap("color")
    seed = seg.zone.seed_xy(bgr.shape[1], bgr.shape[0])
    floor = flood_fill_floor(lab_u8, seed, tolerance=seg.config.flood_fill_tolerance)
    watch.lap("flood_fill")
    return FloorResult(floor, None, None, zone_mask, "flood_fill", watch.finish())


def _segment_floornav(seg: FloorSegmenter, bgr: NDArray[np.uint8]) -> FloorResult:
    watch = _Stopwatch()
    sp = seg.superpixels(bgr, watch)
    stats = grid_stats(bgr, sp.color, sp.labels, sp.zone_mask)
    watch.lap("grid")
    model = floor_model_segment(stats, FIRST_PASS_WEIGHTS, SECOND_PASS_WEIGHTS)
    watch.lap("floor_model")
    floor = boundary_to_image(model.boundary_rows, sp.labels.shape)
    superpixel_floor = stats.mean_of(model.grid_floor.astype(np.float64)) > 0.5
    watch.lap("combine")
    return FloorResult(floor, sp.labels, superpixel_floor, sp.zone_mask, "floornav", watch.finish())


def _segment_floornet(seg: FloorSegmenter, bgr: NDArray[np.uint8]) -> FloorResult:
    watch = _Stopwatch()
    zone_mask = seg.zone_mask(bgr.shape[:2])
    watch.lap("safe_zone")
    lab = scaled_lab(bgr)
    zone_colour = np.median(lab[seg._net_zone_in], axis=0)
    blob = blob_for_reference(lab, zone_colour)
    watch.lap("input")
    assert seg._net is not None
    output = seg._net.run(blob, seg._net_zone_out)
    watch.lap("network")
    learned = None
    unsure = None
    if seg.learned_floor and seg.learned_pass_due:
        learned = learned_floor_pass(
            seg._net, lab, output, zone_colour, seg._net_zone_out, seg.learned_floor
        )
        # The premise stays the first pass's: the safe zone is judged as it is.
        output = replace(output, probability=learned.probability)
        watch.lap("learned_floor")
    elif seg.learned_floor:
        unsure_cells = learned_floor_unsure(lab, output, zone_colour, seg.learned_floor)
        if unsure_cells is not None:
            unsure = cv2.resize(
                unsure_cells.view(np.uint8),
                (zone_mask.shape[1], zone_mask.shape[0]),
                interpolation=cv2.INTER_NEAREST,
            ).astype(bool)
        watch.lap("learned_floor_unsure")
    floor = floor_mask(output, zone_mask, min_zone_confidence=seg.config.zone_min_floor_confidence)
    if unsure is not None:
        unsure &= ~floor
    watch.lap("combine")
    return FloorResult(
        floor,
        None,
        None,
        zone_mask,
        "floornet",
        watch.finish(),
        zone_floor_confidence=output.zone_floor_probability,
        learned_floor_reference=learned.reference if learned is not None else None,
        learned_floor_added_share=learned.added_share if learned is not None else 0.0,
        unsure_mask=unsure,
    )


METHODS: dict[str, Callable[[FloorSegmenter, NDArray[np.uint8]], FloorResult]] = {
    "floornet": _segment_floornet,
    "thesis": _segment_thesis,
    "thesis_junction": _segment_thesis_junction,
    "flood_fill": _segment_flood_fill,
    "floornav": _segment_floornav,
}
