"""The simulator built from the configuration, and the simulated camera's floor
calibration (exact: its geometry is known)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from app.config import FloornavConfig
from app.mapping.calibration import FloorCalibration, homography_from_point_pairs
from app.sim.render import CameraModel, Renderer
from app.sim.world import World, load_named_world


def camera_model(config: FloornavConfig) -> CameraModel:
    return CameraModel(
        width_px=config.camera.width_px,
        height_px=config.camera.height_px,
        fx_px=config.sim.focal_px,
        fy_px=config.sim.focal_px,
        x_m=config.camera.x_m,
        y_m=config.camera.y_m,
        height_m=config.sim.camera_height_m,
        pitch_rad=config.sim.camera_pitch_rad,
        noise_sigma=config.sim.noise_sigma,
    )


def world_from_config(config: FloornavConfig) -> World:
    """The world ``[sim] world_file`` names (a shipped world's name or a path)."""
    return load_named_world(config.sim.world_file)


def renderer_from_config(config: FloornavConfig) -> Renderer:
    """The simulated camera, its sensor noise seeded by ``[sim] seed``."""
    return Renderer(world_from_config(config), camera_model(config), seed=config.sim.seed)


def project_floor_points(model: CameraModel, points_m: NDArray[np.floating]) -> NDArray[np.float64]:
    """(N, 2) robot-frame floor points -> (N, 2) pixels of the simulated camera (its
    pinhole model; NaN behind the camera)."""
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 2)
    eye = np.array([model.x_m, model.y_m, model.height_m])
    world = np.column_stack([pts, np.zeros(len(pts))]) - eye
    cam = world @ model.axes_robot().T  # right, down, forward
    cx, cy = model.principal_point_px
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cx + model.fx_px * cam[:, 0] / cam[:, 2]
        v = cy + model.fy_px * cam[:, 1] / cam[:, 2]
    out = np.column_stack([u, v])
    out[cam[:, 2] <= 0] = np.nan
    return out


def sim_floor_calibration(model: CameraModel) -> FloorCalibration:
    """The floor homography of the simulated camera, fitted through the same code path as
    a real calibration, from a grid of floor points it sees."""
    xs, ys = np.meshgrid(np.linspace(0.5, 2.5, 5), np.linspace(-0.5, 0.5, 5))
    ground = np.column_stack([xs.ravel(), ys.ravel()])
    pixels = project_floor_points(model, ground)
    inside = (
        np.isfinite(pixels).all(axis=1)
        & (pixels[:, 0] >= 0)
        & (pixels[:, 0] <= model.width_px - 1)
        & (pixels[:, 1] >= 0)
        & (pixels[:, 1] <= model.height_px - 1)
    )
    return homography_from_point_pairs(
        pixels[inside], ground[inside], (model.width_px, model.height_px)
    )
