"""The driving-wheel Go2: model, scripted drive, 16-action layout through
env, export metadata, wire protocol, bridge and simulated robot."""

from __future__ import annotations

import math
import time

import mujoco
import numpy as np
import pytest
import torch

from legged_casters import registry
from legged_casters.deploy import protocol as P
from legged_casters.deploy.bridge import Bridge, BridgeConfig
from legged_casters.deploy.policy import ObservationBuilder, load_meta
from legged_casters.deploy.sim_robot import SimRobot
from legged_casters.envs.base import set_timestep
from legged_casters.envs.drive import DrivePrior, wheel_lateral_positions
from legged_casters.robot import build, go2
from legged_casters.tools.export import metadata_yaml, policy_metadata

WHEELS = list(range(12, 16))


def test_layout_model_and_stand(wheel_model):
    layout = go2.action_layout("wheel")
    assert layout.joints == go2.ACTUATED_JOINTS + go2.DRIVE_WHEEL_JOINTS
    assert go2.action_layout("caster").joints == go2.ACTUATED_JOINTS  # the 12-joint robots are unchanged
    m = wheel_model
    assert m.nu == 16
    for i, joint in enumerate(layout.joints):
        act = m.actuator(i)
        assert m.joint(act.trnid[0]).name == joint
        np.testing.assert_allclose(act.forcerange, [-layout.torque_limits[i], layout.torque_limits[i]])
        if i in WHEELS:  # a velocity servo: force = kd (ctrl - qvel)
            assert act.gainprm[0] == pytest.approx(go2.DRIVE_WHEEL_KD) and act.biasprm[1] == 0.0
            assert act.biasprm[2] == pytest.approx(-go2.DRIVE_WHEEL_KD)
            np.testing.assert_allclose(act.ctrlrange, [-go2.DRIVE_WHEEL_VELOCITY_LIMIT, go2.DRIVE_WHEEL_VELOCITY_LIMIT])
            dof = m.joint(joint).dofadr[0]
            assert m.dof_frictionloss[dof] > 0  # rolling resistance, as on the casters
            assert not m.jnt_limited[m.joint(joint).id]
    point = mujoco.MjModel.from_xml_path(str(build.MODEL_FILES["point"]))
    assert m.body_subtreemass[1] == pytest.approx(point.body_subtreemass[1] + 4 * go2.DRIVE_WHEEL_MASS, rel=1e-6)
    # The keyframe stands on the four wheels, nothing else touches the floor.
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, m.key(build.STAND_KEY).id)
    for _ in range(100):
        mujoco.mj_step(m, d)
    loads = []
    for leg in go2.LEGS:
        s = m.sensor(f"{leg}_wheel_contact")
        found, *force = d.sensordata[s.adr[0] : s.adr[0] + 4]
        assert found >= 1
        loads.append(np.linalg.norm(force))
        c = m.sensor(f"{leg}_calf_contact")
        assert d.sensordata[c.adr[0]] == 0
    assert sum(loads) == pytest.approx(m.body_subtreemass[1] * 9.81, rel=0.05)


@pytest.mark.parametrize("timestep", [0.002, 0.005])
@pytest.mark.parametrize("rate", [5.0, -11.1])
def test_scripted_wheels_drive_at_radius_times_rate(wheel_model, timestep, rate):
    """All wheels at one rate, legs holding the stand pose: the robot rolls straight at
    R * rate (within 5 %) without tipping, at the model's step and at the training step."""
    m = mujoco.MjModel.from_xml_path(str(build.MODEL_FILES["wheel"]))
    set_timestep(m, timestep)
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, m.key(build.STAND_KEY).id)
    d.ctrl[WHEELS] = rate
    speeds, tilt, lateral = [], 0.0, 0.0
    for _ in range(int(4.0 / timestep)):
        mujoco.mj_step(m, d)
        if d.time > 2.0:
            speeds.append(d.qvel[0])
        tilt = max(tilt, math.degrees(math.acos(min(1.0, 1 - 2 * (d.qpos[4] ** 2 + d.qpos[5] ** 2)))))
        lateral = max(lateral, abs(d.qpos[1]))
    expect = go2.DRIVE_WHEEL_RADIUS * rate
    assert np.mean(speeds) == pytest.approx(expect, rel=0.05)
    assert tilt < 10.0 and d.qpos[2] > 0.3 and lateral < 0.05


def test_env_reads_the_16_action_layout():
    env = registry.make_env("go2_wheel_flat", num_envs=2, seed=0)
    assert env.num_actions == 16 and env.actions.shape == (2, 16)
    a = torch.zeros(2, 16)
    a[:, 12:] = torch.tensor([1.0, -0.5, 0.2, 0.0])
    a[:, 0] = 0.4
    targets = env.action_targets(a)
    scale = env.cfg.control
    assert targets[0, 12:].tolist() == pytest.approx([10.0 * v for v in (1.0, -0.5, 0.2, 0.0)])
    assert scale.velocity_action_scale == 10.0
    assert targets[0, 0].item() == pytest.approx(go2.NOMINAL_POSE["hip"] + scale.action_scale * 0.4)
    # A wheel's angle is not observed (it turns freely): its joint_pos entries stay 0.
    env.sim.qpos[:, env.joint_qadr[12:]] += 3.0
    env._refresh_state()
    assert torch.all(env._obs_joint_pos()[:, 12:] == 0.0)
    # The actor's feedforward turns each wheel at (vx - wz y) / R.
    prior = env.actor_prior()
    env.set_commands([0.9, 0.0, 0.6])
    obs = env.compute_observations()["policy"]
    out = DrivePrior(prior["cfg"], prior["slices"], prior["action_scale"])(obs, obs[:, :0])
    y = np.array(wheel_lateral_positions())
    expect = (0.9 - 0.6 * y) / (go2.DRIVE_WHEEL_RADIUS * 10.0)
    assert torch.all(out[:, :12] == 0.0)
    np.testing.assert_allclose(out[0, 12:].numpy(), expect, rtol=1e-5)
    env.close()


class _Feedforward(torch.nn.Module):
    """An actor that is only the drive feedforward (the prior without a velocity estimate)."""

    def __init__(self, prior: torch.nn.Module):
        super().__init__()
        self.prior = prior

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.prior(obs, obs[:, :0])


def _write_export(tmp_path, env) -> None:
    """policy.yaml of `env` plus a TorchScript actor that is only the drive feedforward."""
    meta = policy_metadata(env, "go2_wheel_flat")
    (tmp_path / "policy.yaml").write_text(metadata_yaml(meta))
    prior = env.actor_prior()
    module = torch.jit.script(_Feedforward(DrivePrior(prior["cfg"], prior["slices"], prior["action_scale"])))
    module.save(str(tmp_path / "policy.pt"))


def test_export_metadata_and_bridge_commands(tmp_path):
    env = registry.make_env("go2_wheel_flat", num_envs=1, seed=0)
    _write_export(tmp_path, env)
    env.close()
    meta = load_meta(tmp_path)
    assert meta.num_joints == 16 and meta.robot == "wheel"
    assert list(meta.joint_control[12:]) == ["velocity"] * 4 and meta.velocity_action_scale == 10.0
    assert np.all(meta.kp[12:] == 0.0) and np.all(meta.kd[12:] == go2.DRIVE_WHEEL_KD)
    np.testing.assert_allclose(meta.joint_pos_limits[12:], [[-30.1, 30.1]] * 4)
    q = np.asarray(go2.action_layout("wheel").default) + 0.05
    actions = np.zeros(16)
    actions[0], actions[12:] = 0.2, [1.0, -1.0, 5.0, 0.5]
    q_t, dq_t = meta.targets(actions, q)
    assert q_t[0] == pytest.approx(0.25 * 0.2) and np.all(dq_t[:12] == 0.0)
    np.testing.assert_allclose(q_t[12:], q[12:])  # wheels: angle reported, not servoed (kp 0)
    np.testing.assert_allclose(dq_t[12:], [10.0, -10.0, 30.1, 5.0])  # clipped to the velocity limit

    # The bridge: 16-joint states in, commands with a wheel velocity target out.
    sent = []
    bridge = Bridge(
        meta,
        BridgeConfig(standup="linear", standup_time=0.04, backend="torchscript", operator_timeout=0.0),
        lambda w, p: sent.append((w, p)),
    )
    s = P.Sender()
    state = P.RobotState([1.0, 0, 0, 0], [0.0] * 3, list(q), [0.0] * 16, header=s.next_header())
    bridge.commands = np.array([0.9, 0.0, 0.0])
    for k in range(5):
        state.header = s.next_header()
        state.header.stamp_ns = int(k * 0.02e9)
        bridge._control_step(state, time.monotonic())
    cmds = [P.JointCommand.decode(p) for w, p in sent if w == "cmd"]
    assert cmds[0].mode == P.CommandMode.STANDUP and cmds[0].dq[12:] == [0.0] * 4  # wheels held still
    run = [c for c in cmds if c.mode == P.CommandMode.POLICY]
    assert run, [c.mode for c in cmds]
    np.testing.assert_allclose(run[-1].dq[12:], [0.9 / go2.DRIVE_WHEEL_RADIUS] * 4, rtol=1e-4)
    assert run[-1].kp[12:] == [0.0] * 4
    # The operator's default propulsion mode is accepted by a policy without modes; others are refused.
    ops = P.Sender()
    for prop in (P.PropulsionMode.FOUR_WHEEL, P.PropulsionMode.FRONT_WHEEL):
        msg = P.OperatorCommand(vx=0.3, propulsion=prop, header=ops.next_header())
        bridge.on_operator(msg.encode())
    assert bridge.received_operator == 1 and bridge.rejected["out_of_range"] == 1
    assert bridge.commands[0] == pytest.approx(0.3)
    # A 12-joint state is refused (counted), never used.
    bridge.on_state(P.RobotState([1.0, 0, 0, 0], [0.0] * 3, [0.0] * 12, [0.0] * 12, header=s.next_header()).encode())
    assert bridge.rejected["malformed"] == 1


def test_observation_builder_zeroes_wheel_angles(tmp_path):
    env = registry.make_env("go2_wheel_flat", ["noise.enabled=False"], num_envs=1, seed=0)
    _write_export(tmp_path, env)
    env.sim.qpos[:, env.joint_qadr[12:]] += 2.0
    env._refresh_state()
    env.set_commands([0.5, 0.0, -0.3])
    expect = env.compute_observations()["policy"][0].numpy()
    meta = load_meta(tmp_path)
    q = env.joint_pos[0].double().numpy()
    state = P.RobotState(env.base_quat[0].tolist(), env.base_ang_vel[0].tolist(), list(q), env.joint_vel[0].tolist())
    obs = ObservationBuilder(meta).build(state, [0.5, 0.0, -0.3], np.zeros(4), np.zeros(16))
    np.testing.assert_allclose(obs, expect, atol=1e-4)
    env.close()


def test_protocol_carries_16_joints_and_velocity_targets():
    s = P.Sender()
    cmd = P.JointCommand(P.CommandMode.POLICY, [0.1] * 16, [60.0] * 12 + [0.0] * 4, [1.5] * 12 + [2.0] * 4, 3,
                         s.next_header(), dq=[0.0] * 12 + [11.0] * 4)  # fmt: skip
    back = P.JointCommand.decode(cmd.encode())
    assert len(back.q) == 16 and back.dq[12:] == [11.0] * 4 and back.kp[12:] == [0.0] * 4
    assert len(cmd.encode()) == P.JointCommand.size(16)
    st = P.RobotState([1.0, 0, 0, 0], [0.0] * 3, [0.2] * 16, [1.0] * 16, header=s.next_header())
    assert len(P.RobotState.decode(st.encode()).dq) == 16
    bad = bytearray(cmd.encode())
    bad[P.HEADER_SIZE + 1] = 15  # joint count that does not match the length
    with pytest.raises(P.ProtocolError) as err:
        P.JointCommand.decode(bytes(bad))
    assert err.value.reason == "malformed"
    bad[P.HEADER_SIZE + 1] = 0
    with pytest.raises(P.ProtocolError):
        P.JointCommand.decode(bytes(bad))
    old = bytearray(cmd.encode())
    old[2] = 1  # a version-1 peer
    with pytest.raises(P.ProtocolError) as err:
        P.JointCommand.decode(bytes(old))
    assert err.value.reason == "version"


def test_sim_robot_drives_wheels_as_velocity_servos():
    sent = []
    r = SimRobot(lambda which, payload: sent.append((which, payload)), robot="wheel", state_rate=500.0)
    s = P.Sender()
    q = r.data.qpos[r.qadr].copy()
    dq = r.data.qvel[r.dadr].copy()
    kp = np.array([60.0] * 12 + [0.0] * 4)
    kd = np.array([1.5] * 12 + [2.0] * 4)
    dq_t = np.array([0.0] * 12 + [5.0, 5.0, -5.0, 1.0])
    now = time.monotonic()
    r.on_command(
        P.JointCommand(P.CommandMode.POLICY, list(q), list(kp), list(kd), 0, s.next_header(), list(dq_t)).encode()
    )
    r.step(now, int(now * 1e9))
    expect = np.clip(kd * (dq_t - dq), -r.tau_limit, r.tau_limit)  # q target = q: only the kd term
    np.testing.assert_allclose(r.data.ctrl[r.act], expect, atol=1e-4)  # (q travels as float32)
    assert np.all(r.data.ctrl[r.act][12:] != 0.0)
    st = P.RobotState.decode(next(p for w, p in sent if w == "state"))
    assert len(st.q) == 16
    # A 12-joint command is refused by the 16-joint robot.
    r.on_command(P.JointCommand(P.CommandMode.POLICY, [0.0] * 12, [0.0] * 12, [0.0] * 12, 1, s.next_header()).encode())
    assert r.rejected["malformed"] == 1


def test_evaluation_asks_each_task_only_what_it_is_trained_for():
    from legged_casters.tools import evaluate

    wheel = registry.get_task("go2_wheel_flat")
    names = {s.name for s in evaluate.applicable(evaluate.FULL, wheel.env_class, wheel.env_cfg)}
    assert {"vx +0.5", "vx -0.5", "vx +1.0", "vx -1.0", "wz +0.8", "wz -0.8", "random+pushes"} <= names
    assert not names & {"vy +0.4", "vy -0.4", "vx +2.0", "mode front_wheel"}  # no vy, beyond 1.5 m/s, no modes
    caster = registry.get_task("caster_omni")
    assert evaluate.applicable(evaluate.FULL, caster.env_class, caster.env_cfg) == evaluate.FULL
    checks = dict((n, ok) for n, ok, _ in evaluate.verdict([_result("vx +1.0", 0.12)], "go2_wheel_flat"))
    assert checks == {"vx +1.0: |vx error| <= 0.1": False}  # the wheel robot's own bar


def _result(name, err):
    from legged_casters.tools.evaluate import ScenarioResult

    return ScenarioResult(name, "track", (1.0, 0.0, 0.0), err={"vx": err, "vy": 0.0, "wz": 0.0})


def test_cost_of_transport_of_steady_rolling_is_the_rolling_resistance():
    """Energy balance: rolling steadily on flat ground, the motors' positive work per weight
    and distance covers at least the axle friction, c_rr = 0.02, and not much more (the
    rest is lost in the soft wheel-floor contact: measured 0.032 at 1 m/s, the rear wheels
    pushing, the front ones pushed). Checks positive_power (every physics substep) and
    cost_of_transport."""
    from legged_casters.tools import evaluate

    env = registry.make_env("go2_wheel_flat", evaluate.EVAL_SETTINGS, num_envs=2, seed=0)
    env.set_commands([1.0, 0.0, 0.0])
    env.reset()
    a = torch.zeros(2, 16)
    a[:, 12:] = 1.0 / go2.DRIVE_WHEEL_RADIUS / env.cfg.control.velocity_action_scale
    power, xy = [], []
    for k in range(200):
        env.step(a)
        if k >= 100:
            power.append(env.positive_power()[0])
            xy.append(env.base_pos[0, :2].clone())
    assert env.sim.substep_sensordata().shape[1] == env.cfg.sim.decimation  # every physics step counted
    cot = evaluate.cost_of_transport(env, torch.stack(power), torch.stack(xy))
    env.close()
    assert 0.02 <= cot <= 0.045, cot


def test_cot_table_measures_each_shipped_robot_the_same_way(capsys):
    from legged_casters.tools import cot

    assert cot.main(["--duration", "2.0", "--settle", "1.0"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| ") and "robot" not in line]
    robots = {line.split("|")[1].strip() for line in rows}
    assert {"passive casters (ours)", "driving wheels"} <= robots
    for line in rows:
        value = float(line.split("|")[5])
        assert 0.0 < value < 1.0  # a cost of transport, not inf or nan
    assert cot.main(["--settle", "5", "--duration", "2"]) == 2
    assert "--settle" in capsys.readouterr().err


def test_play_says_when_a_profile_commands_what_the_task_never_trained(tmp_path, capsys):
    from legged_casters.tools import play

    policy = build.REPO_ROOT / "resources" / "policies" / "go2_wheel_flat" / "policy.pt"
    argv = ["--policy", str(policy), "--headless", "--no_video", "--profile", "slalom", "--duration", "0.2"]
    assert play.main([*argv, "--num_envs", "1", "--out", str(tmp_path)]) == 0
    assert "commands vy +0.40, outside what go2_wheel_flat is trained for [0, 0]" in capsys.readouterr().out
