"""The ``floornet`` floor model: a small convolutional network run by OpenCV's ``dnn``.

Why a network: the hand-weighed superpixel cues of ``floornav`` learned the shared
scenes (out-of-scene IoU 0.64). A small fully convolutional encoder-decoder sees the
same transferable cues at once (the colour of each pixel relative to the safe zone,
texture, edges, the layout of walls and the wall-floor junction) and, unlike the
column model, can say "no floor here" anywhere, also in the safe zone itself.

Input (`network_input`): the frame at `INPUT_WIDTH_PX` x `INPUT_HEIGHT_PX`, as six
channels: CIELAB (scaled to about [-1, 1]) and CIELAB minus the safe zone's median
colour (the thesis's self-supervision, relative rather than absolute so it carries to
floors never seen). Output: one floor logit per cell of half the input size.

The weights are fitted by ``scripts/train_floor_net.py`` on the shared labelled images
and shipped as an ONNX file beside this module; nothing is downloaded at run time.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

INPUT_WIDTH_PX = 160
INPUT_HEIGHT_PX = 128
"""Network input size. 160 columns keep 4 px of a 640 px frame per cell (the grid the
``floornav`` cues used); the height is a multiple of 16 for the four stride-2 levels."""

OUTPUT_WIDTH_PX = INPUT_WIDTH_PX // 2
OUTPUT_HEIGHT_PX = INPUT_HEIGHT_PX // 2
"""The network answers at half the input size (its stem has stride 2)."""
N_INPUT_CHANNELS = 6
DEFAULT_MODEL_PATH = Path(__file__).with_name("models") / "floor_net.onnx"

LAB_CENTER = np.array([50.0, 0.0, 0.0], dtype=np.float32)
LAB_SCALE = np.array([50.0, 40.0, 40.0], dtype=np.float32)
"""L in [0, 100] and a, b in about [-40, 40] mapped to about [-1, 1]."""


class FloorNetError(RuntimeError):
    """The floor network's model file is missing or unusable."""


_SCALED_FROM_LAB = np.array(
    [
        [1.0 / LAB_SCALE[0], 0.0, 0.0, -LAB_CENTER[0] / LAB_SCALE[0]],
        [0.0, 1.0 / LAB_SCALE[1], 0.0, -LAB_CENTER[1] / LAB_SCALE[1]],
        [0.0, 0.0, 1.0 / LAB_SCALE[2], -LAB_CENTER[2] / LAB_SCALE[2]],
    ],
    dtype=np.float32,
)
"""(Lab - LAB_CENTER) / LAB_SCALE as one affine map, so OpenCV applies it in one pass."""


def scaled_lab(bgr: NDArray[np.uint8]) -> NDArray[np.float32]:
    """The frame at network input size in the network's scaled CIELAB (H, W, 3)."""
    small = cv2.resize(bgr, (INPUT_WIDTH_PX, INPUT_HEIGHT_PX), interpolation=cv2.INTER_AREA)
    lab = cv2.cvtColor(small.astype(np.float32) * (1.0 / 255.0), cv2.COLOR_BGR2Lab)
    return np.asarray(cv2.transform(lab, _SCALED_FROM_LAB), dtype=np.float32)


def blob_for_reference(
    lab_scaled: NDArray[np.float32], reference: NDArray[np.float32]
) -> NDArray[np.float32]:
    """The network's input blob with colours taken relative to ``reference`` (scaled
    Lab): the safe zone's colour, or a floor colour learned earlier (the safe zone
    extended over time and space, `app.mapping.floor_memory`).

    Channels 0-2 are ``lab_scaled``, 3-5 are ``lab_scaled - reference``; planes are
    written one by one (a transposed copy of the stacked image cost 10x more).
    """
    height, width, _ = lab_scaled.shape
    blob = np.empty((1, 6, height, width), dtype=np.float32)
    for channel, plane in enumerate(cv2.split(lab_scaled)):
        blob[0, channel] = plane
        np.subtract(plane, np.float32(reference[channel]), out=blob[0, 3 + channel])
    return blob


def network_input(bgr: NDArray[np.uint8], zone_mask: NDArray[np.bool_]) -> NDArray[np.float32]:
    """The network's (1, 6, INPUT_HEIGHT_PX, INPUT_WIDTH_PX) float32 input blob.

    Parameters
    ----------
    bgr : (H, W, 3) uint8, the frame (any size; it is resized, aspect not kept)
    zone_mask : (INPUT_HEIGHT_PX, INPUT_WIDTH_PX) bool, the safe zone at input size

    Notes
    -----
    The frame is area-resized before the colour conversion, which also smooths it
    (a 640 px frame averages 4x4 pixels per cell, in place of the thesis's Gaussian).
    """
    lab_scaled = scaled_lab(bgr)
    zone_colour = np.median(lab_scaled[zone_mask], axis=0)
    return blob_for_reference(lab_scaled, zone_colour)


@dataclass(frozen=True)
class FloorNetOutput:
    """Per-pixel floor probability at input size, and the safe zone's mean of it.

    Attributes
    ----------
    probability : (OUTPUT_HEIGHT_PX, OUTPUT_WIDTH_PX) float32 in [0, 1]
    zone_floor_probability : float, mean probability inside the safe zone: how sure the
        network is that the safe zone really is floor (the thesis's premise)
    """

    probability: NDArray[np.float32]
    zone_floor_probability: float


def _read_onnx(model_path: Path) -> Any:
    """OpenCV's classic dnn engine where there is a choice (OpenCV 5): on this network it
    ran a median 6.7 ms against the new engine's 8.0 ms on one core, same output to 1e-5."""
    classic = getattr(cv2.dnn, "ENGINE_CLASSIC", None)
    if classic is None:
        return cv2.dnn.readNetFromONNX(str(model_path))
    return cv2.dnn.readNetFromONNX(str(model_path), classic)


class FloorNet:
    """Loads the ONNX floor network once and runs it on frames.

    One instance per thread (an OpenCV ``dnn.Net`` is not thread-safe); the lock makes a
    shared instance safe but serial.
    """

    def __init__(self, model_path: Path = DEFAULT_MODEL_PATH) -> None:
        if not model_path.is_file():
            raise FloorNetError(f"{model_path}: floor network model file not found")
        try:
            self._net = _read_onnx(model_path)
        except cv2.error as exc:
            raise FloorNetError(f"{model_path}: not a usable ONNX model ({exc})") from exc
        self._lock = threading.Lock()
        self.model_path = model_path

    def run(self, blob: NDArray[np.float32], zone_mask: NDArray[np.bool_]) -> FloorNetOutput:
        """Floor probabilities for one `network_input` blob.

        ``zone_mask`` is the safe zone at the output size (OUTPUT_HEIGHT_PX,
        OUTPUT_WIDTH_PX).
        """
        with self._lock:
            self._net.setInput(blob)
            logits = np.asarray(self._net.forward(), dtype=np.float32)
        logits = logits.reshape(OUTPUT_HEIGHT_PX, OUTPUT_WIDTH_PX)
        probability = 1.0 / (1.0 + np.exp(-np.clip(logits, -30.0, 30.0)))
        zone_probability = float(probability[zone_mask].mean()) if zone_mask.any() else 0.0
        return FloorNetOutput(probability.astype(np.float32), zone_probability)


_shared: dict[Path, FloorNet] = {}
_shared_lock = threading.Lock()


def shared_floor_net(model_path: Path = DEFAULT_MODEL_PATH) -> FloorNet:
    """One loaded network per model file for the process (loading costs ~10 ms)."""
    with _shared_lock:
        net = _shared.get(model_path)
        if net is None:
            net = _shared[model_path] = FloorNet(model_path)
        return net


def probability_to_mask(
    probability: NDArray[np.float32], shape: tuple[int, int], *, threshold: float = 0.5
) -> NDArray[np.bool_]:
    """Floor mask at image size: bilinear upsampling of the probability, thresholded."""
    height, width = shape
    full = cv2.resize(probability, (width, height), interpolation=cv2.INTER_LINEAR)
    return np.asarray(full > threshold, dtype=np.bool_)


def floor_mask(
    output: FloorNetOutput,
    zone_mask: NDArray[np.bool_],
    *,
    min_zone_confidence: float,
) -> NDArray[np.bool_]:
    """The floor mask at the size of ``zone_mask`` (the image's safe zone).

    When the network doubts the premise (``zone_floor_probability`` below
    ``min_zone_confidence``) nothing in the safe zone is floor: an obstacle right ahead
    is never called floor because it stands where the floor is assumed.
    """
    mask = probability_to_mask(output.probability, zone_mask.shape)
    if output.zone_floor_probability < min_zone_confidence:
        mask &= ~zone_mask
    return mask


SAME_AS_ZONE = 0.08
"""A learned colour this close (scaled Lab) to the safe zone's adds nothing the first
pass did not already see."""
MATCH_DISTANCE = 0.15
"""Pixels this close to a learned colour are its candidates (about 6 CIELAB units)."""
MIN_CANDIDATE_SHARE = 0.02
"""A second pass runs only when this share of the frame looks like a learned floor the
first pass left out (7 ms of network time is not spent on a few stray pixels)."""


@dataclass(frozen=True)
class LearnedFloorPass:
    """What the learned-floor pass did to one frame.

    Attributes
    ----------
    probability : (OUTPUT_HEIGHT_PX, OUTPUT_WIDTH_PX) float32, the first pass's floor
        probability raised where the second pass found connected floor
    reference : the learned colour used (scaled Lab), or None when no pass ran
    added_share : share of output cells that became floor
    """

    probability: NDArray[np.float32]
    reference: tuple[float, float, float] | None
    added_share: float


UNSURE_DISTANCE = 1.5 * MATCH_DISTANCE
"""`learned_floor_unsure` holds back cells this close to the learned colour: a pass
also takes in the same floor in other light (farther, in shadow). On three rendered
views into the tiled kitchen this covered 93-99 % of what the pass added and about 1 %
of the not-floor cells it could have marked (1x `MATCH_DISTANCE`: 57-64 %)."""


def _near_colour(
    lab_out: NDArray[np.float32], colour: NDArray[np.float32], distance: float = MATCH_DISTANCE
) -> NDArray[np.bool_]:
    """Cells within ``distance`` of ``colour`` (squared distances: no square root)."""
    diff = lab_out - colour
    return np.asarray(np.einsum("ijk,ijk->ij", diff, diff) <= distance * distance, dtype=np.bool_)


def choose_learned_reference(
    lab_out: NDArray[np.float32],
    open_cells: NDArray[np.bool_],
    zone_colour: NDArray[np.float32],
    learned: tuple[tuple[float, float, float], ...],
) -> tuple[float, float, float] | None:
    """The learned floor colour that best explains what the first pass left out: the
    one, unlike the safe zone's, with the largest share (>= `MIN_CANDIDATE_SHARE` of the
    frame) of ``open_cells`` (cells a second pass could still make floor) within
    `MATCH_DISTANCE` of it; None if none qualifies."""
    best: tuple[float, float, float] | None = None
    best_share = MIN_CANDIDATE_SHARE
    for colour in learned:
        c = np.asarray(colour, dtype=np.float32)
        if float(np.linalg.norm(c - zone_colour)) <= SAME_AS_ZONE:
            continue
        near = _near_colour(lab_out, c)
        share = float(np.count_nonzero(near & open_cells)) / near.size
        if share >= best_share:
            best, best_share = colour, share
    return best


def connected_to(extra: NDArray[np.bool_], anchor: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """The parts of ``extra`` (8-connected) that touch ``anchor`` or the bottom row: new
    floor must join the floor the robot stands on, not float in the image (a learned
    colour on a shelf is not floor)."""
    if not extra.any():
        return extra
    seed = anchor.copy()
    seed[-1, :] = True
    grown = cv2.dilate(seed.view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    n, labels = cv2.connectedComponents(extra.view(np.uint8), connectivity=8)
    touching = np.unique(labels[grown & extra])
    keep = np.zeros(n, dtype=bool)
    keep[touching] = True
    keep[0] = False
    return np.asarray(keep[labels], dtype=np.bool_)


LEARNED_FLOOR_MAX_ROW_FRACTION = 0.6
"""The learned-floor pass adds floor only above this fraction of the image height: the
bottom 40 % is the near field (where ``near_false_floor`` is scored and the clearance
stop looks), fixed before measuring."""


def learned_floor_pass(
    net: FloorNet,
    lab_scaled: NDArray[np.float32],
    first: FloorNetOutput,
    zone_colour: NDArray[np.float32],
    zone_mask_out: NDArray[np.bool_],
    learned: tuple[tuple[float, float, float], ...],
) -> LearnedFloorPass:
    """Run the network once more with colours relative to a learned floor colour (when
    one explains part of the frame) and keep the new floor that joins the first pass's."""
    probability = first.probability
    if not learned:
        return LearnedFloorPass(probability, None, 0.0)
    first_floor = probability > 0.5
    lab_out, open_cells = _open_far_cells(lab_scaled, first_floor)
    reference = choose_learned_reference(lab_out, open_cells, zone_colour, learned)
    if reference is None:
        return LearnedFloorPass(probability, None, 0.0)
    near_field_row = _near_field_row(first_floor.shape[0])
    second = net.run(
        blob_for_reference(lab_scaled, np.asarray(reference, dtype=np.float32)), zone_mask_out
    )
    extra = connected_to((second.probability > 0.5) & ~first_floor, first_floor)
    # Not in the near field: what the clearance stop reads there must be the per-frame
    # model's call (and the map's geometry-confirmed floor), never a colour learned
    # elsewhere: a floor-coloured box right ahead is the case that hits things.
    extra[near_field_row:, :] = False
    combined = np.where(extra, np.maximum(probability, second.probability), probability)
    return LearnedFloorPass(
        combined.astype(np.float32), reference, float(np.count_nonzero(extra)) / extra.size
    )


def _near_field_row(rows: int) -> int:
    """The first output row of the near field, where no learned floor is added."""
    return round(LEARNED_FLOOR_MAX_ROW_FRACTION * rows)


def _open_far_cells(
    lab_scaled: NDArray[np.float32], first_floor: NDArray[np.bool_]
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """The frame at output size, and the cells a second pass could still make floor:
    not floor in the first pass, above the near field (where its floor would be dropped,
    so a learned colour that matches the near field is no reason to run the network)."""
    lab_out = np.asarray(
        cv2.resize(lab_scaled, (OUTPUT_WIDTH_PX, OUTPUT_HEIGHT_PX), interpolation=cv2.INTER_AREA),
        dtype=np.float32,
    )
    open_cells = ~first_floor
    open_cells[_near_field_row(first_floor.shape[0]) :, :] = False
    return lab_out, open_cells


def learned_floor_unsure(
    lab_scaled: NDArray[np.float32],
    first: FloorNetOutput,
    zone_colour: NDArray[np.float32],
    learned: tuple[tuple[float, float, float], ...],
) -> NDArray[np.bool_] | None:
    """On a frame without a second pass: the (OUTPUT_HEIGHT_PX, OUTPUT_WIDTH_PX) cells a
    pass relative to a learned floor colour could have made floor, or None.

    Those are the open far cells (`learned_floor_pass`) within `UNSURE_DISTANCE` of the
    colour that explains most of them, grown by one cell (grout lines, speckle). The
    map takes no evidence from them on this frame, so the frames between passes do not
    call a learned floor an obstacle (the passes, rarer, say floor there): ``learned``
    should hold colours whose last pass added floor.
    """
    if not learned:
        return None
    lab_out, open_cells = _open_far_cells(lab_scaled, first.probability > 0.5)
    reference = choose_learned_reference(lab_out, open_cells, zone_colour, learned)
    if reference is None:
        return None
    colour = np.asarray(reference, dtype=np.float32)
    near = _near_colour(lab_out, colour, UNSURE_DISTANCE) & open_cells
    grown = cv2.dilate(near.view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    return np.asarray(grown & open_cells, dtype=np.bool_)


class LearnedPassBackoff:
    """Which learned floor colours may have a second pass on the next frame.

    A second pass costs a whole network run, and it ran on 68 % of the frames of a 120 s
    run under load. Where a learned colour matches something that is not floor (a wall
    near a floor's colour), its passes add nothing. A colour whose pass added less than
    `MIN_ADDED_SHARE` sits out `FIRST_SKIP_FRAMES` frames, doubling on each fruitless
    try up to `MAX_SKIP_FRAMES` (about a second at 30 fps); one pass that adds floor
    clears it. Pure bookkeeping, one instance per perception thread.
    """

    MIN_ADDED_SHARE = 0.002
    """About ten of the 5120 output cells."""
    FIRST_SKIP_FRAMES = 4
    MAX_SKIP_FRAMES = 32

    def __init__(self) -> None:
        self._frame = 0
        self._skips: dict[tuple[float, float, float], tuple[int, int]] = {}
        """colour -> (first frame it may run again, frames to skip after its next miss)"""
        self._fruitful: set[tuple[float, float, float]] = set()

    def eligible(
        self, learned: tuple[tuple[float, float, float], ...]
    ) -> tuple[tuple[float, float, float], ...]:
        """The colours of ``learned`` not sitting out the coming frame (colours no
        longer learned are forgotten, so the table stays as small as the list)."""
        frame = self._frame
        for colour in self._skips.keys() - set(learned):
            del self._skips[colour]
        self._fruitful &= set(learned)
        return tuple(c for c in learned if self._skips.get(c, (0, 0))[0] <= frame)

    def fruitful(
        self, learned: tuple[tuple[float, float, float], ...]
    ) -> tuple[tuple[float, float, float], ...]:
        """The colours of ``learned`` whose latest pass added floor (`learned_floor_unsure`
        holds back the map's evidence only for those)."""
        return tuple(c for c in learned if c in self._fruitful)

    def observe(self, reference: tuple[float, float, float] | None, added_share: float) -> None:
        """What the frame's second pass did (``reference`` None: none ran)."""
        self._frame += 1
        if reference is None:
            return
        if added_share >= self.MIN_ADDED_SHARE:
            self._skips.pop(reference, None)
            self._fruitful.add(reference)
            return
        self._fruitful.discard(reference)
        skip = self._skips.get(reference, (0, self.FIRST_SKIP_FRAMES))[1]
        self._skips[reference] = (self._frame + skip, min(2 * skip, self.MAX_SKIP_FRAMES))
