"""caster_omni_paper (Table I as written): observation layout, Table I terms on hand-made states, propulsion
modes, randomisation on both backends, and PPO plumbing."""

import copy
import math

import pytest
import torch
from rsl_rl.runners import OnPolicyRunner

from legged_casters import registry
from legged_casters.config import ConfigError
from legged_casters.robot import go2

CPU = ["sim.backend=cpu"]


@pytest.fixture(scope="module")
def env():
    e = registry.make_env("caster_omni_paper", CPU, num_envs=4)
    yield e
    e.close()


def _slice(env, group, term):
    start = 0
    for name, dim, _ in env.obs_layout[group]:
        if name == term:
            return slice(start, start + dim)
        start += dim
    raise KeyError(term)


def test_observation_layout(env):
    assert [n for n, _, _ in env.obs_layout["policy"]] == [
        "commands", "mode_mask", "ang_vel", "projected_gravity", "joint_pos", "joint_vel", "actions",
    ]  # fmt: skip
    assert [(n, d) for n, d, _ in env.obs_layout["critic"]] == [
        ("caster_zaxis", 12), ("swivel_pos", 4), ("swivel_vel", 4), ("lin_vel", 3), ("ground_gravity", 3),
    ]  # fmt: skip
    assert env.observation_dims() == {
        "policy": 3 + 4 + 3 + 3 + 12 + 12 + 12, "critic": 12 + 4 + 4 + 3 + 3, "estimator_target": 3,
    }  # fmt: skip
    obs = env.get_observations()
    # The velocity estimator's regression target: the trunk velocity in the trunk frame.
    assert torch.equal(obs["estimator_target"], env.base_lin_vel)
    assert obs["policy"].shape == (4, 49) and obs["critic"].shape == (4, 26)
    # The critic's swivel axes are the model's caster-base z axes (unit vectors, near vertical standing).
    z = obs["critic"][:, _slice(env, "critic", "caster_zaxis")].view(4, 4, 3)
    assert torch.allclose(z.norm(dim=-1), torch.ones(4, 4), atol=1e-5)
    assert (z[..., 2] > 0.7).all()


def _hand_made(env, command, zaxis_dir=None, phi=None, phi_dot=None, mask=None):
    env.commands[:] = torch.tensor(command)
    env.base_quat = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(env.num_envs, 4)
    if zaxis_dir is not None:  # horizontal direction (rad) of every swivel axis, tilted 20 deg
        tilt = math.radians(20)
        z = torch.tensor([math.sin(tilt) * math.cos(zaxis_dir), math.sin(tilt) * math.sin(zaxis_dir), math.cos(tilt)])
        env.caster_zaxis = z.expand(env.num_envs, 4, 3).clone()
    if phi is not None:
        env.swivel_pos = torch.full((env.num_envs, 4), float(phi))
    if phi_dot is not None:
        env.swivel_vel = torch.as_tensor(phi_dot, dtype=torch.float32).expand(env.num_envs, 4).clone()
    if mask is not None:
        env.mode_mask = torch.tensor(mask, dtype=torch.float32).expand(env.num_envs, 4).clone()


def test_posture_term_is_zero_below_90_degrees_and_negative_above(env):
    _hand_made(env, [1.0, 0.0, 0.0], zaxis_dir=math.radians(60))  # axis 60 deg off the command
    assert torch.allclose(env._reward_caster_posture(), torch.zeros(4))
    _hand_made(env, [1.0, 0.0, 0.0], zaxis_dir=math.radians(150))  # axis tilted against the command
    expected = 4 * math.cos(math.radians(150))
    assert torch.allclose(env._reward_caster_posture(), torch.full((4,), expected), atol=1e-4)
    assert env.reward_terms["caster_posture"][1] > 0  # positive weight x negative term = penalty
    # Lateral command: an axis tilted to the left is aligned with vy > 0.
    _hand_made(env, [0.0, 0.5, 0.0], zaxis_dir=math.radians(90))
    assert torch.allclose(env.theta_diffz(), torch.zeros(4, 4), atol=1e-5)


def test_joint_angle_term_penalises_deflection_against_the_command(env):
    _hand_made(env, [-0.6, 0.0, 0.0], phi=math.pi)  # rolling backwards, casters trailing: fine
    assert torch.allclose(env._reward_caster_joint_angle(), torch.zeros(4), atol=1e-6)
    _hand_made(env, [0.6, 0.0, 0.0], phi=math.pi)  # commanded forwards with casters still reversed
    assert torch.allclose(env._reward_caster_joint_angle(), torch.full((4,), 4.0), atol=1e-5)
    assert env.reward_terms["caster_joint_angle"][1] < 0


def test_mask_term_rewards_still_masked_and_moving_unmasked_casters(env):
    fast, still = 20.0, 0.0
    _hand_made(env, [1.0, 0.0, 0.0], phi_dot=[still, still, fast, fast], mask=[1, 1, 0, 0])
    good = env._reward_caster_oscillation_mask()
    _hand_made(env, [1.0, 0.0, 0.0], phi_dot=[fast, fast, still, still], mask=[1, 1, 0, 0])
    bad = env._reward_caster_oscillation_mask()
    assert torch.allclose(good, torch.full((4,), 2 * 1.0 + 2 * 0.5), atol=1e-6)
    assert torch.allclose(bad, torch.zeros(4), atol=1e-6)


def test_gated_terms_do_not_act_below_0_2_m_per_s(env):
    _hand_made(env, [0.15, 0.1, 0.5], zaxis_dir=math.pi, phi=2.5, phi_dot=[5.0] * 4, mask=[1, 1, 1, 0])
    for term in ("caster_posture", "caster_joint_angle", "caster_oscillation_mask"):
        assert torch.allclose(getattr(env, f"_reward_{term}")(), torch.zeros(4)), term
    _hand_made(env, [0.3, 0.0, 0.0], zaxis_dir=math.pi, phi=2.5, phi_dot=[5.0] * 4, mask=[1, 1, 1, 0])
    for term in ("caster_posture", "caster_joint_angle", "caster_oscillation_mask"):
        assert not torch.allclose(getattr(env, f"_reward_{term}")(), torch.zeros(4)), term


def test_table_one_weights_and_sign_decisions(env):
    dt = env.dt
    scales = {name: scale / dt for name, (_, scale) in env.reward_terms.items()}
    assert scales["tracking_lin_vel"] == pytest.approx(2.0) and scales["tracking_ang_vel"] == pytest.approx(0.5)
    assert scales["joint_acc"] == pytest.approx(-2.5e-7)  # acceleration is penalised
    assert scales["termination"] == pytest.approx(-10.0)
    assert env._reward_joint_acc().min() >= 0


def test_modes_reach_the_observation_and_switch_mid_episode():
    e = registry.make_env("caster_omni_paper", CPU, num_envs=2)
    sl = _slice(e, "policy", "mode_mask")
    e.set_mode("front_wheel")
    obs, *_ = e.step(torch.zeros(2, 12))
    assert torch.equal(obs["policy"][:, sl], torch.tensor([[0.0, 0, 1, 1]] * 2))
    e.set_mode("rear_wheel")
    obs, *_ = e.step(torch.zeros(2, 12))
    assert torch.equal(obs["policy"][:, sl], torch.tensor([[1.0, 1, 0, 0]] * 2))
    assert (e.episode_length_buf == 2).all()  # same episode
    with pytest.raises(KeyError, match="unknown propulsion mode"):
        e.set_mode("hover")
    with pytest.raises(ValueError, match="4 values of 0 or 1"):
        e.set_mode([1, 0, 2, 0])


def test_modes_switch_on_their_own_during_training():
    e = registry.make_env(
        "caster_omni_paper", CPU + ["modes.switch_probability=1.0", "commands.resampling_time=0.04"], num_envs=8
    )
    seen = set()
    for _ in range(30):
        e.step(torch.zeros(8, 12))
        seen |= {tuple(m) for m in e.mode_mask.int().tolist()}
    assert seen == {(0, 0, 0, 0), (0, 0, 1, 1), (1, 1, 0, 0)}


def test_any_non_empty_subset_of_oscillating_casters_is_configurable():
    e = registry.make_env(
        "caster_omni_paper", CPU + ["modes.masks={'fl_only': [0, 1, 1, 1]}", "modes.sample=['fl_only']"], num_envs=2
    )
    assert torch.equal(e.mode_mask, torch.tensor([[0.0, 1, 1, 1]] * 2))
    with pytest.raises(ConfigError, match="at least one caster must oscillate"):
        registry.make_env("caster_omni_paper", CPU + ["modes.masks={'none': [1, 1, 1, 1]}", "modes.sample=['none']"])
    with pytest.raises(ConfigError, match="must name modes"):
        registry.make_env("caster_omni_paper", CPU + ["modes.sample=['warp_drive']"], num_envs=2)


@pytest.mark.parametrize("backend", ["cpu", "warp"])
def test_paper_randomisation_lands_in_each_backend(backend):
    e = registry.make_env("caster_omni_paper", [f"sim.backend={backend}", "sim.device=cpu"], num_envs=3)
    damping = e.sim.get_model_field("dof_damping")
    swivel = [e.model.joint(j).dofadr[0] for j in go2.SWIVEL_JOINTS]
    assert damping[:, swivel].min() >= 0.01 - 1e-7 and damping[:, swivel].max() <= 0.1 + 1e-7
    assert damping[:, swivel].std() > 0.005
    wheel = [e.model.joint(j).dofadr[0] for j in go2.WHEEL_JOINTS]
    floss = e.sim.get_model_field("dof_frictionloss")[:, wheel] / e.model.dof_frictionloss[wheel[0]]
    assert floss.min() >= 0.5 - 1e-5 and floss.max() <= 1.5 + 1e-5
    kp = e.sim.get_model_field("actuator_gainprm")[:, :, 0] / torch.tensor(go2.kp(), dtype=torch.float64)
    assert kp.min() >= 0.9 - 1e-5 and kp.max() <= 1.1 + 1e-5
    com = e.sim.get_model_field("body_ipos")[:, e.trunk_id] - torch.tensor(e.model.body_ipos[e.trunk_id])
    assert com.abs().max() <= 0.05 + 1e-6
    obs, rew, *_ = e.step(torch.zeros(3, 12))
    assert torch.isfinite(rew).all()
    e.close()


def test_two_iterations_of_rsl_rl_ppo_with_the_asymmetric_critic(tmp_path):
    e = registry.make_env("caster_omni_paper", CPU, num_envs=4)
    cfg = registry.get_task("caster_omni_paper").train_cfg.to_rsl_rl()
    cfg["num_steps_per_env"] = 8
    runner = OnPolicyRunner(e, copy.deepcopy(cfg), log_dir=str(tmp_path), device="cpu")
    assert runner.alg.actor.obs_dim == 49 and runner.alg.critic.obs_dim == 49 + 26
    runner.learn(num_learning_iterations=2)
    assert runner.current_learning_iteration == 1


def test_long_random_rollout_stays_finite():
    e = registry.make_env("caster_omni_paper", CPU + ["domain_rand.push_interval_s=0.5"], num_envs=16)
    torch.manual_seed(2)
    for _ in range(300):
        obs, rew, dones, extras = e.step(torch.randn(e.num_envs, e.num_actions))
        assert torch.isfinite(obs["policy"]).all() and torch.isfinite(obs["critic"]).all()
        assert torch.isfinite(rew).all()
        for key, value in extras["log"].items():
            assert torch.isfinite(torch.as_tensor(value)).all(), key
    assert e.nonfinite_resets == 0


def test_sim2sim_conditions_keep_the_control_period():
    """evaluate.py --physics-dt / --action-latency-ms / --noise: the evaluation env runs
    the same control period on another physics step, with the latency in whole physics
    steps; impossible values are usage errors; the comparison table reports the largest
    change of an error from the first condition."""
    from legged_casters.tools import evaluate as E
    from legged_casters.tools.common import UsageError

    spec = registry.get_task("caster_omni")
    cfg, _ = registry.task_configs("caster_omni")
    scenarios = E.QUICK[:1]
    cond = E.condition_overrides(cfg, physics_dt=0.002, latency_ms=20.0, noise=True, obs_delay_ms=6.0)
    env = spec.env_class(E.eval_env_cfg(cfg, scenarios, condition=cond))
    try:
        assert env.sim.physics_dt == pytest.approx(0.002)
        assert env.sim.decimation == 10 and env.dt == pytest.approx(0.02)
        assert (env.latency_steps == 10).all() and (env.obs_delay_steps == 3).all()
        assert env.cfg.noise.enabled
    finally:
        env.close()
    trained, _ = registry.task_configs("caster_omni", ["domain_rand.action_latency_range=[0, 0.02]"])
    assert tuple(E.eval_env_cfg(trained, scenarios).domain_rand.action_latency_range) == (0.0, 0.0)
    trained, _ = registry.task_configs("caster_omni", ["domain_rand.observation_delay_range=[0, 0.02]"])
    assert tuple(E.eval_env_cfg(trained, scenarios).domain_rand.observation_delay_range) == (0.0, 0.0)
    with pytest.raises(UsageError, match="whole number"):
        E.condition_overrides(cfg, physics_dt=0.003)
    with pytest.raises(UsageError, match="control period"):
        E.condition_overrides(cfg, latency_ms=30.0)
    with pytest.raises(UsageError, match="observation-delay-ms 25: must be between 0 and the control period"):
        E.condition_overrides(cfg, obs_delay_ms=25.0)
    base = E.ScenarioResult("vx +0.5", "track", (0.5, 0.0, 0.0), {}, {"vx": 0.1, "vy": 0.05, "wz": 0.2})
    worse = E.ScenarioResult("vx +0.5", "track", (0.5, 0.0, 0.0), {}, {"vx": 0.3, "vy": 0.05, "wz": 0.1}, falls=1)
    table = E.format_sim2sim(
        [("5 ms", [base], [("c", True, "x")], {0: 0}), ("latency", [worse], [("c", False, "y")], {0: 1})]
    )
    assert "| latency | 0/1 | 1 | +0.200 (vx +0.5 vx) | -0.100 (vx +0.5 wz) |" in table


def test_sim2sim_tolerance_and_seeds():
    """--seeds: parsed as lists and ranges; the falls table sums every seed; the tolerance
    table (the robot-clock bar) takes the verdict's error checks only, m/s and rad/s apart, and
    says no for a change beyond its bound or for more falls over the seeds."""
    from legged_casters.tools import evaluate as E
    from legged_casters.tools.common import UsageError

    assert E.parse_seeds("0-4") == [0, 1, 2, 3, 4]
    assert E.parse_seeds("0,3,7") == [0, 3, 7]
    assert E.parse_seeds("5, 1-2,2") == [5, 1, 2]
    for bad in ("a", "3-1", "-1", "", "1,,2"):
        with pytest.raises(UsageError, match="--seeds"):
            E.parse_seeds(bad)

    def checks(vx, wz, est, step_s):
        return [
            ("vx +0.5: |vx error| <= 0.15", True, f"{vx:.3f}"),
            ("wz +0.8: |wz error| <= 0.25", True, f"{wz:.3f}"),
            ("fig6 step: vx changes sign within 1.5 s", True, f"{step_s:.2f} s"),  # a time, not an error
            ("estimator RMS error <= 0.1 m/s (worst flat scenario)", False, f"{est:.3f}"),
            ("front_wheel: masked/driven swivel RMS <= 0.2", False, "0.90"),  # a ratio, not an error
        ]

    rows = [
        ("5 ms", [], checks(0.10, 0.20, 0.20, 1.0), {0: 1, 1: 0}),
        ("2 ms", [], checks(0.14, 0.29, 0.18, 0.2), {0: 0, 1: 1}),  # +0.04 m/s, +0.09 rad/s, 1 fall: within
        ("estimator", [], checks(0.10, 0.20, 0.26, 1.0), {0: 0, 1: 0}),  # estimator +0.06 m/s: outside
        ("turn", [], checks(0.10, 0.32, 0.20, 1.0), {0: 0, 1: 0}),  # +0.12 rad/s: outside
        ("falls", [], checks(0.10, 0.20, 0.20, 1.0), {0: 1, 1: 1}),  # 2 falls against 1: outside
    ]
    table = E.format_tolerance(rows, 2).splitlines()
    assert table[0].startswith("sim-to-sim tolerance: every error check within 0.05 m/s (0.1 rad/s for wz)")
    assert "| 2 ms | +0.040 (vx +0.5) | +0.090 (wz +0.8) | 1 | yes |" in table
    assert "| estimator | +0.060 (estimator RMS error) | +0.000 (-) | 0 | no |" in table
    assert "| turn | +0.000 (-) | +0.120 (wz +0.8) | 0 | no |" in table
    assert "| falls | +0.000 (-) | +0.000 (-) | 2 | no |" in table
    falls = E.format_seed_falls(rows[:2], [0, 1]).splitlines()
    assert falls[0] == "| condition | seed 0 | seed 1 | total |"
    assert falls[2:] == ["| 5 ms | 1 | 0 | 1 |", "| 2 ms | 0 | 1 | 1 |"]


def test_robot_clock_ranking_puts_falls_at_the_training_conditions_first():
    """--checkpoints --robot-clock's order: a checkpoint that falls at 5 ms ranks below one
    that does not, even if its falls elsewhere keep it "within" the (relative) bar; then
    within before not, fewer falls, more checks, the newer; the table shows each condition's
    largest changes and verdict."""
    from legged_casters.tools import evaluate as E

    def row(file, it, falls, within, passed=8):
        change = ((0.01, "vx +0.5"), (0.02, "wz +0.8"), within)
        return {"file": file, "iteration": it, "passed": passed, "checks": 16, "falls": falls,
                "changes": [change, change], "within": within}  # fmt: skip

    rows = [
        row("steady_faller.pt", 100, [5, 5, 5], True),  # within (no more falls than at 5 ms), but falls
        row("upright_out.pt", 200, [0, 0, 1], False),
        row("upright_in.pt", 150, [0, 0, 0], True),
        row("upright_in_more_checks.pt", 120, [0, 0, 0], True, passed=10),
    ]
    order = [r["file"] for r in sorted(rows, key=E._robot_clock_key)]
    assert order == ["upright_in_more_checks.pt", "upright_in.pt", "upright_out.pt", "steady_faller.pt"]
    table = E.format_robot_clock_ranking(rows, 5).splitlines()
    assert table[0].startswith("the robot-clock bar: every error check within 0.05 m/s") and "(5 seeds)" in table[0]
    assert "2 ms physics: largest change, m/s; rad/s: within" in table[1]
    assert table[3] == (
        "| 1 | upright_in_more_checks.pt | 120 | 10/16 | 0 / 0 / 0 | +0.010 (vx +0.5); +0.020 (wz +0.8): yes | "
        "+0.010 (vx +0.5); +0.020 (wz +0.8): yes | yes |"
    )
    assert table[-1].startswith("| 4 | steady_faller.pt | 100 | 8/16 | 5 / 5 / 5 |")


def test_a_redrawn_seed_falls_as_its_own_full_run():
    """--seeds reruns only the random-command scenarios for the further seeds: on the
    training conditions that gives the random scenario exactly what a whole run with
    --seed N gives it (the other scenarios' robots do not change its draws or physics)."""
    from legged_casters.tools import evaluate as E

    spec = registry.get_task("caster_omni")
    cfg, _ = registry.task_configs("caster_omni", [])
    track = E.Scenario("vx +0.5", ((0.0, (0.5, 0.0, 0.0)),), 1.0, 0.5)
    pushed = E.Scenario("pushed", ((0.0, (0.0, 0.0, 0.0)),), 2.0, 0.0, copies=2, random_commands=True,
                        kind="random", push_interval=0.5)  # fmt: skip
    whole = spec.env_class(E.eval_env_cfg(cfg, (track, pushed)))
    alone = spec.env_class(E.eval_env_cfg(cfg, (pushed,), terrain_of=(track, pushed)))
    try:
        stand = lambda obs: torch.zeros(obs["policy"].shape[0], 12)  # noqa: E731
        full = E.run_policy(whole, stand, (track, pushed), symmetrise=False, seed=2)[1]
        (redrawn,) = E.run_policy(alone, stand, (pushed,), symmetrise=False, seed=2)
    finally:
        whole.close()
        alone.close()
    assert full.name == redrawn.name == "pushed"
    assert full.err == redrawn.err and full.mean == redrawn.mean and full.falls == redrawn.falls


def test_an_imu_bias_is_constant_per_episode_and_only_on_its_terms():
    """noise.bias (evaluate.py --imu-bias): each env's offset is drawn at reset within the
    bounds, only on the named terms (scaled as the term), the same on every step of the
    episode and redrawn at the next; an unknown term is refused; evaluation has none."""
    from legged_casters.tools import evaluate as E

    spec = registry.get_task("caster_omni")
    cfg, _ = registry.task_configs("caster_omni")
    env = spec.env_class(E.eval_env_cfg(cfg, E.QUICK[:2], condition=E.condition_overrides(cfg, imu_bias=True)))
    try:
        cols = env.policy_obs_columns()
        scale = dict((t, sc) for t, _, sc in env.obs_layout["policy"])
        first = env.obs_bias.clone()
        for term, (a, b) in cols.items():
            bound = E.IMU_BIAS.get(term, 0.0) * scale[term]
            assert (first[:, a:b].abs() <= bound + 1e-7).all(), term
            assert (first[:, a:b] != 0).any() == (bound > 0), term
        env.set_commands(torch.zeros(env.num_envs, 3))
        g0, g1 = cols["projected_gravity"]
        for _ in range(2):
            obs = env.step(torch.zeros(env.num_envs, 12))[0]["policy"]
            assert torch.equal(env.obs_bias, first)
            seen = obs[:, g0:g1] - env.projected_gravity * scale["projected_gravity"]
            assert (seen - first[:, g0:g1]).abs().max() < 1e-5
        env.reset()
        assert not torch.equal(env.obs_bias, first)
    finally:
        env.close()
    with pytest.raises(ValueError, match="noise.bias"):
        registry.make_env("caster_omni", ["sim.backend=cpu", "noise.bias={heading: 0.1}"], num_envs=1)
    assert E.eval_env_cfg(cfg, E.QUICK[:1]).noise.bias == {}


def test_the_training_evaluation_pushes_robots_at_each_scenarios_interval():
    """The quick evaluation (train.py's model_best choice) has a pushed-robots scenario;
    pushes come at each random scenario's own interval and only its falls are counted."""
    from legged_casters.tools import evaluate as E

    pushes = [s for s in E.QUICK if s.kind == "random"]
    assert len(pushes) == 1 and pushes[0].push_interval < pushes[0].duration and pushes[0].copies >= 4
    assert pushes[0].duration > 5.0  # random commands change every 5 s: it must see one change
    spec = registry.get_task("caster_omni")
    still = [f"commands.ranges.{k}=[0, 0]" for k in ("lin_vel_x", "lin_vel_y", "ang_vel_yaw")]
    cfg, _ = registry.task_configs("caster_omni", still)  # random commands that are all zero: |error| = |v|
    often = E.Scenario("often", ((0.0, (0.0, 0.0, 0.0)),), 3.0, 0.0, copies=2, random_commands=True,
                       kind="random", push_interval=0.5)  # fmt: skip
    never = E.Scenario("never", ((0.0, (0.0, 0.0, 0.0)),), 3.0, 0.0, copies=2, random_commands=True,
                       kind="random", push_interval=100.0)  # fmt: skip
    env = spec.env_class(E.eval_env_cfg(cfg, (often, never)))
    try:
        stand = lambda obs: torch.zeros(env.num_envs, 12)  # noqa: E731  the nominal pose, no prior
        res = {r.name: r for r in E.run_scenarios(env, stand, (often, never))}
    finally:
        env.close()
    moved = {n: r.err["vx"] + r.err["vy"] for n, r in res.items()}
    assert moved["often"] > 0.1 and moved["never"] < 0.2 * moved["often"], moved
    summary = E.summary(list(res.values()))
    assert summary["falls"] == sum(r.falls for r in res.values()) and "vx_error" not in summary
    for r in res.values():  # each random scenario attributes its falls to pushes and new commands
        assert 0 <= r.extra["falls_after_push"] <= r.falls and 0 <= r.extra["falls_after_cmd"] <= r.falls


def test_evaluation_seed_redraws_random_commands_and_pushes():
    """evaluate.py --seed: the same seed gives the same random scenario (commands and pushes),
    another seed another one; run_policy (the CLI's path) passes the seed on."""
    from legged_casters.tools import evaluate as E

    spec = registry.get_task("caster_omni")
    cfg, _ = registry.task_configs("caster_omni", [])
    pushed = E.Scenario("pushed", ((0.0, (0.0, 0.0, 0.0)),), 2.0, 0.0, copies=2, random_commands=True,
                        kind="random", push_interval=0.5)  # fmt: skip
    env = spec.env_class(E.eval_env_cfg(cfg, (pushed,)))
    try:
        stand = lambda obs: torch.zeros(env.num_envs, 12)  # noqa: E731
        (a,) = E.run_scenarios(env, stand, (pushed,))
        (b,) = E.run_policy(env, stand, (pushed,), symmetrise=False, seed=0)
        (c,) = E.run_policy(env, stand, (pushed,), symmetrise=False, seed=1)
    finally:
        env.close()
    assert a.err == b.err and a.mean == b.mean
    assert a.err != c.err
    args = E.build_parser().parse_args(["--seed", "3"])
    assert args.seed == 3 and E.build_parser().parse_args([]).seed == 0


def test_falls_are_attributed_to_the_last_push_or_command_within_the_window():
    """falls_after: a fall counts when the robot's last event at or before it is at most the
    window earlier; earlier events, later events and no events do not count."""
    from legged_casters.tools.evaluate import falls_after

    assert falls_after([100], [60], 50) == 1  # 40 steps after a push
    assert falls_after([100], [40], 50) == 0  # 60 steps after: too long ago
    assert falls_after([100], [40, 120], 50) == 0  # the later event does not explain it
    assert falls_after([100], [100], 50) == 1  # pushed on the step it fell
    assert falls_after([100, 300], [90, 280], 50) == 2
    assert falls_after([100, 300], [90], 50) == 1
    assert falls_after([100], [], 50) == 0
