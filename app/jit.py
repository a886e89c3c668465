"""Every numba kernel compiled before the daemon starts, not on the robot's time.

The kernels in app/ are ``@njit(cache=True, nogil=True)``: numba compiles one on its first
call, for that call's argument types, and holds the GIL while it does (7.35 s in one
mapping step on a fresh clone's first ``floornav run``). ``cache=True`` only spares the
processes after the first. `compile_kernels` runs the daemon's own per-frame paths once on
synthetic inputs of the configured size, so every kernel the daemon calls is compiled (or
loaded from numba's on-disk cache) with exactly the types it will be called with.
``floornav run`` calls it before the devices open; ``floornav warmup`` (run by
scripts/setup and the Dockerfile) fills the cache ahead of the first run.
"""

from __future__ import annotations

import importlib
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numba
import numpy as np
from numpy.typing import NDArray

from app.config import FloornavConfig

if TYPE_CHECKING:
    from app.mapping.calibration import FloorCalibration
    from app.mapping.frames import Pose2D
    from app.mapping.ground_map import GroundMapper

KERNEL_MODULES = (
    "app.perception.slic",
    "app.perception.features",
    "app.perception.preprocess",
    "app.perception.free_space",
    "app.perception.planar",
    "app.mapping.occupancy",
    "app.mapping.floor_memory",
    "app.mapping.frontiers",
    "app.mapping.scan_match",
    "app.sim.render",
)
"""The modules that define numba kernels (tests/test_jit.py checks that no other does)."""

METHODS_WITHOUT_NUMBA = {
    "floornet": "runs in OpenCV's dnn, and would load its model file for nothing",
}
"""Segmentation methods warmed only when configured, and why (tests/test_jit.py checks
that they indeed call no kernel)."""

_STEP_M = 0.04
"""Travel between warm-up frames: the third frame lies within the parallax test's
baseline window of the first (`GroundMapper`), so that test runs once when configured."""
_STEP_RAD = 0.02
_MAX_MAPPING_FRAMES = 6
_SIM_FOCAL_WIDTH_PX = 640


@dataclass(frozen=True)
class JitReport:
    """What `compile_kernels` did."""

    seconds: float
    kernels: int
    """Kernels with machine code in this process (kernels called only from other kernels
    have none of their own when their caller was loaded from the cache)."""
    compiled: int
    """Signatures compiled by this call (numba's cache misses)."""
    loaded: int
    """Signatures loaded from numba's on-disk cache by this call."""
    cache_dir: str
    """Where numba keeps its cache ("" = __pycache__ beside the sources)."""

    def summary(self) -> str:
        """E.g. ``41 kernels ready in 0.9 s (cache)``."""
        if self.compiled == 0:
            source = "cache"
        elif self.loaded == 0:
            source = "compiled"
        else:
            source = f"{self.compiled} compiled, {self.loaded} from cache"
        return f"{self.kernels} kernels ready in {self.seconds:.1f} s ({source})"

    def banner_line(self) -> str:
        return f"  jit      {self.summary()}"


def numba_dispatchers(modules: tuple[str, ...] = KERNEL_MODULES) -> dict[str, Any]:
    """``module.name`` -> numba dispatcher of every kernel defined in ``modules``."""
    from numba.core.registry import CPUDispatcher

    found: dict[str, Any] = {}
    for module_name in modules:
        module = importlib.import_module(module_name)
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.py_func.__module__ == module_name:
                found[f"{module_name}.{name}"] = value
    return found


def _cache_counts(dispatchers: dict[str, Any]) -> tuple[int, int]:
    """(cache hits, cache misses) summed over every dispatcher and signature."""
    hits = misses = 0
    for dispatcher in dispatchers.values():
        stats = dispatcher.stats
        hits += sum(stats.cache_hits.values())
        misses += sum(stats.cache_misses.values())
    return hits, misses


def synthetic_room(width: int, height: int, seed: int = 0) -> NDArray[np.uint8]:
    """A BGR frame shaped like a camera's: a wall above the floor, a box standing on it,
    sensor noise (for a real camera, whose frames the warm-up cannot have yet)."""
    rng = np.random.default_rng(seed)
    image = np.empty((height, width, 3), np.int16)
    horizon = int(0.45 * height)
    image[:horizon] = (170, 160, 150)
    image[horizon:] = (60, 100, 140)
    box_x0, box_x1 = width // 10, width // 10 + width // 6
    box_y0, box_y1 = horizon - height // 10, horizon + height // 5
    image[box_y0:box_y1, box_x0:box_x1] = (30, 30, 200)
    image += rng.integers(-6, 7, image.shape, dtype=np.int16)
    return np.clip(image, 0, 255).astype(np.uint8)


def compile_kernels(config: FloornavConfig) -> JitReport:
    """Compile, or load from numba's cache, every kernel the daemon calls with
    ``config``: segmentation by the configured method and by every other method that
    uses numba (the method can be changed live), the ground mapper's update (with the
    parallax test and the scan match when configured) and frontier search, and the
    simulator's renderer when the camera is simulated. About a second from the cache."""
    start_s = time.perf_counter()
    dispatchers = numba_dispatchers()
    hits_before, misses_before = _cache_counts(dispatchers)
    # In a thread of its own: the per-thread scratch buffers the paths allocate (SLIC's
    # workspace, ~11 MB at 640x480) go with it instead of staying with the main thread.
    with ThreadPoolExecutor(1, thread_name_prefix="jit-warmup") as pool:
        pool.submit(_run_daemon_paths, config).result()
    hits_after, misses_after = _cache_counts(dispatchers)
    return JitReport(
        seconds=time.perf_counter() - start_s,
        kernels=sum(1 for dispatcher in dispatchers.values() if dispatcher.signatures),
        compiled=misses_after - misses_before,
        loaded=hits_after - hits_before,
        # numba.config has no type information; CACHE_DIR is $NUMBA_CACHE_DIR as read.
        cache_dir=str(getattr(numba.config, "CACHE_DIR", "")),
    )


def _run_daemon_paths(config: FloornavConfig) -> None:
    """One frame through what the perception and mapping stages (and the simulated
    camera) run, on synthetic inputs of the configured size."""
    from app.mapping.frames import Pose2D
    from app.mapping.ground_map import GroundMapper
    from app.perception.pipeline import METHODS, FloorSegmenter
    from app.sim.setup import renderer_from_config

    camera = config.camera
    if camera.source == "sim":
        renderer = renderer_from_config(config)
        image = renderer.render(renderer.world.start_pose).image
    else:
        image = synthetic_room(camera.width_px, camera.height_px)

    configured = config.perception.method
    methods = [configured] + [
        method for method in METHODS if method != configured and method not in METHODS_WITHOUT_NUMBA
    ]
    floor_mask: NDArray[np.bool_] | None = None
    for method in methods:
        result = FloorSegmenter(config.perception, method=method).segment(image)
        if method == configured:
            floor_mask = result.floor_mask
    assert floor_mask is not None
    # Floor right ahead whatever the method made of the frame, so that rays, obstacle
    # bands and frontiers all exist; set in place to keep the mask's exact array type.
    floor_mask[int(0.75 * camera.height_px) :] = True

    mapper = GroundMapper(daemon_floor_calibration(config), config.mapping, config.camera)
    # Moving frames, as on the robot: travel fades old evidence, and the parallax test
    # (when configured) needs a baseline between two of them.
    pose = Pose2D()
    for step in range(_MAX_MAPPING_FRAMES):
        pose = Pose2D(step * _STEP_M, 0.0, step * _STEP_RAD)
        mapper.update(floor_mask, pose, 0.1 * step, image)
        moved = step >= 1
        if moved and (mapper.parallax is None or mapper.parallax_frames > 0):
            break
    mapper.frontiers(pose)
    if mapper.parallax is not None:
        _run_parallax_test(mapper, floor_mask, image)
    if mapper.localizer is not None:
        _run_scan_match(mapper, pose)


def _run_scan_match(mapper: GroundMapper, pose: Pose2D) -> None:
    """The localizer's scan and match once, directly: in the daemon they wait for enough
    map to match against, which the few warm-up frames need not make."""
    from app.mapping.frames import FLOOR, NOT_FLOOR
    from app.mapping.scan_match import likelihood_field, match_scan, virtual_scan

    localizer = mapper.localizer
    assert localizer is not None
    params = localizer.params
    patch = np.full(mapper.birdseye.grid.shape, FLOOR, np.uint8)
    patch[: patch.shape[0] // 4] = NOT_FLOOR  # a wall across the far quarter
    virtual_scan(
        patch,
        localizer.patch_grid,
        localizer.origin_xy,
        localizer.bearings_rad,
        max_range_m=params.max_range_m,
        endpoint_depth_m=params.endpoint_depth_m,
    )
    field = likelihood_field(
        mapper.grid.log_odds,
        mapper.grid.world_grid,
        (pose.x_m, pose.y_m),
        params.max_range_m,
        occupied_threshold=mapper.grid.params.occupied_threshold,
        sigma_m=params.field_sigma_m,
    )
    n = params.match.min_points
    points = np.column_stack((np.full(n, 1.5), np.linspace(-0.5, 0.5, n)))
    match_scan(field, points, pose, params.match)


def _run_parallax_test(
    mapper: GroundMapper, floor_mask: NDArray[np.bool_], image: NDArray[np.uint8]
) -> None:
    """The parallax test once more, directly, asking for what stands up too: its kernels
    then run whatever the mapper's choice of views made of the frames above (a second
    view straight ahead always gives it parallax to test). The views' pose refinement
    too, on a texture it always finds enough samples in."""
    import cv2

    from app.perception.planar import confirm_floor, refine_reference_pose

    assert mapper.parallax is not None
    gray = np.asarray(
        cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image, np.uint8
    )
    confirm_floor(
        floor_mask,
        gray,
        gray,
        mapper.calibration.H_ground_from_image,
        (0.0, 0.0, 0.0),
        (3 * _STEP_M, 0.0, 0.0),
        mapper.camera_xy_robot,
        mapper.parallax,
        return_standing=True,
    )
    noise = np.random.default_rng(0).integers(0, 256, gray.shape, dtype=np.uint8)
    texture = np.asarray(cv2.GaussianBlur(noise, (0, 0), 2.0), np.uint8)
    refine_reference_pose(
        texture,
        texture,
        np.ones(gray.shape, np.bool_),
        mapper.calibration.H_ground_from_image,
        (0.0, 0.0, 0.0),
        (3 * _STEP_M, 0.0, 0.0),
    )


def daemon_floor_calibration(config: FloornavConfig) -> FloorCalibration:
    """The calibration the daemon maps with: the simulated camera's exact one, or a real
    camera's file. Without that file (the daemon maps once calibrated from the
    dashboard) a simulated camera of the configured size stands in: the kernels' types
    do not depend on the homography's values."""
    from app.devices import load_calibration
    from app.sim.setup import camera_model, sim_floor_calibration

    model = camera_model(config)
    if config.camera.source != "sim":
        calibration, _ = load_calibration(config)
        if calibration is not None:
            return calibration
        # The simulator's focal length is meant for 640 px: keep its field of view, or
        # a small frame would not see the floor points the fit needs.
        scale = config.camera.width_px / _SIM_FOCAL_WIDTH_PX
        model = replace(model, fx_px=model.fx_px * scale, fy_px=model.fy_px * scale)
    return sim_floor_calibration(model)
