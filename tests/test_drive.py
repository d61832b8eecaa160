"""Driving by hand: the stick / button mapping (legged_casters.deploy.drive) and the
gamepad loop of teleop --gamepad, with a fake device (a pipe of js_event records)."""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest

from legged_casters.deploy import drive
from legged_casters.deploy import protocol as P
from legged_casters.deploy.teleop import GamepadLost, JsDevice, drive_gamepad

REPO = Path(__file__).resolve().parents[1]
RANGES = drive.CommandRanges((-0.5, 1.0), (-0.4, 0.4), (-1.2, 1.2))
E = drive.JsEvent


def _inside(d: drive.Drive, ranges: drive.CommandRanges = RANGES) -> bool:
    return all(lo <= v <= hi for v, (lo, hi) in zip((d.vx, d.vy, d.wz), ranges.as_tuples(), strict=True))


def test_dead_zone_and_scaling_stay_inside_the_ranges():
    assert drive.dead_zone(0.05, 0.1) == 0.0 and drive.dead_zone(-0.1, 0.1) == 0.0
    assert drive.dead_zone(1.0, 0.1) == 1.0 and drive.dead_zone(-3.0, 0.1) == -1.0
    assert drive.dead_zone(0.55, 0.1) == pytest.approx(0.5)
    assert drive.dead_zone(math.nan, 0.1) == 0.0 and drive.dead_zone(math.inf, 0.1) == 0.0
    # full travel reaches each end of an asymmetric range, never beyond
    assert drive.sticks_to_velocity(1.0, 1.0, 1.0, RANGES, 0.1) == (1.0, 0.4, 1.2)
    assert drive.sticks_to_velocity(-1.0, -1.0, -1.0, RANGES, 0.1) == (-0.5, -0.4, -1.2)
    assert drive.sticks_to_velocity(0.05, -0.05, 0.0, RANGES, 0.1) == (0.0, 0.0, 0.0)
    for s in (-5.0, -1.0, -0.3, 0.0, 0.3, 1.0, 7.0, math.nan):
        vx, vy, wz = drive.sticks_to_velocity(s, s, s, RANGES, 0.1)
        assert -0.5 <= vx <= 1.0 and -0.4 <= vy <= 0.4 and -1.2 <= wz <= 1.2
    # a range that excludes one sign (the wheel robot's vy (0, 0)) gives 0 there
    assert drive.sticks_to_velocity(1.0, 1.0, 1.0, drive.CommandRanges((0, 1), (0, 0), (-1, 1)), 0.0)[1] == 0.0
    assert RANGES.capped((0.3, 1.0, 1.0)) == drive.CommandRanges((-0.3, 0.3), (-0.4, 0.4), (-1.0, 1.0))
    with pytest.raises(ValueError):
        drive.CommandRanges((1.0, -1.0), (0, 0), (0, 0))


def test_command_ranges_come_from_the_export_and_the_task():
    """The shipped caster_omni export: its env.yaml's ranges (with the curriculum's
    widened vx), its three propulsion modes; a task's defaults from the registry."""
    ranges, modes = drive.policy_limits(REPO / "resources" / "policies" / "caster_omni")
    assert ranges.vy == (-0.5, 0.5) and ranges.wz == (-1.0, 1.0) and ranges.vx == (-4.0, 4.0)
    assert modes == tuple(P.PropulsionMode)
    assert drive.task_command_ranges("go2_wheel_flat").vy == (0.0, 0.0)
    with pytest.raises(ValueError):
        drive.task_command_ranges("no_such_task")
    with pytest.raises(ValueError):
        drive.policy_limits(REPO / "resources")


# --- gamepad -----------------------------------------------------------------------------------
def test_js_event_records_round_trip():
    ev = E(123456, -32767, drive.JS_AXIS, 3)
    raw = ev.encode()
    assert len(raw) == 8 and E.decode(raw) == ev
    assert raw == bytes.fromhex("40e20100") + (-32767).to_bytes(2, "little", signed=True) + bytes([2, 3])
    evs, rest = drive.decode_js_events(raw + raw[:5])
    assert evs == [ev] and rest == raw[:5]


def _pad(**kw) -> drive.Gamepad:
    return drive.Gamepad(RANGES, **kw)


def test_gamepad_sticks_map_to_velocity_and_released_sticks_to_zero():
    pad = _pad()
    m = pad.mapping
    # the kernel's y axis is positive down, x positive right: up / left / left -> +vx / +vy / +wz
    for ev in (E.axis(m.forward_axis, -1.0), E.axis(m.left_axis, -1.0), E.axis(m.turn_axis, -1.0)):
        pad.apply(ev)
    d = pad.drive()
    assert (d.vx, d.vy, d.wz) == pytest.approx((1.0, 0.4, 1.2), abs=1e-4) and _inside(d) and d.flags == 0
    for ev in (E.axis(m.forward_axis, 1.0), E.axis(m.left_axis, 1.0), E.axis(m.turn_axis, 1.0)):
        pad.apply(ev)
    d = pad.drive()
    assert (d.vx, d.vy, d.wz) == pytest.approx((-0.5, -0.4, -1.2), abs=1e-4) and _inside(d)
    for ev in (E.axis(m.forward_axis, 0.04), E.axis(m.left_axis, -0.08), E.axis(m.turn_axis, 0.0)):
        pad.apply(ev)  # released: resting near the centre
    d = pad.drive()
    assert (d.vx, d.vy, d.wz) == (0.0, 0.0, 0.0)
    pad.apply(E.axis(m.forward_axis, -0.55))
    assert pad.drive().vx == pytest.approx(0.5, abs=1e-3)  # half way past the dead zone: half the range


def test_gamepad_stop_latches_until_reset_and_wins_over_it():
    pad = _pad()
    m = pad.mapping
    pad.apply(E.axis(m.forward_axis, -1.0))
    pad.apply(E.button(m.stop_button, True))
    d = pad.drive()
    assert d.stop and d.flags == P.OP_STOP and (d.vx, d.vy, d.wz) == (0.0, 0.0, 0.0)
    pad.apply(E.button(m.stop_button, False))
    assert pad.drive().stop  # latched: released stop button, sticks still pushed
    pad.apply(E.button(m.stop_button, True))
    pad.apply(E.button(m.reset_button, True))  # reset while the stop is held: still stopped
    assert pad.drive().stop
    pad.apply(E.button(m.reset_button, False))
    pad.apply(E.button(m.stop_button, False))
    pad.apply(E.button(m.reset_button, True))
    flags = [pad.drive().flags for _ in range(5)]
    assert flags == [P.OP_RESET] * 3 + [0, 0]  # the reset goes out a few times, then driving resumes
    assert pad.drive().vx == pytest.approx(1.0, abs=1e-4)
    # a stop button already held when the device opens (the driver's initial-state events) stops
    pad2 = _pad()
    pad2.apply(E(0, 1, drive.JS_BUTTON | drive.JS_INIT, m.stop_button))
    assert pad2.drive().stop
    pad3 = _pad()
    pad3.apply(E(0, 1, drive.JS_BUTTON | drive.JS_INIT, m.reset_button))  # a held reset does nothing
    assert pad3.drive().flags == 0


def test_gamepad_mode_buttons_pick_the_policys_modes_only():
    pad = _pad(modes=(P.PropulsionMode.FOUR_WHEEL, P.PropulsionMode.FRONT_WHEEL))
    buttons = {mode: b for b, mode in pad.mapping.mode_buttons}
    pad.apply(E.button(buttons[P.PropulsionMode.FRONT_WHEEL], True))
    assert pad.drive().propulsion == P.PropulsionMode.FRONT_WHEEL
    pad.apply(E.button(buttons[P.PropulsionMode.REAR_WHEEL], True))  # not in this policy: ignored
    assert pad.drive().propulsion == P.PropulsionMode.FRONT_WHEEL
    pad.apply(E.button(buttons[P.PropulsionMode.FOUR_WHEEL], True))
    assert pad.drive().command().propulsion == P.PropulsionMode.FOUR_WHEEL


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.t += max(dt, 0.0)


def test_gamepad_loop_sends_at_its_rate_and_goes_quiet_when_the_pad_is_lost():
    """A pipe stands in for /dev/input/js0: events written to it drive the commands; once
    its writer closes (the pad unplugged), one zero command goes out and nothing more."""
    r, w = os.pipe()
    dev = JsDevice(f"/dev/fd/{r}")
    os.close(r)
    clock, sent = _Clock(), []
    pad = _pad()
    m = pad.mapping
    script = {
        0.0: [E(0, 0, drive.JS_AXIS | drive.JS_INIT, m.forward_axis)],
        0.5: [E.axis(m.forward_axis, -1.0)],
        1.0: [E.axis(m.forward_axis, 0.0)],
        1.5: [E.button(m.stop_button, True), E.button(m.stop_button, False)],
    }

    def read_events():
        got = []
        for t in sorted(t for t in script if t <= clock.t):
            raw = b"".join(ev.encode() for ev in script.pop(t))
            os.write(w, raw[:5])  # a record split across two reads is put back together
            got += dev.read_events()
            os.write(w, raw[5:])
        if clock.t >= 2.0 and not closed:
            os.close(w)
            closed.append(True)
        return got + dev.read_events()

    closed: list[bool] = []
    why = drive_gamepad(read_events, pad, sent.append, rate=10.0, clock=clock, sleep=clock.sleep)
    dev.close()
    assert "lost" in why
    assert len(sent) == 21  # 0.0 .. 2.0 s at 10 Hz: 20 decisions, then the one zero command
    assert all(_inside(d) for d in sent)
    assert [d.vx for d in sent[:5]] == [0.0] * 5 and all(d.vx == pytest.approx(1.0, abs=1e-4) for d in sent[5:10])
    assert [d.vx for d in sent[10:15]] == [0.0] * 5
    assert all(d.stop for d in sent[15:])  # the stop, and the zero command after the loss keeps it
    assert (sent[-1].vx, sent[-1].vy, sent[-1].wz) == (0.0, 0.0, 0.0)


def test_gamepad_read_error_is_a_loss():
    class Broken:
        calls = 0

        def __call__(self):
            self.calls += 1
            if self.calls > 3:
                raise GamepadLost("read error")
            return [E.axis(1, -1.0)]

    clock, sent = _Clock(), []
    why = drive_gamepad(Broken(), _pad(), sent.append, rate=50.0, clock=clock, sleep=clock.sleep)
    assert "lost" in why and len(sent) == 4
    assert [d.vx for d in sent[:3]] == pytest.approx([1.0] * 3, abs=1e-4) and sent[-1].vx == 0.0
    # a device that cannot be read at all: os errors become GamepadLost
    r, w = os.pipe()
    os.close(w)
    dev = JsDevice(f"/dev/fd/{r}")
    os.close(r)
    with pytest.raises(GamepadLost):
        dev.read_events()
    dev.close()


def test_teleop_warns_when_another_operator_has_the_bridge():
    """The bridge follows one operator sender: when its accepted count and last seq stop
    following this gamepad's messages, teleop says so (once), and again when they follow."""
    from legged_casters.deploy.teleop import BridgeListens

    statuses: list[P.BridgeStatus] = []
    listens = BridgeListens(statuses, every=1.0)
    assert listens(0.0, 0, 0) is None  # no bridge heard yet
    lines = []
    other_seq = 5000
    for k in range(1, 61):  # 6 s at 10 Hz; from 2 s on another sender has the bridge, from 4 s on us again
        t = k / 10
        mine = t <= 2.0 or t > 4.0
        last = k if mine else other_seq + k
        statuses.append(P.BridgeStatus(received_operator=k, last_operator_seq=last))  # one accepted per tick
        line = listens(t, k, k)
        if line:
            lines.append((t, line))
    assert len(lines) == 2
    assert 2.0 < lines[0][0] <= 3.2 and "WARNING" in lines[0][1] and "stop" in lines[0][1]
    assert 4.0 < lines[1][0] <= 5.2 and "again" in lines[1][1]


def test_teleop_gamepad_cli_over_zenoh(tmp_path):
    """teleop --gamepad on a FIFO of js_event records, into a zenoh peer: commands at its
    rate inside --max-command, the stop latched, and after the last writer closes (the pad
    gone) one zero command with the stop, then silence and a clean exit."""
    import subprocess
    import sys
    import time

    from test_deploy import free_port, peer, wait_for

    fifo = tmp_path / "js0"
    os.mkfifo(fifo)
    wfd = os.open(fifo, os.O_RDWR)  # the pad: a writer from the start
    port = free_port()
    session = peer(listen=port)
    got: list[P.OperatorCommand] = []
    sub = session.declare_subscriber(
        "t_pad/operator", lambda s: got.append(P.OperatorCommand.decode(s.payload.to_bytes()))
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "legged_casters.deploy.teleop", "--connect", f"tcp/127.0.0.1:{port}",
         "--namespace", "t_pad", "--gamepad", str(fifo), "--task", "caster_omni", "--max-command", "0.5", "0.2", "0.5",
         "--rate", "20"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        assert wait_for(lambda: len(got) > 3, 60.0), "no operator message"
        assert all((o.vx, o.vy, o.wz, o.flags) == (0.0, 0.0, 0.0, 0) for o in got)
        os.write(wfd, E.axis(1, -1.0).encode() + E.axis(0, 1.0).encode())
        assert wait_for(lambda: got[-1].vx == pytest.approx(0.5) and got[-1].vy == pytest.approx(-0.2), 5.0)
        os.write(wfd, E.button(1, True).encode() + E.button(1, False).encode())
        assert wait_for(lambda: got[-1].stop, 5.0)
        os.close(wfd)
        out, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0 and "gamepad lost" in out, out
        n = len(got)
        time.sleep(0.3)
        assert len(got) == n and got[-1].stop and (got[-1].vx, got[-1].vy, got[-1].wz) == (0.0, 0.0, 0.0)
        tol = 1e-6  # float32 on the wire
        assert all(abs(o.vx) <= 0.5 + tol and abs(o.vy) <= 0.2 + tol and abs(o.wz) <= 0.5 + tol for o in got)
    finally:
        if proc.poll() is None:
            proc.kill()
        sub.undeclare()
        session.close()
