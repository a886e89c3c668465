"""Reading and writing image files, with errors that name the file."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from app.fileio import write_bytes_atomic
from app.perception.image_checks import ImageError, check_bgr_image


class ImageFileError(ImageError):
    """An image or mask file is missing, unreadable or unusable."""


def read_bgr(path: Path) -> NDArray[np.uint8]:
    """Read an image file as (H, W, 3) uint8 BGR.

    Grayscale and RGBA files are converted; 16-bit files and anything OpenCV cannot
    decode raise `ImageFileError` naming the file.
    """
    if not path.is_file():
        raise ImageFileError(f"{path}: no such file")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ImageFileError(f"{path}: not a readable image")
    try:
        return check_bgr_image(image, name=str(path))
    except ImageError as exc:
        raise ImageFileError(str(exc)) from exc


def read_mask(path: Path, shape: tuple[int, int] | None = None) -> NDArray[np.bool_]:
    """Read a floor mask (8-bit, 255 = floor) as (H, W) bool; check its size if given."""
    if not path.is_file():
        raise ImageFileError(f"{path}: no such file")
    mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if mask is None:
        raise ImageFileError(f"{path}: not a readable image")
    if mask.size == 0:
        raise ImageFileError(f"{path}: mask has zero size")
    if mask.ndim == 3:
        mask = mask[:, :, 0]
    if shape is not None and mask.shape != shape:
        raise ImageFileError(
            f"{path}: mask is {mask.shape[1]}x{mask.shape[0]} px but its image is "
            f"{shape[1]}x{shape[0]} px"
        )
    return np.asarray(mask > 127)


def write_image_atomic(path: Path, image: NDArray[np.uint8]) -> None:
    """Encode by the file's extension and replace ``path`` atomically (no half files)."""
    ok, encoded = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise ImageFileError(f"{path}: cannot encode an image with this extension")
    write_bytes_atomic(path, encoded.tobytes())
