"""Input checks shared by the perception functions: clear errors before any work."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


class ImageError(ValueError):
    """An image (or mask) has the wrong shape, dtype or size for the requested operation."""


def check_bgr_image(image: NDArray[np.generic], *, name: str = "image") -> NDArray[np.uint8]:
    """Return ``image`` as a contiguous (H, W, 3) uint8 BGR array, or raise `ImageError`.

    Grayscale (H, W) and (H, W, 1) images are expanded to three equal channels; BGRA
    (H, W, 4) drops its alpha channel. Anything else is refused with a message naming
    ``name`` and what was received.
    """
    if not isinstance(image, np.ndarray):
        raise ImageError(f"{name}: expected a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise ImageError(f"{name}: expected dtype uint8, got {image.dtype}")
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 1):
        gray = image.reshape(image.shape[0], image.shape[1])
        image = np.repeat(gray[:, :, None], 3, axis=2)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = image[:, :, :3]
    elif not (image.ndim == 3 and image.shape[2] == 3):
        raise ImageError(
            f"{name}: expected shape (H, W), (H, W, 3) or (H, W, 4), got {image.shape}"
        )
    if image.shape[0] < 8 or image.shape[1] < 8:
        raise ImageError(f"{name}: image of {image.shape[1]}x{image.shape[0]} px is too small")
    return np.ascontiguousarray(image)


def check_mask(
    mask: NDArray[np.generic], shape: tuple[int, int], *, name: str = "mask"
) -> NDArray[np.bool_]:
    """Return ``mask`` as a (H, W) bool array matching ``shape``, or raise `ImageError`."""
    if mask.ndim != 2:
        raise ImageError(f"{name}: expected a 2-D mask, got shape {mask.shape}")
    if mask.size == 0:
        raise ImageError(f"{name}: mask is empty (zero size)")
    if mask.shape != shape:
        raise ImageError(
            f"{name}: mask is {mask.shape[1]}x{mask.shape[0]} px but the image is "
            f"{shape[1]}x{shape[0]} px"
        )
    return np.asarray(mask != 0, dtype=np.bool_)
