"""The command mux: priorities, timeouts with an explicit zero, latched e-stop, one
teleop driver at a time."""

import math

import pytest

from app.control.mux import ZERO, CommandMux, TeleopRefusedError, Twist

FWD = Twist(0.2, 0.0)
TURN = Twist(0.0, 1.0)


def make() -> CommandMux:
    return CommandMux(teleop_timeout_s=0.5, autonomy_timeout_s=0.5)


def test_idle_without_input_is_zero() -> None:
    out = make().output(0.0)
    assert out.twist == ZERO and out.source == "idle"


def test_autonomy_drives_with_its_capture_time() -> None:
    mux = make()
    mux.autonomy(FWD, 10.0, origin_s=9.98)
    out = mux.output(10.01)
    assert (out.twist, out.source, out.origin_s) == (FWD, "autonomy", 9.98)
    assert out.arrival_s == 9.98  # no arrival given: the capture


def test_autonomy_carries_when_the_host_had_its_frame() -> None:
    mux = make()
    mux.autonomy(FWD, 10.0, origin_s=9.95, arrived_s=9.97)
    out = mux.output(10.01)
    assert (out.origin_s, out.arrival_s) == (9.95, 9.97)
    teleop = make()
    teleop.teleop("alice", FWD, 10.0)
    assert teleop.output(10.01).arrival_s == 10.0


def test_teleop_overrides_autonomy_then_autonomy_resumes_after_timeout() -> None:
    mux = make()
    mux.autonomy(FWD, 0.0)
    mux.teleop("alice", TURN, 0.1)
    assert mux.output(0.2).source == "teleop"
    mux.autonomy(FWD, 0.65)  # autonomy keeps publishing meanwhile
    out = mux.output(0.7)  # teleop older than 0.5 s
    assert out.source == "autonomy" and out.twist == FWD


def test_timeout_of_the_driving_input_gives_an_explicit_zero() -> None:
    mux = make()
    mux.teleop("alice", FWD, 0.0)
    assert mux.output(0.5).twist == FWD  # exactly at the timeout: still live
    out = mux.output(0.51)
    assert out.twist == ZERO and out.source == "timeout"
    assert mux.output(5.0).source == "timeout"  # stays an explicit zero until new input


def test_autonomy_timeout_is_an_explicit_zero() -> None:
    mux = make()
    mux.autonomy(FWD, 0.0)
    assert mux.output(0.6).source == "timeout"


def test_estop_latches_over_everything_until_reset() -> None:
    mux = make()
    mux.autonomy(FWD, 0.0)
    mux.estop("button")
    mux.teleop("alice", FWD, 0.1, take_over=True)
    mux.autonomy(FWD, 0.1)
    out = mux.output(0.2)
    assert out.twist == ZERO and out.source == "estop"
    assert mux.output(100.0).source == "estop"  # no timeout releases it
    assert mux.estops == 1
    mux.estop("again")  # a second press while latched is not a new e-stop
    assert mux.estops == 1
    assert mux.reset_estop() is True
    # Inputs from before the reset are gone: nothing drives until sent anew.
    assert mux.output(100.1).twist == ZERO
    mux.autonomy(FWD, 100.2)
    assert mux.output(100.3).twist == FWD


def test_reset_without_estop_reports_false() -> None:
    assert make().reset_estop() is False


def test_single_driver_newer_one_must_take_over() -> None:
    mux = make()
    mux.teleop("alice", FWD, 0.0)
    with pytest.raises(TeleopRefusedError, match="alice"):
        mux.teleop("bob", TURN, 0.1)
    assert mux.output(0.1).twist == FWD
    mux.teleop("bob", TURN, 0.2, take_over=True)
    assert mux.teleop_driver(0.2) == "bob"
    with pytest.raises(TeleopRefusedError):
        mux.teleop("alice", FWD, 0.3)


def test_anyone_may_stop_through_teleop() -> None:
    mux = make()
    mux.teleop("alice", FWD, 0.0)
    mux.teleop("bob", ZERO, 0.1)  # a zero is always accepted
    assert mux.output(0.2).twist == ZERO


def test_an_expired_driver_can_be_replaced_without_take_over() -> None:
    mux = make()
    mux.teleop("alice", FWD, 0.0)
    mux.teleop("bob", TURN, 1.0)
    assert mux.teleop_driver(1.0) == "bob"


def test_release_hands_back_at_once() -> None:
    mux = make()
    mux.autonomy(FWD, 0.0)
    mux.teleop("alice", TURN, 0.0)
    mux.release("bob")  # not bob's to release
    assert mux.output(0.1).source == "teleop"
    mux.release("alice")
    assert mux.output(0.1).source == "autonomy"


def test_twist_must_be_finite() -> None:
    with pytest.raises(ValueError):
        Twist(math.nan, 0.0)
    with pytest.raises(ValueError):
        Twist(0.0, math.inf)
