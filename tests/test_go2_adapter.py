"""The Go2 adapter: Unitree's low-level DDS interface <-> our wire protocol.

The mapping, CRC and refusal tests need nothing beyond the project; the rest needs
the Unitree extra (`./setup.sh unitree`) and runs DDS on loopback only."""

from __future__ import annotations

import random
import signal
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from test_deploy import (  # noqa: F401 (realtime: a fixture)
    LOAD_SLACK_S,
    LOAD_STATE_AGE_MS,
    LOAD_WATCHDOG_S,
    REPO,
    LoopProbe,
    _spawn,
    _stop,
    free_port,
    realtime,
    wait_for,
)
from test_soak import signal_when_ready

from legged_casters.deploy import protocol as P
from legged_casters.deploy import unitree
from legged_casters.deploy.go2_adapter import Go2Adapter, check_interface
from legged_casters.deploy.policy import projected_gravity
from legged_casters.deploy.simple_policy import write_policy
from legged_casters.robot import go2

try:
    unitree.load_sdk()
    SDK_ERROR = ""
except unitree.SdkUnavailable as err:
    SDK_ERROR = str(err)
needs_sdk = pytest.mark.skipif(bool(SDK_ERROR), reason=f"Unitree SDK not installed: {SDK_ERROR}")


def test_motor_map_is_the_documented_permutation():
    """docs/protocol.md: unitree = [3, 4, 5, 0, 1, 2, 9, 10, 11, 6, 7, 8][ours], wheels [13, 12, 15, 14]."""
    legs = [3, 4, 5, 0, 1, 2, 9, 10, 11, 6, 7, 8]
    assert list(unitree.MotorMap.for_robot("caster").motors) == legs
    assert list(unitree.MotorMap.for_robot("point").motors) == legs
    assert list(unitree.MotorMap.for_robot("wheel").motors) == legs + [13, 12, 15, 14]
    assert sorted(go2.UNITREE_MOTOR.values()) == list(range(16))
    assert go2.UNITREE_MOTOR["FR_hip_joint"] == 0 and go2.UNITREE_MOTOR["RL_calf_joint"] == 11


def _robot_crc(words) -> int:
    """The robot's checksum as its firmware's description reads: shift the register left
    one bit per data bit (most significant first), xor the polynomial when the bit
    shifted out was set, and again when the data bit is set."""
    crc = 0xFFFFFFFF
    for w in words:
        for bit in range(31, -1, -1):
            top = crc & 0x80000000
            crc = (crc << 1) & 0xFFFFFFFF
            if top:
                crc ^= 0x04C11DB7
            if (w >> bit) & 1:
                crc ^= 0x04C11DB7
    return crc


def test_crc_table_matches_the_bitwise_definition():
    rng = random.Random(3)
    for n in (1, 2, 17, 202):
        words = [rng.getrandbits(32) for _ in range(n)]
        assert unitree.crc32_words(words) == _robot_crc(words)
    assert unitree.LOWCMD_LAYOUT.size == 812  # the C struct the robot checks


def test_adapter_refuses_a_real_interface_without_the_flag():
    assert check_interface("lo", False, False) is None
    assert check_interface("eth0", True, False) is None
    assert check_interface("eth0", False, True) is None  # dry run never writes
    r = subprocess.run(
        [sys.executable, "-m", "legged_casters.deploy.go2_adapter", "--network-interface", "eth0"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "--real-robot" in r.stderr and "--dry-run" in r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "legged_casters.deploy.fake_go2", "--network-interface", "eth0"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and "loopback only" in r.stderr


@needs_sdk
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_fake_go2_without_zenoh_stops_cleanly_on_a_signal(sig):
    """fake_go2 with no --listen or --connect opens no zenoh session (which installs the stop
    handlers in the other tools): SIGINT and SIGTERM must still run its shutdown (the final
    summary line) and exit 0, also when a shell started it with SIGINT ignored."""
    cmd = [sys.executable, "-m", "legged_casters.deploy.fake_go2", "--summary-every", "0", "--duration", "0"]
    returncode, out = signal_when_ready(cmd, "physics", sig, settle=0.5)
    assert returncode == 0
    assert "fake_go2:" in out and "steps (" in out  # the final summary: the shutdown ran


@needs_sdk
def test_crc_matches_the_sdk_reference(monkeypatch):
    """Against the SDK's own packing and its pure-Python CRC (its Crc() wants a shared
    library the wheel lacks, which a stand-in replaces while the object is built)."""
    import ctypes

    sdk = unitree.load_sdk()

    class _Lib:
        class crc32_core:  # noqa: N801 - the attribute the SDK sets argtypes on
            pass

    monkeypatch.setattr(ctypes, "CDLL", lambda *a, **k: _Lib())
    ref = sdk.reference_crc()
    rng = np.random.default_rng(0)
    for robot in ("caster", "wheel"):
        mm = unitree.MotorMap.for_robot(robot)
        cmd = sdk.new_lowcmd()
        n = len(mm)
        mm.write_command(cmd, rng.normal(size=n), rng.normal(size=n), rng.uniform(0, 40, n), rng.uniform(0, 2, n))
        words = ref._CRC__PackLowCmd(cmd)
        assert struct.pack(f"<{len(words)}I", *words) == unitree.lowcmd_bytes(cmd)[:-4]
        assert cmd.crc == ref._crc_py(words) == unitree.lowcmd_crc(cmd)


@needs_sdk
def test_lowcmd_carries_each_joint_in_its_motor_slot():
    sdk = unitree.load_sdk()
    mm = unitree.MotorMap.for_robot("wheel")
    q, dq, kp, kd = (np.arange(16.0) + k for k in (0.0, 100.0, 200.0, 300.0))
    cmd = sdk.new_lowcmd()
    mm.write_command(cmd, q, dq, kp, kd)
    assert tuple(cmd.head) == unitree.HEAD and cmd.level_flag == unitree.LEVEL_LOW
    fl_hip, rr_wheel = cmd.motor_cmd[3], cmd.motor_cmd[14]
    assert (fl_hip.mode, fl_hip.q, fl_hip.kp) == (1, 0.0, 200.0)
    assert (rr_wheel.dq, rr_wheel.kd) == (115.0, 315.0)
    for i in range(16, 20):  # unused slots: off, with Unitree's stop values
        m = cmd.motor_cmd[i]
        assert m.mode == 0 and m.q == unitree.POS_STOP and m.dq == unitree.VEL_STOP and m.kp == m.kd == 0.0
    servo, *back = mm.read_command(cmd)
    assert servo.all()
    for got, want in zip(back, (q, dq, kp, kd), strict=True):
        np.testing.assert_allclose(got, want)


def _state_bytes(sent: list[bytes]) -> list[P.RobotState]:
    return [P.RobotState.decode(b) for b in sent]


@needs_sdk
def test_adapter_translates_both_ways_and_damps_on_its_watchdog():
    sdk = unitree.load_sdk()
    states, written = [], []
    a = Go2Adapter(
        sdk,
        states.append,
        lambda c: written.append((c.crc, [(m.mode, m.q, m.kp, m.kd) for m in c.motor_cmd])),
        watchdog=0.1,
        damping_kd=1.5,
    )
    mm = a.map
    low = sdk.new_lowstate()
    q = np.linspace(-1.0, 1.0, 12)
    mm.write_state(low, [1.0, 0.0, 0.0, 0.0], [0.1, 0.2, 0.3], q, -q)
    a.on_lowstate(low)
    s = _state_bytes(states)[-1]
    np.testing.assert_allclose(s.q, q, atol=1e-6)
    np.testing.assert_allclose(s.dq, -q, atol=1e-6)
    assert s.robot_mode == P.CommandMode.NONE and low.motor_state[0].q == pytest.approx(q[3])  # FR hip
    bad = sdk.new_lowstate()
    mm.write_state(bad, [0.5, 0.0, 0.0, 0.0], [0.0] * 3, q, q)  # not a unit quaternion
    a.on_lowstate(bad)
    assert len(states) == 1 and a.bad_lowstates == 1

    t0 = time.monotonic()
    a.tick(t0)
    assert not written and a.mode == P.CommandMode.NONE  # nothing before the first command
    sender = P.Sender()
    cmd = P.JointCommand(P.CommandMode.POLICY, q.tolist(), [20.0] * 12, [0.5] * 12, header=sender.next_header())
    a.on_command(cmd.encode())
    a.on_command(
        P.JointCommand(P.CommandMode.POLICY, [0.0] * 16, [1.0] * 16, [1.0] * 16, header=sender.next_header()).encode()
    )
    assert a.rejected["malformed"] == 1
    a.on_command(cmd.encode())  # a replay
    assert a.rejected["out_of_order"] == 1
    answer = P.JointCommand(P.CommandMode.POLICY, q.tolist(), [20.0] * 12, [0.5] * 12, state_seq=s.header.seq,
                            header=sender.next_header())  # fmt: skip
    a.on_command(answer.encode())
    lat = a.inbox.round_trip.take()
    assert len(lat) == 1 and 0.0 <= lat[0] < 5.0  # the state it answers -> its arrival
    a.tick(time.monotonic())
    crc, motors = written[-1]
    assert a.mode == P.CommandMode.POLICY and motors[3] == (1, pytest.approx(q[0]), 20.0, 0.5)
    assert crc == unitree.lowcmd_crc(a.lowcmd)
    a.tick(time.monotonic() + 0.15)  # no command for longer than the watchdog
    _, motors = written[-1]
    assert a.mode == P.CommandMode.DAMPING and all(m[2] == 0.0 and m[3] == 1.5 for m in motors[:12])
    assert "no command" in a.mode_changes[-1][2]
    a.on_lowstate(low)
    assert _state_bytes(states)[-1].robot_mode == P.CommandMode.DAMPING


@needs_sdk
def test_dry_run_never_writes_lowcmd():
    sdk = unitree.load_sdk()
    a = Go2Adapter(sdk, lambda b: None, None)
    sender = P.Sender()
    a.on_command(
        P.JointCommand(P.CommandMode.POLICY, [0.0] * 12, [20.0] * 12, [0.5] * 12, header=sender.next_header()).encode()
    )
    a.tick(time.monotonic())
    assert a.lowcmds_written == 1 and a.last_written is not None  # computed, logged, not sent


@needs_sdk
@pytest.mark.usefixtures("realtime")
def test_full_loop_fake_go2_adapter_bridge(tmp_path):
    """fake Go2 (MuJoCo behind rt/lowstate, rt/lowcmd on loopback DDS) <-> go2_adapter <->
    zenoh <-> bridge <-> the simple gait policy: the robot stands, skates forward under
    a teleop command, stays upright; killing the bridge makes the adapter damp within its
    watchdog; killing the adapter leaves the bridge in its stale-state fault and the
    fake robot damping on its own watchdog."""
    gain, vx = 0.8, 0.5
    policy = write_policy(tmp_path, gait_gain=gain).parent
    port, domain = free_port(), random.randrange(100, 200)
    ns = "t_go2"
    dds = ("--domain-id", str(domain), "--namespace", ns, "--summary-every", "0")
    robot = _spawn("fake_go2", "--listen", f"tcp/127.0.0.1:{port}", "--state-rate", "200", *dds)
    probe = LoopProbe(port, ns)
    states, truths, cmds, statuses, operate = probe.states, probe.truths, probe.cmds, probe.statuses, probe.operate
    adapter = bridge = None

    def start_bridge():
        return _spawn("bridge", "--policy", str(policy), "--connect", f"tcp/127.0.0.1:{port}", "--namespace", ns,
                      "--standup", "linear", "--standup-time", "1.0",
                      "--max-state-age-ms", LOAD_STATE_AGE_MS)  # fmt: skip

    try:
        assert wait_for(lambda: len(truths) > 5, 30.0), "fake Go2 did not start"
        adapter = _spawn(
            "go2_adapter", "--connect", f"tcp/127.0.0.1:{port}", "--cmd-rate", "200",
            "--watchdog-ms", f"{LOAD_WATCHDOG_S * 1e3:g}", *dds,
        )  # fmt: skip
        assert wait_for(lambda: len(states) > 5, 30.0), "adapter forwards no LowState"
        assert states[-1][1].robot_mode == P.CommandMode.NONE
        bridge = start_bridge()
        assert wait_for(lambda: any(c.mode == P.CommandMode.POLICY for _, c in cmds), 30.0), "policy never ran"
        operate(0.0, 1.5)
        n0 = len(truths)
        operate(vx, 3.0)
        moving = truths[n0:]
        dx = moving[-1].pos[0] - moving[0].pos[0]
        dy = moving[-1].pos[1] - moving[0].pos[1]
        print(f"fake Go2 loop: dx {dx:.2f} m, dy {dy:.2f} m in 3 s")
        assert dx > 0.3 and abs(dy) < 0.3 * dx, f"skated dx {dx:.2f} m, dy {dy:.2f} m in 3 s"
        assert min(t.pos[2] for t in truths) > 0.3, "trunk dropped"
        assert max(projected_gravity(s.quat)[2] for _, s in states) < -0.95, "robot tilted"
        assert any(s.robot_mode == P.CommandMode.POLICY for _, s in states)
        st = statuses[-1]
        assert st.state == P.BridgeState.RUNNING and sum(st.rejected) == 0

        # the bridge dies: the adapter writes damping on its watchdog (+ a state period, + slack on a loaded machine)
        bridge.send_signal(signal.SIGKILL)
        bridge.wait(10)
        last_cmd = cmds[-1][0]
        assert wait_for(lambda: states[-1][1].robot_mode == P.CommandMode.DAMPING, 2.0 + LOAD_SLACK_S)
        t_damp = next(t for t, s in states if t > last_cmd and s.robot_mode == P.CommandMode.DAMPING)
        took = f"adapter damped {1e3 * (t_damp - last_cmd):.0f} ms after"
        assert LOAD_WATCHDOG_S - 0.02 <= t_damp - last_cmd <= LOAD_WATCHDOG_S + 0.05 + LOAD_SLACK_S, took

        # a new bridge takes over; then the adapter dies: the bridge faults on stale state
        n1 = len(statuses)
        bridge = start_bridge()
        assert wait_for(lambda: any(s.state == P.BridgeState.RUNNING for s in statuses[n1:]), 30.0), "no 2nd bridge"
        assert wait_for(lambda: states[-1][1].robot_mode == P.CommandMode.POLICY, 5.0)
        adapter.send_signal(signal.SIGKILL)
        adapter.wait(10)
        assert wait_for(lambda: statuses[-1].fault == P.Fault.STALE_STATE, 2.0 + LOAD_SLACK_S), "no fault"
        time.sleep(0.3)  # past the fake robot's own 100 ms watchdog
    finally:
        probe.close()
        _stop(bridge, adapter, robot)
    out = robot.stdout.read() if robot.stdout else ""
    assert "POLICY -> DAMPING (damping commanded)" in out, out[-2000:]  # the adapter's watchdog
    assert "POLICY -> DAMPING (no command for the watchdog time)" in out, out[-2000:]  # the fake's own
    assert "bad CRC 0" in out.splitlines()[-1]


def test_watchdog_damping_leaves_from_the_first_lowcmd_tick_past_the_limit():
    """The adapter (500 Hz, watchdog 100 ms) on the SDK stand-in, whose rt/lowcmd reader is
    called inside the write: after the commands stop, the first damping LowCmd reaches the
    reader no earlier than the watchdog after the last command's arrival and within one
    LowCmd period of it (plus scheduling), in the same tick whose mode change says DAMPING;
    the time the adapter records for it is the write's. Five stops in a row."""
    from sdk_standin import Bus

    sdk = Bus().sdk()
    first_damping: list[float] = []  # the reader's clock at the first damping LowCmd after commands
    commanded = {"on": False}

    def reader(cmd) -> None:
        if commanded["on"] and all(cmd.motor_cmd[i].kp == 0.0 for i in go2.UNITREE_MOTOR.values()):
            first_damping.append(time.monotonic())
            commanded["on"] = False

    sdk.ChannelSubscriber(unitree.LOWCMD_TOPIC, None).Init(reader, 10)
    a = Go2Adapter(sdk, lambda b: None, sdk.ChannelPublisher(unitree.LOWCMD_TOPIC, None).Write, watchdog=0.1)
    sender, q = P.Sender(), go2.default_joint_positions()
    delays = []
    a.start(500.0)
    try:
        for _ in range(5):
            for _ in range(10):  # 0.2 s of commands at 50 Hz
                a.on_command(P.JointCommand(P.CommandMode.POLICY, q, [20.0] * 12, [0.5] * 12,
                                            header=sender.next_header()).encode())  # fmt: skip
                commanded["on"] = True
                time.sleep(0.02)
            last = a.inbox.latest()[1]
            n = len(first_damping)
            assert wait_for(lambda n=n: len(first_damping) > n, 2.0), "no damping LowCmd"
            t_reader = first_damping[-1]
            t_write = a.watchdog_delays()[-1] + last
            t_mode = a.mode_changes[-1][0]
            assert a.mode_changes[-1][1] == P.CommandMode.DAMPING
            assert last + 0.1 <= t_mode <= t_reader <= t_write  # the same tick: mode change, write, its return
            assert t_write - t_reader < 0.05
            delays.append(t_reader - last)
    finally:
        a.stop()
    print("first damping LowCmd after the last command (ms):", [round(1e3 * d, 2) for d in delays])
    assert all(0.1 <= d < 0.1 + 0.002 + 0.1 for d in delays)  # the limit, one 2 ms tick, scheduling slack
