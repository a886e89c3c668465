"""The simulated camera: frames at a fixed rate with their ground truth, or on demand."""

from __future__ import annotations

import time
from collections.abc import Callable

from app.hardware.interfaces import DeviceState
from app.mapping.frames import Pose2D
from app.sim.camera import SimCamera
from app.sim.render import CameraModel, RenderedFrame, Renderer
from app.sim.world import parse_world


def _wait(predicate: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return False


def test_sim_camera_frames_with_truth() -> None:
    world = parse_world("[start]\nx_m = 1.0\ny_m = 1.0\n[[rooms]]\nrect_m = [0, 0, 3, 2]\n")
    renderer = Renderer(world, CameraModel(width_px=160, height_px=120, fx_px=125, fy_px=125))
    with SimCamera(renderer, lambda: world.start_pose, fps=100.0) as camera:
        assert _wait(lambda: camera.latest_with_truth(1.0) is not None)
        pair = camera.latest_with_truth(1.0)
        assert pair is not None
        frame, truth = pair
        assert frame.image is truth.image and truth.pose == world.start_pose
        assert frame.image.shape == (120, 160, 3) and truth.floor_mask.any()
        assert camera.status().state == DeviceState.CONNECTED
    time.sleep(0.02)
    assert camera.latest(0.01) is None  # stale frames are refused


def test_sim_camera_on_demand_renders_the_current_pose() -> None:
    world = parse_world("[start]\nx_m = 1.0\ny_m = 1.0\n[[rooms]]\nrect_m = [0, 0, 3, 2]\n")
    renderer = Renderer(world, CameraModel(width_px=160, height_px=120, fx_px=125, fy_px=125))
    poses = [world.start_pose, Pose2D(2.0, 1.0, 0.0)]
    camera = SimCamera(renderer, lambda: poses[0], fps=None)
    assert camera.latest(1.0) is None  # not open
    with camera:
        first = camera.latest_with_truth(1.0)
        poses[0] = poses[1]
        second = camera.latest_with_truth(1.0)
        assert first is not None and second is not None
        assert first[1].pose == world.start_pose and second[1].pose == poses[1]
        assert second[0].seq == first[0].seq + 1
        # Closer to the wall x = 3: less floor in view.
        assert second[1].floor_mask.sum() < first[1].floor_mask.sum()
        assert camera.status().state == DeviceState.CONNECTED
    assert camera.status().state == DeviceState.DISCONNECTED


def test_sim_camera_stamps_a_frame_when_its_pose_was_taken_not_after_rendering() -> None:
    """A camera stamps its exposure; the pose lookup of a turning robot relies on it."""
    world = parse_world("[start]\nx_m = 1.0\ny_m = 1.0\n[[rooms]]\nrect_m = [0, 0, 3, 2]\n")
    renderer = Renderer(world, CameraModel(width_px=160, height_px=120, fx_px=125, fy_px=125))
    render = renderer.render

    def slow_render(pose: Pose2D) -> RenderedFrame:
        time.sleep(0.05)
        return render(pose)

    renderer.render = slow_render  # type: ignore[method-assign]
    taken_s: list[float] = []

    def pose_source() -> Pose2D:
        taken_s.append(time.monotonic())
        return world.start_pose

    with SimCamera(renderer, pose_source, fps=None) as camera:
        before_s = time.monotonic()
        frame = camera.latest(1.0)
        assert frame is not None
    assert before_s <= frame.timestamp_s <= taken_s[-1]
    # It arrives after the render, as a webcam's frame after its transfer.
    assert frame.arrived_s is not None and frame.arrived_s - frame.timestamp_s >= 0.05
