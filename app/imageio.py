"""Reading and writing image files, with errors that name the file.

Every image that comes from outside (a command's file, a replayed folder, an upload)
goes through `decode_image_bytes`, which reads the size from the file's header and
refuses, before anything is decoded, an image over `MAX_IMAGE_PIXELS` or one whose
header claims more pixels than its bytes could hold. Without this a 35 KB PNG whose
header says 6000x6000 px cost 47 s and 6.8 GB in ``floornav calibrate floor``: the
decoder allocates what the header claims, and everything downstream works on it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from app.fileio import write_bytes_atomic
from app.perception.image_checks import ImageError, check_bgr_image

MAX_IMAGE_PIXELS = 40_000_000
"""Largest image (width x height) read at all: 40 MP, well above any camera we use."""

MAX_IMAGE_FILE_BYTES = 200_000_000
"""Largest image file read into memory (200 MB; a 40 MP uncompressed BMP is 160 MB)."""

PNG_MAX_DEFLATE_RATIO = 1032
"""Deflate (PNG's only compression) tops out near 1032:1 for 8-bit data: a run is at
best a 258-byte match coded in 2 bits (1-bit length code + 1-bit distance code). So a
PNG file cannot hold more than 1032 bytes of filtered rows per file byte; no valid file
(cv2's level-9 PNG of an all-zero image reaches ~1011:1) is refused by this bound."""

JPEG_MAX_PIXELS_PER_BYTE = 1024
"""Huffman-coded JPEG spends at least 1 bit on every 8x8 block of every component (its
DC code; Huffman codes are 1 to 16 bits long), and the components together cover at
least half of the image at full resolution (even odd sampling such as 4x1 with 1x4),
so one file byte holds at most 8 bits x 128 px = 1024 px. Generous: real files, even an
all-black optimised progressive JPEG, stay below ~260 px per byte."""

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # IHDR colour type -> samples per pixel
_JPEG_SOF_HUFFMAN = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7})
_JPEG_SOF_ARITHMETIC = frozenset({0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})  # TEM, RST0-7: no length field
_BMP_UNCOMPRESSED = frozenset({0, 3, 6})  # BI_RGB, BI_BITFIELDS, BI_ALPHABITFIELDS
_SUPPORTED = "PNG, JPEG, BMP, WebP, TIFF"


class ImageFileError(ImageError):
    """An image or mask file is missing, unreadable or unusable."""


@dataclass(frozen=True)
class _Header:
    """What a file's header claims, and the fewest bytes a file holding it can have."""

    width_px: int
    height_px: int
    format: str
    # 0 where the format has no useful bound (RLE BMP, arithmetic JPEG, WebP, TIFF):
    # there only MAX_IMAGE_PIXELS limits what the decoder allocates.
    min_file_bytes: int = 0


def _u16be(data: bytes, at: int) -> int:
    return int.from_bytes(data[at : at + 2], "big")


def _need(data: bytes, n_bytes: int, what: str) -> None:
    if len(data) < n_bytes:
        raise ImageFileError(f"truncated {what} ({len(data)} bytes)")


def _png_header(data: bytes) -> _Header:
    _need(data, 33, "PNG: shorter than its IHDR chunk")
    if data[12:16] != b"IHDR" or int.from_bytes(data[8:12], "big") != 13:
        raise ImageFileError("PNG without an IHDR chunk first")
    width, height = struct.unpack(">II", data[16:24])
    bit_depth, colour_type = data[24], data[25]
    channels = _PNG_CHANNELS.get(colour_type)
    if channels is None or bit_depth not in (1, 2, 4, 8, 16):
        raise ImageFileError(f"PNG with bit depth {bit_depth}, colour type {colour_type}")
    # Filtered rows: one filter byte plus the packed samples (interlacing only adds).
    raw_bytes = height * (1 + (width * channels * bit_depth + 7) // 8)
    return _Header(width, height, "PNG", -(-raw_bytes // PNG_MAX_DEFLATE_RATIO))


def _jpeg_header(data: bytes) -> _Header:
    """Walk the segments up to the first scan: the frame header (SOFn) gives the size."""
    n = len(data)
    pos = 2
    frame: _Header | None = None
    while True:
        if pos >= n:
            raise ImageFileError("truncated JPEG: ends before its image data")
        if data[pos] != 0xFF:
            raise ImageFileError(f"JPEG: no marker at byte {pos}")
        while pos < n and data[pos] == 0xFF:  # fill bytes may precede a marker
            pos += 1
        if pos >= n:
            raise ImageFileError("truncated JPEG: ends before its image data")
        marker = data[pos]
        pos += 1
        if marker in _JPEG_STANDALONE:
            continue
        if marker in (0xD8, 0xD9):
            raise ImageFileError("JPEG: image ends before its frame header (SOF)")
        if marker == 0xDA:
            if frame is None:
                raise ImageFileError("JPEG: image data before its frame header (SOF)")
            # Entropy-coded data never holds FF D9 (FF is stuffed as FF 00), so its
            # absence means the data was cut; OpenCV refuses such files too.
            if data.find(b"\xff\xd9", pos) < 0:
                raise ImageFileError("truncated JPEG: no end-of-image marker")
            return frame
        _need(data, pos + 2, "JPEG: segment header")
        length = _u16be(data, pos)
        if length < 2:
            raise ImageFileError(f"JPEG: segment of length {length} at byte {pos}")
        if marker in _JPEG_SOF_HUFFMAN or marker in _JPEG_SOF_ARITHMETIC:
            if frame is not None:
                raise ImageFileError("JPEG with two frame headers (SOF)")
            _need(data, pos + 8, "JPEG: frame header (SOF)")
            height, width = _u16be(data, pos + 3), _u16be(data, pos + 5)
            blocks = -(-width // 8) * -(-height // 8)
            min_bytes = 0
            if marker in _JPEG_SOF_HUFFMAN:
                min_bytes = -(-blocks * 64 // JPEG_MAX_PIXELS_PER_BYTE)
            frame = _Header(width, height, "JPEG", min_bytes)
        pos += length


def _bmp_header(data: bytes) -> _Header:
    _need(data, 26, "BMP: shorter than its headers")
    pixels_at, dib_size = struct.unpack("<II", data[10:18])
    if dib_size == 12:  # BITMAPCOREHEADER (OS/2): unsigned 16-bit sizes, no compression
        width, height, _, bits = struct.unpack("<HHHH", data[18:26])
        compression = 0
    elif dib_size >= 40:
        _need(data, 34, "BMP: shorter than its info header")
        width, height, _, bits, compression = struct.unpack("<iiHHI", data[18:34])
        height = abs(height)  # negative: rows stored top-down
    else:
        raise ImageFileError(f"BMP with a {dib_size}-byte info header")
    if width < 0 or bits not in (1, 2, 4, 8, 16, 24, 32):
        raise ImageFileError(f"BMP of width {width}, {bits} bits per pixel")
    min_bytes = 0
    if compression in _BMP_UNCOMPRESSED and width and height:
        row_bytes = (width * bits + 7) // 8
        stride = (row_bytes + 3) // 4 * 4
        # The last row's padding is not required: some writers leave it out.
        min_bytes = pixels_at + stride * (height - 1) + row_bytes
    return _Header(width, height, "BMP", min_bytes)


def _webp_header(data: bytes) -> _Header:
    _need(data, 30, "WebP: shorter than its headers")
    if int.from_bytes(data[4:8], "little") + 8 > len(data):
        raise ImageFileError("truncated WebP: shorter than its RIFF header says")
    chunk = data[12:16]
    if chunk == b"VP8 ":
        if data[23:26] != b"\x9d\x01\x2a":
            raise ImageFileError("WebP: VP8 frame without its start code")
        width = int.from_bytes(data[26:28], "little") & 0x3FFF
        height = int.from_bytes(data[28:30], "little") & 0x3FFF
    elif chunk == b"VP8L":
        if data[20] != 0x2F:
            raise ImageFileError("WebP: VP8L frame without its signature")
        bits = int.from_bytes(data[21:25], "little")
        width, height = (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    elif chunk == b"VP8X":
        width = int.from_bytes(data[24:27], "little") + 1
        height = int.from_bytes(data[27:30], "little") + 1
    else:
        raise ImageFileError(f"WebP with a first chunk {chunk!r}")
    return _Header(width, height, "WebP")


def _tiff_header(data: bytes) -> _Header:
    """Width and height (tags 256, 257) of the first image file directory."""
    order = "<" if data[:2] == b"II" else ">"
    big = struct.unpack(order + "H", data[2:4])[0] == 43  # BigTIFF: 64-bit offsets
    if big:
        _need(data, 16, "TIFF: shorter than its header")
        ifd_at = struct.unpack(order + "Q", data[8:16])[0]
        count_fmt, entry_bytes, value_at = "Q", 20, 12
    else:
        _need(data, 8, "TIFF: shorter than its header")
        ifd_at = struct.unpack(order + "I", data[4:8])[0]
        count_fmt, entry_bytes, value_at = "H", 12, 8
    count_size = struct.calcsize(count_fmt)
    _need(data, ifd_at + count_size, "TIFF: directory past the end of the file")
    count = struct.unpack(order + count_fmt, data[ifd_at : ifd_at + count_size])[0]
    first = ifd_at + count_size
    if count > 65535:
        raise ImageFileError(f"TIFF directory of {count} entries")
    _need(data, first + count * entry_bytes, "TIFF: directory past the end of the file")
    sizes: dict[int, int] = {}
    value_formats = {3: "H", 4: "I", 16: "Q"}  # SHORT, LONG, LONG8
    for k in range(count):
        at = first + k * entry_bytes
        tag, kind = struct.unpack(order + "HH", data[at : at + 4])
        if tag in (256, 257) and kind in value_formats:
            fmt = order + value_formats[kind]
            sizes[tag] = struct.unpack_from(fmt, data, at + value_at)[0]
    if 256 not in sizes or 257 not in sizes:
        raise ImageFileError("TIFF without its image width and length tags")
    return _Header(sizes[256], sizes[257], "TIFF")


def _parse_header(data: bytes) -> _Header:
    if data.startswith(_PNG_SIGNATURE):
        return _png_header(data)
    if data.startswith(b"\xff\xd8"):
        return _jpeg_header(data)
    if data.startswith(b"BM"):
        return _bmp_header(data)
    if data.startswith(b"RIFF") and data[8:12] == b"WEBP":
        return _webp_header(data)
    if data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return _tiff_header(data)
    if not data:
        raise ImageFileError("empty file")
    raise ImageFileError(f"unknown format (supported: {_SUPPORTED})")


def image_header_size(data: bytes) -> tuple[int, int, str]:
    """(width px, height px, format) read from the header alone, without decoding.

    Raises `ImageFileError` (with the reason, not the file's name) for unknown formats
    and for data too short or malformed to hold the header.
    """
    header = _parse_header(data)
    return header.width_px, header.height_px, header.format


def check_image_header(
    data: bytes, *, name: str, max_pixels: int = MAX_IMAGE_PIXELS
) -> tuple[int, int, str]:
    """The header's (width px, height px, format), or `ImageFileError` naming ``name``
    when the data cannot be sized, is over ``max_pixels``, or claims more pixels than
    ``len(data)`` bytes could hold (cut short or forged)."""
    try:
        header = _parse_header(data)
    except ImageFileError as exc:
        raise ImageFileError(f"{name}: not a readable image ({exc})") from exc
    width, height, fmt = header.width_px, header.height_px, header.format
    if width == 0 or height == 0:
        raise ImageFileError(f"{name}: {fmt} header claims a {width}x{height} px image")
    pixels = width * height
    if pixels > max_pixels:
        raise ImageFileError(
            f"{name}: {fmt} image of {width}x{height} px ({pixels / 1e6:.1f} MP) is over "
            f"the {max_pixels / 1e6:g} MP limit; refused before decoding"
        )
    if len(data) < header.min_file_bytes:
        raise ImageFileError(
            f"{name}: {fmt} header claims {width}x{height} px ({pixels / 1e6:.1f} MP), "
            f"more than its {len(data)} bytes can hold (at least {header.min_file_bytes} "
            f"needed): truncated or forged; refused before decoding"
        )
    return width, height, fmt


def decode_image_bytes(
    data: bytes, *, name: str, max_pixels: int = MAX_IMAGE_PIXELS
) -> NDArray[Any]:
    """Decode an encoded image (as stored, `cv2.IMREAD_UNCHANGED`) after its header
    passed `check_image_header`; ``name`` (a path, an upload's name) is in every error.

    The one way in for images from outside: files (`read_bgr`, `read_mask`) and uploads.
    """
    check_image_header(data, name=name, max_pixels=max_pixels)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ImageFileError(f"{name}: not a readable image")
    decoded = np.asarray(image)
    if decoded.size == 0:
        raise ImageFileError(f"{name}: image has zero size")
    return decoded


def decode_bgr_bytes(
    data: bytes, *, name: str, max_pixels: int = MAX_IMAGE_PIXELS
) -> NDArray[np.uint8]:
    """`decode_image_bytes` then `check_bgr_image`: (H, W, 3) uint8 BGR or an error."""
    image = decode_image_bytes(data, name=name, max_pixels=max_pixels)
    try:
        return check_bgr_image(image, name=name)
    except ImageError as exc:
        raise ImageFileError(str(exc)) from exc


def read_image_file(path: Path, *, max_file_bytes: int = MAX_IMAGE_FILE_BYTES) -> bytes:
    """The file's bytes, read once and never more than ``max_file_bytes`` + 1 of them."""
    if not path.is_file():
        raise ImageFileError(f"{path}: no such file")
    try:
        with path.open("rb") as handle:
            data = handle.read(max_file_bytes + 1)
    except OSError as exc:
        raise ImageFileError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if len(data) > max_file_bytes:
        raise ImageFileError(
            f"{path}: file is over the {max_file_bytes / 1e6:g} MB limit for an image"
        )
    return data


def read_bgr(path: Path, *, max_pixels: int = MAX_IMAGE_PIXELS) -> NDArray[np.uint8]:
    """Read an image file as (H, W, 3) uint8 BGR.

    Grayscale and RGBA files are converted; 16-bit files, anything OpenCV cannot decode
    and images refused by `check_image_header` raise `ImageFileError` naming the file.
    """
    return decode_bgr_bytes(read_image_file(path), name=str(path), max_pixels=max_pixels)


def read_mask(
    path: Path, shape: tuple[int, int] | None = None, *, max_pixels: int = MAX_IMAGE_PIXELS
) -> NDArray[np.bool_]:
    """Read a floor mask (8-bit, 255 = floor) as (H, W) bool; check its size if given."""
    mask = decode_image_bytes(read_image_file(path), name=str(path), max_pixels=max_pixels)
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
