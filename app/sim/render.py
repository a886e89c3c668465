"""A camera renderer for the simulated world, with ground truth.

A pinhole camera sits on the robot (`CameraModel`: intrinsics, position, pitch). Every
pixel's ray is fixed in the robot frame, so the floor point each pixel sees (robot frame),
its distance and its lighting are computed once. Per frame:

1. the floor points are moved by the robot's pose into the plan frame and the world's
   floor texture is sampled there with ``cv2.remap`` (one mip level per band of rows,
   chosen from the pixel's footprint on the floor, so far tiles do not alias); the
   world's light areas are baked into the renderer's copy of that texture;
2. a numba kernel rasterises every vertical face (walls on both sides, box sides) and
   every box top lower than the camera: each face's corners are clipped to the camera's
   near plane and projected to a bounding box, and every pixel in it intersects its ray
   with the face exactly, keeping the nearest hit (the floor's depth starts the depth
   buffer, so occlusion of and by the floor is exact);
3. shading (ambient + diffuse of the face normal against the light direction, times
   ``1 / (1 + (d / attenuation_distance_m)^2)`` of the distance ``d`` from the camera,
   times the world's light areas' gain at the face's ground point: a dim hallway, a
   patch of sun) and Gaussian sensor noise (a pre-drawn pool read at a random offset
   per frame, seeded);
4. on a glossy floor (worlds whose floor has ``gloss`` > 0 only), reflections: the faces
   are rasterised a second time mirrored below the floor plane (z negated), at half
   resolution (`_MirrorView`) for the rays that meet the floor, and each ceiling light
   adds a blurred spot at its mirror image; a floor pixel blends its own colour with
   that reflection by ``gloss`` times Schlick's Fresnel term of the viewing angle
   (strong at grazing view, weak looking down), the ceiling (``background_color``)
   where nothing is mirrored.

Light areas (`World.light_gain`) are exact on the faces (from `World.light_area_table`,
per pixel) and per texel on the floor; gloss is read from `World.gloss_raster` at
``_GLOSS_CELL_M``. Every kernel runs on every frame whatever the world has (they return at
once when it has no gloss), so rendering any world compiles all of them
(`app.jit.compile_kernels` renders one frame).

The ground truth is the floor mask of each frame (True where the floor is the nearest
surface) and the world's occupancy raster (`World.occupancy`, computed once).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from app.mapping.frames import GroundGrid, Pose2D
from app.sim.world import FloorTexture, World, mip_levels

_NEAR_M = 0.01
"""Faces are clipped to this distance in front of the camera before projection."""
_GLOSS_CELL_M = 0.02
"""Resolution of the gloss raster (read nearest: gloss changes only at floor areas' edges,
and reflections are rendered at half resolution anyway)."""
_FRESNEL_F0 = 0.15
"""Schlick's reflectance looking straight down (a polished floor reflects little
there, most at grazing view)."""
_MIN_REFLECTION = 0.01
"""Floor pixels whose reflection weight is below this skip the mirror pass."""
_REFLECTION_SHIFT = 1
_REFLECTION_STEP = 1 << _REFLECTION_SHIFT
"""Reflections are rendered at 1 / this resolution and read back per block: a glossy
floor blurs them anyway, and the mirror pass (mirrored walls reach far down the image)
costs a quarter."""
_SPOT_SIGMA = 0.6
"""A light's spot is a Gaussian of this many of its disk's projected radii."""
_PlanFrame = tuple[float, float, float, float, float, float, float]
"""The gloss raster's x_max, y_max (the floor texture's too) and cell, then the robot
pose's cos, sin, x and y in the plan frame: a tuple, so the kernels take it by value."""


@dataclass(frozen=True)
class CameraModel:
    """A pinhole camera on the robot, looking forward, pitched down, no roll.

    Pixel centres: (0, 0) is the top-left pixel; ``cx_px``/``cy_px`` default to the
    image centre. Position in the robot frame (x forward, y left, z up).
    """

    width_px: int = 640
    height_px: int = 480
    fx_px: float = 500.0
    fy_px: float = 500.0
    cx_px: float | None = None
    cy_px: float | None = None
    x_m: float = 0.10
    y_m: float = 0.0
    height_m: float = 0.22
    pitch_rad: float = 0.40
    noise_sigma: float = 2.0
    """Standard deviation of the additive sensor noise, in 8-bit levels (0: none)."""

    def __post_init__(self) -> None:
        if not (8 <= self.width_px <= 8192 and 8 <= self.height_px <= 8192):
            raise ValueError(
                f"CameraModel: width_px/height_px must be 8..8192, got "
                f"{self.width_px}x{self.height_px}"
            )
        if not (self.fx_px > 0 and self.fy_px > 0):
            raise ValueError(
                f"CameraModel: fx_px/fy_px must be > 0, got {self.fx_px}, {self.fy_px}"
            )
        if not 0.0 < self.height_m < 10.0:
            raise ValueError(f"CameraModel: height_m must be in (0, 10), got {self.height_m}")
        if not -1.5 < self.pitch_rad < 1.5:
            raise ValueError(f"CameraModel: pitch_rad must be in (-1.5, 1.5), got {self.pitch_rad}")
        if self.noise_sigma < 0:
            raise ValueError(f"CameraModel: noise_sigma must be >= 0, got {self.noise_sigma}")

    @property
    def principal_point_px(self) -> tuple[float, float]:
        cx = (self.width_px - 1) / 2 if self.cx_px is None else self.cx_px
        cy = (self.height_px - 1) / 2 if self.cy_px is None else self.cy_px
        return cx, cy

    def axes_robot(self) -> NDArray[np.float64]:
        """(3, 3) rows: the camera's right, down and forward axes in the robot frame."""
        c, s = math.cos(self.pitch_rad), math.sin(self.pitch_rad)
        return np.array([[0.0, -1.0, 0.0], [-s, 0.0, -c], [c, 0.0, -s]])

    def ray_coordinates(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(W,) and (H,): each column's and each row's coordinate on the image plane one
        unit ahead; the ray of pixel (row, col) is ``u[col] * right + v[row] * down +
        forward`` (`axes_robot`)."""
        cx, cy = self.principal_point_px
        u = (np.arange(self.width_px, dtype=np.float64) - cx) / self.fx_px
        v = (np.arange(self.height_px, dtype=np.float64) - cy) / self.fy_px
        return u, v

    def rays_robot(self) -> NDArray[np.float64]:
        """(H, W, 3) ray directions in the robot frame, scaled so the camera's forward
        component is 1 (so ``C + t * ray`` for t > 0 is in front of the camera)."""
        u, v = self.ray_coordinates()
        uu, vv = np.meshgrid(u, v)
        right, down, forward = self.axes_robot()
        rays: NDArray[np.float64] = (
            uu[..., None] * right + vv[..., None] * down + forward[None, None, :]
        )
        return rays

    def floor_row_px(self, distance_m: float) -> float:
        """Image row (centre column) of the floor point ``distance_m`` ahead of the
        robot's origin; the horizon for an infinite distance."""
        cy = self.principal_point_px[1]
        depression = math.atan2(self.height_m, distance_m - self.x_m)
        return cy + self.fy_px * math.tan(depression - self.pitch_rad)


@dataclass(frozen=True)
class RenderedFrame:
    """One rendered camera image with its ground truth.

    Attributes
    ----------
    image : (H, W, 3) uint8 BGR
    floor_mask : (H, W) bool, True where the floor is the nearest visible surface
    pose : the robot's pose in the plan frame the frame was rendered at
    """

    image: NDArray[np.uint8]
    floor_mask: NDArray[np.bool_]
    pose: Pose2D


class Renderer:
    """Renders a `World` through a `CameraModel` at robot poses (plan frame).

    Holds per-pixel tables and work buffers: not thread-safe (one instance per thread).

    Parameters
    ----------
    world : the floor plan
    camera : intrinsics and mounting
    texel_m : floor texture resolution (the texture is built once per world and size)
    seed : seed of the sensor noise
    """

    def __init__(
        self,
        world: World,
        camera: CameraModel | None = None,
        *,
        texel_m: float = 0.01,
        seed: int = 0,
    ) -> None:
        if not 0.001 <= texel_m <= 0.1:
            raise ValueError(f"texel_m must be in [0.001, 0.1], got {texel_m}")
        self.world = world
        self.camera = camera if camera is not None else CameraModel()
        cam = self.camera
        self.texture = world.floor_raster(texel_m)
        self._floor_levels = _lit_levels(world, self.texture)
        self._rng = np.random.default_rng(seed)
        h, w = cam.height_px, cam.width_px
        # The rays (and their lengths and floor points) are worked out again in the
        # kernels from each column's u and each row's v, to the same bits: as (H, W)
        # tables they held 15 MB of the daemon's memory for a few multiplications.
        rays = cam.rays_robot()
        self._u, self._v = cam.ray_coordinates()
        self._axes = cam.axes_robot()
        self._eye = np.array([cam.x_m, cam.y_m, cam.height_m])
        light = world.spec.lighting
        self._light_xy = np.array([math.cos(light.azimuth_rad), math.sin(light.azimuth_rad)])
        down = -rays[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t_floor = np.where(down > 1e-9, cam.height_m / down, np.inf)
        self._t_floor = t_floor
        floor_xy = self._eye[:2] + t_floor[..., None] * rays[..., :2]
        floor_xy[~np.isfinite(t_floor)] = 0.0
        ray_len = np.linalg.norm(rays, axis=2)
        floor_light = light.ambient + light.diffuse * math.sin(light.elevation_rad)
        dist = np.where(np.isfinite(t_floor), t_floor * ray_len, 0.0)
        self._floor_shade = (floor_light * _attenuation(dist, light.attenuation_distance_m)).astype(
            np.float32
        )
        self._bands = self._mip_bands(floor_xy, t_floor)
        self._map_x = np.empty((h, w), np.float32)
        self._map_y = np.empty((h, w), np.float32)
        self._zbuf = np.empty((h, w), np.float64)
        self._hit = np.empty((h, w), np.int32)
        self._face_rgb = np.empty((h, w, 3), np.float32)
        self._background = np.array(_bgr(light.background_color), np.float64)
        # Gloss on a raster with the texture's corner (so one frame tuple serves both).
        tex_grid = self.texture.grid
        self._gloss_grid = GroundGrid.covering(
            x_min_m=tex_grid.x_max_m - tex_grid.rows * tex_grid.cell_m,
            x_max_m=tex_grid.x_max_m,
            y_min_m=tex_grid.y_max_m - tex_grid.cols * tex_grid.cell_m,
            y_max_m=tex_grid.y_max_m,
            cell_m=_GLOSS_CELL_M,
        )
        self._gloss = np.ascontiguousarray(world.gloss_raster(self._gloss_grid), np.float32)
        self._areas = np.ascontiguousarray(world.light_area_table, np.float64).reshape(-1, 8)
        # Inverse softness: the kernels multiply (a hard edge ramps over a micrometre).
        self._areas[:, 4] = 1.0 / np.maximum(self._areas[:, 4], 1e-6)
        self._has_light = len(self._areas) > 0
        self._has_gloss = world.max_gloss > 0.0
        self._mirror = _MirrorView.of(cam, _REFLECTION_STEP)
        lights = world.spec.lights
        self._lights = np.array(
            [
                (
                    *lamp.position_m,
                    lamp.height_m,
                    lamp.radius_m,
                    *(lamp.intensity * v for v in _bgr(lamp.color)),
                )
                for lamp in lights
            ],
            np.float64,
        ).reshape(len(lights), 7)
        pad = 64
        sigma = cam.noise_sigma
        self._noise = (
            np.clip(np.rint(self._rng.normal(0.0, sigma, (h + pad, (w + pad) * 3))), -127, 127)
            .astype(np.int16)
            .reshape(h + pad, w + pad, 3)
            if sigma > 0
            else np.zeros((h + pad, w + pad, 3), np.int16)
        )
        self._faces = self._face_tables()

    # -- set-up ------------------------------------------------------------------------

    def _mip_bands(
        self, floor_xy: NDArray[np.float64], t_floor: NDArray[np.float64]
    ) -> list[tuple[int, int, int]]:
        """(row_start, row_end, level) bands: the mip level per row, from the floor
        footprint of the centre pixel of the row (larger of its two sides)."""
        cam = self.camera
        texel = self.texture.grid.cell_m
        n_levels = len(self.texture.levels)
        col = cam.width_px // 2
        levels = np.zeros(cam.height_px, np.int64)
        for row in range(cam.height_px):
            if not np.isfinite(t_floor[row, col]):
                levels[row] = n_levels - 1
                continue
            below = min(row + 1, cam.height_px - 1)
            above = max(row - 1, 0)
            if np.isfinite(t_floor[above, col]):
                step = float(np.hypot(*(floor_xy[above, col] - floor_xy[below, col]))) / 2
            else:
                step = float(np.hypot(*(floor_xy[row, col] - floor_xy[below, col])))
            side = float(np.hypot(*(floor_xy[row, col] - floor_xy[row, col - 1])))
            footprint = max(step, side) / texel
            levels[row] = min(n_levels - 1, max(0, math.floor(math.log2(max(footprint, 1.0)))))
        bands: list[tuple[int, int, int]] = []
        start = 0
        for row in range(1, cam.height_px + 1):
            if row == cam.height_px or levels[row] != levels[start]:
                bands.append((start, row, int(levels[start])))
                start = row
        return bands

    def _face_tables(self) -> _FaceTables:
        """Per-face arrays in the plan frame, lighting included."""
        world = self.world
        light = world.spec.lighting
        faces = world.faces
        segs = faces.segments
        n = len(segs)
        edge = segs[:, 2:] - segs[:, :2]
        length = np.hypot(edge[:, 0], edge[:, 1])
        normal = np.column_stack((-edge[:, 1], edge[:, 0])) / np.maximum(length, 1e-12)[:, None]
        # Face normal (left of A->B) against the light; walls are lit on one side only.
        ndotl = math.cos(light.elevation_rad) * (normal @ self._light_xy)
        lit_left = light.ambient + light.diffuse * np.maximum(ndotl, 0.0)
        lit_right = light.ambient + light.diffuse * np.maximum(-ndotl, 0.0)
        grid = self.texture.grid
        texel = grid.cell_m
        tex_row0 = (grid.x_max_m - segs[:, 0]) / texel - 0.5
        tex_col0 = (grid.y_max_m - segs[:, 1]) / texel - 0.5
        boxes = world.boxes
        top_light = light.ambient + light.diffuse * math.sin(light.elevation_rad)
        return _FaceTables(
            segments=np.ascontiguousarray(segs, np.float64).reshape(n, 4),
            height_m=np.ascontiguousarray(faces.height_m, np.float64),
            color=np.ascontiguousarray(faces.color_bgr, np.float64).reshape(n, 3),
            floor_like=np.ascontiguousarray(faces.floor_like, np.bool_),
            lit=np.ascontiguousarray(np.column_stack((lit_left, lit_right)), np.float64),
            tex_origin=np.ascontiguousarray(np.column_stack((tex_row0, tex_col0)), np.float64),
            length_m=np.ascontiguousarray(length, np.float64),
            box_center=np.ascontiguousarray(boxes.center_m, np.float64),
            box_half=np.ascontiguousarray(boxes.half_size_m, np.float64),
            box_yaw=np.ascontiguousarray(np.column_stack((boxes.cos_yaw, boxes.sin_yaw))),
            box_height=np.ascontiguousarray(boxes.height_m, np.float64),
            box_color=np.ascontiguousarray(boxes.color_bgr * top_light, np.float64),
        )

    # -- rendering ---------------------------------------------------------------------

    @property
    def occupancy(self) -> tuple[GroundGrid, NDArray[np.uint8]]:
        """The world's ground-truth occupancy (plan frame, 5 cm, 1 = wall or box)."""
        return self.world.occupancy()

    def render(self, pose: Pose2D) -> RenderedFrame:
        """Render the camera image at the robot pose ``pose`` (plan frame)."""
        cam = self.camera
        h, w = cam.height_px, cam.width_px
        grid = self.texture.grid
        T_plan_robot = pose
        cos_t, sin_t = math.cos(pose.theta_rad), math.sin(pose.theta_rad)
        _floor_maps(
            self._u,
            self._v,
            self._axes,
            self._eye,
            self._t_floor,
            cos_t,
            sin_t,
            pose.x_m,
            pose.y_m,
            grid.x_max_m,
            grid.y_max_m,
            grid.cell_m,
            self._map_x,
            self._map_y,
        )
        floor = np.empty((h, w, 3), np.uint8)
        for start, end, level in self._bands:
            scale = 0.5**level
            map_x = self._map_x[start:end]
            map_y = self._map_y[start:end]
            if level:
                map_x = (map_x + 0.5) * scale - 0.5
                map_y = (map_y + 0.5) * scale - 0.5
            floor[start:end] = cv2.remap(
                self._floor_levels[level],
                map_x,
                map_y,
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
        T_robot_plan = T_plan_robot.inverse()
        f = self._faces
        segs_robot = np.empty_like(f.segments)
        segs_robot[:, :2] = T_robot_plan.apply(f.segments[:, :2])
        segs_robot[:, 2:] = T_robot_plan.apply(f.segments[:, 2:])
        box_center = T_robot_plan.apply(f.box_center) if len(f.box_center) else f.box_center
        rel_cos = f.box_yaw[:, 0] * cos_t + f.box_yaw[:, 1] * sin_t
        rel_sin = f.box_yaw[:, 1] * cos_t - f.box_yaw[:, 0] * sin_t
        light = self.world.spec.lighting
        image = np.empty((h, w, 3), np.uint8)
        mask = np.empty((h, w), np.bool_)
        noise_y = int(self._rng.integers(0, self._noise.shape[0] - h + 1))
        noise_x = int(self._rng.integers(0, self._noise.shape[1] - w + 1))
        gg = self._gloss_grid
        # All floats, whatever the pose was built from: one kernel signature.
        frame = (gg.x_max_m, gg.y_max_m, gg.cell_m, cos_t, sin_t, float(pose.x_m), float(pose.y_m))
        axes = self._axes
        cx, cy = cam.principal_point_px
        _render_faces(
            self._u,
            self._v,
            self._eye,
            axes,
            cam.fx_px,
            cam.fy_px,
            cx,
            cy,
            self._t_floor,
            segs_robot,
            f.height_m,
            f.color,
            f.floor_like,
            f.lit,
            f.tex_origin,
            f.length_m,
            np.ascontiguousarray(box_center, np.float64),
            f.box_half,
            np.ascontiguousarray(np.column_stack((rel_cos, rel_sin))),
            f.box_height,
            f.box_color,
            self.texture.levels[0],
            grid.cell_m,
            light.attenuation_distance_m,
            self._areas,
            frame,
            self._has_light,
            self._zbuf,
            self._hit,
            self._face_rgb,
        )
        m = self._mirror
        reflect = _render_mirror(
            m.u,
            m.v,
            self._eye,
            axes,
            m.fx_px,
            m.fy_px,
            m.cx_px,
            m.cy_px,
            m.t_floor,
            m.fresnel,
            self._has_gloss,
            segs_robot,
            f.height_m,
            f.color,
            f.floor_like,
            f.lit,
            f.tex_origin,
            f.length_m,
            self.texture.levels[0],
            grid.cell_m,
            light.attenuation_distance_m,
            self._gloss,
            self._areas,
            frame,
            self._has_light,
            self._background,
            m.zbuf,
            m.weight,
            m.rgb,
        )
        lights = self._lights.copy()
        if len(lights):
            lights[:, :2] = T_robot_plan.apply(self._lights[:, :2])
        _light_spots(
            lights,
            self._eye,
            axes,
            m.fx_px,
            m.fy_px,
            m.cx_px,
            m.cy_px,
            reflect,
            m.zbuf,
            m.weight,
            m.rgb,
        )
        _compose(
            floor,
            self._floor_shade,
            self._t_floor,
            self._hit,
            self._face_rgb,
            self._background,
            self._noise[noise_y : noise_y + h, noise_x : noise_x + w],
            reflect,
            _REFLECTION_SHIFT,
            m.weight,
            m.rgb,
            image,
            mask,
        )
        return RenderedFrame(image=image, floor_mask=mask, pose=pose)


@dataclass(frozen=True)
class _FaceTables:
    segments: NDArray[np.float64]
    height_m: NDArray[np.float64]
    color: NDArray[np.float64]
    floor_like: NDArray[np.bool_]
    lit: NDArray[np.float64]
    tex_origin: NDArray[np.float64]
    length_m: NDArray[np.float64]
    box_center: NDArray[np.float64]
    box_half: NDArray[np.float64]
    box_yaw: NDArray[np.float64]
    box_height: NDArray[np.float64]
    box_color: NDArray[np.float64]


@dataclass(frozen=True)
class _MirrorView:
    """The camera at 1 / ``step`` resolution, for the mirror pass: one ray per block of
    ``step`` x ``step`` pixels (through its centre), the intrinsics that project onto
    the blocks, each ray's floor hit and Fresnel term, and the pass's work buffers."""

    u: NDArray[np.float64]
    """Each column's ray coordinate (`CameraModel.ray_coordinates`)..."""
    v: NDArray[np.float64]
    """...and each row's."""
    t_floor: NDArray[np.float64]
    fresnel: NDArray[np.float32]
    """Schlick's term of the ray's angle to the floor's normal; 0 for rays that miss it."""
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    zbuf: NDArray[np.float64]
    weight: NDArray[np.float32]
    rgb: NDArray[np.float32]

    @classmethod
    def of(cls, cam: CameraModel, step: int) -> _MirrorView:
        h, w = math.ceil(cam.height_px / step), math.ceil(cam.width_px / step)
        cx, cy = cam.principal_point_px
        centre = (step - 1) / 2
        u = (np.arange(w) * step + centre - cx) / cam.fx_px
        v = (np.arange(h) * step + centre - cy) / cam.fy_px
        uu, vv = np.meshgrid(u, v)
        right, down_axis, forward = cam.axes_robot()
        rays = uu[..., None] * right + vv[..., None] * down_axis + forward[None, None, :]
        ray_len = np.linalg.norm(rays, axis=2)
        down = -rays[..., 2]
        hits = down > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            t_floor = np.where(hits, cam.height_m / down, np.inf)
        cos_view = np.clip(np.where(hits, down / ray_len, 1.0), 0.0, 1.0)
        fresnel = _FRESNEL_F0 + (1.0 - _FRESNEL_F0) * (1.0 - cos_view) ** 5
        return cls(
            u=np.ascontiguousarray(u, np.float64),
            v=np.ascontiguousarray(v, np.float64),
            t_floor=np.ascontiguousarray(t_floor, np.float64),
            fresnel=np.where(hits, fresnel, 0.0).astype(np.float32),
            fx_px=cam.fx_px / step,
            fy_px=cam.fy_px / step,
            cx_px=(cx - centre) / step,
            cy_px=(cy - centre) / step,
            zbuf=np.empty((h, w), np.float64),
            weight=np.empty((h, w), np.float32),
            rgb=np.empty((h, w, 3), np.float32),
        )


def _lit_levels(world: World, texture: FloorTexture) -> list[NDArray[np.uint8]]:
    """The floor texture's mip levels with the world's light areas applied (the
    texture itself when it has none): the floor then costs nothing more per frame."""
    if not world.spec.light_areas:
        return texture.levels
    x, y = texture.grid.cell_centers()
    lit = texture.levels[0] * world.light_gain(x, y)
    return mip_levels(np.clip(lit + 0.5, 0, 255).astype(np.uint8), texture.surfaces)


def _bgr(color: str) -> tuple[float, float, float]:
    r, g, b = (int(color[i : i + 2], 16) for i in (1, 3, 5))
    return (float(b), float(g), float(r))


def _attenuation(distance_m: NDArray[np.float64], scale_m: float) -> NDArray[np.float64]:
    out: NDArray[np.float64] = 1.0 / (1.0 + (distance_m / scale_m) ** 2)
    return out


# -- kernels ---------------------------------------------------------------------------


_Axes = tuple[float, float, float, float, float, float, float, float, float]
"""`CameraModel.axes_robot` row by row, as scalars (`_axes`)."""


@numba.njit(cache=True, nogil=True)
def _axes(axes: NDArray[np.float64]) -> _Axes:
    """The (3, 3) axes as nine scalars: the kernels' inner loops then keep them in
    registers (from an array they are loaded again for every pixel, since the loops also
    write arrays)."""
    return (
        axes[0, 0],
        axes[0, 1],
        axes[0, 2],
        axes[1, 0],
        axes[1, 1],
        axes[1, 2],
        axes[2, 0],
        axes[2, 1],
        axes[2, 2],
    )


_Row = tuple[float, float, float]
"""A row's share of its rays (`_row`)."""


@numba.njit(cache=True, nogil=True)
def _row(vr: float, a: _Axes) -> _Row:
    """Row coordinate ``vr`` times the down axis: the part of `_ray` common to a row,
    worked out once per row."""
    return (vr * a[3], vr * a[4], vr * a[5])


@numba.njit(cache=True, nogil=True)
def _ray(uc: float, row: _Row, a: _Axes) -> tuple[float, float, float]:
    """The ray through a pixel at column coordinate ``uc`` (`CameraModel.ray_coordinates`)
    in a row (`_row`), as `CameraModel.rays_robot` has it: the same operations in the
    same order, so the same bits."""
    return (
        uc * a[0] + row[0] + a[6],
        uc * a[1] + row[1] + a[7],
        uc * a[2] + row[2] + a[8],
    )


@numba.njit(cache=True, nogil=True)
def _ray_length(dx: float, dy: float, dz: float) -> float:
    """``np.linalg.norm`` of a ray, summed in its order."""
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@numba.njit(cache=True, nogil=True)
def _floor_maps(
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    axes: NDArray[np.float64],
    eye: NDArray[np.float64],
    t_floor: NDArray[np.float64],
    cos_t: float,
    sin_t: float,
    x0: float,
    y0: float,
    x_max: float,
    y_max: float,
    texel: float,
    map_x: NDArray[np.float32],
    map_y: NDArray[np.float32],
) -> None:
    """Texture coordinates (level 0: column, row) of every pixel's floor point."""
    h, w = t_floor.shape
    inv = 1.0 / texel
    ex, ey = eye[0], eye[1]
    cam_axes = _axes(axes)
    for r in range(h):
        row = _row(v[r], cam_axes)
        for c in range(w):
            t = t_floor[r, c]
            if not np.isfinite(t):
                map_x[r, c] = -1e6
                map_y[r, c] = -1e6
                continue
            dx, dy, _ = _ray(u[c], row, cam_axes)
            fx = ex + t * dx
            fy = ey + t * dy
            px = x0 + cos_t * fx - sin_t * fy
            py = y0 + sin_t * fx + cos_t * fy
            map_x[r, c] = (y_max - py) * inv - 0.5
            map_y[r, c] = (x_max - px) * inv - 0.5


@numba.njit(cache=True, nogil=True)
def _project_bbox(
    corners: NDArray[np.float64],
    eye: NDArray[np.float64],
    axes: NDArray[np.float64],
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    w: int,
    h: int,
) -> tuple[int, int, int, int]:
    """Pixel bounding box (c0, c1, r0, r1, inclusive-exclusive) of a planar polygon
    (K, 3) in the robot frame, clipped to the near plane; empty when c0 >= c1."""
    k = corners.shape[0]
    cam = np.empty((k, 3))
    for i in range(k):
        for a in range(3):
            cam[i, a] = (
                (corners[i, 0] - eye[0]) * axes[a, 0]
                + (corners[i, 1] - eye[1]) * axes[a, 1]
                + (corners[i, 2] - eye[2]) * axes[a, 2]
            )
    u_min, u_max, v_min, v_max = np.inf, -np.inf, np.inf, -np.inf
    n_in = 0
    for i in range(k):
        j = (i + 1) % k
        zi, zj = cam[i, 2], cam[j, 2]
        if zi >= _NEAR_M:
            n_in += 1
            u = cx + fx * cam[i, 0] / zi
            v = cy + fy * cam[i, 1] / zi
            u_min, u_max = min(u_min, u), max(u_max, u)
            v_min, v_max = min(v_min, v), max(v_max, v)
        if (zi >= _NEAR_M) != (zj >= _NEAR_M):
            s = (_NEAR_M - zi) / (zj - zi)
            xc = cam[i, 0] + s * (cam[j, 0] - cam[i, 0])
            yc = cam[i, 1] + s * (cam[j, 1] - cam[i, 1])
            u = cx + fx * xc / _NEAR_M
            v = cy + fy * yc / _NEAR_M
            u_min, u_max = min(u_min, u), max(u_max, u)
            v_min, v_max = min(v_min, v), max(v_max, v)
    if n_in == 0:
        return 0, 0, 0, 0
    c0 = max(0, math.floor(max(u_min, -1.0)))
    c1 = min(w, math.ceil(min(u_max, w + 1.0)) + 1)
    r0 = max(0, math.floor(max(v_min, -1.0)))
    r1 = min(h, math.ceil(min(v_max, h + 1.0)) + 1)
    if c0 >= c1 or r0 >= r1:
        return 0, 0, 0, 0
    return c0, c1, r0, r1


@numba.njit(cache=True, nogil=True)
def _plan_point(frame: _PlanFrame, rx: float, ry: float) -> tuple[float, float]:
    """A robot-frame ground point in the plan frame."""
    return (
        frame[5] + frame[3] * rx - frame[4] * ry,
        frame[6] + frame[4] * rx + frame[3] * ry,
    )


@numba.njit(cache=True, nogil=True)
def _render_faces(
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    eye: NDArray[np.float64],
    axes: NDArray[np.float64],
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    t_floor: NDArray[np.float64],
    segs: NDArray[np.float64],
    heights: NDArray[np.float64],
    colors: NDArray[np.float64],
    floor_like: NDArray[np.bool_],
    lit: NDArray[np.float64],
    tex_origin: NDArray[np.float64],
    length_m: NDArray[np.float64],
    box_center: NDArray[np.float64],
    box_half: NDArray[np.float64],
    box_yaw: NDArray[np.float64],
    box_height: NDArray[np.float64],
    box_color: NDArray[np.float64],
    texture: NDArray[np.uint8],
    texel: float,
    att_m: float,
    areas: NDArray[np.float64],
    frame: _PlanFrame,
    has_light: bool,
    zbuf: NDArray[np.float64],
    hit: NDArray[np.int32],
    face_rgb: NDArray[np.float32],
) -> None:
    """Depth-tested rasterisation of vertical faces and box tops (robot frame).
    ``hit`` is -1 where the floor (or nothing) is nearest, else 1; ``face_rgb`` then
    holds the shaded colour, times the light areas' gain at the hit's ground point
    when ``has_light`` (applied once per pixel, after the nearest face is known)."""
    h, w = t_floor.shape
    ex, ey, ez = eye[0], eye[1], eye[2]
    cam_axes = _axes(axes)
    tex_h, tex_w = texture.shape[0], texture.shape[1]
    for r in range(h):
        for c in range(w):
            zbuf[r, c] = t_floor[r, c]
            hit[r, c] = -1
    quad = np.empty((4, 3))
    for f in range(segs.shape[0]):
        ax, ay, bx, by = segs[f, 0], segs[f, 1], segs[f, 2], segs[f, 3]
        top = heights[f]
        quad[0, 0], quad[0, 1], quad[0, 2] = ax, ay, 0.0
        quad[1, 0], quad[1, 1], quad[1, 2] = bx, by, 0.0
        quad[2, 0], quad[2, 1], quad[2, 2] = bx, by, top
        quad[3, 0], quad[3, 1], quad[3, 2] = ax, ay, top
        c0, c1, r0, r1 = _project_bbox(quad, eye, axes, fx, fy, cx, cy, w, h)
        if c0 >= c1:
            continue
        edx, edy = bx - ax, by - ay
        wx, wy = ax - ex, ay - ey
        # Camera on the left of A->B sees the left side.
        left = edx * (ey - ay) - edy * (ex - ax) > 0.0
        shade = lit[f, 0] if left else lit[f, 1]
        for r in range(r0, r1):
            row = _row(v[r], cam_axes)
            for c in range(c0, c1):
                dx, dy, dz = _ray(u[c], row, cam_axes)
                denom = dx * edy - dy * edx
                if abs(denom) < 1e-12:
                    continue
                t = (wx * edy - wy * edx) / denom
                if t <= 0.0 or t >= zbuf[r, c]:
                    continue
                s = (wx * dy - wy * dx) / denom
                if s < 0.0 or s > 1.0:
                    continue
                z = ez + t * dz
                if z < 0.0 or z > top:
                    continue
                zbuf[r, c] = t
                hit[r, c] = 1
                d = t * _ray_length(dx, dy, dz)
                gain = shade / (1.0 + (d / att_m) ** 2)
                if floor_like[f]:
                    along = s * length_m[f]
                    tr = int(tex_origin[f, 0] - along / texel) % tex_h
                    tc = int(tex_origin[f, 1] - z / texel) % tex_w
                    for k in range(3):
                        face_rgb[r, c, k] = texture[tr, tc, k] * gain
                else:
                    for k in range(3):
                        face_rgb[r, c, k] = colors[f, k] * gain
    rect = np.empty((4, 3))
    for b in range(box_center.shape[0]):
        top = box_height[b]
        if top >= ez:
            continue  # the camera cannot see this top
        bcx, bcy = box_center[b, 0], box_center[b, 1]
        hx, hy = box_half[b, 0], box_half[b, 1]
        cs, sn = box_yaw[b, 0], box_yaw[b, 1]
        for i in range(4):
            lx = hx if i == 0 or i == 3 else -hx
            ly = hy if i < 2 else -hy
            rect[i, 0] = bcx + cs * lx - sn * ly
            rect[i, 1] = bcy + sn * lx + cs * ly
            rect[i, 2] = top
        c0, c1, r0, r1 = _project_bbox(rect, eye, axes, fx, fy, cx, cy, w, h)
        if c0 >= c1:
            continue
        for r in range(r0, r1):
            row = _row(v[r], cam_axes)
            for c in range(c0, c1):
                dx, dy, dz = _ray(u[c], row, cam_axes)
                if dz >= 0.0:
                    continue
                t = (top - ez) / dz
                if t >= zbuf[r, c]:
                    continue
                px = ex + t * dx - bcx
                py = ey + t * dy - bcy
                if abs(cs * px + sn * py) > hx or abs(-sn * px + cs * py) > hy:
                    continue
                zbuf[r, c] = t
                hit[r, c] = 1
                d = t * _ray_length(dx, dy, dz)
                gain = 1.0 / (1.0 + (d / att_m) ** 2)
                for k in range(3):
                    face_rgb[r, c, k] = box_color[b, k] * gain
    if has_light:
        for r in range(h):
            for c in range(w):
                if hit[r, c] < 0:
                    zbuf[r, c] = np.inf
        _apply_light_areas(u, v, axes, eye, zbuf, areas, frame, face_rgb)


@numba.njit(cache=True, nogil=True)
def _render_mirror(
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    eye: NDArray[np.float64],
    axes: NDArray[np.float64],
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    t_floor: NDArray[np.float64],
    fresnel: NDArray[np.float32],
    has_gloss: bool,
    segs: NDArray[np.float64],
    heights: NDArray[np.float64],
    colors: NDArray[np.float64],
    floor_like: NDArray[np.bool_],
    lit: NDArray[np.float64],
    tex_origin: NDArray[np.float64],
    length_m: NDArray[np.float64],
    texture: NDArray[np.uint8],
    texel: float,
    att_m: float,
    gloss: NDArray[np.float32],
    areas: NDArray[np.float64],
    frame: _PlanFrame,
    has_light: bool,
    ceiling: NDArray[np.float64],
    rzbuf: NDArray[np.float64],
    refl_w: NDArray[np.float32],
    refl_rgb: NDArray[np.float32],
) -> bool:
    """The floor's reflections, on the `_MirrorView` rays: per ray that meets the floor
    its reflection weight (``refl_w``: the floor's gloss there times the Fresnel term)
    and, where that is worth it, the colour its mirrored ray meets (``refl_rgb``, the
    ceiling by default) at depth ``rzbuf``. The faces are mirrored to z in [-height, 0]:
    a ray past its floor point meets them exactly where its reflection meets the
    originals, after the same path length. Box tops are left out (the mirrored camera
    sees them from below, where they are hidden). Every ray that meets the floor gets
    a reflection, also where something stands in front of its floor point: the other
    pixels of its block may see floor. False when no ray reflects."""
    if not has_gloss:
        return False
    h, w = t_floor.shape
    ex, ey, ez = eye[0], eye[1], eye[2]
    cam_axes = _axes(axes)
    g_rows, g_cols = gloss.shape
    inv_cell = 1.0 / frame[2]
    reflects = False
    for r in range(h):
        row = _row(v[r], cam_axes)
        for c in range(w):
            weight = 0.0
            if fresnel[r, c] > 0.0:
                t = t_floor[r, c]
                dx, dy, _ = _ray(u[c], row, cam_axes)
                px, py = _plan_point(frame, ex + t * dx, ey + t * dy)
                gr = math.floor((frame[0] - px) * inv_cell)
                gc = math.floor((frame[1] - py) * inv_cell)
                if 0 <= gr < g_rows and 0 <= gc < g_cols:
                    weight = gloss[gr, gc] * fresnel[r, c]
            if weight >= _MIN_REFLECTION:
                reflects = True
                refl_w[r, c] = weight
                rzbuf[r, c] = np.inf
                for k in range(3):
                    refl_rgb[r, c, k] = ceiling[k]
            else:
                refl_w[r, c] = 0.0
                rzbuf[r, c] = -1.0
    if not reflects:
        return False
    ex, ey, ez = eye[0], eye[1], eye[2]
    tex_h, tex_w = texture.shape[0], texture.shape[1]
    quad = np.empty((4, 3))
    for f in range(segs.shape[0]):
        ax, ay, bx, by = segs[f, 0], segs[f, 1], segs[f, 2], segs[f, 3]
        top = heights[f]
        quad[0, 0], quad[0, 1], quad[0, 2] = ax, ay, 0.0
        quad[1, 0], quad[1, 1], quad[1, 2] = bx, by, 0.0
        quad[2, 0], quad[2, 1], quad[2, 2] = bx, by, -top
        quad[3, 0], quad[3, 1], quad[3, 2] = ax, ay, -top
        c0, c1, r0, r1 = _project_bbox(quad, eye, axes, fx, fy, cx, cy, w, h)
        if c0 >= c1:
            continue
        edx, edy = bx - ax, by - ay
        wx, wy = ax - ex, ay - ey
        left = edx * (ey - ay) - edy * (ex - ax) > 0.0
        shade = lit[f, 0] if left else lit[f, 1]
        for r in range(r0, r1):
            row = _row(v[r], cam_axes)
            for c in range(c0, c1):
                if rzbuf[r, c] < 0.0:
                    continue
                dx, dy, dz = _ray(u[c], row, cam_axes)
                denom = dx * edy - dy * edx
                if abs(denom) < 1e-12:
                    continue
                t = (wx * edy - wy * edx) / denom
                if t <= 0.0 or t >= rzbuf[r, c]:
                    continue
                s = (wx * dy - wy * dx) / denom
                if s < 0.0 or s > 1.0:
                    continue
                z = ez + t * dz
                if z > 0.0 or z < -top:
                    continue
                rzbuf[r, c] = t
                d = t * _ray_length(dx, dy, dz)
                gain = shade / (1.0 + (d / att_m) ** 2)
                if floor_like[f]:
                    along = s * length_m[f]
                    tr = int(tex_origin[f, 0] - along / texel) % tex_h
                    tc = int(tex_origin[f, 1] + z / texel) % tex_w
                    for k in range(3):
                        refl_rgb[r, c, k] = texture[tr, tc, k] * gain
                else:
                    for k in range(3):
                        refl_rgb[r, c, k] = colors[f, k] * gain
    if has_light:
        _apply_light_areas(u, v, axes, eye, rzbuf, areas, frame, refl_rgb)
    return True


@numba.njit(cache=True, nogil=True)
def _apply_light_areas(
    u: NDArray[np.float64],
    v: NDArray[np.float64],
    axes: NDArray[np.float64],
    eye: NDArray[np.float64],
    depth: NDArray[np.float64],
    areas: NDArray[np.float64],
    frame: _PlanFrame,
    rgb: NDArray[np.float32],
) -> None:
    """Multiply ``rgb`` by the light areas' gain (`World.light_gain`) at each ray's
    ground point, where its ``depth`` (ray parameter of what it meets) is positive and
    finite. ``areas``: `World.light_area_table` with the softness inverted."""
    h, w = depth.shape
    ex, ey = eye[0], eye[1]
    cam_axes = _axes(axes)
    for r in range(h):
        row = _row(v[r], cam_axes)
        for c in range(w):
            t = depth[r, c]
            if not 0.0 < t < np.inf:
                continue
            dx, dy, _ = _ray(u[c], row, cam_axes)
            px, py = _plan_point(frame, ex + t * dx, ey + t * dy)
            for a in range(areas.shape[0]):
                inv = areas[a, 4]
                cx0 = min(1.0, max(0.0, (px - areas[a, 0]) * inv + 0.5))
                cx1 = min(1.0, max(0.0, (areas[a, 2] - px) * inv + 0.5))
                cy0 = min(1.0, max(0.0, (py - areas[a, 1]) * inv + 0.5))
                cy1 = min(1.0, max(0.0, (areas[a, 3] - py) * inv + 0.5))
                cover = cx0 * cx1 * cy0 * cy1
                if cover > 0.0:
                    rgb[r, c, 0] *= 1.0 + cover * (areas[a, 5] - 1.0)
                    rgb[r, c, 1] *= 1.0 + cover * (areas[a, 6] - 1.0)
                    rgb[r, c, 2] *= 1.0 + cover * (areas[a, 7] - 1.0)


@numba.njit(cache=True, nogil=True)
def _light_spots(
    lights: NDArray[np.float64],
    eye: NDArray[np.float64],
    axes: NDArray[np.float64],
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    reflect: bool,
    rzbuf: NDArray[np.float64],
    refl_w: NDArray[np.float32],
    refl_rgb: NDArray[np.float32],
) -> None:
    """Add each ceiling light's mirror image (``lights`` rows: robot-frame x, y, height,
    radius, then B, G, R brightness) to the reflection as a Gaussian spot as wide as the
    light's disk looks from here, where no mirrored face is nearer."""
    if not reflect:
        return
    h, w = rzbuf.shape
    rim = np.empty((5, 3))
    for i in range(lights.shape[0]):
        lx, ly, lz, radius = lights[i, 0], lights[i, 1], -lights[i, 2], lights[i, 3]
        for j in range(5):
            ox = radius if j == 1 else (-radius if j == 2 else 0.0)
            oy = radius if j == 3 else (-radius if j == 4 else 0.0)
            for a in range(3):
                rim[j, a] = (
                    (lx + ox - eye[0]) * axes[a, 0]
                    + (ly + oy - eye[1]) * axes[a, 1]
                    + (lz - eye[2]) * axes[a, 2]
                )
        depth = rim[0, 2]
        if depth < _NEAR_M:
            continue
        u = cx + fx * rim[0, 0] / depth
        v = cy + fy * rim[0, 1] / depth
        su, sv = 0.0, 0.0
        for j in range(1, 5):
            if rim[j, 2] < _NEAR_M:
                continue
            su = max(su, abs(cx + fx * rim[j, 0] / rim[j, 2] - u))
            sv = max(sv, abs(cy + fy * rim[j, 1] / rim[j, 2] - v))
        su = max(1.0, _SPOT_SIGMA * su)
        sv = max(1.0, _SPOT_SIGMA * sv)
        # Out to 2.5 sigma (the rest is below 5 % of the peak).
        c0, c1 = max(0, int(u - 2.5 * su)), min(w, int(u + 2.5 * su) + 2)
        r0, r1 = max(0, int(v - 2.5 * sv)), min(h, int(v + 2.5 * sv) + 2)
        for r in range(r0, r1):
            dv = (r - v) / sv
            for c in range(c0, c1):
                if refl_w[r, c] <= 0.0 or rzbuf[r, c] < depth:
                    continue
                du = (c - u) / su
                q = du * du + dv * dv
                if q > 6.25:
                    continue
                g = math.exp(-0.5 * q)
                for k in range(3):
                    refl_rgb[r, c, k] += lights[i, 4 + k] * g


@numba.njit(cache=True, nogil=True)
def _compose(
    floor: NDArray[np.uint8],
    floor_shade: NDArray[np.float32],
    t_floor: NDArray[np.float64],
    hit: NDArray[np.int32],
    face_rgb: NDArray[np.float32],
    background: NDArray[np.float64],
    noise: NDArray[np.int16],
    reflect: bool,
    refl_shift: int,
    refl_w: NDArray[np.float32],
    refl_rgb: NDArray[np.float32],
    image: NDArray[np.uint8],
    mask: NDArray[np.bool_],
) -> None:
    """Shaded floor (blended with its reflection), faces or background per pixel, plus
    noise; the floor mask."""
    h, w = hit.shape
    for r in range(h):
        for c in range(w):
            is_floor = hit[r, c] < 0 and np.isfinite(t_floor[r, c])
            mask[r, c] = is_floor
            if hit[r, c] >= 0:
                v0, v1, v2 = face_rgb[r, c, 0], face_rgb[r, c, 1], face_rgb[r, c, 2]
            elif is_floor:
                shade = floor_shade[r, c]
                v0, v1, v2 = floor[r, c, 0] * shade, floor[r, c, 1] * shade, floor[r, c, 2] * shade
                if reflect:
                    rr, rc = r >> refl_shift, c >> refl_shift
                    wr = refl_w[rr, rc]
                    if wr > 0.0:
                        keep = 1.0 - wr
                        v0 = v0 * keep + wr * refl_rgb[rr, rc, 0]
                        v1 = v1 * keep + wr * refl_rgb[rr, rc, 1]
                        v2 = v2 * keep + wr * refl_rgb[rr, rc, 2]
            else:
                v0, v1, v2 = background[0], background[1], background[2]
            image[r, c, 0] = min(255, max(0, int(v0 + noise[r, c, 0] + 0.5)))
            image[r, c, 1] = min(255, max(0, int(v1 + noise[r, c, 1] + 0.5)))
            image[r, c, 2] = min(255, max(0, int(v2 + noise[r, c, 2] + 0.5)))
