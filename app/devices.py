"""The devices a configuration selects, opened and closed together: the camera, the
Uno's serial port (and how to make its link), the floor calibration, and for the
simulator the world, the simulated robot and the simulated Uno.

`open_uno` is the one place that chooses the Uno backend (``[serial] backend``); the
daemon and ``floornav uno-check`` both get their port from it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from app.config import ConfigError, ConfigIssue, FloornavConfig, SerialConfig
from app.hardware.cameras import OpenCVCamera, ReplayCamera
from app.hardware.interfaces import Camera, MotorPlant
from app.hardware.link_settings import link_config
from app.hardware.serial_link import UnoLink
from app.hardware.simavr import SimavrUno
from app.mapping.calibration import CalibrationError, FloorCalibration, Intrinsics
from app.mapping.calibration_files import load_floor_calibration, load_intrinsics
from app.mapping.frames import Pose2D
from app.sim.camera import SimCamera
from app.sim.robot import RobotParams, SimRobot
from app.sim.setup import camera_model, renderer_from_config, sim_floor_calibration
from app.sim.uno_process import SimulatedUnoProcess
from app.sim.world import World


@dataclass
class SimHandles:
    """The simulated world behind the devices (for ground truth and fault injection)."""

    world: World
    robot: SimRobot
    uno: SimulatedUnoProcess | None
    """The pure-Python Uno, in its own process (None when the firmware runs in simavr)."""
    camera: SimCamera | None
    T_plan_odom: Pose2D
    """Where odometry's origin (the robot at start-up) lies in the floor plan."""


@dataclass(frozen=True)
class UnoDevice:
    """The started Uno: where to open it and what it is."""

    port: str
    description: str
    simulated: SimulatedUnoProcess | None = None
    """The simulated Uno's process (backend "sim"), for observation and fault injection."""


@contextlib.contextmanager
def open_uno(serial: SerialConfig, plant: MotorPlant | None = None) -> Iterator[UnoDevice]:
    """Start the Uno ``serial.backend`` names (simulated ones only; a real board is just
    a port) and yield where to open it; a simulated one is stopped on exit.

    ``plant`` receives the simulated motor outputs and feeds back the encoders (a
    trivial integrating plant when None); a real board ignores it.

    Raises
    ------
    SimulatedUnoError, SimavrError : a simulated Uno that cannot start.
    """
    if serial.backend == "sim":
        with SimulatedUnoProcess(plant) as uno:
            yield UnoDevice(uno.port, f"simulated Uno on {uno.port}", uno)
    elif serial.backend == "simavr":
        with SimavrUno(plant) as firmware:
            yield UnoDevice(firmware.port, f"firmware in simavr on {firmware.port}")
    else:
        yield UnoDevice(serial.port, f"Uno on {serial.port}")


@dataclass
class Devices:
    camera: Camera
    port: str
    make_link: Callable[[], UnoLink]
    """Builds the serial link (inside the event loop)."""
    calibration: FloorCalibration | None
    calibration_problem: str
    """Why ``calibration`` is None ("" when it is set)."""
    intrinsics: Intrinsics | None = None
    sim: SimHandles | None = None
    description: dict[str, str] = field(default_factory=dict)
    """What is connected, for the start-up banner and the status."""


def robot_params(config: FloornavConfig) -> RobotParams:
    drive = config.drive
    return RobotParams(
        wheel_base_m=drive.wheel_base_m,
        wheel_radius_m=drive.wheel_radius_m,
        max_wheel_speed_m_s=drive.max_wheel_speed_m_s,
        deadband_pwm=drive.pwm_deadband,
        ticks_per_rev=drive.ticks_per_rev,
        radius_m=config.mapping.robot_radius_m,
        wheel_scale_sigma_frac=config.sim.wheel_scale_sigma_frac,
        slip_sigma_frac=config.sim.slip_sigma_frac,
        encoder_tick_noise=config.sim.encoder_tick_noise,
    )


def load_calibration(config: FloornavConfig) -> tuple[FloorCalibration | None, str]:
    """The floor calibration for a real camera, or (None, why not)."""
    path = Path(config.mapping.floor_calibration_file)
    size = (config.camera.width_px, config.camera.height_px)
    if not path.is_file():
        return None, (
            f"no floor calibration at {path} (mapping.floor_calibration_file): run "
            "`floornav calibrate floor IMAGE --pattern CxR --square-m S --out "
            f"{path}` or calibrate from the dashboard"
        )
    try:
        return load_floor_calibration(path, size), ""
    except CalibrationError as exc:
        return None, f"floor calibration {path} unusable: {exc}"


@contextlib.contextmanager
def open_devices(config: FloornavConfig) -> Iterator[Devices]:
    """Open what ``config`` names; everything is closed again on exit.

    Raises
    ------
    ConfigError : a simulated camera with a real Uno (nothing would move in its view).
    WorldError, CalibrationError, OSError : a sim world, intrinsics file or device
        that cannot be opened at all (a camera or Uno that fails later is retried).
    """
    if config.camera.source == "sim" and config.serial.backend == "port":
        raise ConfigError(
            "configuration",
            [
                ConfigIssue(
                    "camera.source",
                    "'sim' renders the simulated robot, which only moves with serial.backend "
                    "'sim' or 'simavr'; with a real Uno use a real camera ('device')",
                )
            ],
        )
    with contextlib.ExitStack() as stack:
        cam_cfg = config.camera
        intrinsics = (
            load_intrinsics(Path(cam_cfg.intrinsics_file), (cam_cfg.width_px, cam_cfg.height_px))
            if cam_cfg.intrinsics_file
            else None
        )
        uses_sim = cam_cfg.source == "sim" or config.serial.backend in ("sim", "simavr")
        sim: SimHandles | None = None
        description: dict[str, str] = {}
        if uses_sim:
            renderer = renderer_from_config(config)
            world = renderer.world
            robot = SimRobot(world, robot_params(config), seed=config.sim.seed)
            robot.start()
            stack.callback(robot.close)
            sim = SimHandles(world, robot, None, None, world.start_pose)
            description["world"] = world.name

        camera: Camera
        calibration: FloorCalibration | None
        if cam_cfg.source == "sim":
            assert sim is not None
            sim_camera = SimCamera(renderer, lambda: sim.robot.pose, fps=cam_cfg.fps_hz)
            sim.camera = sim_camera
            camera = sim_camera
            calibration, problem = sim_floor_calibration(camera_model(config)), ""
            description["camera"] = (
                f"simulated {cam_cfg.width_px}x{cam_cfg.height_px} @ {cam_cfg.fps_hz:g} fps"
            )
        elif cam_cfg.source == "device":
            device: int | str = int(cam_cfg.device) if cam_cfg.device.isdigit() else cam_cfg.device
            camera = OpenCVCamera(
                device, width_px=cam_cfg.width_px, height_px=cam_cfg.height_px, fps=cam_cfg.fps_hz
            )
            calibration, problem = load_calibration(config)
            description["camera"] = f"webcam {cam_cfg.device}"
        else:
            camera = ReplayCamera(cam_cfg.device, fps=cam_cfg.fps_hz, loop=True)
            calibration, problem = load_calibration(config)
            description["camera"] = f"replay {cam_cfg.device}"
        stack.callback(camera.close)

        uno = stack.enter_context(open_uno(config.serial, sim.robot if sim is not None else None))
        if sim is not None:
            sim.uno = uno.simulated
        port = uno.port
        description["serial"] = uno.description
        timing = link_config(config.serial)
        yield Devices(
            camera=camera,
            port=port,
            make_link=lambda: UnoLink(port, config=timing),
            calibration=calibration,
            calibration_problem=problem,
            intrinsics=intrinsics,
            sim=sim,
            description=description,
        )
