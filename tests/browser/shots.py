"""Screenshots small enough to keep in the repository (docs/screenshots/)."""

from __future__ import annotations

import io
from pathlib import Path

from PIL import Image
from playwright.sync_api import Page

MAX_BYTES = 150_000


def save_screenshot(page: Page, path: Path, *, full_page: bool = False) -> int:
    """Write a screenshot of ``page`` as a palette PNG (a fraction of the size of
    chromium's; the dashboard's flat colours survive it): 256 colours, fewer when that
    is still over `MAX_BYTES` (a camera frame in view). Returns its size."""
    png = page.screenshot(full_page=full_page)
    image = Image.open(io.BytesIO(png)).convert("RGB")
    path.parent.mkdir(parents=True, exist_ok=True)
    for colours in (256, 128, 64):
        small = image.quantize(
            colors=colours, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE
        )
        small.save(path, optimize=True)
        if path.stat().st_size < MAX_BYTES:
            break
    return path.stat().st_size
