"""Stage 1 of the thesis pipeline: Gaussian smoothing and colour-space conversion."""

from __future__ import annotations

from typing import Literal

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

ColorSpace = Literal["lab", "rgb"]

# cv2's 8-bit Lab stores L*255/100, a+128, b+128; these undo that into CIELAB units.
_LAB_SCALE = np.array([100.0 / 255.0, 1.0, 1.0], dtype=np.float32)
_LAB_OFFSET = np.array([0.0, -128.0, -128.0], dtype=np.float32)
_RGB_SCALE = np.full(3, 100.0 / 255.0, dtype=np.float32)
_RGB_OFFSET = np.zeros(3, dtype=np.float32)


def smooth(image_bgr: NDArray[np.uint8], *, sigma_px: float = 5.0) -> NDArray[np.uint8]:
    """Gaussian smoothing with standard deviation ``sigma_px`` (the thesis uses 5).

    Parameters
    ----------
    image_bgr : (H, W, 3) uint8
    sigma_px : float
        Standard deviation in pixels; 0 returns the input unchanged. The kernel is
        truncated at 3 sigma, which keeps 99.7 % of its mass.

    Returns
    -------
    (H, W, 3) uint8, the smoothed image.
    """
    if sigma_px < 0:
        raise ValueError(f"sigma_px must be >= 0, got {sigma_px}")
    if sigma_px == 0:
        return image_bgr
    ksize = 2 * int(np.ceil(3.0 * sigma_px)) + 1
    return _u8(cv2.GaussianBlur(image_bgr, (ksize, ksize), sigmaX=sigma_px, sigmaY=sigma_px))


def to_color_space(
    image_bgr: NDArray[np.uint8],
    *,
    space: ColorSpace = "lab",
    out: NDArray[np.float32] | None = None,
) -> NDArray[np.float32]:
    """Convert a BGR image to float32 features for SLIC and the classifier.

    Parameters
    ----------
    image_bgr : (H, W, 3) uint8
    space : {"lab", "rgb"}
        ``"lab"``: CIELAB with L in [0, 100] and a, b in about [-128, 127] (D65), as
        ``skimage.color.rgb2lab`` gives up to 8-bit quantisation. ``"rgb"``: R, G, B scaled
        to [0, 100] so that the SLIC compactness keeps the same meaning in both spaces.
    out : (H, W, 3) float32, optional
        Buffer to write into (reused on the per-frame path).

    Returns
    -------
    (H, W, 3) float32
    """
    if space == "lab":
        converted = to_lab_u8(image_bgr)
        scale, offset = _LAB_SCALE, _LAB_OFFSET
    elif space == "rgb":
        converted = _u8(cv2.cvtColor(image_bgr, cv2.COLOR_BGR2RGB))
        scale, offset = _RGB_SCALE, _RGB_OFFSET
    else:
        raise ValueError(f"unknown colour space {space!r}; expected 'lab' or 'rgb'")
    if out is None or out.shape != converted.shape or out.dtype != np.float32:
        out = np.empty(converted.shape, dtype=np.float32)
    _scale_channels(converted, scale, offset, out)
    return out


@numba.njit(cache=True, nogil=True)
def _scale_channels(
    image: NDArray[np.uint8],
    scale: NDArray[np.float32],
    offset: NDArray[np.float32],
    out: NDArray[np.float32],
) -> None:
    # One fused pass (numpy's multiply-then-add makes two and casts on the way).
    height, width, channels = image.shape
    for y in range(height):
        for x in range(width):
            for c in range(channels):
                out[y, x, c] = image[y, x, c] * scale[c] + offset[c]


def to_gray(image_bgr: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 BGR -> (H, W) uint8 luminance."""
    return _u8(cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY))


def to_lab_u8(image_bgr: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 BGR -> OpenCV's 8-bit Lab (L*255/100, a+128, b+128)."""
    return _u8(cv2.cvtColor(image_bgr, cv2.COLOR_BGR2Lab))


def _u8(array: object) -> NDArray[np.uint8]:
    """Type an OpenCV result as the uint8 array it is (no copy)."""
    return np.asarray(array, dtype=np.uint8)
