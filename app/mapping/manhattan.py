"""Heading held by the building's straight lines (a Manhattan-world constraint).

Wheel odometry's heading drifts (one tyre a percent larger turns the estimate about a
degree a second at cruise speed), and floor odometry cannot stop it where the floor has
no texture of its own (a polished corridor, whose only texture is reflections that move
unlike the floor). Walls, cupboards and the boxes against them mostly run along two
perpendicular directions, and their feet are straight lines on the floor that the camera
sees wherever it looks: the floor's edge. Their direction in the world is fixed, so the
direction seen from the robot gives the robot's heading, modulo a quarter turn.

`floor_edge_segments` finds those lines: image edges (Canny) along the colour floor's
boundary, joined into segments (probabilistic Hough, the thesis's junction tools), each
fitted again on the floor to its own edge pixels, moved to the gradient's peak (a wall
beside the robot's way seen a pixel nearer at its far end is a degree off on the
floor). `HeadingAxis` learns the building's axis
from the first lines seen (odometry has not drifted yet) and then reads, in each frame
it is handed with lines close to the axis, how far the heading has turned off it (the
mapper hands it the frames where floor odometry missed: `GroundMapper.follow_floor`);
a small Kalman filter weighs that against how far odometry may have drifted since.
Lines further off than the filter expects (a diagonal wall, a box turned on the floor, a
curved sofa) are not used, so a building that is not rectilinear corrects nothing
rather than something wrong; a line a degree or two off the axis pulls the heading by
part of that while only it is in view. A heading that has turned further off than the
gate (a spin turn's slip where floor odometry could not follow it) is turned back only
when frame after frame, from views apart, the lines agree on one offset and none lie
inside the gate: one frame's stray line is no evidence, a building seen consistently
askew is.

Pure functions and a small state on numpy arrays; no I/O.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from app.mapping.calibration import FloorCalibration


@dataclass(frozen=True)
class ManhattanParams:
    """How `floor_edge_segments` finds the floor's straight edges and `HeadingAxis` uses
    them.

    Attributes
    ----------
    band_px : image edges count only this close (a square window) to the colour floor's
        boundary: the boundary itself is as coarse as the mask, the edge is exact.
    canny_low, canny_high : Canny hysteresis thresholds (grey levels).
    hough_votes, min_segment_px, max_gap_px : ``cv2.HoughLinesP`` threshold, shortest
        segment and largest gap, in pixels.
    max_range_m : segments reaching further from the robot are not used (the floor
        homography magnifies a pixel's error with distance).
    min_length_m : shorter segments on the floor are not used.
    learn_length_m : segment length, summed over frames, needed to fix the axis.
    learn_window_rad, learn_agreement : the axis is fixed where this wide a window either
        side of a direction (modulo a quarter turn) holds this share of that length.
    gate_rad : segments further than this from the axis (modulo a quarter turn) are never
        used to correct, however uncertain the heading...
    min_gate_rad : ...and those this close always are (see `HeadingAxis.observe`).
    gate_sigmas : the gate in between: this many times the offset's expected spread.
    min_frame_length_m : a frame corrects only with at least this much segment length
        inside the gate.
    line_sigma_rad : one frame's measurement noise (the segments' median direction on
        the floor, `scripts/measure_localization.py`: about a degree).
    start_sigma_rad : the heading's uncertainty once the axis is fixed.
    drift_rad2_per_m, drift_rad2_per_rad : the heading's variance added by a metre of
        travel and a radian of turn (odometry's drift as a random walk: about a degree
        a metre, unequal tyres, and a degree a radian, slip in spin turns).
    floor_drift_share : of that variance, the share left where floor odometry holds the
        motion (a tenth of the wheels' drift: it keeps headings to a few hundredths of a
        degree a step).
    recover_limit_rad : beyond the gate, segments up to this far off the axis are
        evidence that the heading has turned away (further off, a quarter turn's
        ambiguity nears)...
    recover_frames, recover_agreement_rad : ...and the heading is turned back by their
        offset once this many frames in a row (none with segments inside the gate) agree
        on it to within this either side of their median...
    recover_travel_m, recover_turn_rad : ...seen from views this far apart (travel or
        turn: not one object's edge seen again and again from one place).
    """

    band_px: int = 9
    canny_low: int = 40
    canny_high: int = 120
    hough_votes: int = 30
    min_segment_px: int = 30
    max_gap_px: int = 4
    max_range_m: float = 3.0
    min_length_m: float = 0.5
    learn_length_m: float = 20.0
    learn_window_rad: float = math.radians(1.5)
    learn_agreement: float = 0.5
    gate_rad: float = math.radians(6.0)
    min_gate_rad: float = math.radians(1.5)
    gate_sigmas: float = 2.5
    min_frame_length_m: float = 0.5
    line_sigma_rad: float = math.radians(1.5)
    start_sigma_rad: float = math.radians(1.0)
    drift_rad2_per_m: float = math.radians(1.0) ** 2
    drift_rad2_per_rad: float = math.radians(1.0) ** 2
    floor_drift_share: float = 0.01
    recover_limit_rad: float = math.radians(25.0)
    recover_frames: int = 6
    recover_agreement_rad: float = math.radians(1.5)
    recover_travel_m: float = 0.5
    recover_turn_rad: float = 0.5


def floor_edge_segments(
    gray: NDArray[np.uint8],
    floor_mask: NDArray[np.bool_],
    calibration: FloorCalibration,
    within_range: NDArray[np.bool_],
    params: ManhattanParams | None = None,
) -> NDArray[np.float64]:
    """Straight edges of the floor, on the floor, in the robot frame.

    Parameters
    ----------
    gray : (H, W) uint8 image.
    floor_mask : (H, W) bool, True = floor (any segmentation).
    calibration : the floor calibration (`FloorCalibration.image_to_ground`; a lens model
        is undone).
    within_range : (H, W) bool, the pixels whose floor point is within
        ``params.max_range_m`` (`app.mapping.ipm.build_ground_lookup`'s ``valid``, built
        once for the camera): the floor homography magnifies a pixel's error with
        distance.
    params : see `ManhattanParams`.

    Returns
    -------
    (n, 2) float64: each segment's direction in the robot frame (radians, in
    [-pi/2, pi/2): a line has no sense) and its length in metres on the floor. Segments
    touching the image's border (the view's edge, not the floor's) are not found.
    """
    p = params if params is not None else ManhattanParams()
    if not gray.shape == floor_mask.shape == within_range.shape:
        raise ValueError(
            f"image {gray.shape}, floor mask {floor_mask.shape} and range mask"
            f" {within_range.shape} differ"
        )
    mask = np.ascontiguousarray(floor_mask, np.uint8)
    square = np.ones((3, 3), np.uint8)
    boundary = mask ^ np.asarray(cv2.erode(mask, square, borderValue=1), np.uint8)
    near = cv2.dilate(boundary, np.ones((p.band_px, p.band_px), np.uint8))
    edges = cv2.Canny(gray, p.canny_low, p.canny_high)
    # Edge pixels beyond the range go before the lines are joined: a wall's foot running
    # off towards the horizon still gives its near part.
    edges[(near == 0) | ~within_range] = 0
    edges[:2, :] = 0
    edges[-2:, :] = 0
    edges[:, :2] = 0
    edges[:, -2:] = 0
    found = cv2.HoughLinesP(
        edges,
        1.0,
        math.pi / 360.0,
        p.hough_votes,
        minLineLength=p.min_segment_px,
        maxLineGap=p.max_gap_px,
    )
    if found is None:
        return np.zeros((0, 2), np.float64)
    ends = np.asarray(found, np.float64).reshape(-1, 4)
    # (x, y) of every edge pixel (some: Hough found segments); OpenCV takes a fifth of
    # numpy nonzero's time here.
    pixels = np.asarray(cv2.findNonZero(edges), np.float64).reshape(-1, 2)
    # Each segment is fitted again, on the floor, to its own edge pixels, each moved to
    # where its edge really is: Hough's ends lie on a 1-pixel, half-degree lattice, and a
    # hard edge's pixels on either side of it at random, and the floor homography turns
    # a pixel's error along a line into a degree or more of its direction.
    located = _edge_centres(gray, pixels)
    on_floor = calibration.image_to_ground(located)  # NaN above the horizon
    segments = []
    for own in _supports(pixels, ends):
        fitted = _fit_on_floor(on_floor[own])
        if fitted is None:
            continue
        direction, length, reach = fitted
        # Some slack: the pixels kept in range moved up to half a pixel to their edge.
        if reach <= 1.05 * p.max_range_m and length >= p.min_length_m:
            segments.append((direction, length))
    return np.asarray(segments, np.float64).reshape(-1, 2)


SEGMENT_SUPPORT_PX = 1.5
"""Edge pixels this close across a Hough segment (and along it, within a pixel of its
ends) are its own."""
MIN_SUPPORT = 5
"""A segment fitted to fewer edge pixels on the floor is not used."""


def _edge_centres(gray: NDArray[np.uint8], pixels: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 2) the edge ``pixels`` (x, y) moved to the peak of the gradient's magnitude
    across the edge (a parabola through it and its two neighbours along the gradient;
    at most half a pixel): Canny keeps one pixel of the two a hard edge lies between,
    whichever has the larger gradient by a grey level."""
    if len(pixels) == 0:
        return pixels
    image = np.asarray(gray, np.float32)
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3)
    magnitude = cv2.magnitude(gx, gy)
    cols = pixels[:, 0].astype(np.intp)
    rows = pixels[:, 1].astype(np.intp)
    across = np.stack([gx[rows, cols], gy[rows, cols]], axis=1).astype(np.float64)
    across /= np.maximum(np.hypot(across[:, 0], across[:, 1]), 1e-9)[:, None]

    def at(points: NDArray[np.float64]) -> NDArray[np.float64]:
        map_x = np.ascontiguousarray(points[:, 0], np.float32).reshape(1, -1)
        map_y = np.ascontiguousarray(points[:, 1], np.float32).reshape(1, -1)
        sampled = cv2.remap(
            magnitude, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        return np.asarray(sampled, np.float64).reshape(-1)

    before = at(pixels - across)
    centre = magnitude[rows, cols].astype(np.float64)
    after = at(pixels + across)
    curvature = before - 2.0 * centre + after
    peaked = curvature < -1e-6
    shift = np.zeros(len(pixels))
    shift[peaked] = 0.5 * (before[peaked] - after[peaked]) / curvature[peaked]
    return pixels + np.clip(shift, -0.5, 0.5)[:, None] * across


def _supports(pixels: NDArray[np.float64], ends: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(segments, pixels): the edge ``pixels`` (x, y) each Hough segment (x0, y0, x1,
    y1 per row of ``ends``) owns: within `SEGMENT_SUPPORT_PX` across it, and along it
    within a pixel of its ends."""
    start = ends[:, None, :2]
    delta = ends[:, 2:] - ends[:, :2]
    length = np.maximum(np.hypot(delta[:, 0], delta[:, 1]), 1e-9)[:, None]
    unit_x, unit_y = delta[:, 0:1] / length, delta[:, 1:2] / length
    offset = pixels[None, :, :] - start
    along = offset[:, :, 0] * unit_x + offset[:, :, 1] * unit_y
    across = offset[:, :, 1] * unit_x - offset[:, :, 0] * unit_y
    return np.asarray(
        (np.abs(across) <= SEGMENT_SUPPORT_PX) & (along >= -1.0) & (along <= length + 1.0),
        dtype=np.bool_,
    )


def _fit_on_floor(ground: NDArray[np.float64]) -> tuple[float, float, float] | None:
    """The line through one segment's edge pixels on the floor (total least squares):
    its direction modulo a half turn in [-pi/2, pi/2), its length and the furthest
    reach of its pixels from the robot; None with fewer than `MIN_SUPPORT` on the floor."""
    ground = ground[np.isfinite(ground).all(axis=1)]
    if len(ground) < MIN_SUPPORT:
        return None
    centred = ground - ground.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)
    line = vectors[:, 1]  # the direction of largest spread
    spread = centred @ line
    direction = math.atan2(float(line[1]), float(line[0]))
    # A line's direction modulo a half turn, in [-pi/2, pi/2).
    direction = (direction + math.pi / 2) % math.pi - math.pi / 2
    reach = float(np.max(np.hypot(ground[:, 0], ground[:, 1])))
    return direction, float(spread.max() - spread.min()), reach


def quarter_turn_offset(
    angle_rad: NDArray[np.float64] | float, axis_rad: float
) -> NDArray[np.float64]:
    """How far each angle is from the axis or a multiple of a quarter turn off it, in
    [-pi/4, pi/4)."""
    quarter = math.pi / 2
    return np.asarray((np.asarray(angle_rad) - axis_rad + quarter / 2) % quarter - quarter / 2)


_LEARN_KEPT = 400
"""Segments kept while learning the axis (the latest: odometry drifts meanwhile)."""


def _weighted_median(values: NDArray[np.float64], weights: NDArray[np.float64]) -> float:
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cumulative, cumulative[-1] / 2.0)])


class HeadingAxis:
    """The building's axis in the world frame, learned once, and the heading corrections
    it gives (see the module docstring).

    Attributes
    ----------
    axis_rad : the axis (modulo a quarter turn), None until learned.
    frames_used : frames that had segments inside the gate (corrections made).
    recoveries : headings turned back from beyond the gate.
    """

    def __init__(self, params: ManhattanParams | None = None) -> None:
        self.params = params if params is not None else ManhattanParams()
        self.axis_rad: float | None = None
        self.frames_used = 0
        self.recoveries = 0
        self.variance_rad2 = self.params.start_sigma_rad**2
        """The heading's variance about the axis (radians squared)."""
        self._learning: list[tuple[float, float]] = []
        """(direction modulo a quarter turn, length) of the segments seen while
        learning."""
        self._travel_m = 0.0
        self._turned_rad = 0.0
        """Odometry's travel and turn so far (how far apart two frames' views are)."""
        self._beyond: deque[tuple[float, float, float]] = deque(maxlen=self.params.recover_frames)
        """(offset, travel, turn) of the latest frames in a row whose segments all lay
        beyond the gate (`_recover`)."""

    def moved(self, distance_m: float, turn_rad: float, *, floor_held: bool = False) -> None:
        """Odometry moved the robot: the heading is that much less certain (a random
        walk, ``drift_rad2_per_m`` and ``drift_rad2_per_rad``; ``floor_held``: floor
        odometry lined the floors up over this motion, which leaves
        ``floor_drift_share`` of the wheels' drift)."""
        p = self.params
        self._travel_m += abs(distance_m)
        self._turned_rad += abs(turn_rad)
        share = p.floor_drift_share if floor_held else 1.0
        self.variance_rad2 += share * p.drift_rad2_per_m * abs(distance_m)
        self.variance_rad2 += share * p.drift_rad2_per_rad * abs(turn_rad)

    def observe(
        self, segments: NDArray[np.float64], heading_rad: float, *, may_correct: bool = True
    ) -> float | None:
        """One frame's `floor_edge_segments` seen at the estimated ``heading_rad``: the
        heading correction (radians, to add to the heading), or None (no axis yet, no
        segment near it, or not ``may_correct``: the segments only teach the axis).

        A one-state Kalman filter on the heading's offset from the axis: the frame's
        measurement is its segments' length-weighted median offset (noise
        ``line_sigma_rad``), over those inside the gate: ``gate_sigmas`` times the
        offset's expected spread (the heading's uncertainty and the line's), within
        [``min_gate_rad``, ``gate_rad``]. A heading that odometry keeps well (floor
        odometry) keeps the gate narrow, so a box a few degrees askew is not taken for a
        wall; the gain falls as the heading becomes certain, so one frame's stray line
        moves it little. Frames whose segments all lie beyond the gate go to
        `_recover`."""
        p = self.params
        if len(segments) == 0:
            return None
        world = segments[:, 0] + heading_rad
        length = segments[:, 1]
        if self.axis_rad is None:
            self._learn(world, length)
            return None
        if not may_correct:
            return None
        offset = quarter_turn_offset(world, self.axis_rad)
        spread = math.sqrt(self.variance_rad2 + p.line_sigma_rad**2)
        gate = min(max(p.gate_sigmas * spread, p.min_gate_rad), p.gate_rad)
        near = np.abs(offset) <= gate
        if float(length[near].sum()) < p.min_frame_length_m:
            return self._recover(offset, length, gate)
        self._beyond.clear()
        self.frames_used += 1
        gain = self.variance_rad2 / (self.variance_rad2 + p.line_sigma_rad**2)
        self.variance_rad2 *= 1.0 - gain
        return -gain * _weighted_median(offset[near], length[near])

    def _recover(
        self, offset: NDArray[np.float64], length: NDArray[np.float64], gate: float
    ) -> float | None:
        """A frame with no segment inside the gate: its segments between the gate and
        ``recover_limit_rad`` give one offset (their length-weighted median); once
        ``recover_frames`` such frames in a row, from views ``recover_travel_m`` or
        ``recover_turn_rad`` apart, agree on it within ``recover_agreement_rad``, the
        heading turns back by all of it (their median) and is as sure as when the axis was
        learned. Returns that turn, or None."""
        p = self.params
        far = (np.abs(offset) > gate) & (np.abs(offset) <= p.recover_limit_rad)
        if float(length[far].sum()) < p.min_frame_length_m:
            return None
        self._beyond.append(
            (_weighted_median(offset[far], length[far]), self._travel_m, self._turned_rad)
        )
        if len(self._beyond) < p.recover_frames:
            return None
        offsets = np.array([seen[0] for seen in self._beyond])
        middle = float(np.median(offsets))
        if float(np.max(np.abs(offsets - middle))) > p.recover_agreement_rad:
            return None
        first, last = self._beyond[0], self._beyond[-1]
        if last[1] - first[1] < p.recover_travel_m and last[2] - first[2] < p.recover_turn_rad:
            return None
        self._beyond.clear()
        self.recoveries += 1
        self.variance_rad2 = p.start_sigma_rad**2
        return -middle

    def _learn(self, world_rad: NDArray[np.float64], length: NDArray[np.float64]) -> None:
        """Keep the segments' directions modulo a quarter turn; once they hold
        ``learn_length_m``, fix the axis at the densest direction if +-
        ``learn_window_rad`` around it holds ``learn_agreement`` of the length (the
        axis: their length-weighted median there). Until then, and while no direction
        stands out, keep adding: odometry drifts slowly, and a few stray lines (a door's
        edge, a reflection) make no peak."""
        p = self.params
        self._learning.extend(
            zip(quarter_turn_offset(world_rad, 0.0).tolist(), length.tolist(), strict=True)
        )
        seen = np.array(self._learning, np.float64)
        total = float(seen[:, 1].sum())
        if total < p.learn_length_m:
            return
        # Every segment's direction as a candidate: the length within the window of each.
        pairwise = seen[:, 0][:, None] - seen[:, 0][None, :]
        within = np.abs(quarter_turn_offset(pairwise, 0.0)) <= p.learn_window_rad
        around = within @ seen[:, 1]
        best = int(np.argmax(around))
        best_centre, best_share = float(seen[best, 0]), float(around[best]) / total
        if best_share < p.learn_agreement:
            if len(self._learning) > _LEARN_KEPT:
                del self._learning[: len(self._learning) - _LEARN_KEPT]
            return
        offsets = quarter_turn_offset(seen[:, 0], best_centre)
        near = np.abs(offsets) <= p.learn_window_rad
        middle = _weighted_median(offsets[near], seen[near, 1])
        self.axis_rad = float(quarter_turn_offset(best_centre + middle, 0.0))
        self.variance_rad2 = p.start_sigma_rad**2
        self._learning.clear()

    def summary(self) -> dict[str, float | int | None]:
        """For the run report: the axis in degrees (None: not learned) and the frames
        that corrected the heading."""
        return {
            "axis_deg": None if self.axis_rad is None else round(math.degrees(self.axis_rad), 2),
            "corrections": self.frames_used,
            "recoveries": self.recoveries,
        }

    def restore(self, axis_rad: float | None) -> None:
        """Continue with an axis learned before (a loaded map's), or learn it again."""
        self.axis_rad = axis_rad
        self.variance_rad2 = self.params.start_sigma_rad**2
        self._learning.clear()
        self._beyond.clear()
