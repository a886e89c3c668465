"""`Runtime.calibrate_with` on a Runtime that is built but not run (no devices are
opened: the calibration verbs only need a frame in the slot and the mapping thread)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np
import pytest

from app.config import FloornavConfig, load_config
from app.devices import Devices
from app.hardware.interfaces import CameraFrame, DeviceState, DeviceStatus
from app.mapping.calibration import CalibrationError, FloorCalibration
from app.messages import FrameMsg
from app.runtime import Runtime
from app.sim.setup import camera_model, sim_floor_calibration


class IdleCamera:
    """Never opened (the Runtime is not run); the status asks how it is."""

    def open(self) -> None: ...

    def latest(self, max_age_s: float) -> CameraFrame | None:
        return None

    def status(self) -> DeviceStatus:
        return DeviceStatus(DeviceState.DISCONNECTED, "not opened")

    def close(self) -> None: ...


@contextlib.contextmanager
def standalone_runtime(config: FloornavConfig | None = None) -> Iterator[Runtime]:
    """A Runtime with the simulator's floor calibration and no devices (never run: its
    verbs work, its stages do not); its worker threads are stopped on exit."""
    config = config or load_config(None, perception={"method": "flood_fill"})
    devices = Devices(
        camera=IdleCamera(),
        port="",
        make_link=lambda: None,  # type: ignore[arg-type,return-value]
        calibration=sim_floor_calibration(camera_model(config)),
        calibration_problem="",
    )
    runtime = Runtime(config, devices)
    try:
        yield runtime
    finally:
        for worker in runtime.workers:
            worker.shutdown()


def publish_frame(runtime: Runtime) -> None:
    image = np.zeros((480, 640, 3), np.uint8)
    runtime.frames.publish(FrameMsg(image, runtime.clock(), 1))


def other_calibration(runtime: Runtime) -> FloorCalibration:
    """A calibration that is not the live one (same numbers, new object)."""
    return sim_floor_calibration(camera_model(runtime.config))


async def test_a_preview_changes_nothing_live() -> None:
    with standalone_runtime() as rt:
        publish_frame(rt)
        rt.shared.autonomous = True  # exploring
        live, mapper = rt.calibration, rt.mapper
        fitted = other_calibration(rt)
        result = await rt.calibrate_with(lambda image: fitted, apply=False)
        assert result is fitted
        assert rt.calibration is live and rt.mapper is mapper  # the map was not reset
        assert rt.shared.autonomous and not rt.shared.calibrating
        assert rt.policy.last_stop is None
        with pytest.raises(ValueError, match="saves nothing"):
            await rt.calibrate_with(lambda image: fitted, lambda c: None, apply=False)


async def test_an_applied_calibration_replaces_the_live_one_and_the_map() -> None:
    with standalone_runtime() as rt:
        publish_frame(rt)
        rt.shared.autonomous = True
        mapper = rt.mapper
        saved: list[FloorCalibration] = []
        fitted = other_calibration(rt)
        assert await rt.calibrate_with(lambda image: fitted, saved.append) is fitted
        assert saved == [fitted] and rt.calibration is fitted
        assert rt.mapper is not None and rt.mapper is not mapper
        assert not rt.shared.autonomous  # stopped: start again
        assert rt.policy.last_stop is None  # a success is no stop to explain


def fail(image: np.ndarray) -> FloorCalibration:
    raise CalibrationError("chessboard 7x5 not found in the image")


async def test_a_failed_calibration_that_stopped_autonomy_says_so() -> None:
    with standalone_runtime() as rt:
        publish_frame(rt)
        rt.shared.autonomous = True
        live, mapper = rt.calibration, rt.mapper
        with pytest.raises(CalibrationError):
            await rt.calibrate_with(fail)
        assert rt.calibration is live and rt.mapper is mapper
        assert not rt.shared.autonomous and not rt.shared.calibrating
        last = rt.status()["last_stop"]
        assert last["cause"] == "calibration" and not last["latched"]
        assert last["reason"] == (
            "calibration failed: chessboard 7x5 not found in the image; "
            "autonomy stays off until started"
        )
        assert rt.policy.stops_by_cause["calibration"] == 1
        assert rt.policy.holding(rt.clock()) is None  # recorded, never held
        assert rt.policy.latched is None


async def test_a_failed_calibration_while_idle_is_no_stop() -> None:
    with standalone_runtime() as rt:
        publish_frame(rt)
        with pytest.raises(CalibrationError):
            await rt.calibrate_with(fail)
        assert rt.policy.last_stop is None
        assert rt.policy.stops_by_cause["calibration"] == 0
