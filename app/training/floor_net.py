"""Training the ``floornet`` floor network (needs the ``train`` extra: PyTorch, onnx).

Used by ``scripts/train_floor_net.py`` (fit on every labelled image, export the ONNX
file the daemon ships) and by ``floornav eval --cv --method floornet`` (one fit per
fold of whole scenes, scored on the held-out scenes). Every constant below was fixed
before any held-out score was looked at; none is tuned per fold.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from app.perception.floor_net import (
    INPUT_HEIGHT_PX,
    INPUT_WIDTH_PX,
    OUTPUT_HEIGHT_PX,
    OUTPUT_WIDTH_PX,
    blob_for_reference,
    network_input,
    scaled_lab,
)
from app.perception.safe_zone import Trapezoid, safe_zone_mask

EPOCHS = 90
BATCH = 12
LEARNING_RATE = 3e-3
WEIGHT_DECAY = 1e-4
NEAR_NONFLOOR_WEIGHT = 3.0
"""Non-floor pixels in the bottom 40 % weigh 3x: called floor, they are what the robot hits."""
STORE_SCALE = 2
"""Training images are kept at twice the input size so crops stay sharp."""
COPY_PASTE_PROBABILITY = 0.5
"""Share of training views that get another image's non-floor pasted onto their floor:
an obstacle standing in front of the robot, often right in the safe zone."""
RECOLOUR_PROBABILITY = 0.5
"""Share of training views whose far floor is recoloured as another material (a
threshold into a tiled kitchen, a rug): floor all the same."""
LEARNED_REFERENCE_PROBABILITY = 0.6
"""Share of the recoloured views whose colours are taken relative to the recoloured
material instead of the safe zone: the daemon's learned-floor pass hands the network a
floor colour learned elsewhere, and this teaches that use (without it, whether the pass
works was an accident of the particular weights)."""
MIN_RECOLOUR_SHIFT = 15.0
"""The smallest Lab distance between a floor and its recoloured material: a new
material, not a shade of the old one."""


def _torch() -> Any:
    try:
        import torch
    except ImportError as exc:  # pragma: no cover - depends on the extra
        raise RuntimeError(
            "training the floor network needs PyTorch: pip install -e '.[train]'"
        ) from exc
    return torch


@dataclass(frozen=True)
class TrainingImage:
    """One labelled image kept at ``STORE_SCALE`` x the network input size."""

    bgr: NDArray[np.uint8]
    floor: NDArray[np.uint8]


def prepare(bgr: NDArray[np.uint8], floor: NDArray[np.bool_]) -> TrainingImage:
    size = (INPUT_WIDTH_PX * STORE_SCALE, INPUT_HEIGHT_PX * STORE_SCALE)
    small = np.asarray(cv2.resize(bgr, size, interpolation=cv2.INTER_AREA), dtype=np.uint8)
    mask = cv2.resize(floor.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    return TrainingImage(small, np.asarray(mask >= 0.5, dtype=np.uint8))


def augment(
    image: TrainingImage, rng: np.random.Generator
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """A random view of one image at network input size: what another camera, another
    pitch and other light would show. Crops keep the image's bottom edge (the robot's
    own floor) and move the horizon; colours, exposure, blur and noise vary."""
    height, width = image.floor.shape
    scale = rng.uniform(0.6, 1.0)
    crop_h = round(height * scale)
    crop_w = round(width * min(1.0, scale * rng.uniform(0.85, 1.15)))
    x0 = int(rng.integers(0, width - crop_w + 1))
    y0 = height - crop_h
    bgr = image.bgr[y0:, x0 : x0 + crop_w]
    floor = image.floor[y0:, x0 : x0 + crop_w]
    if rng.random() < 0.5:
        bgr, floor = bgr[:, ::-1], floor[:, ::-1]
    size = (INPUT_WIDTH_PX, INPUT_HEIGHT_PX)
    bgr = np.asarray(
        cv2.resize(np.ascontiguousarray(bgr), size, interpolation=cv2.INTER_AREA), np.uint8
    )
    floor = np.asarray(
        cv2.resize(np.ascontiguousarray(floor), size, interpolation=cv2.INTER_NEAREST), np.uint8
    )
    pixels = bgr.astype(np.float32)
    # Exposure, contrast, white balance and a gamma curve.
    pixels = pixels * rng.uniform(0.6, 1.4) + rng.uniform(-25, 25)
    mean = pixels.mean(axis=(0, 1), keepdims=True)
    pixels = (pixels - mean) * rng.uniform(0.7, 1.3) + mean
    pixels *= rng.uniform(0.85, 1.15, size=3)
    pixels = 255.0 * (np.clip(pixels, 0, 255) / 255.0) ** rng.uniform(0.7, 1.4)
    if rng.random() < 0.4:  # vignetting, as cheap webcams show
        yy, xx = np.mgrid[0:INPUT_HEIGHT_PX, 0:INPUT_WIDTH_PX].astype(np.float32)
        r2 = ((xx / INPUT_WIDTH_PX - 0.5) ** 2 + (yy / INPUT_HEIGHT_PX - 0.5) ** 2) * 2
        pixels *= (1.0 - rng.uniform(0.1, 0.5) * r2)[:, :, None]
    if rng.random() < 0.3:
        pixels = cv2.GaussianBlur(pixels, (0, 0), rng.uniform(0.5, 1.5))
    pixels += rng.normal(0.0, rng.uniform(0.0, 6.0), size=pixels.shape)
    return np.clip(pixels, 0, 255).astype(np.uint8), floor


def paste_obstacle(
    bgr: NDArray[np.uint8],
    floor: NDArray[np.uint8],
    donor_bgr: NDArray[np.uint8],
    donor_floor: NDArray[np.uint8],
    rng: np.random.Generator,
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Paste the non-floor pixels of a random window of the donor view onto ``bgr``,
    standing with its bottom in the lower part of the frame; those pixels become
    not-floor. Returns new arrays (the inputs are unchanged); unchanged copies if the
    window held too little non-floor."""
    height, width = floor.shape
    win_w = max(4, round(width * rng.uniform(0.15, 0.45)))
    win_h = max(4, round(height * rng.uniform(0.25, 0.7)))
    x0 = int(rng.integers(0, width - win_w + 1))
    y0 = int(rng.integers(0, height - win_h + 1))
    piece = donor_floor[y0 : y0 + win_h, x0 : x0 + win_w] == 0
    out_bgr, out_floor = bgr.copy(), floor.copy()
    if piece.mean() < 0.3:
        return out_bgr, out_floor
    centre_x = rng.uniform(0.2, 0.8) * width
    bottom = rng.uniform(0.6, 1.0) * height
    tx0 = round(centre_x - win_w / 2)
    ty0 = round(bottom - win_h)
    # Clip the window to the frame.
    sx0, sy0 = max(0, -tx0), max(0, -ty0)
    sx1 = min(win_w, width - tx0)
    sy1 = min(win_h, height - ty0)
    if sx1 <= sx0 or sy1 <= sy0:
        return out_bgr, out_floor
    piece = piece[sy0:sy1, sx0:sx1]
    source = donor_bgr[y0 + sy0 : y0 + sy1, x0 + sx0 : x0 + sx1]
    target = (slice(ty0 + sy0, ty0 + sy1), slice(tx0 + sx0, tx0 + sx1))
    out_bgr[target][piece] = source[piece]
    out_floor[target][piece] = 0
    return out_bgr, out_floor


def recolour_far_floor(
    bgr: NDArray[np.uint8], floor: NDArray[np.uint8], rng: np.random.Generator
) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
    """Give the floor beyond a random, slightly slanted line another material's colour
    and contrast (the texture kept). The line leaves 20-70 % of the floor's rows beyond
    it and stays above the safe zone (the top 75 % of the view). Returns the new view and
    the recoloured pixels (all floor; the labels do not change); the view unchanged and
    an empty mask if that floor is under 5 % of the view. The input is unchanged."""
    height, width = floor.shape
    rows, cols = np.mgrid[0:height, 0:width]
    floor_rows = rows[floor > 0]
    if floor_rows.size == 0:
        return bgr.copy(), np.zeros(floor.shape, dtype=np.bool_)
    line_row = min(float(np.quantile(floor_rows, rng.uniform(0.2, 0.7))), 0.75 * height)
    slope = rng.uniform(-0.3, 0.3)
    beyond = (rows < line_row + slope * (cols - width / 2)) & (rows < 0.75 * height) & (floor > 0)
    if beyond.mean() < 0.05:
        return bgr.copy(), np.zeros_like(beyond)
    shift = np.zeros(3)
    while np.linalg.norm(shift) < MIN_RECOLOUR_SHIFT:
        shift = np.array([rng.uniform(-30, 30), rng.uniform(-25, 25), rng.uniform(-25, 25)])
    lab = cv2.cvtColor(bgr.astype(np.float32) * (1.0 / 255.0), cv2.COLOR_BGR2Lab)
    part = lab[beyond]
    mean = part.mean(axis=0)
    part = (part - mean) * rng.uniform(0.6, 1.6) + mean + shift
    part[:, 0] = np.clip(part[:, 0], 2.0, 98.0)
    lab[beyond] = part
    recoloured = cv2.cvtColor(lab, cv2.COLOR_Lab2BGR)[beyond] * 255.0
    out = bgr.copy()
    out[beyond] = np.clip(np.rint(recoloured), 0, 255).astype(np.uint8)
    return out, beyond


def training_input(
    bgr: NDArray[np.uint8],
    zone_mask: NDArray[np.bool_],
    reference_pixels: NDArray[np.bool_] | None,
) -> NDArray[np.float32]:
    """The network's input for one view: colours relative to the safe zone, or to the
    median colour of ``reference_pixels`` (a floor material other than the zone's)."""
    if reference_pixels is None or not reference_pixels.any():
        return network_input(bgr, zone_mask)
    lab_scaled = scaled_lab(bgr)
    return blob_for_reference(lab_scaled, np.median(lab_scaled[reference_pixels], axis=0))


def input_zone_mask(zone: Trapezoid) -> NDArray[np.bool_]:
    return safe_zone_mask((INPUT_HEIGHT_PX, INPUT_WIDTH_PX), zone)


def build_model() -> Any:
    """The network: a small U-Net, stride-2 stem, output at half the input size."""
    torch = _torch()
    nn = torch.nn

    def block(c_in: int, c_out: int, stride: int = 1, dilation: int = 1) -> Any:
        return nn.Sequential(
            nn.Conv2d(c_in, c_out, 3, stride, padding=dilation, dilation=dilation, bias=False),
            nn.BatchNorm2d(c_out),
            nn.ReLU(inplace=True),
        )

    class FloorNetModule(nn.Module):  # type: ignore[misc,name-defined]
        def __init__(self) -> None:
            super().__init__()
            self.enc1 = nn.Sequential(block(6, 16, 2), block(16, 16))
            self.enc2 = nn.Sequential(block(16, 32, 2), block(32, 32))
            self.enc3 = nn.Sequential(block(32, 64, 2), block(64, 64))
            self.enc4 = nn.Sequential(block(64, 96, 2), block(96, 96), block(96, 96, dilation=2))
            self.up = nn.Upsample(scale_factor=2, mode="nearest")
            self.dec3 = block(96 + 64, 64)
            self.dec2 = block(64 + 32, 32)
            self.dec1 = block(32 + 16, 16)
            self.head = nn.Conv2d(16, 1, 1)

        def forward(self, x: Any) -> Any:
            f1 = self.enc1(x)
            f2 = self.enc2(f1)
            f3 = self.enc3(f2)
            f4 = self.enc4(f3)
            d3 = self.dec3(torch.cat([self.up(f4), f3], 1))
            d2 = self.dec2(torch.cat([self.up(d3), f2], 1))
            d1 = self.dec1(torch.cat([self.up(d2), f1], 1))
            return self.head(d1)

    return FloorNetModule()


ProgressFn = Callable[[int, float], None]


def train(
    images: Sequence[TrainingImage],
    zone: Trapezoid,
    *,
    epochs: int = EPOCHS,
    seed: int = 0,
    progress: ProgressFn | None = None,
) -> Any:
    """Fit a fresh network on ``images``; returns the torch module in eval mode."""
    torch = _torch()
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = build_model()
    optimiser = torch.optim.AdamW(model.parameters(), lr=LEARNING_RATE, weight_decay=WEIGHT_DECAY)
    steps_per_epoch = max(1, math.ceil(len(images) / BATCH))
    total_steps = epochs * steps_per_epoch
    schedule = torch.optim.lr_scheduler.OneCycleLR(
        optimiser, max_lr=LEARNING_RATE, total_steps=total_steps, pct_start=0.15
    )
    zone_mask = input_zone_mask(zone)
    out_h, out_w = OUTPUT_HEIGHT_PX, OUTPUT_WIDTH_PX
    near_rows = np.arange(out_h) >= out_h - round(0.4 * out_h)
    model.train()
    for epoch in range(epochs):
        order = rng.permutation(len(images))
        epoch_loss = 0.0
        for step in range(steps_per_epoch):
            batch = order[step * BATCH : (step + 1) * BATCH]
            inputs, targets = [], []
            for index in batch:
                bgr, floor = augment(images[index], rng)
                reference_pixels = None
                if rng.random() < RECOLOUR_PROBABILITY:
                    bgr, recoloured = recolour_far_floor(bgr, floor, rng)
                    if rng.random() < LEARNED_REFERENCE_PROBABILITY:
                        reference_pixels = recoloured
                if len(images) > 1 and rng.random() < COPY_PASTE_PROBABILITY:
                    donor = int(rng.integers(0, len(images) - 1))
                    donor += donor >= index
                    donor_bgr, donor_floor = augment(images[donor], rng)
                    bgr, floor = paste_obstacle(bgr, floor, donor_bgr, donor_floor, rng)
                if reference_pixels is not None:
                    reference_pixels = reference_pixels & (floor > 0)
                inputs.append(training_input(bgr, zone_mask, reference_pixels)[0])
                small = cv2.resize(
                    floor.astype(np.float32), (out_w, out_h), interpolation=cv2.INTER_AREA
                )
                targets.append(small)
            x = torch.from_numpy(np.stack(inputs))
            y = torch.from_numpy(np.stack(targets)[:, None])
            weight = torch.ones_like(y)
            weight[:, :, near_rows, :] += (NEAR_NONFLOOR_WEIGHT - 1.0) * (
                1.0 - y[:, :, near_rows, :]
            )
            logits = model(x)
            bce = torch.nn.functional.binary_cross_entropy_with_logits(logits, y, weight=weight)
            p = torch.sigmoid(logits)
            inter = (p * y).sum(dim=(1, 2, 3))
            union = (p + y - p * y).sum(dim=(1, 2, 3))
            soft_iou = ((inter + 1.0) / (union + 1.0)).mean()
            loss = bce + (1.0 - soft_iou)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            schedule.step()
            epoch_loss += float(loss.detach())
        if progress is not None:
            progress(epoch + 1, epoch_loss / steps_per_epoch)
    model.eval()
    return model


def predict_probability(model: Any, bgr: NDArray[np.uint8], zone: Trapezoid) -> NDArray[np.float32]:
    """Floor probability at half the input size from a torch model (for CV scoring)."""
    torch = _torch()
    blob = network_input(bgr, input_zone_mask(zone))
    with torch.no_grad():
        logits = np.asarray(model(torch.from_numpy(blob)).numpy()[0, 0], dtype=np.float32)
    return np.asarray(1.0 / (1.0 + np.exp(-logits)), dtype=np.float32)


def export_onnx(model: Any, path: Path) -> None:
    """Write the model as ONNX for OpenCV's dnn (opset 13, fixed input size)."""
    torch = _torch()
    path.parent.mkdir(parents=True, exist_ok=True)
    dummy = torch.zeros(1, 6, INPUT_HEIGHT_PX, INPUT_WIDTH_PX)
    tmp = path.with_suffix(".tmp.onnx")
    torch.onnx.export(
        model,
        (dummy,),
        str(tmp),
        input_names=["input"],
        output_names=["floor_logit"],
        opset_version=13,
        dynamo=False,
    )
    tmp.replace(path)
