"""Render docs/sample-room.jpg: a synthetic 640x480 robot's-eye view of a room (a tiled
floor in perspective, two walls, a box standing on the floor). It is the shipped sample
for `floornav segment`, written by this script so that no third-party image is copied.

Run: .venv/bin/python scripts/make_sample_room.py
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

WIDTH, HEIGHT = 640, 480
OUT = Path(__file__).resolve().parents[1] / "docs" / "sample-room.jpg"


def main() -> None:
    rng = np.random.default_rng(7)
    # Floor texture seen from above: 1 px = 1 cm, 4 m x 4 m of 40 cm tiles.
    top = np.empty((400, 400, 3), np.uint8)
    top[:] = (120, 150, 175)
    top[::40, :] = (95, 120, 140)
    top[:, ::40] = (95, 120, 140)
    noise = rng.normal(0, 6, top.shape)
    top = np.clip(top + noise, 0, 255).astype(np.uint8)
    image = np.empty((HEIGHT, WIDTH, 3), np.uint8)
    image[:] = (200, 205, 210)  # back wall
    image[:, :140] = (175, 185, 190)  # left wall, in shade
    horizon = 210
    # The floor quad: far edge on the horizon, near edge past the image bottom.
    src = np.float32([[0, 0], [399, 0], [399, 399], [0, 399]])
    dst = np.float32([[140, horizon], [640, horizon], [900, 700], [-260, 700]])
    floor = cv2.warpPerspective(top, cv2.getPerspectiveTransform(src, dst), (WIDTH, HEIGHT))
    floor_mask = np.zeros((HEIGHT, WIDTH), np.uint8)
    cv2.fillConvexPoly(floor_mask, dst.astype(np.int32), 1)
    left_wall_floor = np.array([[0, 330], [140, horizon], [140, HEIGHT], [0, HEIGHT]], np.int32)
    cv2.fillConvexPoly(floor_mask, left_wall_floor, 1)
    image[floor_mask > 0] = floor[floor_mask > 0]
    cv2.line(image, (0, 330), (140, horizon), (70, 70, 80), 3)  # skirting boards
    cv2.line(image, (140, horizon), (WIDTH, horizon), (70, 70, 80), 3)
    cv2.line(image, (140, 0), (140, horizon), (160, 165, 170), 2)  # wall corner
    # A cardboard box standing on the floor, front face and top.
    cv2.fillConvexPoly(
        image, np.array([[400, 250], [520, 250], [520, 340], [400, 340]]), (60, 110, 160)
    )
    cv2.fillConvexPoly(
        image, np.array([[400, 250], [520, 250], [500, 232], [415, 232]]), (90, 150, 200)
    )
    image = cv2.GaussianBlur(image, (3, 3), 0)
    image = np.clip(image + rng.normal(0, 3, image.shape), 0, 255).astype(np.uint8)
    OUT.parent.mkdir(exist_ok=True)
    cv2.imwrite(str(OUT), image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
