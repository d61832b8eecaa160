"""The Go2's own remote: LowState.wireless_remote decoded (deploy/drive.py), turned into
operator commands and a local stop by the adapter (go2_adapter --remote), checked with
an SDK stand-in (tests/sdk_standin.py) so that it runs without CycloneDDS, and against
the fake Go2 (MuJoCo) with the remote's bytes injected and no bridge at all."""

from __future__ import annotations

import math
import struct
import time

import numpy as np
import pytest
from sdk_standin import Bus, new_lowstate
from test_deploy import LOAD_STATE_AGE_MS, _spawn, _stop, free_port, peer, realtime, wait_for  # noqa: F401 (fixture)

from legged_casters.deploy import drive, unitree
from legged_casters.deploy import protocol as P
from legged_casters.deploy.go2_adapter import REMOTE_RESUME_WHY, REMOTE_STOP_WHY, Go2Adapter

RANGES = drive.CommandRanges((-0.5, 1.0), (-0.4, 0.4), (-1.2, 1.2))
enc = drive.RemoteState.encode


def test_remote_bytes_are_read_at_unitrees_offsets():
    """Built by hand at the offsets of unitree_sdk2's xRockerBtnDataStruct: head 0-1, the
    xKeySwitchUnion bits at 2-3 (R1 bit 0 ... left bit 15), float lx 4, rx 8, ry 12, L2 16,
    ly 20."""
    assert drive.REMOTE_BUTTONS == (
        "R1", "L1", "start", "select", "R2", "L2", "F1", "F2", "A", "B", "X", "Y", "up", "right", "down", "left",
    )  # fmt: skip
    raw = bytearray(40)
    raw[0:2] = b"\x55\xaa"
    raw[2:4] = ((1 << 5) | (1 << 9) | (1 << 15)).to_bytes(2, "little")  # L2, B, left
    for offset, value in ((4, 0.25), (8, -0.5), (12, 0.75), (16, 1.0), (20, -1.0)):
        struct.pack_into("<f", raw, offset, value)
    s = drive.RemoteState.decode(raw)
    assert (s.lx, s.rx, s.ry, s.l2, s.ly) == (0.25, -0.5, 0.75, 1.0, -1.0) and s.present
    assert s.pressed("L2", "B") and s.pressed("left") and not s.pressed("A") and not s.pressed("L2", "A")
    assert enc(("L2", "B", "left"), lx=0.25, rx=-0.5, ry=0.75, l2=1.0, ly=-1.0) == bytes(raw)
    assert not drive.RemoteState.decode(bytes(40)).present  # no remote: 40 zero bytes
    with pytest.raises(ValueError):
        drive.RemoteState.decode(bytes(39))


def _remote(**kw) -> drive.Remote:
    return drive.Remote(RANGES, **kw)


def _vel(d: drive.Drive):
    return d.vx, d.vy, d.wz


def test_remote_sticks_and_combinations():
    r = _remote()
    r.update(drive.RemoteState.decode(enc(ly=1.0, lx=-1.0, rx=-1.0)))  # forward, left, turn left
    assert _vel(r.drive()) == pytest.approx((1.0, 0.4, 1.2)) and r.drive().flags == 0
    r.update(drive.RemoteState.decode(enc(ly=-1.0, lx=1.0, rx=1.0)))
    assert _vel(r.drive()) == pytest.approx((-0.5, -0.4, -1.2))
    r.update(drive.RemoteState.decode(enc(ly=0.05, lx=-0.09, rx=0.0)))  # released
    assert _vel(r.drive()) == (0.0, 0.0, 0.0)
    r.update(drive.RemoteState.decode(enc(ly=math.nan, lx=math.inf)))  # garbage reads as released
    assert _vel(r.drive()) == (0.0, 0.0, 0.0)
    for pressed in (("L2",), ("B",)):  # half a combination does nothing
        r.update(drive.RemoteState.decode(enc(pressed)))
        assert not r.stopped
    r.update(drive.RemoteState.decode(enc(("L2", "B"), ly=1.0)))
    assert r.stopped and r.drive().flags == P.OP_STOP and _vel(r.drive()) == (0.0, 0.0, 0.0)
    r.update(drive.RemoteState.decode(enc(("L2", "B", "start"))))  # reset pressed with the stop: stop
    assert r.stopped
    r.update(drive.RemoteState.decode(enc(("L2",))))
    r.update(drive.RemoteState.decode(enc(("L2", "start"))))
    assert not r.stopped and [r.drive().flags for _ in range(4)] == [P.OP_RESET] * 3 + [0]
    r.update(drive.RemoteState.decode(enc(("Y",))))
    assert r.drive().propulsion == P.PropulsionMode.FRONT_WHEEL
    r.update(drive.RemoteState.decode(enc(("A",))))
    assert r.drive().propulsion == P.PropulsionMode.REAR_WHEEL
    only4 = _remote(modes=(P.PropulsionMode.FOUR_WHEEL,))
    only4.update(drive.RemoteState.decode(enc(("Y",))))
    assert only4.drive().propulsion == P.PropulsionMode.FOUR_WHEEL
    r.update(drive.RemoteState.decode(bytes(40)))  # the remote went away: zero, no flags
    assert _vel(r.drive()) == (0.0, 0.0, 0.0) and r.drive().flags == 0


def _adapter(ops: list, written: list, sdk=None) -> Go2Adapter:
    sdk = sdk or Bus().sdk()
    return Go2Adapter(
        sdk,
        lambda b: None,
        lambda c: written.append([(m.mode, m.q, m.kp, m.kd) for m in c.motor_cmd]),
        damping_kd=1.5,
        remote=_remote(),
        publish_operator=ops.append,
        remote_rate=20.0,
    )


def _low(remote: bytes, finite: bool = True):
    low = new_lowstate()
    mm = unitree.MotorMap.for_robot("caster")
    q = np.full(12, 0.3)
    mm.write_state(low, [1.0, 0.0, 0.0, 0.0] if finite else [math.nan] * 4, [0.0] * 3, q, 0 * q)
    low.wireless_remote = list(remote)
    return low


def _ops(ops: list) -> list[P.OperatorCommand]:
    return [P.OperatorCommand.decode(b) for b in ops]


def test_adapter_damps_on_the_remote_stop_at_the_next_lowcmd_whatever_the_bridge_sends():
    ops, written = [], []
    a = _adapter(ops, written)
    sender = P.Sender()
    policy = P.JointCommand(P.CommandMode.POLICY, [0.1] * 12, [20.0] * 12, [0.5] * 12, header=sender.next_header())
    a.on_command(policy.encode())
    t = time.monotonic()
    a.on_lowstate(_low(enc()))
    a.tick(t)
    assert a.mode == P.CommandMode.POLICY and written[-1][3][2] == 20.0  # FL hip in Unitree slot 3
    # the stop arrives in a LowState whose IMU is broken (dropped for the bridge): it still stops
    a.on_lowstate(_low(enc(("L2", "B")), finite=False))
    assert a.bad_lowstates == 1
    a.on_command(
        P.JointCommand(P.CommandMode.POLICY, [0.1] * 12, [20.0] * 12, [0.5] * 12, header=sender.next_header()).encode()
    )  # the bridge keeps sending its policy
    a.tick(t + 0.002)  # the next LowCmd
    assert a.mode == P.CommandMode.DAMPING and a.mode_changes[-1][2] == REMOTE_STOP_WHY
    assert all(m[2] == 0.0 and m[3] == 1.5 for m in (written[-1][i] for i in a.map.motors))
    assert _ops(ops)[-1].stop  # the bridge is told at once
    # releasing the buttons keeps the stop; the reset combination waits for the bridge's stand-up
    a.on_lowstate(_low(enc()))
    a.tick(t + 0.004)
    assert a.mode_changes[-1][2] == REMOTE_STOP_WHY
    a.on_lowstate(_low(enc(("L2", "start"))))
    a.tick(t + 0.006)
    assert a.mode == P.CommandMode.DAMPING and a.targets(t + 0.006)[1] == REMOTE_RESUME_WHY
    assert _ops(ops)[-1].reset and not _ops(ops)[-1].stop
    a.on_command(
        P.JointCommand(P.CommandMode.POLICY, [0.1] * 12, [20.0] * 12, [0.5] * 12, header=sender.next_header()).encode()
    )
    a.tick(time.monotonic())
    assert a.mode == P.CommandMode.DAMPING  # a policy command does not end it
    standup = P.JointCommand(P.CommandMode.STANDUP, [0.2] * 12, [30.0] * 12, [1.0] * 12, header=sender.next_header())
    a.on_command(standup.encode())
    a.tick(time.monotonic())
    assert a.mode == P.CommandMode.STANDUP and written[-1][3][2] == 30.0


def test_adapter_remote_stop_before_any_bridge_command_damps():
    ops, written = [], []
    a = _adapter(ops, written)
    a.tick(time.monotonic())
    assert not written and a.mode == P.CommandMode.NONE  # no bridge, no remote: writes nothing
    a.on_lowstate(_low(enc(("L2", "B"))))
    a.tick(time.monotonic())
    assert a.mode == P.CommandMode.DAMPING and written and all(written[-1][i][2] == 0.0 for i in a.map.motors)


def test_adapter_remote_stop_holds_when_the_operator_link_fails():
    """Publishing to the bridge raises (the link gone): the LowCmd loop goes on damping."""
    written = []

    def broken(_payload):
        raise RuntimeError("session closed")

    a = _adapter([], written)
    a.publish_operator = broken
    a.on_lowstate(_low(enc(("L2", "B"))))
    for k in range(3):
        a.tick(time.monotonic() + 0.002 * k)
    assert a.mode == P.CommandMode.DAMPING and len(written) == 3 and a.operator_errors >= 1


def test_adapter_publishes_the_remotes_commands_at_its_rate_and_one_zero_when_it_goes():
    ops, written = [], []
    a = _adapter(ops, written)
    t0 = time.monotonic()
    for k in range(250):  # 0.5 s of LowState and LowCmd at 500 Hz, left stick full forward
        now = t0 + k * 0.002
        a.on_remote(enc(ly=1.0, rx=-0.5), now)
        a.tick(now)
    got = _ops(ops)
    assert 9 <= len(got) <= 11  # 20 Hz
    assert all(o.vx == pytest.approx(1.0) and o.vy == 0.0 and 0.0 < o.wz <= 1.2 and o.flags == 0 for o in got)
    a.on_remote(enc(), t0 + 0.5)  # sticks released
    a.tick(t0 + 0.56)
    assert _ops(ops)[-1].vx == 0.0 and _ops(ops)[-1].wz == 0.0
    n = len(ops)
    for k in range(1, 100):  # no LowState for a while: the remote is gone
        a.tick(t0 + 0.56 + k * 0.002)
    assert len(ops) == n + 1 and _vel(_ops(ops)[-1]) == (0.0, 0.0, 0.0)
    a.on_remote(bytes(40), t0 + 1.0)  # zero bytes (no remote) do not count as a report
    for k in range(50):
        a.tick(t0 + 1.0 + k * 0.002)
    assert len(ops) == n + 1


@pytest.mark.realtime
def test_fake_go2_damps_on_the_remote_stop_without_a_bridge():
    """The fake Go2 (MuJoCo) and the adapter, both on the SDK stand-in's channels, no bridge
    and no zenoh: the sticks give operator commands inside the ranges; L2+B set on the
    fake's remote makes the adapter damp within one LowState and one LowCmd period (2 ms
    each here), and the fake robot applies it."""
    from legged_casters.deploy.fake_go2 import FakeGo2

    sdk = Bus().sdk()
    ops = []
    robot = FakeGo2(sdk, state_rate=500.0, watchdog=0.1)
    a = Go2Adapter(
        sdk,
        lambda b: None,
        sdk.ChannelPublisher(unitree.LOWCMD_TOPIC, None).Write,
        damping_kd=1.5,
        remote=_remote(),
        publish_operator=ops.append,
    )
    sub = sdk.ChannelSubscriber(unitree.LOWSTATE_TOPIC, None)
    sub.Init(a.on_lowstate, 10)
    robot.start()
    a.start(500.0)
    try:
        time.sleep(0.3)
        assert a.lowstates > 50 and robot.mode == P.CommandMode.HOLD and not ops  # nothing from a silent remote
        robot.set_wireless_remote(enc(ly=1.0, lx=1.0))
        time.sleep(0.3)
        got = _ops(ops)
        assert len(got) >= 3 and all(o.vx == pytest.approx(1.0) and o.vy == pytest.approx(-0.4) for o in got)
        robot.set_wireless_remote(enc())
        time.sleep(0.1)
        assert _vel(_ops(ops)[-1]) == (0.0, 0.0, 0.0)
        robot.set_wireless_remote(enc(("L2", "B")))
        t_set = robot.remote_set_at
        deadline = time.monotonic() + 1.0
        while robot.mode != P.CommandMode.DAMPING and time.monotonic() < deadline:
            time.sleep(0.001)
        assert a.mode == P.CommandMode.DAMPING and robot.mode == P.CommandMode.DAMPING
        t_damp = next(t for t, mode, why in a.mode_changes if why == REMOTE_STOP_WHY)
        print(f"remote stop -> adapter damping: {1e3 * (t_damp - t_set):.2f} ms")
        assert t_damp - t_set < 0.004 + 0.010  # a LowState and a LowCmd period, with scheduling slack
        assert _ops(ops)[-1].stop
    finally:
        a.stop()
        robot.stop()


def test_adapter_cli_refuses_a_remote_without_ranges_or_with_secure(capsys):
    from legged_casters.deploy.go2_adapter import main

    assert main(["--remote"]) == 2
    assert "--policy" in capsys.readouterr().err
    assert main(["--remote", "--task", "caster_omni", "--secure", "certs"]) == 2
    assert "--secure" in capsys.readouterr().err
    assert main(["--remote", "--task", "no_such_task"]) == 2
    assert "unknown task" in capsys.readouterr().err


try:
    unitree.load_sdk()
    SDK_ERROR = ""
except unitree.SdkUnavailable as err:
    SDK_ERROR = str(err)


@pytest.mark.skipif(bool(SDK_ERROR), reason=f"Unitree SDK not installed: {SDK_ERROR}")
def test_real_sdk_lowstate_carries_the_remote_to_the_adapter():
    """With Unitree's own LowState_ (wireless_remote: 40 uint8) instead of the stand-in."""
    sdk = unitree.load_sdk()
    low = sdk.new_lowstate()
    assert len(low.wireless_remote) == unitree.WIRELESS_REMOTE_SIZE
    ops, written = [], []
    a = _adapter(ops, written, sdk=sdk)
    unitree.MotorMap.for_robot("caster").write_state(low, [1.0, 0.0, 0.0, 0.0], [0.0] * 3, np.zeros(12), np.zeros(12))
    low.wireless_remote = list(enc(("L2", "B")))
    a.on_lowstate(low)
    a.tick(time.monotonic())
    assert a.mode == P.CommandMode.DAMPING and _ops(ops)[-1].stop


@pytest.mark.usefixtures("realtime")
def test_remote_drives_and_stops_a_bridge_through_the_adapter(tmp_path):
    """The fake Go2 and the adapter in this process (SDK stand-in), the adapter on zenoh,
    a bridge with the simple policy in another process: the remote's sticks reach the
    bridge as operator commands; L2+B damps the adapter at once and latches the bridge in
    STOPPED; L2+start resets the bridge, and the adapter follows its new stand-up."""
    from legged_casters.deploy.fake_go2 import FakeGo2
    from legged_casters.deploy.simple_policy import write_policy

    policy = write_policy(tmp_path, gait_gain=0.8).parent
    port, ns = free_port(), "t_remote"
    keys = P.keys(ns)
    session = peer(listen=port)
    statuses: list[P.BridgeStatus] = []
    sdk = Bus().sdk()
    robot = FakeGo2(sdk, state_rate=200.0, watchdog=0.1)
    a = Go2Adapter(
        sdk,
        session.declare_publisher(keys["state"]).put,
        sdk.ChannelPublisher(unitree.LOWCMD_TOPIC, None).Write,
        damping_kd=1.0,
        remote=_remote(),
        publish_operator=session.declare_publisher(keys["operator"]).put,
    )
    subs = [
        session.declare_subscriber(keys["cmd"], lambda s: a.on_command(s.payload.to_bytes())),
        session.declare_subscriber(
            keys["status"], lambda s: statuses.append(P.BridgeStatus.decode(s.payload.to_bytes()))
        ),
    ]
    sdk.ChannelSubscriber(unitree.LOWSTATE_TOPIC, None).Init(a.on_lowstate, 10)
    robot.start()
    a.start(200.0)
    bridge = _spawn("bridge", "--policy", str(policy), "--connect", f"tcp/127.0.0.1:{port}", "--namespace", ns,
                    "--standup", "linear", "--standup-time", "1.0",
                    "--max-state-age-ms", LOAD_STATE_AGE_MS)  # fmt: skip
    try:
        robot.set_wireless_remote(enc())  # a remote that reports, sticks released
        assert wait_for(lambda: statuses and statuses[-1].state == P.BridgeState.RUNNING, 60.0), "bridge not running"
        assert wait_for(lambda: a.mode == P.CommandMode.POLICY, 5.0)
        n0 = statuses[-1].received_operator
        robot.set_wireless_remote(enc(ly=1.0))
        assert wait_for(lambda: statuses[-1].received_operator > n0 + 5, 5.0), "bridge takes no remote command"
        assert sum(statuses[-1].rejected) == 0
        robot.set_wireless_remote(enc(("L2", "B")))
        t_set = robot.remote_set_at
        assert wait_for(lambda: a.mode == P.CommandMode.DAMPING, 1.0)
        t_damp = next(t for t, mode, why in a.mode_changes if why == REMOTE_STOP_WHY)
        assert t_damp - t_set < 0.005 + 0.005 + 0.010  # a LowState and a LowCmd period at 200 Hz, slack
        assert wait_for(lambda: statuses[-1].state == P.BridgeState.STOPPED, 2.0), "bridge not stopped"
        assert statuses[-1].fault == P.Fault.OPERATOR_STOP
        robot.set_wireless_remote(enc(("L2",)))
        time.sleep(0.2)
        assert a.mode == P.CommandMode.DAMPING and statuses[-1].state == P.BridgeState.STOPPED
        robot.set_wireless_remote(enc(("L2", "start")))
        assert wait_for(lambda: a.mode == P.CommandMode.STANDUP, 5.0), "adapter did not follow the stand-up"
        robot.set_wireless_remote(enc())
        assert wait_for(lambda: statuses[-1].state == P.BridgeState.RUNNING and a.mode == P.CommandMode.POLICY, 10.0)
    finally:
        _stop(bridge)
        a.stop()
        robot.stop()
        for s in subs:
            s.undeclare()
        session.close()
