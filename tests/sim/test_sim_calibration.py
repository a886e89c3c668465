"""IPM against the simulator's known geometry: the renderer's own per-pixel floor rays
are the ground truth for the look-up table."""

from __future__ import annotations

import numpy as np
import pytest

from app.config import FloornavConfig
from app.mapping.ipm import build_ground_lookup
from app.sim.render import CameraModel
from app.sim.setup import camera_model, project_floor_points, sim_floor_calibration


def renderer_floor_point(model: CameraModel, u: int, v: int) -> np.ndarray:
    """Where the renderer's ray through pixel (u, v) meets the floor (robot frame)."""
    ray = model.rays_robot()[v, u]
    eye = np.array([model.x_m, model.y_m, model.height_m])
    t = -eye[2] / ray[2]
    return (eye + t * ray)[:2]


@pytest.mark.parametrize(("distance_m", "tolerance_m"), [(1.0, 0.01), (2.0, 0.03)])
def test_lookup_matches_the_simulated_camera(distance_m: float, tolerance_m: float) -> None:
    model = camera_model(FloornavConfig())
    calibration = sim_floor_calibration(model)
    lookup = build_ground_lookup(calibration, max_range_m=4.0)
    row = round(model.floor_row_px(distance_m))
    for u in (40, 320, 600):
        truth = renderer_floor_point(model, u, row)
        mapped = np.array([lookup.x_m[row, u], lookup.y_m[row, u]])
        assert np.linalg.norm(mapped - truth) <= tolerance_m
    assert calibration.reprojection_rms_px < 1e-3


def test_projection_agrees_with_the_renderer_rows() -> None:
    model = camera_model(FloornavConfig())
    for distance_m in (0.5, 1.0, 3.0):
        u, v = project_floor_points(model, np.array([[distance_m, 0.0]]))[0]
        assert u == pytest.approx(model.principal_point_px[0])
        assert v == pytest.approx(model.floor_row_px(distance_m))
