"""The base env and go2_flat on the CPU backend: resets, randomisation, finiteness,
configs, and rsl_rl training plumbing."""

import copy
import math

import numpy as np
import pytest
import torch
from rsl_rl.runners import OnPolicyRunner

from legged_casters import registry
from legged_casters.config import dump_yaml, load_yaml
from legged_casters.envs.go2_flat import Go2FlatCfg
from legged_casters.robot import go2

CPU = ["sim.backend=cpu"]
FIXED = CPU + [f"domain_rand.{k}=false" for k in ("randomize_gains", "randomize_friction", "randomize_base_mass")]
FIXED += ["domain_rand.randomize_com=false", "domain_rand.push_robots=false", "noise.enabled=false"]
FIXED += ["init_state.joint_pos_noise=0.0", "init_state.base_vel_noise=0.0", "init_state.random_yaw=false"]
"""No randomisation, pushes, noise or random start: two envs differ only where a test makes them."""


@pytest.fixture(scope="module")
def env():
    e = registry.make_env("go2_flat", CPU, num_envs=8)
    yield e
    e.close()


def test_observation_groups_and_layout(env):
    obs = env.get_observations()
    dims = env.observation_dims()
    assert set(obs.keys()) == {"policy", "critic"}
    assert obs["policy"].shape == (8, dims["policy"]) and obs["critic"].shape == (8, dims["critic"])
    assert dims["policy"] == 3 + 3 + 3 + 3 + 12 + 12 + 12
    names = [name for name, _, _ in env.obs_layout["policy"]]
    assert names == list(env.OBSERVATIONS["policy"])
    assert env.noise_vec.shape == (dims["policy"],)


def test_reset_restores_only_the_selected_envs(env):
    torch.manual_seed(0)
    for _ in range(20):
        env.step(torch.randn(env.num_envs, env.num_actions) * 0.5)
    before = env.sim.qpos.clone()
    ids = torch.tensor([1, 5])
    env.reset_idx(ids)
    after = env.sim.qpos
    keep = [i for i in range(env.num_envs) if i not in (1, 5)]
    assert torch.equal(after[keep], before[keep])
    nominal = env.nominal_qpos.double()
    for i in (1, 5):
        # Joints within the reset noise of the nominal pose, upright, at the origin.
        noise = env.cfg.init_state.joint_pos_noise
        assert torch.allclose(after[i, env.joint_qadr], nominal[env.joint_qadr], atol=noise)
        assert torch.allclose(after[i, 0:2], torch.zeros(2, dtype=after.dtype))
        assert abs(after[i, 3:7].norm() - 1) < 1e-6 and abs(after[i, 4]) < 1e-6 and abs(after[i, 5]) < 1e-6
    assert (env.episode_length_buf[ids] == 0).all()
    assert (env.actions[ids] == 0).all()


def test_randomised_parameters_land_in_the_backend(env):
    dr = env.cfg.domain_rand
    friction = env.sim.get_model_field("geom_friction")[:, :, 0]
    assert friction.min() >= dr.friction_range[0] and friction.max() <= dr.friction_range[1]
    assert friction[:, 0].unique().numel() == env.num_envs  # each env its own draw
    mass = env.sim.get_model_field("body_mass")[:, env.trunk_id]
    offset = mass - go2.TRUNK_MASS
    assert offset.min() >= dr.added_mass_range[0] - 1e-6 and offset.max() <= dr.added_mass_range[1] + 1e-6
    assert mass.unique().numel() == env.num_envs
    kp = env.sim.get_model_field("actuator_gainprm")[:, :, 0]
    bias = env.sim.get_model_field("actuator_biasprm")
    assert torch.allclose(bias[:, :, 1], -kp)
    ratio = kp / torch.tensor(go2.kp(), dtype=kp.dtype)
    assert ratio.min() >= dr.kp_scale_range[0] - 1e-6 and ratio.max() <= dr.kp_scale_range[1] + 1e-6
    assert ratio.std() > 0.01
    kd_ratio = -bias[:, :, 2] / torch.tensor(go2.kd(), dtype=kp.dtype)
    assert kd_ratio.min() >= dr.kd_scale_range[0] - 1e-6 and kd_ratio.max() <= dr.kd_scale_range[1] + 1e-6
    com = env.sim.get_model_field("body_ipos")[:, env.trunk_id] - torch.tensor(env.model.body_ipos[env.trunk_id])
    assert com.abs().max() <= dr.com_offset_range[1] + 1e-6 and com.std() > 0.005


def test_joint_damping_patterns_randomise_matching_joints():
    e = registry.make_env("go2_flat", CPU + ["domain_rand.joint_damping={'*_calf_joint': [0.2, 0.4]}"], num_envs=4)
    damping = e.sim.get_model_field("dof_damping")
    calf = [e.model.joint(f"{leg}_calf_joint").dofadr[0] for leg in go2.LEGS]
    hip = [e.model.joint(f"{leg}_hip_joint").dofadr[0] for leg in go2.LEGS]
    assert damping[:, calf].min() >= 0.2 and damping[:, calf].max() <= 0.4
    assert (damping[:, hip] == 0).all()
    with pytest.raises(ValueError, match="matches no joint"):
        registry.make_env("go2_flat", CPU + ["domain_rand.joint_damping={'*_knee': [0.1, 0.2]}"], num_envs=2)


def test_long_random_rollout_stays_finite():
    e = registry.make_env("go2_flat", CPU + ["domain_rand.push_interval_s=0.5"], num_envs=16)
    torch.manual_seed(1)
    resets = 0
    for _ in range(300):
        obs, rew, dones, extras = e.step(torch.randn(e.num_envs, e.num_actions))
        assert torch.isfinite(obs["policy"]).all() and torch.isfinite(obs["critic"]).all()
        assert torch.isfinite(rew).all()
        assert extras["time_outs"].dtype == torch.bool
        resets += int(dones.sum())
        if dones.any():
            for key, value in extras["log"].items():
                assert np.isfinite(float(value)), key
    assert resets > 0  # random actions make robots fall, and fallen robots are reset
    assert e.nonfinite_resets == 0


def test_nan_actions_end_the_episode_instead_of_poisoning_the_batch(env):
    actions = torch.zeros(env.num_envs, env.num_actions)
    actions[2, 3] = float("nan")
    obs, rew, dones, extras = env.step(actions)
    assert dones[2] and not extras["time_outs"][2]
    assert torch.isfinite(obs["policy"]).all() and torch.isfinite(rew).all()


def test_reward_terms_are_looked_up_by_name_and_zero_weights_switch_off():
    e = registry.make_env("go2_flat", CPU + ["rewards.scales.torques=0.0"], num_envs=2)
    assert "torques" not in e.reward_terms and "tracking_lin_vel" in e.reward_terms
    _, scale = e.reward_terms["tracking_lin_vel"]
    assert scale == pytest.approx(1.0 * e.dt)
    with pytest.raises(ValueError, match="unknown reward term 'typo'"):
        registry.make_env("go2_flat", CPU + ["rewards.scales.typo=1.0"], num_envs=2)


def test_tracking_reward_prefers_matching_velocity(env):
    env.commands[:] = torch.tensor([0.5, 0.0, 0.0])
    env.base_lin_vel = torch.zeros(env.num_envs, 3)
    env.base_lin_vel[:4, 0] = 0.5
    r = env._reward_tracking_lin_vel()
    assert torch.allclose(r[:4], torch.ones(4)) and (r[4:] < 0.5).all()


def test_env_config_round_trips_through_yaml(tmp_path):
    _, _ = registry.task_configs("go2_flat")
    cfg = registry.get_task("go2_flat").env_cfg
    path = dump_yaml(cfg, tmp_path / "env.yaml")
    back = load_yaml(Go2FlatCfg, path)
    assert back == cfg


def test_command_curriculum_widens_the_range_when_tracking_is_good():
    e = registry.make_env(
        "go2_flat", CPU + ["commands.curriculum=true", "commands.max_lin_vel_x=[-2.0, 2.0]"], num_envs=4
    )
    _, scale = e.reward_terms["tracking_lin_vel"]
    e.episode_length_buf[:] = 500
    e.episode_sums["tracking_lin_vel"][:2] = 0.9 * scale * e.max_episode_length  # good tracking
    e.update_curriculum(torch.tensor([0, 1]))
    e.common_step_counter = e.max_episode_length - 1
    e.step(torch.zeros(4, 12))  # the step that completes the period
    assert e.command_ranges["lin_vel_x"] == [-1.25, 1.25]
    e.episode_length_buf[:] = 500
    e.episode_sums["tracking_lin_vel"][:2] = 0.5 * scale * e.max_episode_length  # poor tracking
    e.update_curriculum(torch.tensor([0, 1]))
    e.common_step_counter = 2 * e.max_episode_length - 1
    e.step(torch.zeros(4, 12))
    assert e.command_ranges["lin_vel_x"] == [-1.25, 1.25]
    state = copy.deepcopy(e.get_state())
    e2 = registry.make_env("go2_flat", CPU, num_envs=2)
    e2.set_state(state)
    assert e2.command_ranges["lin_vel_x"] == [-1.25, 1.25]


def test_edge_curriculum_widens_each_end_on_its_own_tracking():
    e = registry.make_env(
        "go2_flat",
        CPU + ["commands.curriculum=true", "commands.curriculum_mode=edge", "commands.max_lin_vel_x=[-1.5, 3.0]"],
        num_envs=4,
    )
    sigma = e.cfg.rewards.tracking_sigma

    def score(vx_measured, steps=50, length=100):
        # envs 0/1 commanded at the forward/backward end, 2 in the middle (never counted), 3 standing
        e.commands[:] = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.0, 0.0]])
        e.base_lin_vel[:, 0] = torch.tensor(vx_measured)
        e.episode_length_buf[:] = length
        e.terminated_buf[:] = False
        for _ in range(steps):
            e._score_edges()

    # forward end tracked (error 0.05), backward end not (the robot stands): only +vx widens;
    # a robot whose state went non-finite (env 2, not in a band) changes nothing
    score([0.95, 0.0, float("nan"), 5.0])
    e.common_step_counter = e.max_episode_length - 1
    e.step(torch.zeros(4, 12))  # the step that completes the period
    assert e.command_ranges["lin_vel_x"] == [-1.0, 1.25]
    assert e.edge_tracking[1] > 0.9 and e.edge_tracking[0] < 0.1
    assert math.isclose(e.edge_tracking[1], math.exp(-(0.05**2) / sigma), rel_tol=0.05)
    # steps within curriculum_settle_s of a new command do not count: nothing to judge, no change
    score([0.0, -1.0, 0.0, 0.0], length=1)
    e.common_step_counter = 2 * e.max_episode_length - 1
    e.step(torch.zeros(4, 12))
    assert e.command_ranges["lin_vel_x"] == [-1.0, 1.25]
    # now the backward end tracks; the forward band is [1.0, 1.25] and the robot at +1.0 is in it
    score([1.0, -1.0, 0.0, 0.0])
    e.common_step_counter = 3 * e.max_episode_length - 1
    e.step(torch.zeros(4, 12))
    assert e.command_ranges["lin_vel_x"] == [-1.25, 1.5]
    # the ends stop at max_lin_vel_x
    for k in range(4, 12):
        score([1.0, -1.0, 0.0, 0.0])
        e.commands[0, 0], e.commands[1, 0] = e.command_ranges["lin_vel_x"][1], e.command_ranges["lin_vel_x"][0]
        e.base_lin_vel[:2, 0] = e.commands[:2, 0]
        for _ in range(50):
            e._score_edges()
        e.common_step_counter = k * e.max_episode_length - 1
        e.step(torch.zeros(4, 12))
    assert e.command_ranges["lin_vel_x"] == [-1.5, 3.0]
    with pytest.raises(ValueError, match="curriculum_settle_s"):
        registry.make_env(
            "go2_flat", CPU + ["commands.curriculum_mode=edge", "commands.curriculum_settle_s=20"], num_envs=1
        )


def test_two_iterations_of_rsl_rl_ppo(tmp_path):
    e = registry.make_env("go2_flat", CPU, num_envs=4)
    train_cfg = registry.get_task("go2_flat").train_cfg
    cfg = train_cfg.to_rsl_rl()
    cfg["num_steps_per_env"] = 8
    runner = OnPolicyRunner(e, copy.deepcopy(cfg), log_dir=str(tmp_path), device="cpu")
    runner.learn(num_learning_iterations=2)
    assert runner.current_learning_iteration == 1
    saved = sorted(p.name for p in tmp_path.glob("model_*.pt"))
    assert saved
    state = torch.load(tmp_path / saved[-1], weights_only=True)
    assert "actor_state_dict" in state or any("actor" in k for k in state)


def test_observation_delay_of_a_whole_period_shows_the_policy_the_previous_state():
    """domain_rand.observation_delay_range = (dt, dt): the policy's state terms (joint_pos,
    joint_vel, ang_vel, projected_gravity) are those the undelayed env showed one step
    earlier, while its actions term, the critic and the env's own state are the present; the
    first observation after a reset has no delay. A delay beyond the control period is
    refused."""
    plain = registry.make_env("go2_flat", FIXED, num_envs=2)
    period = plain.dt
    late = registry.make_env(
        "go2_flat", [*FIXED, f"domain_rand.observation_delay_range=[{period}, {period}]"], num_envs=2
    )
    assert (late.obs_delay_steps == late.sim.decimation).all() and (plain.obs_delay_steps == 0).all()
    cols = plain.policy_obs_columns()
    state = [cols[t] for t in ("ang_vel", "projected_gravity", "joint_pos", "joint_vel")]
    g = torch.Generator().manual_seed(0)
    actions = [0.5 * torch.randn(2, plain.num_actions, generator=g) for _ in range(3)]
    first = []
    for e in (plain, late):
        e.set_commands([0.5, 0.0, 0.2])  # the delay's draws shift the random stream: same commands by hand
        first.append(e.reset()["policy"].clone())
    torch.testing.assert_close(first[1], first[0])  # no delay right after a reset
    shown = [first[0]]
    for a in actions:
        plain_obs, _, _, _ = plain.step(a)
        late_obs, _, _, _ = late.step(a)
        torch.testing.assert_close(late.joint_pos, plain.joint_pos)  # the physics is not delayed
        torch.testing.assert_close(late_obs["critic"], plain_obs["critic"])
        for lo, hi in state:
            torch.testing.assert_close(late_obs["policy"][:, lo:hi], shown[-1][:, lo:hi], atol=1e-6, rtol=0)
        lo, hi = cols["actions"]
        torch.testing.assert_close(late_obs["policy"][:, lo:hi], plain_obs["policy"][:, lo:hi])
        shown.append(plain_obs["policy"].clone())
    assert not torch.allclose(shown[-1], shown[-2])  # the robot moved: the test compares something
    with pytest.raises(ValueError, match="control period"):
        registry.make_env("go2_flat", [*FIXED, f"domain_rand.observation_delay_range=[0, {2 * period}]"], num_envs=2)
    plain.close()
    late.close()


def test_motor_strength_scales_the_pd_torque_and_the_torque_limit():
    """domain_rand.motor_strength_range = (0.5, 0.5): every motor's Kp, Kd and torque limit are
    halved, so a target at the end of a joint's range gives at most half the torque, and
    exactly half where the nominal motor saturates; off, (1, 1), keeps the nominal model; a
    non-positive strength is refused."""
    plain = registry.make_env("go2_flat", FIXED, num_envs=2)
    weak = registry.make_env("go2_flat", [*FIXED, "domain_rand.motor_strength_range=[0.5, 0.5]"], num_envs=2)
    nominal = torch.tensor(plain.model.actuator_forcerange, dtype=torch.float64)
    limits = [e.sim.get_model_field("actuator_forcerange").double() for e in (plain, weak)]
    torch.testing.assert_close(limits[0], nominal.expand(2, -1, -1))
    torch.testing.assert_close(limits[1], 0.5 * nominal.expand(2, -1, -1))
    kp = weak.sim.get_model_field("actuator_gainprm")[..., 0]
    torch.testing.assert_close(kp.double(), 0.5 * torch.tensor(plain.model.actuator_gainprm[:, 0]).expand(2, -1))
    torques = []
    for e in (plain, weak):
        e.step(torch.full((2, e.num_actions), 50.0))  # targets clamped to the far end of each range
        # the first substep's actuator forces: from the same standing state in both envs
        first = e.sim.substep_sensordata()[:, 0]
        torques.append(first[:, e._sensor_columns(e._torque_sensors)].abs().float())
    limit = nominal[:, 1].float().expand(2, -1)
    saturated = torques[0] > limit - 1e-3
    assert saturated.sum() >= 8  # most nominal motors hit their limit: the test compares limits
    assert (torques[1] <= 0.5 * limit + 1e-3).all()
    torch.testing.assert_close(torques[1][saturated], 0.5 * limit[saturated], atol=1e-3, rtol=0)
    with pytest.raises(ValueError, match="motor_strength_range"):
        registry.make_env("go2_flat", [*FIXED, "domain_rand.motor_strength_range=[0.0, 1.0]"], num_envs=2)
    plain.close()
    weak.close()


def test_set_commands_holds_them_through_timers_and_resets():
    e = registry.make_env("go2_flat", CPU + ["commands.resampling_time=0.1"], num_envs=3)
    e.set_commands([0.6, -0.2, 0.3])
    for _ in range(12):
        e.step(torch.zeros(3, 12))
    e.reset_idx(torch.tensor([1]))
    assert torch.allclose(e.commands, torch.tensor([0.6, -0.2, 0.3]).expand(3, 3))


def test_latency_and_delay_draws_give_every_whole_substep_the_same_weight():
    """A 0-20 ms range at 5 ms physics draws 0, 1, 2, 3 and 4 substeps equally often (a
    rounded uniform draw in seconds gave the ends, 0 and 20 ms, half the weight of the
    others); a range's ends round to the nearest substep and never pass one control step."""
    env = registry.make_env("go2_flat", [*FIXED, "sim.timestep=0.005", "sim.decimation=4"], num_envs=2)
    assert env.sim.physics_dt == 0.005 and env.sim.decimation == 4
    torch.manual_seed(0)
    share = torch.bincount(env._draw_substeps((0.0, 0.02), 50_000), minlength=5).float() / 50_000
    assert torch.allclose(share, torch.full((5,), 0.2), atol=0.01), share
    assert set(env._draw_substeps((0.006, 0.014), 2_000).tolist()) == {1, 2, 3}
    assert set(env._draw_substeps((0.018, 0.02), 100).tolist()) == {4}


def test_action_latency_of_a_whole_period_applies_each_action_one_step_late():
    """domain_rand.action_latency_range = (dt, dt): the actuators keep the previous step's
    targets for the whole control period, so actions (a1, a2) move the robot exactly as
    (0, a1) do without latency; a reset starts from the nominal targets again."""
    plain = registry.make_env("go2_flat", FIXED, num_envs=2)
    period = plain.dt
    late = registry.make_env("go2_flat", [*FIXED, f"domain_rand.action_latency_range=[{period}, {period}]"], num_envs=2)
    assert (late.latency_steps == late.sim.decimation).all() and (plain.latency_steps == 0).all()
    g = torch.Generator().manual_seed(0)
    a1, a2 = (0.5 * torch.randn(2, plain.num_actions, generator=g) for _ in range(2))
    for e in (plain, late):
        e.reset_idx(torch.arange(2))
    late.step(a1)
    late.step(a2)
    plain.step(torch.zeros_like(a1))
    plain.step(a1)
    torch.testing.assert_close(late.joint_pos, plain.joint_pos, atol=1e-6, rtol=0)
    late.reset_idx(torch.arange(2))
    torch.testing.assert_close(late.held_targets, late.action_targets(torch.zeros_like(a1)))
    with pytest.raises(ValueError, match="control period"):
        registry.make_env("go2_flat", [*FIXED, f"domain_rand.action_latency_range=[0, {2 * period}]"], num_envs=2)
    plain.close()
    late.close()


def test_ground_slope_tilts_gravity_and_the_imu_sees_it():
    env = registry.make_env("caster_omni", FIXED, num_envs=3)
    try:
        env.set_commands([0.0, 0.0, 0.0])
        env.set_ground_slope(torch.tensor([0.0, 4.0, 4.0]), torch.tensor([0.0, 0.0, math.pi / 2]))
        env.reset_idx(torch.arange(3))
        assert torch.allclose(env.ground_slope_deg(), torch.tensor([0.0, 4.0, 4.0]), atol=1e-3)
        s = math.sin(math.radians(4.0))
        # The robot faces +x: downhill ahead shows as gravity pulling forward, downhill to
        # the left as gravity pulling left; the ground's normal is the trunk's z either way.
        assert torch.allclose(env.projected_gravity[1, :2], torch.tensor([s, 0.0]), atol=2e-3)
        assert torch.allclose(env.projected_gravity[2, :2], torch.tensor([0.0, s]), atol=2e-3)
        assert torch.allclose(env.ground_gravity[:, :2], torch.zeros(3, 2), atol=2e-3)
        start = env.base_pos[:, :2].clone()
        for _ in range(50):  # 1 s, the nominal pose
            env.step(torch.zeros(3, env.num_actions))
        moved = env.base_pos[:, :2] - start
        assert moved[0].abs().max() < 0.02
        assert moved[1, 0] > 0.1
        assert env.ground_slope_deg()[1] > 3.9  # stays over resets
        env.reset_idx(torch.tensor([1]))
        assert abs(float(env.ground_slope_deg()[1]) - 4.0) < 1e-3
    finally:
        env.close()


def test_slope_draw_covers_the_range_in_the_configured_share_of_episodes():
    env = registry.make_env(
        "caster_omni", FIXED + ["terrain.slope_deg=6.0", "terrain.slope_fraction=0.5"], num_envs=200
    )
    try:
        deg = env.ground_slope_deg()
        tilted = deg > 1e-3
        assert 0.35 < float(tilted.float().mean()) < 0.65
        assert float(deg.max()) <= 6.0 + 1e-3 and float(deg[tilted].max()) > 4.0
        downhill = torch.atan2(env.gravity_dir[tilted, 1], env.gravity_dir[tilted, 0])
        assert float(downhill.min()) < -2.0 and float(downhill.max()) > 2.0  # every direction
    finally:
        env.close()


def test_reversal_commands_flip_the_planar_command_before_them(env):
    cfg = env.cfg.commands
    saved = (cfg.reverse_fraction, cfg.standing_fraction, cfg.single_axis_fraction)
    try:
        cfg.reverse_fraction, cfg.standing_fraction, cfg.single_axis_fraction = 1.0, 1.0, 0.0
        env.commands[:] = torch.tensor([1.2, -0.3, 0.5])
        env.resample_commands(torch.arange(env.num_envs))
        # a reversal wins over a stop drawn for the same robot
        assert torch.allclose(env.commands, torch.tensor([-1.2, 0.3, 0.5]).expand(env.num_envs, 3))
    finally:
        cfg.reverse_fraction, cfg.standing_fraction, cfg.single_axis_fraction = saved


def test_stand_still_waits_for_the_trunk_to_slow_down(env):
    env.set_commands([0.0, 0.0, 0.0])
    env.joint_pos = (env.default_joint_pos + 0.1).expand(env.num_envs, -1).clone()
    env.base_lin_vel = torch.zeros(env.num_envs, 3)
    env.base_lin_vel[0, 0] = 1.0
    saved = env.cfg.rewards.stand_still_max_speed
    try:
        env.cfg.rewards.stand_still_max_speed = None
        everywhere = env._reward_stand_still()
        assert (everywhere > 0).all()
        env.cfg.rewards.stand_still_max_speed = 0.2
        gated = env._reward_stand_still()
        assert gated[0] == 0 and torch.equal(gated[1:], everywhere[1:])
    finally:
        env.cfg.rewards.stand_still_max_speed = saved
        env.external_commands = False
        env._refresh_state()
