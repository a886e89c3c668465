"""The one typed configuration of floornav, loaded from ``config.toml``.

Every section is a strict pydantic model: unknown keys are rejected, every number has
bounds, and units are part of the field names (``_px``, ``_rad``, ``_frac``, ...). Any
value can be overridden from the environment as ``FLOORNAV_<SECTION>__<KEY>``, for example
``FLOORNAV_PERCEPTION__SMOOTHING_SIGMA_PX=3``. Precedence: explicit keyword arguments >
environment > ``config.toml`` > defaults here.
"""

from __future__ import annotations

import contextvars
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

DEFAULT_CONFIG_PATH = Path("config.toml")

FloorMethod = Literal["floornet", "thesis", "thesis_junction", "flood_fill", "floornav"]
"""Floor segmentation methods selectable by name (see ``app.perception.pipeline``)."""

Fraction = Annotated[float, Field(ge=0.0, le=1.0)]


class StrictModel(BaseModel):
    """Base of every config section: unknown keys are errors, values are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class SafeZoneConfig(StrictModel):
    """Trapezoid in front of the robot that is assumed to be floor.

    Corners are fractions of the image width (x) and height (y), origin top-left.
    The bottom edge spans ``bottom_left_x_frac..bottom_right_x_frac`` at ``bottom_y_frac``,
    the top edge ``top_left_x_frac..top_right_x_frac`` at ``top_y_frac``.
    """

    bottom_left_x_frac: Fraction = 0.25
    bottom_right_x_frac: Fraction = 0.75
    top_left_x_frac: Fraction = 0.40
    top_right_x_frac: Fraction = 0.60
    top_y_frac: Fraction = 0.80
    bottom_y_frac: Fraction = 1.0

    @model_validator(mode="after")
    def _check_shape(self) -> SafeZoneConfig:
        if not self.bottom_left_x_frac < self.bottom_right_x_frac:
            raise ValueError("bottom_left_x_frac must be smaller than bottom_right_x_frac")
        if not self.top_left_x_frac < self.top_right_x_frac:
            raise ValueError("top_left_x_frac must be smaller than top_right_x_frac")
        if not self.top_y_frac < self.bottom_y_frac:
            raise ValueError("top_y_frac must be smaller than bottom_y_frac (y grows downwards)")
        return self


class JunctionConfig(StrictModel):
    """Floor-junction masking (Canny, contours, probabilistic Hough lines)."""

    canny_low: Annotated[int, Field(ge=0, le=1000)] = 10
    canny_high: Annotated[int, Field(ge=1, le=1000)] = 30
    hough_threshold: Annotated[int, Field(ge=1, le=1000)] = 10
    min_line_length_frac: Annotated[float, Field(gt=0.0, le=1.0)] = 0.03
    max_line_gap_px: Annotated[int, Field(ge=0, le=200)] = 8
    vertical_tolerance_rad: Annotated[float, Field(ge=0.0, le=0.8)] = 0.2
    junction_radius_frac: Annotated[float, Field(gt=0.0, le=0.5)] = 0.05

    @model_validator(mode="after")
    def _check_canny(self) -> JunctionConfig:
        if self.canny_low > self.canny_high:
            raise ValueError("canny_low must not exceed canny_high")
        return self


class PerceptionConfig(StrictModel):
    """Floor segmentation from one camera frame (thesis chapters 2-5)."""

    method: FloorMethod = "floornet"
    smoothing_sigma_px: Annotated[float, Field(ge=0.0, le=20.0)] = 5.0
    color_space: Literal["lab", "rgb"] = "lab"
    slic_backend: Literal["numba", "skimage"] = "numba"
    n_superpixels: Annotated[int, Field(ge=4, le=5000)] = 200
    compactness: Annotated[float, Field(gt=0.0, le=100.0)] = 10.0
    slic_max_iter: Annotated[int, Field(ge=1, le=50)] = 10
    flood_fill_tolerance: Annotated[float, Field(gt=0.0, le=100.0)] = 18.0
    fill_gaps_px: Annotated[int, Field(ge=0, le=51)] = 0
    """Morphological closing of the floor mask with a disk this wide (0: off, as in the
    thesis). Closes seams between planks or tiles that a pixel method leaves as thin
    not-floor lines (the map would hold them as walls); obstacles wider than this stay."""
    floornet_model_path: str = ""
    """ONNX model of the ``floornet`` method; empty: the one shipped with floornav
    (``scripts/train_floor_net.py`` writes it)."""
    zone_min_floor_confidence: Fraction = 0.5
    """Below this ``zone_floor_confidence`` the safe zone is taken for an obstacle, not
    floor: the way ahead counts as blocked and the robot turns to look elsewhere."""
    zone_min_known_floor: Fraction = 0.6
    """...unless the map already knows at least this share of the zone's ground is floor
    (confirmed flat by motion parallax or driven over) and geometry sees nothing
    standing in the zone: a threshold or a new floor material the colour method doubts,
    where geometry has shown floor. 1.0: only a zone the map knows whole."""
    learned_floor_pass_period_s: Annotated[float, Field(ge=0.0, le=10.0)] = 1.0
    """The daemon runs ``floornet``'s second pass for a learned floor colour (a whole
    extra network run) at most this often; on the frames between, the map takes no
    evidence where the pass would have looked. 0: on every frame that needs one."""
    safe_zone: SafeZoneConfig = SafeZoneConfig()
    junction: JunctionConfig = JunctionConfig()


class CameraConfig(StrictModel):
    """The camera: expected frame size and its calibration file."""

    width_px: Annotated[int, Field(ge=64, le=4096)] = 640
    height_px: Annotated[int, Field(ge=48, le=4096)] = 480
    intrinsics_file: str = ""
    """``floornav calibrate intrinsics --out`` output (JSON, or OpenCV XML/YAML); empty:
    no lens model (the floor homography then applies to raw pixels)."""
    x_m: Annotated[float, Field(ge=-1.0, le=1.0)] = 0.10
    """Camera position in the robot frame (x forward); rays of the map start here."""
    y_m: Annotated[float, Field(ge=-1.0, le=1.0)] = 0.0
    source: Literal["sim", "device", "replay"] = "sim"
    """``sim``: rendered from the simulated robot's pose; ``device``: a webcam
    (``device``); ``replay``: a video, image folder or recording (``device`` is its path;
    a ``.mcap`` recording plays at its recorded timing, whatever ``fps_hz`` says)."""
    device: str = "0"
    """Webcam index (``0``) or path (``/dev/v4l/by-id/...``), or the replay source."""
    fps_hz: Annotated[float, Field(gt=0.0, le=240.0)] = 30.0


class MappingConfig(StrictModel):
    """Inverse perspective mapping, the occupancy grid and frontier search."""

    floor_calibration_file: str = "calibration/floor.json"
    """``floornav calibrate floor --out`` output: ``H_ground_from_image``."""
    birdseye_x_min_m: Annotated[float, Field(ge=0.0, le=2.0)] = 0.10
    birdseye_x_max_m: Annotated[float, Field(gt=0.0, le=10.0)] = 3.0
    birdseye_half_width_m: Annotated[float, Field(gt=0.0, le=5.0)] = 1.5
    birdseye_cell_m: Annotated[float, Field(ge=0.002, le=0.1)] = 0.01
    max_range_m: Annotated[float, Field(gt=0.0, le=20.0)] = 3.0
    """Floor farther than this is not trusted (pixels shrink with range)."""
    grid_size_m: Annotated[float, Field(ge=2.0, le=200.0)] = 20.0
    grid_cell_m: Annotated[float, Field(ge=0.01, le=0.5)] = 0.05
    log_odds_free: Annotated[float, Field(ge=-5.0, lt=0.0)] = -0.4
    log_odds_occupied: Annotated[float, Field(gt=0.0, le=5.0)] = 0.85
    log_odds_min: Annotated[float, Field(ge=-20.0, lt=0.0)] = -2.0
    log_odds_max: Annotated[float, Field(gt=0.0, le=20.0)] = 3.5
    free_threshold: Annotated[float, Field(ge=-20.0, le=0.0)] = -0.5
    """A cell is free below this log-odds (default: two floor sightings)."""
    occupied_threshold: Annotated[float, Field(ge=0.0, le=20.0)] = 0.5
    """A cell is occupied above this log-odds (default: one sighting; raise it when
    perception leaves speckles of false obstacles)."""
    obstacle_band_m: Annotated[float, Field(gt=0.0, le=0.5)] = 0.03
    free_evidence_range_m: Annotated[float, Field(gt=0.0, le=20.0)] = 2.0
    """Floor seen farther than this from the camera gives the map no free evidence."""
    obstacle_evidence_range_m: Annotated[float, Field(gt=0.0, le=20.0)] = 1.0
    """A floor boundary farther than this from the camera gives the map no occupied
    evidence: far away one image row spans centimetres of floor, so a far boundary is
    misplaced by cells and a far perception miss paints a wall across open floor (the
    robot looks again from closer before it gets there)."""
    far_boundary_margin_m: Annotated[float, Field(ge=0.0, le=2.0)] = 0.25
    """Floor within this of a boundary beyond ``obstacle_evidence_range_m`` gives no free
    evidence either: that boundary is misplaced by about one perception row (the
    network's output rows span about 0.22 m of floor at 2 m on the simulated camera), and
    free cells leaking past a wall the map does not hold yet are frontiers behind it."""
    evidence_half_distance_m: Annotated[float, Field(gt=0.0, le=10000.0)] = 10.0
    """Evidence halves per this much travel, never with time alone, so a standing robot
    keeps its map (10 m: what the old 30 s half-life gave at the 0.35 m/s cruise)."""
    evidence_turn_radius_m: Annotated[float, Field(ge=0.0, le=1.0)] = 0.10
    """Turning counts as travel at this radius: half the wheel base, the distance each
    wheel rolls in a spin turn (heading drift stales a map as much as distance does)."""
    frontier_min_cells: Annotated[int, Field(ge=1, le=10000)] = 10
    frontier_size_penalty_m: Annotated[float, Field(ge=0.0, le=100.0)] = 0.0
    """Trades path length for larger frontiers (see ``app.mapping.frontiers``)."""
    frontier_turn_penalty_m_per_rad: Annotated[float, Field(ge=0.0, le=10.0)] = 0.3
    """Adds this much to a frontier's path length per radian it lies off the heading."""
    frontier_exclude_radius_m: Annotated[float, Field(ge=0.0, le=5.0)] = 0.5
    """Frontiers this close to the robot are ignored (the camera cannot see beside it)."""
    frontier_probe_edges: bool = True
    """With no reachable frontier left, drive up to an edge of the floor that geometry
    has not seen standing (a rug, a threshold) so the parallax test can look at it
    (`app.mapping.frontiers`); exploration finishes when no such edge is left."""
    robot_radius_m: Annotated[float, Field(gt=0.0, le=2.0)] = 0.12
    inflation_radius_m: Annotated[float, Field(ge=0.0, le=2.0)] = 0.15
    """Paths keep the robot's centre at least this far from occupied cells' centres."""
    path_clearance_preferred_m: Annotated[float, Field(ge=0.0, le=3.0)] = 0.30
    """Paths prefer to keep the centre this far from obstacles (the robot's side 0.18 m
    clear); closer costs more, up to ``path_clearance_cost`` (`app.mapping.frontiers`)."""
    path_clearance_cost: Annotated[float, Field(ge=0.0, le=20.0)] = 1.0
    """A move at ``inflation_radius_m`` costs 1 + this times its length (0: shortest paths,
    which graze every obstacle at the inflation radius)."""
    parallax_floor: bool = True
    """Motion parallax between two frames (`app.perception.planar`, ~2-3 ms nogil per
    tested frame, at most 5 a second): floor it finds flat joins the map's confirmed
    floor (`app.mapping.floor_memory`), where colour edges are no walls, and what it
    finds standing is an obstacle whatever its colour. Needs frames without lens
    distortion (off when ``camera.intrinsics_file`` is set)."""
    parallax_baseline_m: Annotated[float, Field(ge=0.03, le=0.5)] = 0.12
    """Camera travel between the two frames compared (nearest stored view is used)."""
    parallax_max_turn_rad: Annotated[float, Field(ge=0.0, le=1.0)] = 0.2
    standing_by_horizon: bool = True
    """Floor never appears above the camera's horizon: where the floor mask runs up a
    column past it, the upper part of that run, down to where its colour changes, is a
    surface standing up (a floor-coloured box or cupboard taller than the camera) and an
    obstacle (`app.perception.standing`; ~4 ms on the frames it fires on, nothing on the
    others). Needs no motion, unlike the parallax test."""
    floor_odometry: bool = True
    """Visual odometry on the floor (`GroundMapper`): each time the camera has moved
    ``floor_odometry_step_m`` or turned ``floor_odometry_step_rad`` since the last key
    frame, the two views' floors are lined up pixel for pixel
    (`app.perception.planar.refine_reference_pose`, ~3-5 ms, nogil) and the pose takes
    the motion the floor shows instead of the wheels' (which slip, most in spin turns).
    On a floor without texture the wheels carry on alone. Needs frames without lens
    distortion, like the parallax test."""
    floor_odometry_step_m: Annotated[float, Field(ge=0.01, le=0.3)] = 0.05
    floor_odometry_step_rad: Annotated[float, Field(ge=0.01, le=0.5)] = 0.1
    scan_matching: bool = False
    """Localize against the map (`app.mapping.scan_match`): wheel odometry drifts (slip,
    tyre scale), and a map fused at drifting poses smears. Off by default: on the same
    scripted tours it left the pose further from the truth than odometry alone
    (`scripts/measure_localization.py`, docs/measurements/localization.json). Every
    ``scan_match_period_s`` the frame's floor boundary, read as a range scan, is matched
    against the map's obstacles around the odometry pose (~2-3 ms, nogil); a confident
    match moves odometry ``scan_match_gain_frac`` of the way (at most
    ``scan_match_max_step_m`` / ``scan_match_max_step_rad`` per match)."""
    scan_match_period_s: Annotated[float, Field(ge=0.05, le=10.0)] = 0.25
    scan_match_window_m: Annotated[float, Field(ge=0.02, le=0.5)] = 0.15
    """The match searches the odometry pose +- this in x and y..."""
    scan_match_window_rad: Annotated[float, Field(ge=0.01, le=0.5)] = 0.105
    """...and +- this in heading (6 degrees): more drift than a period's worth."""
    scan_match_gain_frac: Annotated[float, Field(gt=0.0, le=1.0)] = 0.5
    """Fraction of a match's offset applied: the next matches finish the move, so one
    wrong match moves the pose only part of the way."""
    scan_match_max_step_m: Annotated[float, Field(gt=0.0, le=0.2)] = 0.03
    scan_match_max_step_rad: Annotated[float, Field(gt=0.0, le=0.2)] = 0.02
    manhattan_heading: bool = True
    """Hold the heading to the building's axis (`app.mapping.manhattan`): walls and the
    furniture along them meet the floor in straight lines along two square directions;
    the first seen fix the axis, and where floor odometry missed its last step, each
    frame with such a line near the axis corrects the heading by a small Kalman filter
    (a line's noise ``manhattan_line_sigma_rad``, odometry's drift about a degree a
    metre). Odometry's heading drift (a degree a second with unequal tyres, uncorrected
    by floor odometry on a floor without texture) would otherwise smear the map. Lines
    further than ``manhattan_gate_rad`` off the axis are never used: in a building that
    is not rectilinear it does nothing. ~2-6 ms a frame (Canny, Hough; OpenCV, nogil),
    off the motors' path, only while the axis is learned or floor odometry misses (where
    it holds, it holds the heading better)."""
    manhattan_gate_rad: Annotated[float, Field(gt=0.0, le=0.3)] = 0.105
    manhattan_line_sigma_rad: Annotated[float, Field(gt=0.0, le=0.2)] = 0.026

    @model_validator(mode="after")
    def _check_extent(self) -> MappingConfig:
        if self.birdseye_x_min_m >= self.birdseye_x_max_m:
            raise ValueError("birdseye_x_min_m must be smaller than birdseye_x_max_m")
        if self.birdseye_cell_m > self.grid_cell_m:
            raise ValueError("birdseye_cell_m must not exceed grid_cell_m")
        if (
            not self.log_odds_min
            <= self.free_threshold
            <= self.occupied_threshold
            <= self.log_odds_max
        ):
            raise ValueError(
                "need log_odds_min <= free_threshold <= occupied_threshold <= log_odds_max"
            )
        return self


class SimConfig(StrictModel):
    """The simulated world (used when the camera or the Uno is simulated)."""

    world_file: str = ""
    """The world: a shipped world's name (``two-rooms``, ``home``, ``office``; their files
    are ``app/sim/worlds/NAME.toml``, which also show the format) or the path of a world
    TOML file (ending in ``.toml`` or holding a ``/``); empty: the default world,
    ``two-rooms`` (also called ``default``). ``floornav run --world`` sets it."""
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    """Seed of the simulator's random draws (the simulated camera's sensor noise): a run
    with the same world, seed and config renders the same frames. ``floornav run
    --seed`` sets it; the run report reads it here."""
    camera_height_m: Annotated[float, Field(gt=0.02, le=2.0)] = 0.22
    camera_pitch_rad: Annotated[float, Field(ge=-0.2, le=1.4)] = 0.40
    """Downward tilt of the simulated camera."""
    focal_px: Annotated[float, Field(ge=50.0, le=5000.0)] = 500.0
    noise_sigma: Annotated[float, Field(ge=0.0, le=50.0)] = 2.0
    """Sensor noise of the simulated camera in 8-bit levels."""
    wheel_scale_sigma_frac: Annotated[float, Field(ge=0.0, le=0.1)] = 0.005
    """Std of each simulated wheel's ground travel per encoder-counted rotation, drawn
    once per run from ``seed`` (tyre radius, load): the residual of a calibrated robot,
    which makes wheel odometry drift systematically. 0: the wheels roll exactly."""
    slip_sigma_frac: Annotated[float, Field(ge=0.0, le=0.5)] = 0.03
    """Std of the simulated wheels' slip in a spin turn or a hard acceleration (a
    fraction of the travel, correlated over ~0.3 s; a fifth of it rolling straight).
    0: no slip (`app.sim.robot`)."""
    encoder_tick_noise: Annotated[float, Field(ge=0.0, le=5.0)] = 0.0
    """Std of the count error each simulated encoder tick adds (ticks; it accumulates
    like lost or double counts). 0: exact counts."""

    @field_validator("world_file")
    @classmethod
    def _known_world(cls, value: str) -> str:
        """A bare name must be a shipped world: a typo fails here, naming the worlds,
        not when the daemon starts (paths are read then, as every path of the config)."""
        from app.sim.worlds import UnknownWorldError, resolve_world_path

        try:
            resolve_world_path(value)
        except UnknownWorldError as exc:
            raise ValueError(str(exc)) from None
        return value


class SerialConfig(StrictModel):
    """The link to the Uno (``docs/protocol.md``); numbers map to
    `app.hardware.serial_link.UnoLinkConfig`, whose docstrings give the reasons."""

    backend: Literal["sim", "simavr", "port"] = "sim"
    """``sim``: the pure-Python simulated Uno on a pty (default, fast); ``simavr``: the
    real firmware run in simavr by ``firmware/sim/harness``; ``port``: a real Uno."""
    port: str = "/dev/serial/by-id/usb-Arduino__www.arduino.cc__0043-if00"
    """Used with ``backend = "port"``; prefer a stable /dev/serial/by-id/ path."""
    handshake_timeout_s: Annotated[float, Field(gt=0.0, le=30.0)] = 3.0
    ack_timeout_ms: Annotated[float, Field(gt=0.0, le=1000.0)] = 100.0
    heartbeat_period_ms: Annotated[float, Field(ge=20.0, le=200.0)] = 100.0
    """Must stay well below the firmware's 250 ms deadman."""
    telemetry_period_ms: Annotated[int, Field(ge=20, le=1000)] = 50
    silence_timeout_ms: Annotated[float, Field(ge=50.0, le=5000.0)] = 200.0
    backoff_initial_s: Annotated[float, Field(gt=0.0, le=10.0)] = 0.1
    backoff_max_s: Annotated[float, Field(gt=0.0, le=60.0)] = 2.0

    @model_validator(mode="after")
    def _check_timing(self) -> SerialConfig:
        if self.silence_timeout_ms <= self.telemetry_period_ms:
            raise ValueError("silence_timeout_ms must exceed telemetry_period_ms")
        if self.backoff_max_s < self.backoff_initial_s:
            raise ValueError("backoff_max_s must not be below backoff_initial_s")
        return self


class DriveConfig(StrictModel):
    """The differential drive: geometry (for odometry and kinematics), the motors' PWM
    response and the limits every command is held to."""

    wheel_base_m: Annotated[float, Field(gt=0.02, le=2.0)] = 0.20
    wheel_radius_m: Annotated[float, Field(gt=0.005, le=0.5)] = 0.033
    ticks_per_rev: Annotated[int, Field(ge=1, le=100000)] = 360
    """Encoder counts per wheel revolution (both edges of both channels)."""
    max_wheel_speed_m_s: Annotated[float, Field(gt=0.0, le=5.0)] = 0.5
    """Wheel surface speed at PWM 255 (measure it: drive at 255, read the encoders)."""
    pwm_deadband: Annotated[int, Field(ge=0, le=200)] = 30
    """PWM at or below which the wheels do not turn; commands start just above it."""
    max_linear_speed_m_s: Annotated[float, Field(gt=0.0, le=2.0, validate_default=True)] = 0.35
    """At most ``max_wheel_speed_m_s``: faster than its wheels no robot goes."""
    max_angular_speed_rad_s: Annotated[float, Field(gt=0.0, le=10.0, validate_default=True)] = 1.5
    """At most ``2 * max_wheel_speed_m_s / wheel_base_m`` (both wheels at full speed,
    opposite ways)."""
    max_linear_accel_m_s2: Annotated[float, Field(gt=0.0, le=20.0)] = 1.0
    max_angular_accel_rad_s2: Annotated[float, Field(gt=0.0, le=50.0)] = 5.0
    control_period_ms: Annotated[float, Field(ge=5.0, le=100.0)] = 20.0
    """How often the command mux is evaluated (timeouts, ramps); new perception results
    are sent at once, without waiting for the tick."""

    @field_validator("max_linear_speed_m_s")
    @classmethod
    def _linear_within_the_wheels(cls, value: float, info: ValidationInfo) -> float:
        wheel = info.data.get("max_wheel_speed_m_s")
        if wheel is not None and value > wheel:
            raise ValueError(
                f"{value:g} exceeds drive.max_wheel_speed_m_s {wheel:g} (the wheels' top speed)"
            )
        return value

    @field_validator("max_angular_speed_rad_s")
    @classmethod
    def _angular_within_the_wheels(cls, value: float, info: ValidationInfo) -> float:
        wheel, base = info.data.get("max_wheel_speed_m_s"), info.data.get("wheel_base_m")
        if wheel is not None and base is not None and value > 2.0 * wheel / base:
            raise ValueError(
                f"{value:g} exceeds 2 * drive.max_wheel_speed_m_s / drive.wheel_base_m = "
                f"{2.0 * wheel / base:g} rad/s (the wheels' top speed, opposite ways)"
            )
        return value


class SteeringConfig(StrictModel):
    """Choosing the window of advancement (heading and speed) from the map."""

    cruise_speed_m_s: Annotated[float, Field(gt=0.0, le=2.0)] = 0.35
    turn_speed_rad_s: Annotated[float, Field(gt=0.0, le=10.0)] = 1.5
    heading_gain_per_s: Annotated[float, Field(gt=0.0, le=20.0)] = 2.0
    """Angular speed per radian of heading error."""
    turn_in_place_rad: Annotated[float, Field(gt=0.0, le=3.2)] = 0.7
    """Heading errors above this turn in place instead of driving an arc."""
    min_advance_m: Annotated[float, Field(gt=0.0, le=5.0)] = 0.35
    """A direction is open when this much free floor lies along it."""
    slow_down_m: Annotated[float, Field(gt=0.0, le=5.0)] = 0.5
    """Speed falls linearly as the free range ahead shrinks from this to the clearance."""
    lookahead_m: Annotated[float, Field(gt=0.0, le=5.0)] = 0.6
    """Aim at the frontier path this far ahead."""
    window_margin_rad: Annotated[float, Field(ge=0.0, le=1.0)] = 0.15
    """Keep the heading this far inside an open window's edges."""
    smoothing: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.4
    """Exponential smoothing of successive commands (0: none)."""
    frontier_period_s: Annotated[float, Field(gt=0.0, le=10.0)] = 0.5
    goal_patience_s: Annotated[float, Field(gt=0.0, le=600.0)] = 8.0
    """A goal the robot has come no closer to (by path) for this long is given up: it
    cannot be seen from anywhere the robot can go (`app.runtime.exploration.GoalPatience`)."""
    local_window_m: Annotated[float, Field(ge=1.0, le=20.0)] = 6.0
    """Side of the map window around the robot that steering looks at."""
    explored_after_s: Annotated[float, Field(ge=0.0, le=600.0)] = 10.0
    """No reachable frontier for this long finishes exploring (`app.runtime.exploration`):
    the robot returns to its start, stops (state ``explored``) and the map is saved."""
    return_home: bool = True
    """After exploring, drive back to where autonomy started (else stop where it is)."""
    home_tolerance_m: Annotated[float, Field(gt=0.0, le=2.0)] = 0.3
    """Back home means this close to the start."""
    return_timeout_s: Annotated[float, Field(gt=0.0, le=3600.0)] = 180.0
    """Not home after this long: finish where the robot is."""


class SafetyConfig(StrictModel):
    """The host's stop layers (the firmware's deadman is the last one)."""

    perception_max_age_s: Annotated[float, Field(gt=0.0, le=5.0)] = 0.5
    """Autonomy stops when the newest floor result is older than this."""
    camera_max_age_s: Annotated[float, Field(gt=0.0, le=5.0)] = 0.5
    """A camera without a frame this recent counts as gone."""
    teleop_timeout_s: Annotated[float, Field(gt=0.0, le=5.0)] = 0.5
    autonomy_timeout_s: Annotated[float, Field(gt=0.0, le=5.0)] = 0.5
    min_clearance_floor_m: Annotated[float, Field(ge=0.0, le=3.0)] = 0.10
    """The least ``min_clearance_m`` may be. Only config.toml sets it (it is not a live
    key), so nobody on the network can turn the clearance stop off."""
    min_clearance_m: Annotated[float, Field(ge=0.0, le=3.0, validate_default=True)] = 0.20
    """Free floor needed ahead of the robot's front edge to move forward; at least
    ``min_clearance_floor_m`` (checked also when only the floor is set)."""
    auto_resume: bool = True
    """After a protective stop (Uno link blip, camera gap, stale perception) autonomy
    resumes by itself once the cause has been clear for ``resume_after_clear_s``;
    otherwise it waits for ``POST /api/start``."""
    resume_after_clear_s: Annotated[float, Field(ge=0.0, le=60.0)] = 1.0
    fault_latch_repeats: Annotated[int, Field(ge=1, le=100)] = 3
    """This many protective stops of one device cause within ``fault_latch_window_s``
    latch a fault that needs the operator (``POST /api/fault/reset``)."""
    fault_latch_window_s: Annotated[float, Field(gt=0.0, le=3600.0)] = 60.0
    device_lost_latch_s: Annotated[float, Field(gt=0.0, le=600.0)] = 5.0
    """A camera or Uno gone for longer than this latches a fault."""

    @field_validator("min_clearance_m")
    @classmethod
    def _clearance_above_floor(cls, value: float, info: ValidationInfo) -> float:
        floor = info.data.get("min_clearance_floor_m")
        if floor is not None and value < floor:
            raise ValueError(
                f"{value:g} is below safety.min_clearance_floor_m {floor:g} (the floor is "
                "set in config.toml only)"
            )
        return value


class RuntimeConfig(StrictModel):
    """The daemon."""

    autostart: Literal["never", "simulator", "always"] = "simulator"
    """When to start exploring without being told: ``simulator`` only when the Uno is
    simulated (``serial.backend`` ``sim`` or ``simavr``), so a real robot never drives
    before someone presses start; ``always`` also on a real robot; ``never``: wait for
    ``POST /api/start``. ``true`` / ``false`` mean ``always`` / ``never``."""
    log_json: bool = False
    """One JSON object per log line instead of text."""

    @field_validator("autostart", mode="before")
    @classmethod
    def _autostart_from_bool(cls, value: object) -> object:
        if isinstance(value, bool):
            return "always" if value else "never"
        return value

    log_level: Literal["debug", "info", "warning", "error"] = "info"
    explored_map_file: str = "explored-map.npz"
    """Where the map is saved when exploration finishes, unless ``floornav run --map``
    names a file (a relative path is taken from the working directory)."""


WEB_TOKEN_PATTERN = r"^([A-Za-z0-9._~-]{16,})?$"
"""A bearer token: empty, or 16+ characters that are also valid in a WebSocket
subprotocol (browsers send it there, see ``app/web/auth.py``)."""


class WebConfig(StrictModel):
    """The HTTP API and dashboard."""

    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=1, le=65535)] = 8080
    token: Annotated[str, Field(pattern=WEB_TOKEN_PATTERN)] = ""
    """Bearer token for every state-changing request; empty: the ``FLOORNAV_TOKEN``
    environment variable, else ``token_file`` (generated on first start)."""
    token_file: str = "~/.config/floornav/token"
    require_token_for_status: bool = False
    """Also require the token for status, config, metrics and the video and telemetry
    sockets (otherwise anyone who can reach the port may watch)."""
    allowed_origins: list[str] = []
    """Browser origins (``http://host:port``) allowed to open WebSockets besides the
    server's own."""
    telemetry_hz: Annotated[float, Field(ge=1.0, le=30.0)] = 10.0
    jpeg_quality: Annotated[int, Field(ge=10, le=95)] = 70


class ViserConfig(StrictModel):
    """The viser 3D view (its own server, bound to localhost, proxied under /viser)."""

    enabled: bool = True
    port: Annotated[int, Field(ge=1, le=65535)] = 8081


MQTT_ID_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
"""A robot id: one MQTT topic level that is also a Home Assistant object id."""


def _default_robot_id() -> str:
    """The host's name (up to its first dot, other characters turned to ``-``), else
    ``floornav``."""
    import re
    import socket

    name = re.sub(r"[^A-Za-z0-9_-]", "-", socket.gethostname().split(".")[0])[:64]
    return name if re.fullmatch(MQTT_ID_PATTERN, name) else "floornav"


class MqttConfig(StrictModel):
    """The MQTT bridge (`app.bridges.mqtt`): state, telemetry and the map out, commands
    in, under ``<topic_prefix>/<robot_id>/``."""

    url: str | None = None
    """The broker, ``mqtt://host[:1883]`` or ``mqtts://host[:8883]`` (TLS); None: the
    bridge is off."""
    robot_id: Annotated[str, Field(pattern=MQTT_ID_PATTERN)] = Field(
        default_factory=_default_robot_id
    )
    """This robot's topic level (letters, digits, ``_``, ``-``); default: the host name."""
    username: str = ""
    """Empty: connect without a user name."""
    password_file: str = ""
    """File whose first line is the password (``~`` expanded); empty: no password."""
    ca_file: str = ""
    """CA certificates (PEM) that signed an ``mqtts`` broker's certificate; empty: the
    system's."""
    topic_prefix: Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]+(/[A-Za-z0-9_-]+)*$")] = "floornav"
    homeassistant: bool = False
    """Publish Home Assistant MQTT discovery messages (a state sensor, a stop button)."""
    homeassistant_prefix: Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]+$")] = "homeassistant"
    homeassistant_start_token: bool = False
    """Also a start button; its retained discovery message then carries the token, so
    let only Home Assistant read ``<homeassistant_prefix>/#`` (broker ACL)."""
    telemetry_period_s: Annotated[float, Field(ge=0.1, le=60.0)] = 0.5
    map_period_s: Annotated[float, Field(ge=1.0, le=600.0)] = 5.0
    """The map PNG is published at most this often, and only when it changed."""
    keepalive_s: Annotated[int, Field(ge=5, le=600)] = 15
    """The broker publishes the last will ``offline`` 1.5x this after the robot vanishes
    without closing its connection (a process killed outright goes at once)."""
    reconnect_min_s: Annotated[float, Field(gt=0.0, le=60.0)] = 0.5
    reconnect_max_s: Annotated[float, Field(gt=0.0, le=300.0)] = 5.0
    """Reconnect backoff doubles from min to max; each wait is 50-90 % of it, so a
    broker that comes back is reached within ``reconnect_max_s``."""

    @field_validator("url")
    @classmethod
    def _check_url(cls, value: str | None) -> str | None:
        if value is None or value == "":
            return None
        from urllib.parse import urlsplit

        try:
            parts = urlsplit(value)
            parts.port  # noqa: B018 (raises for a bad port)
        except ValueError as exc:
            raise ValueError(f"not a URL: {exc}") from None
        if parts.scheme not in ("mqtt", "mqtts"):
            raise ValueError("the scheme must be mqtt:// or mqtts:// (TLS)")
        if not parts.hostname:
            raise ValueError("the URL needs a host")
        if parts.username is not None or parts.password is not None:
            raise ValueError("put the user in mqtt.username and the password in a file")
        if parts.path not in ("", "/") or parts.query or parts.fragment:
            raise ValueError("the URL has only scheme, host and port")
        return value

    @model_validator(mode="after")
    def _check_backoff(self) -> MqttConfig:
        if self.reconnect_max_s < self.reconnect_min_s:
            raise ValueError("reconnect_max_s must not be below reconnect_min_s")
        return self

    def broker(self) -> tuple[str, int, bool] | None:
        """``(host, port, tls)`` of ``url``, or None when the bridge is off."""
        if self.url is None:
            return None
        from urllib.parse import urlsplit

        parts = urlsplit(self.url)
        tls = parts.scheme == "mqtts"
        return parts.hostname or "", parts.port or (8883 if tls else 1883), tls


class FoxgloveConfig(StrictModel):
    """The Foxglove live view (`app.bridges.foxglove_view`): camera, map, transforms,
    scene and logs for the Foxglove app over its WebSocket protocol. Read-only: it offers
    clients nothing that changes the robot."""

    port: Annotated[int, Field(ge=1, le=65535)] | None = None
    """The view's WebSocket port (Foxglove's own default is 8765); None: the view is off."""
    host: str = "127.0.0.1"
    """Bound like the dashboard (``[web] host``): the default keeps it on this machine,
    ``0.0.0.0`` shows the camera to anyone who reaches the port (the Foxglove protocol
    has no token: it cannot change the robot, but the camera is not private then)."""
    image_period_s: Annotated[float, Field(ge=0.1, le=10.0)] = 0.2
    """The camera with the floor overlay (JPEG at ``[web] jpeg_quality``) at most this
    often, 10 Hz at most. Each image costs ~2 ms of CPU (overlay ~1.6, JPEG ~0.5 on a
    640x480 frame): 5 Hz keeps the whole view under 5 % of the daemon's CPU per frame
    with a client watching, 10 Hz (0.1) costs ~7 %. Transforms go at 10 Hz anyway."""
    map_period_s: Annotated[float, Field(ge=0.2, le=600.0)] = 1.0
    """The occupancy grid at most this often, when it changed (or a client subscribed)."""


_toml_path: contextvars.ContextVar[Path | None] = contextvars.ContextVar(
    "floornav_config_path", default=None
)


class FloornavConfig(BaseSettings):
    """Root of the configuration tree (one section per subsystem)."""

    model_config = SettingsConfigDict(
        extra="forbid",
        frozen=True,
        env_prefix="FLOORNAV_",
        env_nested_delimiter="__",
        case_sensitive=False,
    )

    perception: PerceptionConfig = PerceptionConfig()
    camera: CameraConfig = CameraConfig()
    mapping: MappingConfig = MappingConfig()
    serial: SerialConfig = SerialConfig()
    sim: SimConfig = SimConfig()
    drive: DriveConfig = DriveConfig()
    steering: SteeringConfig = SteeringConfig()
    safety: SafetyConfig = SafetyConfig()
    runtime: RuntimeConfig = RuntimeConfig()
    web: WebConfig = WebConfig()
    viser: ViserConfig = ViserConfig()
    mqtt: MqttConfig = MqttConfig()
    foxglove: FoxgloveConfig = FoxgloveConfig()

    def autostarts(self) -> bool:
        """True if the daemon starts exploring on its own (`RuntimeConfig.autostart`)."""
        mode = self.runtime.autostart
        return mode == "always" or (mode == "simulator" and self.serial.backend != "port")

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        path = _toml_path.get()
        sources: list[PydanticBaseSettingsSource] = [init_settings, env_settings]
        if path is not None:
            sources.append(TomlConfigSettingsSource(settings_cls, toml_file=path))
        return tuple(sources)


@dataclass(frozen=True)
class ConfigIssue:
    """One validation problem, with the dotted key path it belongs to."""

    key: str
    message: str

    def __str__(self) -> str:
        return f"{self.key}: {self.message}"


class ConfigError(Exception):
    """The configuration could not be loaded; ``issues`` names every bad key."""

    def __init__(self, source: str, issues: list[ConfigIssue]) -> None:
        self.source = source
        self.issues = issues
        lines = "\n".join(f"  {issue}" for issue in issues)
        super().__init__(f"invalid configuration in {source}:\n{lines}")


def _issues_from_validation(error: ValidationError) -> list[ConfigIssue]:
    issues = []
    for item in error.errors():
        key = ".".join(str(part) for part in item["loc"]) or "<root>"
        message = item["msg"]
        if key == "<root>":
            issues.append(ConfigIssue(key=key, message=message))
            continue
        if item["type"] not in ("extra_forbidden", "missing") and "input" in item:
            message = f"{message} (got {item['input']!r})"
        issues.append(ConfigIssue(key=key, message=message))
    return issues


def load_config(path: Path | None = DEFAULT_CONFIG_PATH, **overrides: Any) -> FloornavConfig:
    """Load and validate the configuration.

    Parameters
    ----------
    path : Path or None
        TOML file to read. ``None`` uses the built-in defaults plus the environment.
    **overrides
        Section values that take precedence over everything (used by tests and the CLI).

    Raises
    ------
    ConfigError
        The file is missing or not valid TOML, or a value is out of bounds or unknown;
        each issue names its dotted key path (``perception.safe_zone.top_y_frac``).
    """
    source = str(path) if path is not None else "<defaults>"
    if path is not None:
        if not path.is_file():
            raise ConfigError(source, [ConfigIssue("<file>", "file not found")])
        try:
            with path.open("rb") as handle:
                tomllib.load(handle)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(source, [ConfigIssue("<file>", f"not valid TOML: {exc}")]) from exc
    token = _toml_path.set(path)
    try:
        return FloornavConfig(**overrides)
    except ValidationError as exc:
        raise ConfigError(source, _issues_from_validation(exc)) from exc
    finally:
        _toml_path.reset(token)
