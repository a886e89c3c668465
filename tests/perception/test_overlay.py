"""The overlay a person looks at: floor tinted, safe zone outlined, the rest untouched."""

import numpy as np

from app.perception.overlay import FLOOR_TINT_BGR, draw_overlay


def test_tints_only_the_floor_with_the_expected_blend() -> None:
    image = np.full((4, 6, 3), 100, np.uint8)
    mask = np.zeros((4, 6), bool)
    mask[2:, :] = True
    out = draw_overlay(image, mask, alpha=0.5)
    assert np.array_equal(out[:2], image[:2])  # not floor: untouched
    expected = np.round(0.5 * 100 + 0.5 * np.array(FLOOR_TINT_BGR, float))
    assert np.abs(out[3, 0].astype(float) - expected).max() <= 1
    assert image[3, 0, 0] == 100  # the input is not modified


def test_safe_zone_outline_is_drawn() -> None:
    image = np.zeros((40, 60, 3), np.uint8)
    corners = np.array([[10.0, 39.0], [50.0, 39.0], [40.0, 20.0], [20.0, 20.0]])
    out = draw_overlay(image, np.zeros((40, 60), bool), safe_zone_corners_px=corners)
    assert out[20, 30].any() and not out[5, 5].any()
