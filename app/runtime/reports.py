"""What the daemon tells people: the live status (API, dashboard) and the run report
(``floornav run --report``). Both are JSON-ready dictionaries built from the stages'
published messages and counters; nothing here changes the run."""

from __future__ import annotations

import math
import os
import statistics
from typing import TYPE_CHECKING, Any

import numpy as np

from app.mapping.occupancy import fill_remembered
from app.runtime.service_status import service_status
from app.runtime.telemetry import newest, percentiles_ms

if TYPE_CHECKING:
    from app.runtime.core import Runtime


def status(rt: Runtime) -> dict[str, Any]:
    """A JSON-ready snapshot for the API and the dashboard."""
    shared = rt.shared
    now = rt.clock()
    floor, map_msg, drive = shared.floors.peek(), shared.maps.peek(), shared.drives.peek()
    stop = shared.protective_stop
    hold = shared.policy.holding(now)
    latched = shared.policy.latched
    link = shared.link
    pose = shared.odometry.pose
    frontier = rt.mapping.frontier
    recent = newest(rt.perception.frame_ages, 30)
    camera_status = rt.devices.camera.status()
    problems = rt.health.device_problems(now) if link is not None else {}
    device_problem = "; ".join(p for p in problems.values() if p) or None
    return {
        "state": rt.state.value,
        "autonomous": shared.autonomous,
        "exploration": exploration_status(rt),
        "estop": shared.mux.estop_reason,
        "fault": latched.reason if latched is not None else None,
        "devices_problem": device_problem,
        "teleop_driver": shared.mux.teleop_driver(now),
        "uptime_s": round(rt.elapsed_s(), 2),
        "fps": round(shared.counters.frames_perceived / rt.elapsed_s(), 2),
        "frame_age_ms": round((now - floor.capture_s) * 1000, 1) if floor else None,
        "pickup_age_ms": round(statistics.median(recent) * 1000, 2) if recent else None,
        "stage_ms": shared.stages.recent_ms(),
        # Percentiles refreshed once a second (50 lags), not on every poll.
        "loop_lag_ms": rt.loop_lag.summary_ms(reuse_within=50),
        "pose": {
            "x_m": round(pose.x_m, 3),
            "y_m": round(pose.y_m, 3),
            "theta_rad": round(pose.theta_rad, 3),
        },
        "distance_m": round(shared.odometry.distance_m, 3),
        "camera": {
            "state": camera_status.state.value,
            "detail": camera_status.detail,
            "ok": shared.camera_ok,
            "description": rt.devices.description.get("camera", ""),
        },
        "serial": {
            "state": link.state.value if link else "disconnected",
            "detail": link.status().detail if link else "",
            "port": rt.devices.port,
            "reconnects": link.stats.reconnects if link else 0,
            "crc_errors": link.stats.crc_errors if link else 0,
            "timeouts": link.stats.timeouts if link else 0,
        },
        "calibration": None
        if rt.calibration is None
        else {"reprojection_rms_px": rt.calibration.reprojection_rms_px},
        "calibration_problem": rt.calibration_problem or None,
        "command": None
        if drive is None
        else {
            "v_m_s": round(drive.twist.v_m_s, 3),
            "omega_rad_s": round(drive.twist.omega_rad_s, 3),
            "left_pwm": drive.left_pwm,
            "right_pwm": drive.right_pwm,
            "source": drive.source,
            "age_ms": round((now - drive.sent_s) * 1000, 1),
        },
        "frontier": None
        if frontier is None
        else {
            "goal_xy": list(frontier.goal.xy) if frontier.goal else None,
            "reason": frontier.reason,
            "clusters": len(frontier.clusters),
        },
        "clearance_ahead_m": round(map_msg.clearance_ahead_m, 3) if map_msg else None,
        "zone_floor_confidence": round(floor.zone_floor_confidence, 3) if floor else None,
        "zone_min_floor_confidence": shared.config.perception.zone_min_floor_confidence,
        "zone_known_floor": (
            round(map_msg.zone_known_floor, 3)
            if map_msg is not None and map_msg.zone_known_floor is not None
            else None
        ),
        "zone_min_known_floor": shared.config.perception.zone_min_known_floor,
        # What holds the robot back now: the drive stage's last gate, else a hold that
        # applies whatever the command (a device gone, a latched fault).
        "stop_cause": stop.cause if stop is not None else (hold.cause if hold else None),
        "stop_reason": stop.reason if stop is not None else (hold.reason if hold else None),
        "last_stop": shared.policy.last_stop.as_dict(now) if shared.policy.last_stop else None,
        "fault_latched": latched.as_dict(now) if latched is not None else None,
        "stops_by_cause": dict(shared.policy.stops_by_cause),
        "counters": dict(shared.counters.__dict__),
        "estops": shared.mux.estops,
        # The MQTT bridge (`app.bridges.mqtt`): connected / connecting / stopped, or off.
        "mqtt": service_status(rt, "mqtt") or {"state": "off"},
        "transitions": [
            {
                "t": round(t.wall_time, 3),
                "from": t.old.value,
                "to": t.new.value,
                "reason": t.reason,
            }
            for t in rt.transitions[-10:]
        ],
    }


def exploration_status(rt: Runtime) -> dict[str, Any]:
    """The exploration's phase (``exploring``, ``returning``, ``explored``), why, and
    the way home."""
    exploration = rt.mapping.exploration
    home = exploration.home_distance_m(rt.shared.odometry.pose)
    started = rt.shared.started_s
    at = exploration.explored_at_s
    return {
        "phase": exploration.phase.value,
        "reason": exploration.reason,
        "home_xy": list(exploration.home_xy) if exploration.home_xy is not None else None,
        "home_distance_m": round(home, 3) if home is not None else None,
        "explored_after_s": round(at - started, 1)
        if at is not None and started is not None
        else None,
    }


def report(rt: Runtime) -> dict[str, Any]:
    """The run report ``floornav run --report`` writes (sim-only fields null on
    hardware)."""
    from app.sim.truth import coverage_reachable, map_truth_scores, marks_near_truth

    shared = rt.shared
    counters = shared.counters
    elapsed = rt.elapsed_s()
    sim = rt.devices.sim
    mapper = shared.mapper
    truth: dict[str, float] | None = None
    truth_live: dict[str, float] | None = None
    reachable: float | None = None
    standing_near: float | None = None
    if sim is not None and mapper is not None and rt.devices.camera is sim.camera:
        # Scored: the map as the robot knows it, the one it explores, goes home and
        # saves on (faded evidence at its last class); `map_truth_live`: the evidence
        # alone, as travel has faded it.
        live = mapper.grid.classify()
        classes = fill_remembered(live.copy(), mapper.grid.remembered)
        near = marks_near_truth(
            mapper.memory.standing != 0, mapper.grid.world_grid, sim.T_plan_odom, sim.world
        )
        standing_near = round(near, 4) if near is not None else None
        truth = map_truth_scores(
            classes, mapper.grid.world_grid, sim.T_plan_odom, sim.world
        ).as_dict()
        truth_live = map_truth_scores(
            live, mapper.grid.world_grid, sim.T_plan_odom, sim.world
        ).as_dict()
        reachable = round(
            coverage_reachable(
                classes,
                mapper.grid.world_grid,
                sim.T_plan_odom,
                sim.world,
                shared.config.mapping.robot_radius_m,
            ),
            4,
        )
    pose = shared.odometry.pose
    link = shared.link
    policy = shared.policy
    now = rt.clock()
    return {
        "duration_s": round(elapsed, 2),
        "frames": counters.frames_perceived,
        "fps": round(counters.frames_perceived / elapsed, 2),
        "camera_frames": counters.frames_captured,
        "frames_mapped": counters.frames_mapped,
        "frames_skipped_by_capture": counters.frames_skipped,
        "bad_frames": counters.bad_frames,
        "latency_ms": percentiles_ms(rt.drive.latencies),
        "latency_from_arrival_ms": percentiles_ms(rt.drive.host_latencies),
        "frame_age_at_perception_ms": percentiles_ms(rt.perception.frame_ages),
        "floor_wait_for_mapping_ms": percentiles_ms(rt.mapping.floor_waits),
        "map_wait_for_steering_ms": percentiles_ms(rt.steering_stage.map_waits),
        "stage_ms": shared.stages.summary_ms(),
        "loop_lag_ms": rt.loop_lag.summary_ms(),
        "collisions": sim.robot.collisions if sim is not None else None,
        "collision_events": rt.collisions.events if sim is not None else None,
        "coverage_ratio": truth["coverage_ratio"] if truth else None,
        "coverage_reachable": reachable,
        "map_iou": truth["map_iou"] if truth else None,
        "map_truth": truth,
        "map_truth_live": truth_live,
        "pose_error_m": shared.pose_error.summary() if shared.pose_error is not None else None,
        "heading_error_deg": shared.pose_error.heading_summary_deg()
        if shared.pose_error is not None
        else None,
        "pose_error_track": [list(row) for row in shared.pose_error.track]
        if shared.pose_error is not None
        else None,
        "distance_m": round(shared.odometry.distance_m, 3),
        "home_distance_m": round(math.hypot(pose.x_m, pose.y_m), 3),
        "exploration": exploration_status(rt),
        "time_to_coverage_s": rt.coverage.clock.summary() if truth is not None else None,
        "world": sim.world.name if sim is not None else None,
        "seed": shared.config.sim.seed if sim is not None else None,
        "floor_memory": None
        if mapper is None
        else {
            "confirmed_m2": round(
                float(mapper.memory.confirmed.sum()) * mapper.grid.world_grid.cell_m**2, 2
            ),
            # Floor the robot's footprint covered (`FloorMemory.driven`; its track is
            # passable with the body's clearance).
            "driven_m2": round(
                float(np.count_nonzero(mapper.memory.driven)) * mapper.grid.world_grid.cell_m**2,
                2,
            ),
            "appearances": len(mapper.memory.appearances()),
            "unlearned": mapper.memory.unlearned,
            "standing_by_horizon_frames": mapper.standing_frames,
            "standing_m2": round(
                float(np.count_nonzero(mapper.memory.standing)) * mapper.grid.world_grid.cell_m**2,
                2,
            ),
            "standing_near_truth": standing_near,
            # Of it, what stands where its foot was seen (only that keeps an edge from
            # probes: `FloorMemory.standing_seen`).
            "standing_seen_m2": round(
                float(np.count_nonzero(mapper.memory.standing_seen()))
                * mapper.grid.world_grid.cell_m**2,
                2,
            ),
            "probe_edge_share": mapper.probe_edge_share(),
            "parallax_tests": mapper.parallax_frames,
            "parallax_unaligned": mapper.parallax_unaligned,
            "second_passes": counters.learned_floor_passes,
            "second_passes_adding_floor": counters.learned_floor_passes_adding,
            "second_pass_share": round(
                counters.learned_floor_passes / max(counters.frames_perceived, 1), 3
            ),
        },
        "floor_odometry": None
        if mapper is None or not mapper.floor_odometry
        else {"steps": mapper.floor_odometry_steps, "applied": mapper.floor_odometry_applied},
        "heading_axis": None
        if mapper is None or mapper.heading_axis is None
        else mapper.heading_axis.summary(),
        "scan_match": None
        if mapper is None or mapper.localizer is None
        else {"attempts": mapper.localizer.attempts, "applied": mapper.localizer.applied},
        "estops": shared.mux.estops,
        "faults": counters.faults,
        "fault_latched": policy.latched.as_dict(now) if policy.latched else None,
        "protective_stops": {
            cause: count
            for cause, count in policy.stops_by_cause.items()
            if cause in ("link", "camera", "stale")
        },
        "last_stop": policy.last_stop.as_dict(now) if policy.last_stop else None,
        "watchdog_stops": counters.watchdog_stops,
        "clearance_stops": counters.clearance_stops,
        "premise_stops": counters.premise_stops,
        "zone_known_floor_frames": counters.zone_known_floor_frames,
        "steering_decisions": dict(rt.steering_stage.reasons),
        "goals_given_up": rt.mapping.goals_given_up,
        "frontier_clusters_given_up": rt.mapping.clusters_given_up,
        "edge_probes_opened": rt.mapping.probes_opened,
        "commands_sent": counters.commands_sent,
        "send_errors": counters.send_errors,
        "serial": None
        if link is None
        else {
            "reconnects": link.stats.reconnects,
            "timeouts": link.stats.timeouts,
            "crc_errors": link.stats.crc_errors,
            # The Uno's own deadman cut the motors while the host was driving: DRIVEs
            # (or heartbeats) reached it more than 250 ms apart.
            "deadman_trips_seen": link.stats.deadman_trips_seen,
            "rtt_ms_p50": link.stats.rtt_median_ms(),
            # The kernel's tty layer, timed by the link's probe (recent bytes), and the
            # time the host could not listen, excused from silence and ACK timeouts.
            "tty_probe_ms_p50": _ms(link.tty_probe.latency_ms(50) if link.tty_probe else None),
            "tty_probe_ms_max": _ms(link.tty_probe.latency_ms(100) if link.tty_probe else None),
            "not_listening_s": round(link.stall_clock.stalled_s(), 3),
        },
        "uno_restarts": getattr(sim.uno, "restarts", None) if sim is not None else None,
        "rss_mb": rt.rss.summary(),
        "method": shared.config.perception.method,
        "final_state": rt.state.value,
        "shutdown_reason": rt.shutdown_reason or None,
        "crash": rt.crash,
        "final_motor_pwm": list(sim.uno.pwm) if sim is not None and sim.uno is not None else None,
        "pid": os.getpid(),
    }


def _ms(value: float | None) -> float | None:
    return None if value is None else round(value, 2)
