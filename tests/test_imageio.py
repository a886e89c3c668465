"""The image reader: sizes read from headers, oversized or lying files refused before
any decoding (issue: a 6000x6000 PNG of 35 KB took 47 s and 6.8 GB), normal files read."""

from __future__ import annotations

import struct
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from app import imageio
from app.cli import main
from app.hardware.cameras import ReplayCamera
from app.hardware.interfaces import DeviceState
from app.imageio import (
    MAX_IMAGE_PIXELS,
    ImageFileError,
    check_image_header,
    decode_bgr_bytes,
    decode_image_bytes,
    image_header_size,
    read_bgr,
    read_image_file,
    read_mask,
)

from .conftest import room_scene


def _chunk(kind: bytes, payload: bytes) -> bytes:
    crc = zlib.crc32(kind + payload)
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)


def hand_built_png(
    width: int, height: int, *, colour_type: int = 2, rows: int = 2, seed: int = 0
) -> bytes:
    """A PNG whose IHDR claims ``width`` x ``height`` 8-bit pixels but whose IDAT holds
    only ``rows`` rows of noise: tens of KB, built without ever making the big image."""
    channels = {0: 1, 2: 3, 6: 4}[colour_type]
    rng = np.random.default_rng(seed)
    raw = b"".join(
        b"\x00" + rng.integers(0, 256, width * channels, dtype=np.uint8).tobytes()
        for _ in range(rows)
    )
    ihdr = struct.pack(">IIBBBBB", width, height, 8, colour_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", ihdr)
        + _chunk(b"IDAT", zlib.compress(raw, 9))
        + _chunk(b"IEND", b"")
    )


def encode(ext: str, image: np.ndarray, params: list[int] | None = None) -> bytes:
    ok, data = cv2.imencode(ext, image, params or [])
    assert ok
    return data.tobytes()


def with_jpeg_size(jpeg: bytes, width: int, height: int) -> bytes:
    """``jpeg`` with its frame header (SOF0, baseline) claiming another size."""
    at = jpeg.index(b"\xff\xc0") + 2  # the segment's length field
    return jpeg[: at + 3] + struct.pack(">HH", height, width) + jpeg[at + 7 :]


@pytest.fixture
def no_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if anything reaches the decoder."""

    def refuse(*_args: object) -> None:
        raise AssertionError("cv2.imdecode was called")

    monkeypatch.setattr(imageio.cv2, "imdecode", refuse)


def test_a_6000x6000_png_of_tens_of_kb_is_refused_fast_without_decoding(
    tmp_path: Path, no_decoding: None
) -> None:
    big = tmp_path / "big.png"
    big.write_bytes(hand_built_png(6000, 6000))
    assert 20_000 < big.stat().st_size < 60_000
    start = time.perf_counter()
    with pytest.raises(ImageFileError) as caught:
        read_bgr(big)
    assert time.perf_counter() - start < 0.5
    message = str(caught.value)
    assert str(big) in message
    assert "6000x6000" in message and "can hold" in message
    assert "refused before decoding" in message


def test_48_megapixels_are_refused_whatever_the_file_size(no_decoding: None) -> None:
    png = hand_built_png(8000, 6000, colour_type=0, rows=1)
    with pytest.raises(ImageFileError, match=r"x\.png: PNG image of 8000x6000 px \(48\.0 MP\)"):
        check_image_header(png, name="x.png")
    jpeg = with_jpeg_size(encode(".jpg", np.zeros((16, 16, 3), np.uint8)), 8000, 6000)
    assert image_header_size(jpeg) == (8000, 6000, "JPEG")
    with pytest.raises(ImageFileError, match=r"over the 40 MP limit"):
        decode_image_bytes(jpeg, name="x.jpg")


def test_the_pixel_limit_is_a_keyword(no_decoding: None) -> None:
    assert MAX_IMAGE_PIXELS == 40_000_000
    png = encode(".png", np.zeros((100, 100, 3), np.uint8))
    with pytest.raises(ImageFileError, match=r"over the 0\.005 MP limit"):
        decode_image_bytes(png, name="small.png", max_pixels=5000)


def test_a_jpeg_claiming_more_than_it_holds_is_refused(no_decoding: None) -> None:
    jpeg = with_jpeg_size(encode(".jpg", np.zeros((16, 16, 3), np.uint8)), 6000, 6000)
    with pytest.raises(ImageFileError, match=r"more than its .* bytes can hold"):
        decode_bgr_bytes(jpeg, name="lying.jpg")


def test_truncated_files_are_refused_before_decoding(no_decoding: None) -> None:
    image, _ = room_scene(64, 48)
    jpeg = encode(".jpg", image)
    sof = jpeg.index(b"\xff\xc0")
    for cut, reason in [
        (jpeg[:sof], "truncated JPEG"),
        (jpeg[: sof + 5], "truncated JPEG: frame header"),
        (jpeg[: len(jpeg) // 2], "no end-of-image marker"),
        (b"\xff\xd8\xff\xd9", "ends before its frame header"),
    ]:
        with pytest.raises(ImageFileError, match=rf"cut\.jpg: not a readable image .*{reason}"):
            decode_image_bytes(cut, name="cut.jpg")
    png = encode(".png", image)
    with pytest.raises(ImageFileError, match=r"cut\.png: not a readable image .*truncated PNG"):
        decode_image_bytes(png[:20], name="cut.png")
    bmp = encode(".bmp", image)
    with pytest.raises(ImageFileError, match=r"cut\.bmp: BMP header claims 64x48 px"):
        decode_image_bytes(bmp[: len(bmp) // 2], name="cut.bmp")
    webp = encode(".webp", image)
    with pytest.raises(ImageFileError, match=r"truncated WebP"):
        decode_image_bytes(webp[: len(webp) // 2], name="cut.webp")


def test_highly_compressible_real_images_are_not_refused() -> None:
    """The ratio bounds are the formats' own limits, so the most compressible real files
    (all-black PNGs at level 9 reach ~1011:1 of deflate's 1032:1) still pass."""
    black = np.zeros((2000, 2000), np.uint8)
    png = encode(".png", black, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert len(png) < 5000
    assert decode_image_bytes(png, name="black.png").shape == (2000, 2000)
    black_bgr = np.zeros((1000, 1000, 3), np.uint8)
    png = encode(".png", black_bgr, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert check_image_header(png, name="black.png") == (1000, 1000, "PNG")
    jpeg = encode(
        ".jpg", black_bgr, [cv2.IMWRITE_JPEG_OPTIMIZE, 1, cv2.IMWRITE_JPEG_PROGRESSIVE, 1]
    )
    assert check_image_header(jpeg, name="black.jpg") == (1000, 1000, "JPEG")
    no_floor = encode(".png", np.zeros((480, 640), np.uint8), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert check_image_header(no_floor, name="mask.png") == (640, 480, "PNG")


@pytest.mark.parametrize(
    ("ext", "params", "fmt"),
    [
        (".png", [], "PNG"),
        (".jpg", [], "JPEG"),
        (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1], "JPEG"),
        (".bmp", [], "BMP"),
        (".webp", [], "WebP"),
        (".webp", [cv2.IMWRITE_WEBP_QUALITY, 101], "WebP"),  # lossless: VP8L
        (".tiff", [], "TIFF"),
    ],
)
def test_header_sizes_of_every_format(ext: str, params: list[int], fmt: str) -> None:
    image, _ = room_scene(333, 251)
    data = encode(ext, image, params)
    assert image_header_size(data) == (333, 251, fmt)
    assert decode_bgr_bytes(data, name=f"x{ext}").shape == (251, 333, 3)


def test_webp_with_alpha_has_an_extended_header() -> None:
    image = np.dstack([room_scene(40, 30)[0], np.full((30, 40), 200, np.uint8)])
    data = encode(".webp", image, [cv2.IMWRITE_WEBP_QUALITY, 101])
    assert image_header_size(data)[:2] == (40, 30)


@pytest.mark.parametrize("kind", ["jpg", "png", "gray.png", "rgba.png", "bmp"])
def test_normal_files_are_still_read(tmp_path: Path, kind: str) -> None:
    image, _ = room_scene(160, 120, seed=3)
    stored: np.ndarray = image
    if kind == "gray.png":
        stored = image.mean(axis=2).astype(np.uint8)
    elif kind == "rgba.png":
        stored = np.dstack([image, np.full(image.shape[:2], 255, np.uint8)])
    path = tmp_path / f"photo.{kind}"
    assert cv2.imwrite(str(path), stored)
    got = read_bgr(path)
    assert got.shape == (120, 160, 3) and got.dtype == np.uint8
    if kind in ("png", "rgba.png", "bmp"):
        assert np.array_equal(got, image)
    elif kind == "gray.png":
        assert np.array_equal(got[:, :, 0], stored) and np.array_equal(got[:, :, 2], stored)
    else:
        assert np.abs(got.astype(int) - image).mean() < 8


def test_masks_go_through_the_same_checks(tmp_path: Path) -> None:
    mask = np.zeros((48, 64), np.uint8)
    mask[30:] = 255
    path = tmp_path / "m_floor.png"
    cv2.imwrite(str(path), mask)
    assert np.array_equal(read_mask(path, (48, 64)), mask > 0)
    lying = tmp_path / "lying_floor.png"
    lying.write_bytes(hand_built_png(6000, 6000, colour_type=0, rows=1))
    with pytest.raises(ImageFileError, match=r"lying_floor\.png: PNG header claims 6000x6000"):
        read_mask(lying)


def test_non_images_empty_and_missing_files_name_the_file_and_reason(tmp_path: Path) -> None:
    notes = tmp_path / "notes.txt"
    notes.write_text("hello, not an image")
    with pytest.raises(ImageFileError, match=r"notes\.txt: not a readable image \(unknown format"):
        read_bgr(notes)
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(ImageFileError, match=r"empty\.png: not a readable image \(empty file"):
        read_bgr(empty)
    with pytest.raises(ImageFileError, match=r"missing\.jpg: no such file"):
        read_bgr(tmp_path / "missing.jpg")
    with pytest.raises(ImageFileError, match=r"no such file"):
        read_bgr(tmp_path)  # a folder


def test_a_valid_header_with_a_broken_body_is_still_refused(tmp_path: Path) -> None:
    png = encode(".png", room_scene(64, 48)[0])
    broken = tmp_path / "broken.png"
    idat = png.index(b"IDAT") + 4
    broken.write_bytes(png[: idat + 10] + b"\x00" * 50 + png[idat + 60 :])
    with pytest.raises(ImageFileError, match=r"broken\.png: not a readable image"):
        read_bgr(broken)


def test_the_file_size_itself_is_bounded(tmp_path: Path, no_decoding: None) -> None:
    path = tmp_path / "big.bmp"
    path.write_bytes(b"BM" + b"\x00" * 2000)
    with pytest.raises(ImageFileError, match=r"big\.bmp: file is over the 0\.001 MB limit"):
        read_image_file(path, max_file_bytes=1000)
    assert len(read_image_file(path, max_file_bytes=2002)) == 2002


def test_calibrate_floor_refuses_the_big_png_quickly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], no_decoding: None
) -> None:
    big = tmp_path / "BIG.png"
    big.write_bytes(hand_built_png(6000, 6000))
    start = time.perf_counter()
    code = main(["calibrate", "floor", str(big), "--pattern", "9x6", "--square-m", "0.025"])
    assert time.perf_counter() - start < 1.0
    assert code == 1
    err = capsys.readouterr().err
    assert err.startswith("floornav calibrate floor: ")
    assert f"{big}: PNG header claims 6000x6000 px" in err
    assert "refused before decoding" in err


def _wait(predicate: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return False


def test_replaying_an_image_folder_refuses_a_lying_file(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "000.png"), room_scene(64, 48)[0])
    (tmp_path / "001.png").write_bytes(hand_built_png(6000, 6000))
    with ReplayCamera(tmp_path, fps=100.0) as camera:
        assert _wait(lambda: camera.status().state == DeviceState.FAILED)
        assert "001.png: PNG header claims 6000x6000 px" in camera.status().detail
