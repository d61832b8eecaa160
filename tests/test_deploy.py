"""Zenoh deployment: protocol, export reader, bridge safety, sim robot, full loop (loopback only)."""

from __future__ import annotations

import contextlib
import math
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
import zenoh

from legged_casters.deploy import protocol as P
from legged_casters.deploy import transport
from legged_casters.deploy.bridge import Bridge, BridgeConfig, ZenohBridge, warm_up
from legged_casters.deploy.policy import (
    ObservationBuilder,
    PolicyFormatError,
    PolicyRunner,
    load_meta,
    projected_gravity,
)
from legged_casters.deploy.sim_robot import ZenohSimRobot
from legged_casters.deploy.simple_policy import DEFAULT_TERMS, write_policy
from legged_casters.deploy.standup import Righting, RightingCfg, StandUp, StandUpCfg
from legged_casters.robot import build, go2
from legged_casters.utils.math import quat_rotate_inverse

REPO = Path(__file__).resolve().parents[1]
DT = 0.02
THIGHS = [i for i, j in enumerate(go2.ACTUATED_JOINTS) if "_thigh_" in j]
HIPS = [go2.ACTUATED_JOINTS.index(f"{leg}_hip_joint") for leg in ("FL", "FR", "RL")]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def realtime():
    """SCHED_FIFO for this thread and the threads it starts (zenoh's, the bridge's): the
    timing tests measure our code, not the other jobs on a shared machine. Falls back
    to normal priority where the OS refuses."""
    old = os.sched_getscheduler(0), os.sched_getparam(0)
    transport.set_realtime(10)
    yield
    with contextlib.suppress(OSError):
        os.sched_setscheduler(0, old[0], old[1])


def peer(listen: int | None = None, connect: int | None = None) -> zenoh.Session:
    return zenoh.open(
        transport.make_config(
            "peer",
            listen=[f"tcp/127.0.0.1:{listen}"] if listen else None,
            connect=[f"tcp/127.0.0.1:{connect}"] if connect else None,
        )
    )


def wait_for(cond, timeout: float, period: float = 0.005) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(period)
    return cond()


def standing_state(sender: P.Sender, q=None, stamp_ns: int | None = None) -> P.RobotState:
    h = sender.next_header()
    if stamp_ns is not None:
        h.stamp_ns = stamp_ns
    q = go2.default_joint_positions() if q is None else q
    return P.RobotState([1.0, 0.0, 0.0, 0.0], [0.0] * 3, list(q), [0.0] * 12, header=h)


class FakeRobot:
    """Feeds a Bridge standing states on an absolute 50 Hz clock, in a thread (`quat`:
    the trunk's orientation, upright unless set)."""

    def __init__(self, deliver, q=None, period: float = DT):
        self.deliver, self.q, self.period = deliver, q, period
        self.quat = [1.0, 0.0, 0.0, 0.0]
        self.sender = P.Sender()
        self.running = True
        self.paused = False
        self.stamp_offset = 0.0  # s added to the stamps (a robot clock jump)
        self.frozen_stamp: int | None = None  # a robot clock that stopped
        self.last_publish = 0.0
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        t0 = time.monotonic()
        k = 0
        while self.running:
            deadline = t0 + k * self.period
            time.sleep(max(0.0, deadline - time.monotonic()))
            if not self.paused:
                stamp = int((deadline + self.stamp_offset) * 1e9) if self.frozen_stamp is None else self.frozen_stamp
                state = standing_state(self.sender, self.q, stamp)
                state.quat = list(self.quat)
                self.deliver(state.encode())
                self.last_publish = time.monotonic()
            k += 1

    def stop(self):
        self.running = False
        self.thread.join(1.0)


class Recorder:
    """Collects published (time, JointCommand) pairs from a Bridge's publish callback."""

    def __init__(self):
        self.cmds: list[tuple[float, P.JointCommand]] = []
        self.statuses: list[P.BridgeStatus] = []
        self.lock = threading.Lock()

    def __call__(self, which: str, payload: bytes):
        now = time.monotonic()
        with self.lock:
            if which == "cmd":
                self.cmds.append((now, P.JointCommand.decode(payload)))
            else:
                self.statuses.append(P.BridgeStatus.decode(payload))

    def modes(self):
        with self.lock:
            return [c.mode for _, c in self.cmds]


def op(sender: P.Sender, vx=0.0, flags=0, prop=P.PropulsionMode.FOUR_WHEEL) -> bytes:
    return P.OperatorCommand(vx, 0.0, 0.0, prop, flags, sender.next_header()).encode()


# --- protocol ------------------------------------------------------------------------------
def test_protocol_roundtrip_and_typed_rejections():
    s = P.Sender()
    st = standing_state(s)
    st.gyro = [0.1, -0.2, 0.3]
    back = P.RobotState.decode(st.encode())
    assert np.allclose(back.q, st.q, atol=1e-6) and np.allclose(back.gyro, st.gyro, atol=1e-6)
    assert back.header.seq == st.header.seq and back.header.epoch == s.epoch
    cmd = P.JointCommand(P.CommandMode.POLICY, [0.1] * 12, [60.0] * 12, [1.5] * 12, 7, s.next_header())
    c2 = P.JointCommand.decode(cmd.encode())
    assert c2.state_seq == 7 and np.allclose(c2.kp, 60.0)
    o = P.OperatorCommand.decode(op(s, 0.5, P.OP_STOP))
    assert o.stop and not o.reset and math.isclose(o.vx, 0.5)
    status = P.BridgeStatus(state=P.BridgeState.RUNNING, rejected=[1, 2, 3, 4, 5], commands=9, rate_hz=50.0)
    st2 = P.BridgeStatus.decode(status.encode())
    assert st2.rejected_by_reason()["out_of_order"] == 5 and st2.commands == 9 and st2.rate_hz == 50.0

    good = st.encode()
    cases = {
        "malformed": [good[:-1], good + b"\0", b"", b"\x00" * P.RobotState.size(), cmd.encode()],
        "version": [good[:2] + bytes([P.VERSION + 1]) + good[3:]],
        "nonfinite": [],
        "out_of_range": [],
    }
    for bad in (float("nan"), float("inf")):
        x = standing_state(s)
        x.q[3] = bad
        cases["nonfinite"].append(x.encode())  # struct packs NaN / inf; decoding must refuse them
    x = standing_state(s)
    x.quat = [2.0, 0.0, 0.0, 0.0]
    cases["out_of_range"].append(x.encode())
    for flags in (0x01, 0x80):  # no state flag bits are defined: docs/protocol.md
        x = standing_state(s)
        x.flags = flags
        cases["out_of_range"].append(x.encode())
    for reason, payloads in cases.items():
        for buf in payloads:
            with pytest.raises(P.ProtocolError) as e:
                P.RobotState.decode(buf)
            assert e.value.reason == reason
    with pytest.raises(ValueError):  # a non-finite command cannot even be encoded
        P.JointCommand(P.CommandMode.POLICY, [float("nan")] * 12, [0.0] * 12, [0.0] * 12).encode()


def test_sequence_filter_replay_reorder_restart():
    f = P.SequenceFilter()
    f.check(P.Header(epoch=1, seq=5))
    for seq in (5, 4, 0):
        with pytest.raises(P.ProtocolError, match="out_of_order"):
            f.check(P.Header(epoch=1, seq=seq))
    f.check(P.Header(epoch=1, seq=9))
    f.check(P.Header(epoch=2, seq=0))  # the sender restarted: new epoch accepted
    with pytest.raises(P.ProtocolError, match="replaced"):
        f.check(P.Header(epoch=1, seq=100))  # a replay of the old session cannot take over


def test_a_far_future_seq_cannot_lock_the_stream_out():
    """One message of the current epoch with a seq far ahead is rejected; the real stream
    goes on; a gap within the window (lost messages) is accepted."""
    f = P.SequenceFilter()
    f.check(P.Header(epoch=1, seq=10))
    with pytest.raises(P.ProtocolError, match="jumps more than"):
        f.check(P.Header(epoch=1, seq=0xFFFFFFFF))
    f.check(P.Header(epoch=1, seq=11))
    f.check(P.Header(epoch=1, seq=11 + P.SequenceFilter.WINDOW))
    assert f.last_seq == 11 + P.SequenceFilter.WINDOW


def test_reanchor_accepts_the_next_message_whatever_its_seq():
    """A message inside the window that ran ahead of the real stream makes it out of order;
    reanchor() takes the next message of the epoch as the new anchor, once, and a replaced
    epoch stays rejected."""
    f = P.SequenceFilter(window=10)
    f.check(P.Header(epoch=1, seq=5))
    f.check(P.Header(epoch=1, seq=15))  # ran ahead, within the window
    for seq in (6, 7):
        with pytest.raises(P.ProtocolError, match="out_of_order"):
            f.check(P.Header(epoch=1, seq=seq))
    f.reanchor()
    f.check(P.Header(epoch=1, seq=8))  # behind the anchor: accepted after the re-anchor
    f.check(P.Header(epoch=1, seq=9))
    with pytest.raises(P.ProtocolError, match="out_of_order"):
        f.check(P.Header(epoch=1, seq=9))  # once only: replays are rejected again
    f.check(P.Header(epoch=2, seq=1000))  # a new epoch may start at any seq
    f.reanchor()
    with pytest.raises(P.ProtocolError, match="replaced"):
        f.check(P.Header(epoch=1, seq=10))
    f.check(P.Header(epoch=2, seq=3))


def test_operator_filter_accepts_each_seq_once_and_follows_a_jump_only_when_continued():
    """The operator stream: a jump within the window leaves the real stream behind it
    accepted (each seq once); a jump further ahead, or another epoch, is held until a
    second message continues it; replays and replaced epochs are rejected."""
    H = P.Header
    f = P.OperatorFilter(window=8)
    f.check(H(1, 10))  # the first epoch is accepted at once
    f.check(H(1, 18))  # 8 ahead: accepted
    for seq in (11, 12, 17):  # the stream it jumped over: accepted, once each
        f.check(H(1, seq))
    for seq, why in ((12, "accepted before"), (18, "accepted before"), (17, "accepted before"), (10, "behind")):
        with pytest.raises(P.ProtocolError, match=why):
            f.check(H(1, seq))
    for far in (27, 0xFFFFFFFF, 1000):  # one message far ahead is held, and changes nothing
        with pytest.raises(P.ProtocolError, match="held"):
            f.check(H(1, far))
        assert f.last_seq == 18
    f.check(H(1, 19))  # the real stream goes on, and drops the held jump:
    with pytest.raises(P.ProtocolError, match="held"):
        f.check(H(1, 1001))  # a second stray message later does not continue the first
    f.check(H(1, 20))
    with pytest.raises(P.ProtocolError, match="new epoch"):
        f.check(H(2, 0))  # another epoch: held
    f.check(H(2, 1))  # the new epoch continues: followed (a restarted operator)
    assert (f.epoch, f.last_seq) == (2, 1)
    with pytest.raises(P.ProtocolError, match="replaced"):
        f.check(H(1, 21))
    with pytest.raises(P.ProtocolError, match="held"):
        f.check(H(2, 100))  # a real gap of more than the window ...
    f.check(H(2, 101))  # ... is followed from the second message after it
    assert f.last_seq == 101


def test_zenoh_config_file_pass_through(tmp_path):
    port = free_port()
    f = tmp_path / "zenoh.json5"
    f.write_text(
        f'{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }},\n'
        "  scouting: { multicast: { enabled: true } },\n"
        "  transport: { link: { tls: { enable_mtls: true } } } }\n"
    )
    cfg = transport.make_config(config_file=f)
    assert cfg.get_json("transport/link/tls/enable_mtls") == "true"  # file settings kept
    assert cfg.get_json("scouting/multicast/enabled") == "false"  # scouting only with --multicast-scouting
    assert cfg.get_json("mode") == '"peer"'
    assert transport.make_config("client", config_file=f).get_json("mode") == '"client"'
    a = zenoh.open(cfg)  # the file's endpoint is used: a second session reaches it
    b = peer(connect=port)
    got = []
    try:
        sub = a.declare_subscriber("t_cfg/x", lambda s: got.append(s.payload.to_bytes()))
        pub = b.declare_publisher("t_cfg/x")
        assert wait_for(lambda: (pub.put(b"hi"), bool(got))[1], 5.0, period=0.05)
        sub.undeclare()
    finally:
        b.close()
        a.close()


def test_client_mode_reaches_a_listening_peer():
    port = free_port()
    a = peer(listen=port)
    b = zenoh.open(transport.make_config("client", connect=[f"tcp/127.0.0.1:{port}"]))
    got = []
    try:
        sub = a.declare_subscriber("t_client/x", lambda s: got.append(s.payload.to_bytes()))
        pub = b.declare_publisher("t_client/x")
        assert wait_for(lambda: (pub.put(b"hi"), bool(got))[1], 5.0, period=0.05)
        sub.undeclare()
    finally:
        b.close()
        a.close()


# --- export reader / observation -----------------------------------------------------------
def test_observation_matches_training_conventions(tmp_path):
    meta = load_meta(write_policy(tmp_path))
    rng = np.random.default_rng(1)
    quat = rng.normal(size=4)
    quat /= np.linalg.norm(quat)
    ref = quat_rotate_inverse(torch.tensor(quat[None]), torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64))
    assert np.allclose(projected_gravity(quat), ref.numpy()[0], atol=1e-12)

    q = np.asarray(go2.default_joint_positions()) + rng.normal(0, 0.1, 12)
    state = P.RobotState(list(quat), [1.0, 2.0, 3.0], list(q), list(rng.normal(0, 2, 12)))
    last = rng.normal(0, 1, 12).astype(np.float32)
    obs = ObservationBuilder(meta).build(state, [0.5, -0.2, 0.3], [0, 0, 1, 1], last).copy()
    expect = np.concatenate(
        [
            [0.5, -0.2, 0.3],
            [0, 0, 1, 1],
            np.asarray(state.gyro) * 0.25,
            projected_gravity(quat),
            q - meta.default_joint_pos,
            np.asarray(state.dq) * 0.05,
            last,
        ]
    )
    assert obs.shape == (49,) and np.allclose(obs, expect, atol=1e-6)


def test_sim_imu_matches_trunk_orientation():
    """The IMU site is aligned with the trunk: gravity from imu_quat equals the training
    env's gravity from the free joint's quaternion, and imu_gyro equals qvel[3:6]."""
    m = mujoco.MjModel.from_xml_path(str(build.MODEL_FILES["caster"]))
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    d.qpos[3:7] = [0.96, 0.1, -0.2, 0.15]
    d.qpos[3:7] /= np.linalg.norm(d.qpos[3:7])
    d.qvel[3:6] = [0.3, -0.5, 0.8]
    mujoco.mj_forward(m, d)
    sq = d.sensor("imu_quat").data
    assert np.allclose(projected_gravity(sq), projected_gravity(d.qpos[3:7]), atol=1e-9)
    assert np.allclose(d.sensor("imu_gyro").data, d.qvel[3:6], atol=1e-9)


def test_onnx_and_torchscript_agree(tmp_path):
    meta = load_meta(write_policy(tmp_path, crouch_gain=0.7, bias=np.linspace(-0.1, 0.1, 12)))
    onnx_p, ts_p = PolicyRunner(meta, "onnx"), PolicyRunner(meta, "torchscript")
    obs = np.random.default_rng(2).normal(size=49).astype(np.float32)
    assert np.allclose(onnx_p(obs), ts_p(obs), atol=1e-6)
    assert math.isclose(
        float(onnx_p(obs)[THIGHS[0]]), 0.7 * obs[0] + float(np.linspace(-0.1, 0.1, 12)[1]), rel_tol=1e-5
    )


def test_unknown_or_unmeasurable_obs_term_rejected_at_startup(tmp_path):
    bad = [*DEFAULT_TERMS[:2], {"name": "foot_clearance", "dim": 4, "scale": 1.0}]
    with pytest.raises(PolicyFormatError, match="unknown observation term 'foot_clearance'") as e:
        load_meta(write_policy(tmp_path / "a", terms=bad))
    for known in ("commands", "projected_gravity", "joint_vel", "mode_mask"):
        assert known in str(e.value)
    flat = [{"name": "base_lin_vel", "dim": 3, "scale": 2.0}, *DEFAULT_TERMS]
    with pytest.raises(PolicyFormatError, match="base_lin_vel.*real Go2 does not measure"):
        load_meta(write_policy(tmp_path / "b", terms=flat))
    # the command-line bridge fails before opening zenoh, with the same message
    r = subprocess.run(
        [sys.executable, "-m", "legged_casters.deploy.bridge", "--policy", str(tmp_path / "b")],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert r.returncode == 2 and "base_lin_vel" in r.stderr and "real Go2" in r.stderr
    assert "Traceback" not in r.stderr


def test_sim_robot_pd_uses_each_commands_gains_and_torque_limits():
    from legged_casters.deploy.sim_robot import SimRobot

    sent = []
    r = SimRobot(lambda which, payload: sent.append((which, payload)), state_rate=500.0, watchdog=0.1)
    s = P.Sender()
    q_before, dq_before = r.data.qpos[r.qadr].copy(), r.data.qvel[r.dadr].copy()
    target = q_before + 0.1
    kp, kd = np.linspace(5.0, 30.0, 12), np.full(12, 0.5)
    kp[2] = 2000.0  # FL calf: saturates
    now = time.monotonic()
    r.on_command(P.JointCommand(P.CommandMode.POLICY, target, kp, kd, 0, s.next_header()).encode())
    r.step(now, int(now * 1e9))
    expect = np.clip(kp * (target - q_before) - kd * dq_before, -r.tau_limit, r.tau_limit)
    assert np.allclose(r.data.ctrl[r.act], expect, atol=1e-9)
    assert math.isclose(r.data.actuator_force[r.act[2]], go2.TORQUE_LIMIT["calf"], rel_tol=1e-9)
    assert r.mode is P.CommandMode.POLICY
    st = P.RobotState.decode(next(p for w, p in sent if w == "state"))
    assert np.allclose(st.q, q_before, atol=1e-6) and st.robot_mode == P.CommandMode.HOLD  # state before the step
    dq_before = r.data.qvel[r.dadr].copy()
    r.step(now + 0.15, int((now + 0.15) * 1e9))  # 150 ms without commands: watchdog -> damping
    assert r.mode is P.CommandMode.DAMPING
    assert np.allclose(r.data.ctrl[r.act], -1.0 * dq_before, atol=1e-9)  # kp = 0, kd = damping_kd = 1


# --- bridge logic (no zenoh) ---------------------------------------------------------------
def _bridge(tmp_path, rec, **kw) -> Bridge:
    policy_kw = {k: kw.pop(k) for k in ("crouch_gain", "nan_above", "bias") if k in kw}
    meta = load_meta(write_policy(tmp_path, **policy_kw))
    # staleness is tested over zenoh below; here a generous limit keeps a loaded machine from tripping it
    kw.setdefault("max_state_age", 0.5)
    kw.setdefault("operator_timeout", 0.0)
    kw.setdefault("standup", "linear")  # short: these tests are about what follows it
    cfg = BridgeConfig(standup_time=kw.pop("standup_time", 0.1), **kw)
    return Bridge(meta, cfg, rec)


def test_warm_up_leaves_no_first_time_work_for_the_control_path(tmp_path):
    """bridge.warm_up (run by the bridge before its session opens) takes a scratch bridge
    through righting, the fold, the policy, a stop, a reset and a stale-state fault, with
    a status after every state; after it, a real bridge's stand-up, policy steps and
    statuses import no module (a first np.percentile imported numpy.ma inside the status,
    under the lock that the next state waits on)."""
    meta = load_meta(write_policy(tmp_path))
    runner = PolicyRunner(meta)
    scratch = warm_up(meta, BridgeConfig(), runner)
    went = [(s, f) for _, s, f in scratch.transitions]
    for step in [(P.BridgeState.RUNNING, P.Fault.NONE), (P.BridgeState.STOPPED, P.Fault.OPERATOR_STOP),
                 (P.BridgeState.WAITING, P.Fault.NONE), (P.BridgeState.DAMPING, P.Fault.STALE_STATE)]:  # fmt: skip
        assert step in went, went
    assert scratch.policy_steps > 0 and any("righting" in n for n in scratch.notes)
    assert "numpy.ma" in sys.modules
    before = set(sys.modules)
    rec = Recorder()
    b = Bridge(meta, BridgeConfig(standup="linear", standup_time=0.1, max_state_age=60.0), rec, runner)
    sender = P.Sender()
    for k in range(12):
        b.on_state(standing_state(sender, stamp_ns=k * int(DT * 1e9)).encode())
        b.status().encode()
    assert b.state is P.BridgeState.RUNNING and b.policy_steps > 0 and b.status().rate_hz > 0
    assert set(sys.modules) == before, sorted(set(sys.modules) - before)


def test_no_motion_before_state_then_linear_standup_ramp(tmp_path, realtime):
    rec = Recorder()
    b = _bridge(tmp_path, rec, standup_time=0.2)
    b.start()
    try:
        time.sleep(0.15)
        assert rec.modes() == [] and b.state is P.BridgeState.WAITING
        crouch = np.asarray(go2.default_joint_positions()) + np.tile([0.0, 0.4, -0.5], 4)
        robot = FakeRobot(b.on_state, q=crouch)
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)
        robot.stop()
    finally:
        b.stop()
    cmds = [c for _, c in rec.cmds]
    ramp = [c for c in cmds if c.mode == P.CommandMode.STANDUP]
    assert len(ramp) == 10  # 0.2 s at 50 Hz
    assert np.allclose(ramp[0].q, crouch + 0.1 * (b.default - crouch), atol=1e-5)  # starts at the measured pose
    assert np.allclose(ramp[-1].q, b.default, atol=1e-5)
    assert all(np.allclose(c.kp, go2.kp()) for c in ramp)


def test_fold_standup_folds_tucks_and_lifts_to_the_default_pose(tmp_path, realtime):
    rec = Recorder()
    b = _bridge(tmp_path, rec, standup="fold", standup_time=0.4)
    crouch = np.asarray(go2.default_joint_positions()) + np.tile([0.3, 0.4, -0.5], 4)
    robot = FakeRobot(b.on_state, q=crouch)  # upright trunk: no attitude feedback
    b.start()
    try:
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 4.0)
    finally:
        robot.stop()
        b.stop()
    ramp = np.array([c.q for _, c in rec.cmds if c.mode == P.CommandMode.STANDUP])
    su = StandUpCfg(lift_time=0.4)
    assert len(ramp) == round(su.duration / DT)  # fold 0.5 s + tuck 0.7 s + lift 0.4 s at 50 Hz
    fold = ramp[: round(su.fold_time / DT)]
    assert np.allclose(fold[:, 0::3], crouch[0::3]) and np.allclose(fold[:, 1::3], crouch[1::3])  # hips, thighs hold
    assert np.allclose(fold[-1, 2::3], su.tuck[2])  # calves folded
    tucked = ramp[round((su.fold_time + su.tuck_time) / DT) - 1]
    assert np.allclose(tucked, np.tile(su.tuck, 4), atol=1e-6)
    assert np.allclose(ramp[-1], b.default, atol=1e-6)


def test_fold_standup_levels_the_trunk_with_its_legs_and_hips():
    """Nose up (gravity towards -x in the trunk frame): the front legs give way and the rear
    legs push; rolled onto the right side (gravity towards -y): the right legs push, the
    left ones give way and the hips turn to roll it back."""
    names = go2.ACTUATED_JOINTS
    su = StandUp(names, np.asarray(go2.default_joint_positions()))
    t = su.cfg.fold_time + su.cfg.tuck_time + 0.5 * su.cfg.lift_time
    level = su.targets(t, np.zeros(12), np.array([0.0, 0.0, -1.0])).reshape(4, 3)
    nose_up = su.targets(t, np.zeros(12), np.array([-0.2, 0.0, -0.98])).reshape(4, 3) - level
    right_down = su.targets(t, np.zeros(12), np.array([0.0, -0.2, -0.98])).reshape(4, 3) - level
    front, left = np.array([go2.leg_signs(leg) for leg in go2.LEGS]).T
    ext = nose_up[:, 2]  # calf: +1 per unit of extension (thigh -1/2)
    assert np.allclose(ext, -0.4 * front) and np.allclose(nose_up[:, 1], 0.2 * front)
    assert np.allclose(right_down[:, 2], -0.4 * left) and np.allclose(right_down[:, 0], 0.3)
    assert list(names[:3]) == ["FL_hip_joint", "FL_thigh_joint", "FL_calf_joint"]
    with pytest.raises(ValueError, match="linear"):
        StandUp(["a", "b"], np.zeros(2))


def test_righting_keyframes_are_mirrored_by_the_side_that_lies_down():
    """The legs on the lower side get the keyframe's first half whichever side that is;
    hips turn outwards by the same angle on both sides; every target is clipped to the
    joint limits and the motion ends on the last keyframe."""
    names = list(go2.ACTUATED_JOINTS)
    limits = np.array(go2.joint_ranges())  # the rear thighs' range differs from the front ones
    cfg = RightingCfg()
    r = Righting(names, cfg, limits)
    start = np.asarray(go2.default_joint_positions())
    end = sum(cfg.durations)
    left_down = r.targets(end, start, 1.0).reshape(4, 3)  # FL, FR, RL, RR
    right_down = r.targets(end, start, -1.0).reshape(4, 3)
    mirror = np.array([1, 0, 3, 2])  # FL <-> FR, RL <-> RR
    assert np.allclose(left_down[:, 1:], right_down[mirror, 1:])
    assert np.allclose(left_down[:, 0], -right_down[mirror, 0])
    last = np.array(cfg.keyframes[-1])
    expect_fl = np.clip([last[0], last[1], last[3]], limits[:3, 0], limits[:3, 1])  # FL on the lower side
    expect_rr = np.clip([-last[4], last[6], last[7]], limits[9:, 0], limits[9:, 1])  # RR: upper side, hip mirrored
    assert np.allclose(left_down[0], expect_fl) and np.allclose(left_down[3], expect_rr)
    assert np.allclose(r.targets(0.0, start, 1.0), start)  # starts from the measured pose
    batch = r.targets(np.array([0.3, end]), np.stack([start, start]), np.array([1.0, -1.0]))
    assert np.allclose(batch[0], r.targets(0.3, start, 1.0)) and np.allclose(batch[1], right_down.ravel())
    assert r.needed(np.array([0.0, 0.0, 1.0])) and not r.needed(np.array([0.0, -0.5, -0.86]))  # 180 / 31 deg
    assert r.needed(np.array([0.0, -0.7, -0.71]), 40.0) and not r.needed(np.array([0.0, -0.7, -0.71]), 60.0)
    for bad in (
        {"durations": (0.5,)},
        {"keyframes": ((0.0,) * 7,), "durations": (0.5,)},
        {"durations": (0.5, 0.0, 0.5)},
        {"start_tilt_deg": 70.0},
        {"max_tries": 0},
    ):
        with pytest.raises(ValueError, match="righting"):
            RightingCfg(**bad)


def _feed(b: Bridge, sender: P.Sender, steps: int, k0: int, quat, q=None) -> int:
    """Deliver `steps` states 20 ms apart (robot clock k * DT) to a bridge in this thread."""
    for k in range(k0, k0 + steps):
        state = standing_state(sender, q, int(k * DT * 1e9))
        state.quat = list(quat)
        b.on_state(state.encode())
    return k0 + steps


def test_a_robot_on_its_back_is_righted_first_and_damped_after_the_last_try(tmp_path):
    """Upside down (tilt 180 deg): the stand-up sends the righting targets; a robot still on
    its back after each try starts another, and after max_tries the bridge damps with
    FALLEN. Once upright after a try, the fold stand-up starts from the pose it is in."""
    upside_down, upright = [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    rec = Recorder()
    b = _bridge(tmp_path, rec, standup="fold", max_state_age=1e3)
    sender = P.Sender()
    r = b.righting
    per_try = math.ceil(r.duration / DT - 1e-9)  # control steps of a try: the last one judges the tilt
    k = _feed(b, sender, per_try * r.cfg.max_tries, 0, upside_down)
    assert b.state is P.BridgeState.DAMPING and b.fault is P.Fault.FALLEN
    assert "after righting, after 3 stand-up tries" in b.fault_detail
    assert [n.split(" (")[0] for n in b.notes] == [f"STANDUP: righting, try {i} of 3" for i in (1, 2, 3)]
    cmds = [c for _, c in rec.cmds if c.mode == P.CommandMode.STANDUP]
    start = np.asarray(go2.default_joint_positions())
    side = float(Righting.side_down(np.array([0.0, 0.0, 1.0])))
    for i in (0, per_try // 2, per_try - 1):
        assert np.allclose(cmds[i].q, r.targets((i + 1) * DT, start, side), atol=1e-5)
    assert np.allclose(cmds[per_try].q, r.targets(DT, start, side), atol=1e-5)  # try 2 starts over

    rec2 = Recorder()
    b2 = _bridge(tmp_path, rec2, standup="fold", max_state_age=1e3)
    k = _feed(b2, sender, per_try - 1, k, upside_down)
    crouch = start + np.tile([0.2, 0.3, -0.4], 4)
    k = _feed(b2, sender, round(b2.folding.duration / DT) + 2, k, upright, crouch)
    assert b2.state is P.BridgeState.RUNNING and len(b2.notes) == 1
    fold = [c.q for _, c in rec2.cmds if c.mode == P.CommandMode.STANDUP][per_try:]
    assert np.allclose(fold[0], b2.folding.targets(DT, crouch, np.array([0.0, 0.0, -1.0])), atol=1e-5)

    # a fold that ends tilted 30 deg (rolled about +x: right side down, propped up, not standing)
    # does not start the policy; one that tips the trunk to 70 deg is cut short: both right it again
    tilted_30, tilted_70 = [math.cos(math.radians(15)), math.sin(math.radians(15)), 0.0, 0.0], [
        math.cos(math.radians(35)), math.sin(math.radians(35)), 0.0, 0.0]  # fmt: skip
    b4 = _bridge(tmp_path, Recorder(), standup="fold", max_state_age=1e3)
    fold_steps = math.ceil(b4.folding.duration / DT - 1e-9)
    k = _feed(b4, sender, fold_steps, k, tilted_30)
    assert b4.state is P.BridgeState.STANDUP and b4.notes == [
        "STANDUP: righting, try 2 of 3 (trunk tilted 30 deg, right side down)"]  # fmt: skip
    # still lying tilted 30 deg: each righting hands over to a fold (under 40 deg), which ends
    # tilted again; the third failed try damps it
    k = _feed(b4, sender, 2 * (per_try + fold_steps) - 1, k, tilted_30)
    assert b4.state is P.BridgeState.STANDUP and len(b4.notes) == 2
    k = _feed(b4, sender, 1, k, tilted_30)
    assert b4.state is P.BridgeState.DAMPING and b4.fault is P.Fault.FALLEN and len(b4.notes) == 2
    assert b4.fault_detail == "trunk tilted 30 deg after the fold, after 3 stand-up tries"
    b5 = _bridge(tmp_path, Recorder(), standup="fold", max_state_age=1e3)
    k = _feed(b5, sender, 5, k, upright)
    k = _feed(b5, sender, 1, k, tilted_70)
    assert b5.righting_side is not None and b5.notes[0].startswith("STANDUP: righting, try 2 of 3 (trunk tilted 70")

    rec3 = Recorder()
    b3 = _bridge(tmp_path, rec3, standup="fold", righting=False, max_state_age=1e3)
    assert b3.righting is None
    _feed(b3, sender, 3, k, upside_down)
    assert b3.state is P.BridgeState.STANDUP and not b3.notes
    assert np.allclose(rec3.cmds[0][1].q, b3.folding.targets(DT, start, np.array([0.0, 0.0, 1.0])), atol=1e-5)


def test_a_fall_while_running_damps_until_a_reset_stands_it_up_again(tmp_path, realtime):
    rec = Recorder()
    b = _bridge(tmp_path, rec, standup_time=0.1)
    robot = FakeRobot(b.on_state)
    b.start()
    try:
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING and b.policy_steps > 3, 2.0)
        half = math.radians(50.0) / 2  # rolled 50 deg: beyond the default 45
        robot.quat = [math.cos(half), math.sin(half), 0.0, 0.0]
        assert wait_for(lambda: b.state is P.BridgeState.DAMPING, 1.0)
        assert b.fault is P.Fault.FALLEN and "50 deg" in b.fault_detail
        assert rec.cmds[-1][1].mode == P.CommandMode.DAMPING
        time.sleep(0.1)
        assert b.state is P.BridgeState.DAMPING  # latched: the robot lies as it fell
        robot.quat = [1.0, 0.0, 0.0, 0.0]
        operator = P.Sender()
        b.on_operator(P.OperatorCommand(flags=P.OP_RESET, header=operator.next_header()).encode())
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)  # stood up again
    finally:
        robot.stop()
        b.stop()


def _run_against_a_500hz_robot(b: Bridge, policy_steps: int) -> None:
    """Start `b`, stream it standing states at 500 Hz (a Go2's rate) until it has taken
    `policy_steps` policy steps, then stop the stream (the bridge keeps running)."""
    b.start()
    robot = FakeRobot(b.on_state, period=0.002)
    try:
        assert wait_for(lambda: b.policy_steps >= policy_steps, 3.0)
    finally:
        robot.stop()


def test_policy_steps_on_the_robot_clock_with_a_fast_state_stream(tmp_path, realtime):
    """A Go2 publishes state at 500 Hz: the bridge answers exactly every 10th state (its
    timestamp reaches the next 20 ms deadline), not every state, not on its own clock."""
    rec = Recorder()
    b = _bridge(tmp_path, rec, standup_time=0.1)
    try:
        _run_against_a_500hz_robot(b, 30)
    finally:
        b.stop()
    seqs = [c.state_seq for _, c in rec.cmds]
    assert len(seqs) >= 35 and set(np.diff(seqs)) == {10}, np.diff(seqs)
    ts = [t for t, c in rec.cmds]
    assert abs(np.mean(np.diff(ts)) - DT) < 0.001


def test_the_trace_stamps_each_answered_states_arrival_before_its_answer(tmp_path, realtime):
    """--trace: for every command that answers a state, that state's seq, its arrival and
    the command's own send stamp, on the same monotonic clock; damping on the bridge's
    timer (no state answered) is not traced."""
    rec = Recorder()
    b = _bridge(tmp_path, rec, standup_time=0.1, max_state_age=0.05)
    b.start_trace(steps=1000)
    _run_against_a_500hz_robot(b, 10)
    assert wait_for(lambda: b.state is P.BridgeState.DAMPING, 1.0)  # stale: damping on the bridge's own timer
    time.sleep(3 * DT)
    b.stop()
    path = tmp_path / "trace.csv"
    rows = b.write_trace(path)
    lines = path.read_text().splitlines()
    assert lines[0] == "state_seq,arrival_ns,sent_ns" and len(lines) == rows + 1
    trace = [tuple(int(x) for x in line.split(",")) for line in lines[1:]]
    answered = [(c.state_seq, c.header.stamp_ns) for _, c in rec.cmds if c.state_seq != P.NO_STATE_SEQ]
    assert any(c.state_seq == P.NO_STATE_SEQ for _, c in rec.cmds)  # the timer's damping, not in the trace
    assert [(seq, sent) for seq, _, sent in trace] == answered
    for _, arrival, sent in trace:
        assert 0 <= sent - arrival < 50_000_000  # arrival, then the step and the send on the same clock
    capped = _bridge(tmp_path, Recorder())
    capped.start_trace(steps=3)
    capped.trace.extend([(1, 0, 0)] * 5)
    assert len(capped.trace) == 3  # the newest `steps` commands only


def test_local_clock_mode_steps_on_the_bridge_clock(tmp_path, realtime):
    """--clock local: absolute deadlines of the bridge's own clock, newest state each time."""
    rec = Recorder()
    b = _bridge(tmp_path, rec, standup_time=0.1, clock="local")
    b.start()
    robot = FakeRobot(b.on_state, period=0.002)
    try:
        assert wait_for(lambda: b.policy_steps >= 40, 3.0)
        with b._cv:
            stale_ok = b.state is P.BridgeState.RUNNING
            n_running = len(rec.cmds)
        robot.paused = True  # and the staleness rule still applies
        assert wait_for(lambda: b.state is P.BridgeState.DAMPING, 0.5)
    finally:
        robot.stop()
        b.stop()
    assert stale_ok
    steps = [(t, c) for t, c in rec.cmds[:n_running] if c.mode in (P.CommandMode.STANDUP, P.CommandMode.POLICY)]
    ts = np.array([t for t, _ in steps])
    assert abs(np.mean(np.diff(ts)) - DT) < 0.001 and np.max(np.abs(np.diff(ts) - DT)) < 0.015
    seq_steps = np.diff([c.state_seq for _, c in steps])
    assert 9.0 <= np.mean(seq_steps) <= 11.0  # about every 10th state of a 500 Hz stream, the newest one


def test_robot_clock_jump_reanchors_and_frozen_clock_gives_damping(tmp_path, realtime):
    rec = Recorder()
    b = _bridge(tmp_path, rec, max_state_age=0.1)
    b.start()
    robot = FakeRobot(b.on_state)
    try:
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)
        robot.stamp_offset = -5.0  # the robot's clock restarts 5 s back: keep stepping every state
        n = b.policy_steps
        time.sleep(0.3)
        assert b.state is P.BridgeState.RUNNING and b.policy_steps >= n + 10
        robot.frozen_stamp = int(time.monotonic() * 1e9)  # states keep coming, their clock stands still
        t_freeze = time.monotonic()
        assert wait_for(lambda: b.state is P.BridgeState.DAMPING, 1.0)
        assert b.fault is P.Fault.STALE_STATE and time.monotonic() - t_freeze < 0.1 + 2 * DT + 0.05
    finally:
        robot.stop()
        b.stop()


def test_a_robot_clock_one_to_two_periods_back_latches_a_stale_state_fault(tmp_path, realtime):
    """docs/deploy.md, Clock: a 50 Hz robot clock that steps back 1.5 periods is not taken
    for a restart (that needs more than two); no state reaches the next deadline within
    the staleness limit + one period, and the stopped-clock rule latches STALE_STATE while
    the states keep arriving (a small state age in the status)."""
    rec = Recorder()
    b = _bridge(tmp_path, rec, max_state_age=None)  # the default, 1.5 control periods
    b.start()
    robot = FakeRobot(b.on_state)
    try:
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)
        robot.stamp_offset = -1.5 * DT
        assert wait_for(lambda: b.state is P.BridgeState.DAMPING, 0.5) and b.fault is P.Fault.STALE_STATE
        n = b.received_state
        time.sleep(0.1)
        assert b.received_state >= n + 3 and b.status().state_age_ms < 2 * DT * 1e3
    finally:
        robot.stop()
        b.stop()


@pytest.mark.parametrize("backend", ["onnx", "torchscript"])
def test_targets_clipped_and_nonfinite_policy_output_never_published(tmp_path, realtime, backend):
    rec = Recorder()
    bias = np.zeros(12)
    bias[2] = 100.0  # FL calf: default -1.5 + 0.25 * 100 is far above the joint range
    b = _bridge(tmp_path, rec, nan_above=0.5, bias=bias, max_command=(2.0, 1.0, 1.0), backend=backend)
    opsend = P.Sender()
    b.start()
    robot = FakeRobot(b.on_state)
    try:
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING and b.policy_steps > 3, 2.0)
        policy = [c for _, c in rec.cmds if c.mode == P.CommandMode.POLICY]
        assert policy and all(math.isclose(c.q[2], go2.CALF_RANGE[1], rel_tol=1e-6) for c in policy)
        b.on_operator(op(opsend, vx=1.0))  # the policy returns NaN for vx > 0.5
        assert wait_for(lambda: b.state is P.BridgeState.DAMPING, 1.0)
        assert b.fault is P.Fault.NONFINITE_ACTION
        n_policy = len(policy)
        time.sleep(0.1)
    finally:
        robot.stop()
        b.stop()
    after = [c for _, c in rec.cmds if c.mode == P.CommandMode.POLICY]
    assert len(after) <= n_policy + 1  # at most the one computed before the operator message landed
    assert rec.modes()[-1] == P.CommandMode.DAMPING
    assert all(np.all(np.isfinite(c.q)) for _, c in rec.cmds)  # Recorder decodes: NaN would have raised


def test_operator_command_reaches_policy_and_times_out(tmp_path, realtime):
    rec = Recorder()
    b = _bridge(tmp_path, rec, crouch_gain=0.4, operator_timeout=0.3)
    s = P.Sender()
    b.start()
    robot = FakeRobot(b.on_state)
    try:
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)
        b.on_operator(op(s, vx=0.5))
        time.sleep(0.1)
        thigh = rec.cmds[-1][1].q[THIGHS[0]]
        assert math.isclose(thigh, go2.NOMINAL_POSE["thigh"] + 0.25 * 0.4 * 0.5, abs_tol=1e-5)
        time.sleep(0.4)  # no operator message for longer than the timeout: zero command
        thigh = rec.cmds[-1][1].q[THIGHS[0]]
        assert math.isclose(thigh, go2.NOMINAL_POSE["thigh"], abs_tol=1e-5)
        assert b.state is P.BridgeState.RUNNING
    finally:
        robot.stop()
        b.stop()


def test_heading_hold_turns_back_to_the_heading_of_the_straight_command(tmp_path):
    def yawed(deg):
        half = math.radians(deg) / 2
        return [math.cos(half), 0.0, 0.0, math.sin(half)]

    b = _bridge(tmp_path, Recorder(), heading_hold=2.0, max_command=(1.0, 1.0, 0.5))
    straight = np.array([0.5, 0.0, 0.0])
    assert b._hold_heading(straight, yawed(30.0))[2] == 0.0  # latches 30 deg: no error yet
    assert b._hold_heading(straight, yawed(35.0))[2] == pytest.approx(2.0 * math.radians(-5.0))
    assert b._hold_heading(straight, yawed(20.0))[2] == pytest.approx(2.0 * math.radians(10.0))
    assert b._hold_heading(straight, yawed(-30.0))[2] == 0.5  # clipped to max_command's |wz|
    # the wrap: latched at 175 deg, now at -175 deg: 10 deg to the left of it, turn right
    b.heading_ref = None
    b._hold_heading(straight, yawed(175.0))
    assert b._hold_heading(straight, yawed(-175.0))[2] == pytest.approx(2.0 * math.radians(-10.0))
    # an operator's turn passes unchanged and releases the heading; so does a zero command
    turn = np.array([0.5, 0.0, 0.3])
    assert list(b._hold_heading(turn, yawed(90.0))) == [0.5, 0.0, 0.3] and b.heading_ref is None
    b._hold_heading(straight, yawed(90.0))
    assert b.heading_ref == pytest.approx(math.radians(90.0))
    assert list(b._hold_heading(np.zeros(3), yawed(60.0))) == [0.0, 0.0, 0.0] and b.heading_ref is None
    assert b._hold_heading(np.array([0.0, 0.3, 0.0]), yawed(60.0))[2] == 0.0  # sideways latches too
    with pytest.raises(ValueError, match="heading_hold"):
        _bridge(tmp_path, Recorder(), heading_hold=-1.0)


def test_heading_hold_off_by_default_passes_the_operators_wz(tmp_path, realtime):
    rec = Recorder()
    b = _bridge(tmp_path, rec)
    assert b.cfg.heading_hold == 0.0
    seen = []
    build = b.obs.build
    b.obs.build = lambda msg, commands, *a: (seen.append(np.array(commands)), build(msg, commands, *a))[1]
    s = P.Sender()
    b.start()
    robot = FakeRobot(b.on_state)
    robot.quat = [math.cos(0.3), 0.0, 0.0, math.sin(0.3)]
    try:
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)
        b.on_operator(op(s, vx=0.5))
        assert wait_for(lambda: seen and seen[-1][0] == 0.5, 1.0)
        assert seen[-1][2] == 0.0
    finally:
        robot.stop()
        b.stop()
    rec = Recorder()
    b = _bridge(tmp_path, rec, heading_hold=2.0)
    seen.clear()
    build = b.obs.build
    b.obs.build = lambda msg, commands, *a: (seen.append(np.array(commands)), build(msg, commands, *a))[1]
    b.start()
    robot = FakeRobot(b.on_state)
    try:
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)
        b.on_operator(op(s, vx=0.5))
        assert wait_for(lambda: seen and seen[-1][0] == 0.5, 1.0)
        robot.quat = [math.cos(0.05), 0.0, 0.0, math.sin(0.05)]  # turned 0.1 rad left of the latched heading
        assert wait_for(lambda: seen[-1][2] == pytest.approx(-0.2, abs=1e-6), 1.0)
    finally:
        robot.stop()
        b.stop()


def test_policy_exception_gives_damping(tmp_path, realtime, capsys):
    rec = Recorder()
    b = _bridge(tmp_path, rec)
    calls = []

    def broken(obs):
        calls.append(1)
        if len(calls) > 3:
            raise RuntimeError("inference failed")
        return np.zeros(12, np.float32)

    b.runner = broken
    b.start()
    robot = FakeRobot(b.on_state)
    try:
        assert wait_for(lambda: b.state is P.BridgeState.DAMPING, 2.0)
        assert b.fault is P.Fault.INTERNAL_ERROR and rec.modes()[-1] == P.CommandMode.DAMPING
    finally:
        robot.stop()
        b.stop()
    assert "inference failed" in capsys.readouterr().err


def test_stop_latches_until_reset(tmp_path, realtime):
    rec = Recorder()
    b = _bridge(tmp_path, rec)
    s = P.Sender()
    b.start()
    robot = FakeRobot(b.on_state)
    try:
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)
        b.on_operator(op(s, flags=P.OP_STOP))
        assert wait_for(lambda: b.state is P.BridgeState.STOPPED, 0.5)
        n_stop = len(rec.cmds)
        for _ in range(10):  # ordinary operator traffic does not release the latch
            b.on_operator(op(s, vx=0.3))
            time.sleep(0.02)
        assert b.state is P.BridgeState.STOPPED
        latched = [c for _, c in rec.cmds[n_stop:]]
        assert len(latched) >= 8 and all(c.mode == P.CommandMode.DAMPING for c in latched)
        assert all(np.all(np.asarray(c.kp) == 0.0) for c in latched)
        b.on_operator(op(s, flags=P.OP_RESET))
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)
        modes = rec.modes()
        assert P.CommandMode.STANDUP in modes[n_stop:]  # reset stands up again before the policy runs
    finally:
        robot.stop()
        b.stop()


def test_after_any_single_operator_message_the_next_stop_stops(tmp_path, realtime):
    """No single operator message (any seq, any epoch, motion, reset or stop) can make the
    same operator's next stop be dropped: the stop damps the robot within 100 ms, and the
    operator's reset and motion commands after it are accepted too (nothing poisoned).
    Each case ends with a window of the operator's own messages, so that the next case's
    injected message is again the only one the stream has not passed."""
    rec = Recorder()
    b = _bridge(tmp_path, rec)
    s = P.Sender()
    b.start()
    robot = FakeRobot(b.on_state)
    W = P.OperatorFilter.WINDOW
    headers = {  # the injected message's header, from the operator's next seq s.seq
        "seq +1000": lambda: P.Header(s.epoch, s.seq - 1 + 1000),
        "seq +window": lambda: P.Header(s.epoch, s.seq - 1 + W),
        "seq +window+1": lambda: P.Header(s.epoch, s.seq + W),
        "seq +65536": lambda: P.Header(s.epoch, s.seq - 1 + 65536),
        "seq 0xFFFFFFFF": lambda: P.Header(s.epoch, 0xFFFFFFFF),
        "the operator's next seq": lambda: P.Header(s.epoch, s.seq),
        "a replay of the last seq": lambda: P.Header(s.epoch, s.seq - 1),
        "seq 0": lambda: P.Header(s.epoch, 0),
        "new epoch, seq 0": lambda: P.Header(P.new_epoch(), 0),
        "new epoch, seq 0xFFFFFFFF": lambda: P.Header(P.new_epoch(), 0xFFFFFFFF),
    }
    kinds = {"motion": (1.0, 0), "reset": (0.0, P.OP_RESET), "stop": (0.0, P.OP_STOP)}
    try:
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)
        for _ in range(3):
            b.on_operator(op(s, vx=0.1))
        for name, header in headers.items():
            for kind, (vx, flags) in kinds.items():
                case = f"{kind} with {name}"
                h = header()
                b.on_operator(P.OperatorCommand(vx, 0.0, 0.0, P.PropulsionMode.FOUR_WHEEL, flags, h).encode())
                if flags & P.OP_STOP:  # a stop from anywhere stops; the operator's reset still releases it
                    assert b.state is P.BridgeState.STOPPED, case
                    b.on_operator(op(s, flags=P.OP_RESET))
                    if name == "the operator's next seq":  # the injected stop took this reset's seq: once more
                        assert b.state is P.BridgeState.STOPPED, case
                        b.on_operator(op(s, flags=P.OP_RESET))
                    assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0), case
                assert b.state is P.BridgeState.RUNNING, case
                n = len(rec.cmds)
                t = time.monotonic()
                b.on_operator(op(s, flags=P.OP_STOP))
                assert wait_for(
                    lambda n=n: (
                        b.state is P.BridgeState.STOPPED
                        and any(c.mode == P.CommandMode.DAMPING for _, c in rec.cmds[n:])
                    ),
                    0.1,
                ), case
                assert time.monotonic() - t < 0.1, case
                b.on_operator(op(s, flags=P.OP_RESET))
                assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0), case
                got = b.received_operator
                for _ in range(W):  # motion commands are accepted again; the stream passes the injected seq
                    b.on_operator(op(s, vx=0.3))
                # at most one lost: the real message whose seq an injected one took
                assert b.received_operator - got >= W - 1 and b.commands[0] == pytest.approx(0.3), case
        assert b.operator_filter.epoch == s.epoch
        # a stop naming a propulsion mode the export lacks still stops (a motion command is refused)
        del b.mode_masks[P.PropulsionMode.REAR_WHEEL]
        rejected = b.rejected["out_of_range"]
        b.on_operator(op(s, vx=0.3, prop=P.PropulsionMode.REAR_WHEEL))
        assert b.rejected["out_of_range"] == rejected + 1 and b.state is P.BridgeState.RUNNING
        b.on_operator(op(s, flags=P.OP_STOP, prop=P.PropulsionMode.REAR_WHEEL))
        assert b.state is P.BridgeState.STOPPED and b.rejected["out_of_range"] == rejected + 1
    finally:
        robot.stop()
        b.stop()


def test_a_replaced_operator_still_stops_the_robot(tmp_path, realtime):
    """Two operator sources (a gamepad and the Go2 remote, say): once the second has taken
    over the stream, the first one's motion commands are refused, but its stop still stops."""
    rec = Recorder()
    b = _bridge(tmp_path, rec)
    first, second = P.Sender(), P.Sender()
    b.start()
    robot = FakeRobot(b.on_state)
    try:
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)
        for _ in range(3):
            b.on_operator(op(first, vx=0.1))
        for _ in range(3):
            b.on_operator(op(second, vx=0.2))
        assert b.operator_filter.epoch == second.epoch
        refused = b.rejected["out_of_order"]
        b.on_operator(op(first, vx=0.5))
        assert b.rejected["out_of_order"] == refused + 1 and b.commands[0] == pytest.approx(0.2)
        b.on_operator(op(first, flags=P.OP_STOP))
        assert b.state is P.BridgeState.STOPPED
        assert wait_for(lambda: any(c.mode == P.CommandMode.DAMPING for _, c in rec.cmds), 0.1)
    finally:
        robot.stop()
        b.stop()


def test_one_state_ahead_of_the_stream_cannot_lock_the_robot_out(tmp_path, realtime):
    """One valid state whose seq is ahead of the real stream. Beyond the bridge's
    window (+1000, +65536) it is rejected and the policy runs on. Inside the window it is
    accepted, the real states behind it are out of order and the bridge latches a
    stale-state fault; an operator reset re-anchors the sequence and the robot stands up
    and runs again at once, not only when the real stream has passed the forged seq."""
    rec = Recorder()
    b = _bridge(tmp_path, rec, max_state_age=0.1)
    assert b.state_filter.window == 200  # a 1 kHz stream in twice the 100 ms limit
    ops = P.Sender()
    b.start()
    robot = FakeRobot(b.on_state)

    def forged(jump: int) -> bytes:
        s = robot.sender  # its seq is the next one: s.seq - 1 is the last state it sent
        h = P.Header(s.epoch, s.seq - 1 + jump, time.monotonic_ns())
        return P.RobotState([1.0, 0.0, 0.0, 0.0], [0.0] * 3, go2.default_joint_positions(), [0.0] * 12,
                            header=h).encode()  # fmt: skip

    try:
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)
        for jump in (1000, 65536):
            b.on_state(forged(jump))
        n = b.policy_steps
        time.sleep(0.3)
        assert b.rejected["out_of_order"] == 2
        assert b.state is P.BridgeState.RUNNING and b.policy_steps >= n + 10
        b.on_state(forged(200))  # inside the window: 4 s of the 50 Hz stream is now "old"
        assert wait_for(lambda: b.state is P.BridgeState.DAMPING, 1.0) and b.fault is P.Fault.STALE_STATE
        assert b.rejected["out_of_order"] > 2
        n_fault = len(rec.cmds)
        b.on_operator(op(ops, flags=P.OP_RESET))
        t_reset = time.monotonic()
        assert wait_for(lambda: b.state is P.BridgeState.RUNNING, 2.0)
        assert time.monotonic() - t_reset < 1.0  # the real stream would pass the forged seq only after 4 s
        assert P.CommandMode.STANDUP in rec.modes()[n_fault:]
        n = b.policy_steps
        time.sleep(0.2)
        assert b.state is P.BridgeState.RUNNING and b.policy_steps >= n + 5
    finally:
        robot.stop()
        b.stop()


# --- bridge over zenoh ---------------------------------------------------------------------
def test_state_loss_gives_damping_within_two_periods(tmp_path, realtime):
    port = free_port()
    hub = peer(listen=port)
    meta = load_meta(write_policy(tmp_path))
    cfg = BridgeConfig(standup="linear", standup_time=0.2, operator_timeout=0.0)
    zb = ZenohBridge(hub, "t_loss", meta, cfg).start()
    sess = peer(connect=port)
    robot = ZenohSimRobot(sess, "t_loss", watchdog=0.1)
    cmd_times: list[tuple[float, int]] = []
    sub = sess.declare_subscriber(
        "t_loss/cmd", lambda s: cmd_times.append((time.monotonic(), P.JointCommand.decode(s.payload.to_bytes()).mode))
    )
    state_times: list[float] = []
    sub2 = sess.declare_subscriber("t_loss/state", lambda s: state_times.append(time.monotonic()))
    try:
        robot.start()
        assert wait_for(lambda: zb.bridge.state is P.BridgeState.RUNNING, 5.0)
        time.sleep(0.5)
        robot.robot.publish_state.clear()  # the robot's state publisher dies; the robot keeps running
        assert wait_for(lambda: zb.bridge.state is P.BridgeState.DAMPING, 1.0)
        time.sleep(0.1)
    finally:
        robot.stop()
        zb.stop()
        sub.undeclare()
        sub2.undeclare()
        sess.close()
        hub.close()
    assert zb.bridge.fault is P.Fault.STALE_STATE
    last_state = state_times[-1]
    first_damping = next(t for t, m in cmd_times if m == P.CommandMode.DAMPING)
    assert first_damping - last_state <= 2 * DT, f"damping {1e3 * (first_damping - last_state):.1f} ms after state"
    policy_after = [t for t, m in cmd_times if m == P.CommandMode.POLICY and t > first_damping]
    assert policy_after == []


def test_malformed_flood_is_counted_and_publishes_nothing(tmp_path, realtime):
    port = free_port()
    hub = peer(listen=port)
    meta = load_meta(write_policy(tmp_path))
    cfg = BridgeConfig(standup="linear", standup_time=1.0, operator_timeout=0.0, max_state_age=30.0, status_period=0.05)
    zb = ZenohBridge(hub, "t_flood", meta, cfg).start()
    sess = peer(connect=port)
    cmds, statuses = [], []
    subs = [
        sess.declare_subscriber("t_flood/cmd", lambda s: cmds.append(s.payload.to_bytes())),
        sess.declare_subscriber(
            "t_flood/status", lambda s: statuses.append(P.BridgeStatus.decode(s.payload.to_bytes()))
        ),
    ]
    block = zenoh.CongestionControl.BLOCK
    pub_state = sess.declare_publisher("t_flood/state", congestion_control=block)
    pub_op = sess.declare_publisher("t_flood/operator", congestion_control=block)
    rng = np.random.default_rng(3)
    robot, opsend = P.Sender(), P.Sender()
    expected = dict.fromkeys(P.REJECT_REASONS, 0)

    def send(pub, payload, reason):
        pub.put(payload)
        expected[reason] += 1

    try:
        time.sleep(0.3)
        valid = standing_state(robot).encode()
        good_op = op(opsend)
        for i in range(3000):
            kind = i % 10
            if kind == 0:
                send(pub_state, rng.bytes(int(rng.integers(0, 300))), "malformed")
            elif kind == 1:
                send(pub_state, valid[: int(rng.integers(0, len(valid)))], "malformed")
            elif kind == 2:
                send(pub_state, valid[:2] + bytes([int(rng.integers(P.VERSION + 1, 256))]) + valid[3:], "version")
            elif kind == 3:
                x = standing_state(robot)
                x.dq[int(rng.integers(12))] = rng.choice([np.nan, np.inf, -np.inf])
                send(pub_state, x.encode(), "nonfinite")
            elif kind == 4:
                x = standing_state(robot)
                x.quat = [0.0, 0.0, 0.0, 0.0]
                send(pub_state, x.encode(), "out_of_range")
            elif kind == 5:
                send(pub_op, rng.bytes(P.OperatorCommand.SIZE), "malformed")
            elif kind == 6:
                send(pub_op, good_op[:-3], "malformed")
            elif kind == 7:
                bad = bytearray(op(opsend))
                struct.pack_into("<f", bad, P.HEADER_SIZE, float("nan"))
                send(pub_op, bytes(bad), "nonfinite")
            elif kind == 8:
                send(pub_state, P.JointCommand.decode(_any_cmd()).encode(), "malformed")  # wrong type on state
            else:
                bad = bytearray(op(opsend))
                bad[P.HEADER_SIZE + 12] = 9  # propulsion mode 9
                send(pub_op, bytes(bad), "out_of_range")
        assert wait_for(lambda: zb.bridge.rejected == expected, 10.0), (zb.bridge.rejected, expected)
        time.sleep(0.1)
        assert cmds == [] and zb.bridge.state is P.BridgeState.WAITING  # nothing published because of them

        # one valid state starts the stand-up: one command; then replays of old seqs
        first = standing_state(robot)
        pub_state.put(first.encode())
        assert wait_for(lambda: len(cmds) == 1, 2.0)
        for i in range(1000):
            x = standing_state(robot)
            x.header.seq = int(rng.integers(0, first.header.seq + 1))
            send(pub_state, x.encode(), "out_of_order")
            if i == 0:
                pub_op.put(good_op)  # accepted: the operator's first message
            elif i % 100 == 0:
                send(pub_op, good_op, "out_of_order")  # the same message again
        assert wait_for(lambda: zb.bridge.rejected == expected, 10.0), (zb.bridge.rejected, expected)
        time.sleep(0.15)
        assert len(cmds) == 1
        assert wait_for(lambda: statuses and statuses[-1].rejected_by_reason() == expected, 1.0)
        assert sum(expected.values()) == 3000 + 1000 + 9
    finally:
        zb.stop()
        for s in subs:
            s.undeclare()
        sess.close()
        hub.close()


def _any_cmd() -> bytes:
    return P.JointCommand(
        P.CommandMode.DAMPING, [0.0] * 12, [0.0] * 12, [1.0] * 12, 0, P.Sender().next_header()
    ).encode()


def test_teleop_cli_sends_valid_operator_messages():
    port = free_port()
    a = peer(listen=port)
    got: list[P.OperatorCommand] = []
    key = "t_teleop/operator"
    sub = a.declare_subscriber(key, lambda s: got.append(P.OperatorCommand.decode(s.payload.to_bytes())))
    try:
        args = ["--connect", f"tcp/127.0.0.1:{port}", "--namespace", "t_teleop"]
        for extra in (["--vx", "0.4", "--propulsion", "rear_wheel", "--duration", "0.3"], ["--stop"]):
            r = subprocess.run(
                [sys.executable, "-m", "legged_casters.deploy.teleop", *args, *extra],
                cwd=REPO,
                env={**os.environ, "PYTHONPATH": str(REPO)},
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert r.returncode == 0, r.stderr
    finally:
        sub.undeclare()
        a.close()
    moving = [m for m in got if m.vx > 0]
    assert moving and all(math.isclose(m.vx, 0.4, rel_tol=1e-6) for m in moving)
    assert all(m.propulsion == P.PropulsionMode.REAR_WHEEL for m in moving)
    assert got[len(moving)].vx == 0.0  # a zero command after the duration
    assert got[-1].stop and not got[-1].reset


# --- full loop: two processes over zenoh ---------------------------------------------------
LOAD_STATE_AGE_MS = "1000"
"""The bridge's staleness limit (--max-state-age-ms) in the process tests, which check what
the loop does (stand-up, driving, damping when a side dies), not how fast: other processes
holding the CPU at SCHED_FIFO can starve a tool for tens of ms, and the default 30 ms limit
would then latch a fault mid-test. The timing itself (the default limits, latency, jitter,
stale faults) is measured by legged_casters.deploy.bench and scripts/soak.py; the watchdogs'
timing in simulated time (test_sim_robot_pd_and_watchdog) and by the adapter test on the SDK
stand-in."""
LOAD_WATCHDOG_S = 0.5
"""The robot side's command watchdog (--watchdog-ms) in the same tests: longer than the
stalls such load causes, so that the robot damps only when the bridge is gone."""
LOAD_SLACK_S = 1.0
"""Extra seconds the process tests allow for something to happen on a loaded machine
(a damping state to arrive after a side dies)."""


def _spawn(module: str, *args: str) -> subprocess.Popen:
    # at normal priority until the tool has loaded (this process may be SCHED_FIFO: `realtime`)
    return subprocess.Popen(
        transport.normal_priority_cmd(
            [sys.executable, "-m", f"legged_casters.deploy.{module}", *args, "--rt-priority", "10"]
        ),
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


class LoopProbe:
    """A zenoh peer beside a sim_robot + bridge pair: records states and commands (with
    their arrival times), sim truth and bridge statuses, and plays the operator."""

    def __init__(self, port: int, ns: str):
        self.sess = peer(connect=port)
        self.states: list[tuple[float, P.RobotState]] = []
        self.truths: list[P.SimTruth] = []
        self.cmds: list[tuple[float, P.JointCommand]] = []
        self.statuses: list[P.BridgeStatus] = []

        def timed(log, cls):
            return lambda s: log.append((time.monotonic(), cls.decode(s.payload.to_bytes())))

        self.subs = [
            self.sess.declare_subscriber(f"{ns}/state", timed(self.states, P.RobotState)),
            self.sess.declare_subscriber(f"{ns}/cmd", timed(self.cmds, P.JointCommand)),
            self.sess.declare_subscriber(
                f"{ns}/sim/truth", lambda s: self.truths.append(P.SimTruth.decode(s.payload.to_bytes()))
            ),
            self.sess.declare_subscriber(
                f"{ns}/status", lambda s: self.statuses.append(P.BridgeStatus.decode(s.payload.to_bytes()))
            ),
        ]
        self.opub = self.sess.declare_publisher(f"{ns}/operator")
        self.opsend = P.Sender()

    def operate(self, vx: float, seconds: float) -> None:
        """Send the operator command vx at 20 Hz for `seconds`."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.opub.put(op(self.opsend, vx=vx))
            time.sleep(0.05)

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.sess.close()


def _stop(*procs: subprocess.Popen | None) -> None:
    """Ctrl-C each process still running; kill it if it does not end in 10 s."""
    for p in procs:
        if p is not None and p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()


def test_full_loop_sim_robot_and_bridge(tmp_path, realtime):
    """sim_robot and bridge as separate processes: stand-up, then the simple gait policy
    (hips swing left/right in antiphase with an amplitude proportional to vx) stands
    still at vx = 0 and skates forward at vx = 0.5; the robot stays up, the policy steps
    once per 20 ms of the robot's clock; then the bridge is killed and the robot damps."""
    gain, vx = 0.8, 0.5
    policy = write_policy(tmp_path, gait_gain=gain).parent
    port = free_port()
    ns = "t_loop"
    robot = _spawn("sim_robot", "--listen", f"tcp/127.0.0.1:{port}", "--namespace", ns,
                   "--watchdog-ms", f"{LOAD_WATCHDOG_S * 1e3:g}")  # fmt: skip
    probe = LoopProbe(port, ns)
    states, truths, cmds, statuses, operate = probe.states, probe.truths, probe.cmds, probe.statuses, probe.operate
    bridge = None
    try:
        assert wait_for(lambda: len(states) > 5, 20.0), "sim robot did not start"
        bridge = _spawn(
            "bridge", "--policy", str(policy), "--connect", f"tcp/127.0.0.1:{port}", "--namespace", ns,
            "--standup", "linear", "--standup-time", "1.0", "--max-state-age-ms", LOAD_STATE_AGE_MS,
        )  # fmt: skip
        assert wait_for(lambda: any(c.mode == P.CommandMode.POLICY for _, c in cmds), 20.0), "policy never ran"

        operate(0.0, 2.0)
        n0, n0t = len(states), len(truths)
        operate(vx, 3.0)
        # vx = 0: stands still
        t_still = [t for t in truths[:n0t] if t.sim_time > truths[n0t - 1].sim_time - 1.5]
        assert np.linalg.norm(np.subtract(t_still[-1].pos[:2], t_still[0].pos[:2])) < 0.03, "moved without a command"
        # vx = 0.5: hips swing in antiphase with amplitude action_scale * gain * vx, and the robot skates forward
        hips = np.array([np.asarray(s.q)[HIPS] for _, s in states[n0 + 50 :]])
        amp = np.sqrt(2.0) * hips[:, 0].std()
        expect = 0.25 * gain * vx
        assert 0.6 * expect < amp < 1.3 * expect, f"hip amplitude {amp:.3f} rad, policy asks {expect:.3f}"
        assert np.corrcoef(hips[:, 0], hips[:, 1])[0, 1] < -0.8  # FL against FR
        assert np.corrcoef(hips[:, 0], hips[:, 2])[0, 1] > 0.8  # FL with RL
        moving = truths[n0t:]
        dx = moving[-1].pos[0] - moving[0].pos[0]
        dy = moving[-1].pos[1] - moving[0].pos[1]
        print(f"full loop: hip amplitude {amp:.3f} rad (policy {expect:.3f}), dx {dx:.2f} m, dy {dy:.3f} m in 3 s")
        assert dx > 0.3 and abs(dy) < 0.2 * dx, f"skated dx {dx:.2f} m, dy {dy:.2f} m in 3 s"
        assert min(t.pos[2] for t in truths) > 0.3, "trunk dropped"
        assert max(projected_gravity(s.quat)[2] for _, s in states) < -0.95, "robot tilted"

        # one policy step per control period of the robot's clock (the wall-clock rate and its
        # jitter are a timing promise, measured by deploy.bench: a loaded machine skips periods)
        stamp = {s.header.seq: s.header.stamp_ns for _, s in states}
        answered = [stamp[c.state_seq] for _, c in cmds if c.mode == P.CommandMode.POLICY and c.state_seq in stamp]
        period = float(np.median(np.diff(answered))) / 1e9
        assert len(answered) > 100 and abs(period - DT) < 0.001, f"policy steps {1e3 * period:.2f} ms apart"
        st = statuses[-1]
        assert st.state == P.BridgeState.RUNNING and st.rate_hz > 0
        assert sum(st.rejected) == 0
        assert all(s.robot_mode in (P.CommandMode.HOLD, P.CommandMode.STANDUP, P.CommandMode.POLICY) for _, s in states)

        # the bridge dies: the robot damps on its watchdog (+ one state period, + slack on a loaded machine)
        bridge.send_signal(signal.SIGKILL)
        bridge.wait(10)
        last_cmd = cmds[-1][0]
        assert wait_for(lambda: states[-1][1].robot_mode == P.CommandMode.DAMPING, 2.0 + LOAD_SLACK_S)
        t_damp = next(t for t, s in states if t > last_cmd and s.robot_mode == P.CommandMode.DAMPING)
        took = f"robot damped {1e3 * (t_damp - last_cmd):.0f} ms after last cmd"
        assert t_damp - last_cmd <= LOAD_WATCHDOG_S + DT + LOAD_SLACK_S, took
        assert t_damp - last_cmd >= LOAD_WATCHDOG_S - 0.02, took  # and not before the watchdog limit
    finally:
        probe.close()
        _stop(bridge, robot)


WHEEL_POLICY = REPO / "resources" / "policies" / "go2_wheel_flat"


def test_full_loop_wheel_robot_runs_the_shipped_wheel_policy(tmp_path, realtime):
    """The 16-joint path end to end over zenoh: sim_robot --robot wheel and the bridge
    with the shipped go2_wheel_flat export. The robot stands up with its wheels held,
    drives forward under vx = 0.5 with the wheels as velocity servos, stays upright,
    and damps when the bridge dies."""
    port = free_port()
    ns = "t_wheel"
    robot = _spawn(
        "sim_robot", "--robot", "wheel", "--listen", f"tcp/127.0.0.1:{port}", "--namespace", ns,
        "--watchdog-ms", f"{LOAD_WATCHDOG_S * 1e3:g}",
    )  # fmt: skip
    probe = LoopProbe(port, ns)
    states, truths, cmds, operate = probe.states, probe.truths, probe.cmds, probe.operate
    bridge = None
    try:
        assert wait_for(lambda: len(states) > 5, 20.0), "sim robot did not start"
        assert len(states[-1][1].q) == 16
        bridge = _spawn(
            "bridge", "--policy", str(WHEEL_POLICY), "--connect", f"tcp/127.0.0.1:{port}", "--namespace", ns,
            "--standup", "linear", "--standup-time", "0.5", "--max-state-age-ms", LOAD_STATE_AGE_MS,
        )  # fmt: skip
        assert wait_for(lambda: any(c.mode == P.CommandMode.POLICY for _, c in cmds), 20.0), "policy never ran"
        standup = [c for _, c in cmds if c.mode == P.CommandMode.STANDUP]
        assert standup and all(c.dq[12:] == [0.0] * 4 and c.kp[12:] == [0.0] * 4 for c in standup)

        operate(0.0, 1.0)
        n0 = len(truths)
        operate(0.5, 4.0)
        moving = truths[n0:]
        dx = moving[-1].pos[0] - moving[0].pos[0]
        dy = moving[-1].pos[1] - moving[0].pos[1]
        late = [t.lin_vel[0] for t in moving if t.sim_time > moving[-1].sim_time - 1.5]
        print(f"wheel loop: dx {dx:.2f} m, dy {dy:.2f} m in 4 s, late vx {np.mean(late):.2f} m/s")
        assert 0.35 < np.mean(late) < 0.65 and dx > 1.2 and abs(dy) < 0.3 * dx
        policy = [c for _, c in cmds if c.mode == P.CommandMode.POLICY]
        wheel_rates = np.array([c.dq[12:] for c in policy[-25:]])
        assert np.all(wheel_rates > 2.0), "wheels are not driven forward"  # 0.5 m/s is ~5.6 rad/s
        assert min(t.pos[2] for t in truths) > 0.3, "trunk dropped"
        assert max(projected_gravity(s.quat)[2] for _, s in states) < -0.95, "robot tilted"

        bridge.send_signal(signal.SIGKILL)
        bridge.wait(10)
        assert wait_for(lambda: states[-1][1].robot_mode == P.CommandMode.DAMPING, 2.0 + LOAD_SLACK_S)
    finally:
        probe.close()
        _stop(bridge, robot)


def test_shipped_caster_export_still_loads_and_runs_in_the_bridge(tmp_path):
    """The shipped caster export runs in the bridge, also as a 12-joint export written before the
    wheel robot was (its policy.yaml without joint_control, which then means all position)."""
    import shutil

    import yaml

    old = tmp_path / "caster_omni"
    shutil.copytree(REPO / "resources" / "policies" / "caster_omni", old)
    data = yaml.safe_load((old / "policy.yaml").read_text())
    assert data.pop("joint_control") == ["position"] * 12
    (old / "policy.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    meta = load_meta(old)
    assert meta.num_joints == 12 and all(meta.position_mask) and meta.velocity_action_scale == 0.0
    sent = []
    cfg = BridgeConfig(standup="linear", standup_time=0.02, operator_timeout=0.0)
    bridge = Bridge(meta, cfg, lambda w, p: sent.append(p))
    s = P.Sender()
    for k in range(4):
        bridge._control_step(standing_state(s, stamp_ns=int(k * DT * 1e9)), time.monotonic())
    run = [P.JointCommand.decode(p) for p in sent]
    run = [c for c in run if c.mode == P.CommandMode.POLICY]
    assert run and len(run[-1].q) == 12 and run[-1].dq == [0.0] * 12


@pytest.mark.parametrize(
    ("module", "args", "message"),
    [
        ("teleop", ["--listen", "127.0.0.1:7447"], "e.g. tcp/127.0.0.1:7447"),
        ("bridge", ["--connect", "localhost:7447"], "e.g. tcp/localhost:7447"),
        ("sim_robot", ["--mode", "client", "--connect", "tcp/127.0.0.1:{closed}"], "nothing answered there"),
        ("teleop", ["--zenoh-config", "/nonexistent.json5"], "--zenoh-config"),
    ],
)
def test_bad_endpoints_give_one_line_with_the_fix(module, args, message):
    closed = free_port()
    args = [a.format(closed=closed) for a in args]
    out = subprocess.run(
        [sys.executable, "-m", f"legged_casters.deploy.{module}", *args, "--duration", "0.1"],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{module}: error: ") and message in lines[0], out.stderr
    assert "Traceback" not in out.stderr


def test_a_port_in_use_is_named_not_a_zenoh_traceback():
    port = free_port()
    hub = peer(listen=port)
    try:
        out = subprocess.run(
            [sys.executable, "-m", "legged_casters.deploy.sim_robot", "--listen", f"tcp/127.0.0.1:{port}",
             "--duration", "0.1"],
            cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    finally:
        hub.close()
    assert out.returncode == 2 and "the port is already in use" in out.stderr and "Traceback" not in out.stderr


def test_round_trip_latency_matches_commands_to_their_state():
    rt = P.RoundTrip(keep=4)
    assert rt.summary() == "latency -"
    for seq in range(6):
        rt.sent(seq, 10.0 + seq)
    rt.answered(5, 15.002)  # the command computed from state 5, 2 ms later
    rt.answered(5, 15.1)  # a second command for the same state is not a new sample
    rt.answered(0xFFFFFFFF, 16.0)  # a timed damping command answers no state
    rt.answered(0, 16.0)  # state 0 was dropped from the bounded table
    assert rt.take() == [pytest.approx(0.002)]
    rt.sent(7, 1.0)
    rt.answered(7, 1.004)
    assert rt.summary() == "latency p50 4.0 / p99 4.0 ms" and rt.take() == []


def test_live_status_lines(tmp_path, capsys):
    """The bridge prints each state change with its fault and a one-line summary; teleop
    says when no bridge is known to have received its messages."""
    from legged_casters.deploy import bridge as B

    fake = type("FakeBridge", (), {"fault_detail": ""})()
    fake.transitions = [(0.0, P.BridgeState.STANDUP, P.Fault.NONE), (1.0, P.BridgeState.RUNNING, P.Fault.NONE)]
    assert B._print_transitions(fake, 0) == 2
    fake.transitions.append((2.0, P.BridgeState.DAMPING, P.Fault.STALE_STATE))
    assert B._print_transitions(fake, 2) == 3
    out = capsys.readouterr().out.splitlines()
    assert out == ["bridge: START -> STANDUP", "bridge: STANDUP -> RUNNING", "bridge: RUNNING -> DAMPING (STALE_STATE)"]
    line = B.status_line(P.BridgeStatus(state=P.BridgeState.RUNNING, rate_hz=50.0, rejected=[2, 0, 0, 0, 1]))
    assert line.startswith("RUNNING, 50.0 Hz") and "{'malformed': 2, 'out_of_order': 1}" in line
    port = free_port()
    run = subprocess.run(
        [sys.executable, "-m", "legged_casters.deploy.teleop", "--connect", f"tcp/127.0.0.1:{port}", "--listen",
         f"tcp/127.0.0.1:{free_port()}", "--duration", "0.1"],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert run.returncode == 0 and "heard no bridge status on go2/status" in run.stdout
