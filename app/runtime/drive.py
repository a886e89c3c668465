"""The drive stage and the host's stop layers in front of it.

Every ``drive.control_period_ms``, and at once on every new command, the drive stage
takes the mux's output (e-stop > teleop > autonomy), passes it through the `SafetyGate`
(protective stops and latched faults, a safe zone that is not floor, too little
clearance), rate-limits it and sends wheel PWM to the Uno. The firmware's deadman is
the layer below all of these."""

from __future__ import annotations

import dataclasses
import logging
import math

from app.channels import wait_event
from app.config import FloornavConfig, PerceptionConfig
from app.control.kinematics import RateLimiter, twist_to_pwm
from app.control.mux import MuxOutput, Twist
from app.hardware.interfaces import DeviceState
from app.hardware.serial_link import LinkError, NotConnectedError
from app.messages import DriveMsg, FloorMsg, MapMsg
from app.runtime.context import Shared
from app.runtime.stops import ProtectiveStop
from app.runtime.telemetry import FloatWindow

log = logging.getLogger("floornav.runtime")


def _ms_over(age_s: float) -> int:
    """An age that is over its limit, in whole ms rounded up: a map 500.4 ms old is
    shown as 501 against a 500 ms limit, never as "500 ms old (> 500 ms)"."""
    return math.ceil(age_s * 1000)


def zone_not_floor(shared: Shared, now: float) -> FloorMsg | None:
    """The newest floor result if the safe zone it shows blocks the way (`zone_blocks`)."""
    floor = shared.floors.peek()
    return floor if zone_blocks(shared.config, floor, shared.maps.peek(), now) else None


def zone_blocks(
    config: FloornavConfig, floor: FloorMsg | None, map_msg: MapMsg | None, now: float
) -> bool:
    """Whether the safe zone blocks the way: the floor result is fresh and its
    ``zone_floor_confidence`` is below ``perception.zone_min_floor_confidence``, and the
    fresh map does not know the zone's ground is floor (at least
    ``perception.zone_min_known_floor`` of it confirmed flat by parallax or driven
    over, nothing standing in it).

    Geometry over colour, as in the map: a threshold or a floor material the colour
    method doubts is not an obstacle where geometry has shown floor. An obstacle in the
    zone is seen standing, or hides the ground behind it (which is then not confirmed
    from here), so the map does not wave it through."""
    max_age_s = config.safety.perception_max_age_s
    if floor is None or floor.age_s(now) > max_age_s:
        return False
    fresh_map = map_msg is not None and map_msg.age_s(now) <= max_age_s
    known = map_msg.zone_known_floor if map_msg is not None and fresh_map else None
    return premise_broken(config.perception, floor.zone_floor_confidence, known)


def premise_broken(
    perception: PerceptionConfig, zone_floor_confidence: float, zone_known_floor: float | None
) -> bool:
    """Perception doubts the safe zone is floor (confidence below
    ``zone_min_floor_confidence``) and the map does not know it is (``zone_known_floor``,
    None for no map, below ``zone_min_known_floor``)."""
    if zone_floor_confidence >= perception.zone_min_floor_confidence:
        return False
    return zone_known_floor is None or zone_known_floor < perception.zone_min_known_floor


def without_forward_motion(out: MuxOutput) -> MuxOutput:
    """``out`` with its forward speed taken away (turning stays allowed)."""
    return dataclasses.replace(out, twist=Twist(0.0, out.twist.omega_rad_s))


class SafetyGate:
    """The host's stop layers on top of the mux. ``shared.protective_stop`` says which
    one holds the robot back after each call; `app.runtime.stops.StopPolicy` decides
    whether a cause is a protective stop or a latched fault."""

    def __init__(self, shared: Shared) -> None:
        self.shared = shared

    def staleness(self, now: float) -> str | None:
        """Why perception or the map is too old to drive on, or None."""
        shared = self.shared
        max_age_s = shared.config.safety.perception_max_age_s
        floor, map_msg = shared.floors.peek(), shared.maps.peek()
        if floor is None or map_msg is None:
            return "no perception or map yet"
        # Judged on capture times, so it trips before the mux's own timeout on the
        # (later) steering time would: the stop is counted as what it is.
        for what, age_s in (("perception", floor.age_s(now)), ("map", map_msg.age_s(now))):
            if age_s > max_age_s:
                return f"{what} {_ms_over(age_s)} ms old (> {max_age_s * 1000:.0f} ms)"
        return None

    def apply(self, out: MuxOutput, now: float) -> MuxOutput:
        shared = self.shared
        shared.protective_stop = None
        stale = self.staleness(now) if shared.autonomous else None
        event = shared.policy.observe("stale", stale, now)
        if event is not None:
            shared.counters.watchdog_stops += 1
            log.warning(
                "stale perception or map (%s): motors zero", stale, extra={"event": "watchdog_stop"}
            )
            shared.on_stop(event)
        if out.source == "autonomy" or (shared.autonomous and out.source == "timeout"):
            hold = shared.policy.holding(now)
            if hold is None and not shared.autonomous:
                hold = ProtectiveStop("idle", "autonomy is off: motors zero")
            if hold is not None:
                if hold.cause != "idle":
                    shared.protective_stop = hold
                return MuxOutput(Twist(), "watchdog", now, now)
        out = self._premise(out, now)
        return self._clearance(out, now)

    def _premise(self, out: MuxOutput, now: float) -> MuxOutput:
        """The thesis's premise: the safe zone right ahead is floor. When perception says
        it is not, the way ahead is blocked: no forward motion (turning stays allowed;
        steering turns to look elsewhere). It holds autonomy back, or any command that
        would move forward, and clears by itself when the zone is floor again."""
        shared = self.shared
        floor = zone_not_floor(shared, now)
        applies = floor is not None and (out.source == "autonomy" or out.twist.v_m_s > 0)
        minimum = shared.config.perception.zone_min_floor_confidence
        problem = None
        if applies and floor is not None:
            map_msg = shared.maps.peek()
            known = map_msg.zone_known_floor if map_msg is not None else None
            map_says = (
                f"; the map knows {known:.0%} of it"
                f" (< {shared.config.perception.zone_min_known_floor:.0%})"
                if known is not None
                else ""
            )
            problem = (
                f"safe zone is not floor (confidence {floor.zone_floor_confidence:.2f} < "
                f"{minimum:.2f}{map_says})"
            )
        event = shared.policy.observe("not_floor", problem, now)
        if problem is None:
            return out
        if event is not None:
            shared.counters.premise_stops += 1
            log.info(
                "%s: no forward motion",
                problem,
                extra={
                    "event": "premise_stop",
                    "zone_floor_confidence": round(floor.zone_floor_confidence, 3)
                    if floor is not None
                    else None,
                    "source": out.source,
                },
            )
        then = "turning to look elsewhere" if out.source == "autonomy" else "no forward motion"
        shared.protective_stop = ProtectiveStop("not_floor", f"{problem}: {then}")
        if out.twist.v_m_s <= 0:
            return out
        return without_forward_motion(out)

    def _clearance(self, out: MuxOutput, now: float) -> MuxOutput:
        shared = self.shared
        safety = shared.config.safety
        problem = None
        if out.twist.v_m_s > 0:
            # Forward motion needs a map fresh enough to say what is ahead, whoever
            # commands it: an operator driving on a stalled perception drives blind.
            map_msg = shared.maps.peek()
            if map_msg is None:
                problem = "clearance unknown: no map yet"
            elif map_msg.age_s(now) > safety.perception_max_age_s:
                problem = (
                    f"clearance unknown: map {_ms_over(map_msg.age_s(now))} ms old "
                    f"(> {safety.perception_max_age_s * 1000:.0f} ms)"
                )
            elif map_msg.clearance_ahead_m < safety.min_clearance_m:
                problem = (
                    f"clearance {map_msg.clearance_ahead_m:.2f} m ahead < "
                    f"{safety.min_clearance_m:.2f} m"
                )
        event = shared.policy.observe("clearance", problem, now)
        if problem is None:
            return out
        if event is not None:
            shared.counters.clearance_stops += 1
            log.debug("%s: no forward motion", problem, extra={"event": "clearance_stop"})
        shared.protective_stop = ProtectiveStop("clearance", f"{problem}: no forward motion")
        return without_forward_motion(out)


class DriveStage:
    """mux -> `SafetyGate` -> rate limiter -> wheel PWM on the Uno."""

    def __init__(self, shared: Shared, limiter: RateLimiter) -> None:
        self.shared = shared
        self.limiter = limiter
        self.gate = SafetyGate(shared)
        self.latencies = FloatWindow()
        """Capture-to-command latency of each new autonomy command (seconds)."""
        self.host_latencies = FloatWindow()
        """The same from the frame's arrival at the host (seconds): the host's part,
        without the camera's transfer (or the simulator's render)."""
        self.latencies_total = 0
        self._last_latency_origin = -1.0
        self._last_pwm: tuple[int, int] | None = None

    async def run(self) -> None:
        shared = self.shared
        link = shared.link
        assert link is not None
        while True:
            period = shared.config.drive.control_period_ms / 1000.0
            await wait_event(shared.wake_drive, period)
            shared.wake_drive.clear()
            start = shared.clock()
            out = self.gate.apply(shared.mux.output(start), start)
            twist = self.limiter(out.twist, start)
            pwm = twist_to_pwm(twist, shared.config.drive)
            new_autonomy = out.source == "autonomy" and out.origin_s != self._last_latency_origin
            if pwm == self._last_pwm and not new_autonomy:
                continue  # the link's heartbeat keeps repeating it
            if link.state is not DeviceState.CONNECTED:
                self._last_pwm = None
                continue
            try:
                if pwm == (0, 0) and out.source == "estop":
                    await link.stop_motors()
                else:
                    await link.drive(*pwm)
            except NotConnectedError:
                self._last_pwm = None
                continue
            except LinkError as exc:
                shared.counters.send_errors += 1
                log.warning("drive command failed: %s", exc, extra={"event": "send_error"})
                continue
            sent = shared.clock()
            self._last_pwm = pwm
            shared.counters.commands_sent += 1
            shared.stages.add("drive", sent - start)
            if new_autonomy:
                self._last_latency_origin = out.origin_s
                self.latencies.append(sent - out.origin_s)
                self.host_latencies.append(sent - out.arrival_s)
                self.latencies_total += 1
            decision = shared.decisions.peek()
            shared.drives.publish(
                DriveMsg(
                    twist,
                    pwm[0],
                    pwm[1],
                    out.source,
                    sent,
                    out.origin_s,
                    decision.heading_rad
                    if decision is not None and out.source == "autonomy"
                    else None,
                )
            )
