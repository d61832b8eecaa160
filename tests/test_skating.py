"""caster_omni (the skating configuration): the gait prior, its clock, the actor that
carries it, its export and the bridge's copy of the clock, and the evaluation."""

import copy
import dataclasses

import numpy as np
import pytest
import torch
import yaml
from rsl_rl.runners import OnPolicyRunner

from legged_casters import registry
from legged_casters.config import ConfigError
from legged_casters.deploy import protocol as P
from legged_casters.deploy.policy import ObservationBuilder, PolicyFormatError, load_meta
from legged_casters.envs.gait import GaitPrior, GaitPriorCfg, gait_prior, stop_pose
from legged_casters.learning.models import PriorMLPModel
from legged_casters.robot import go2
from legged_casters.tools import evaluate, export

TASK = "caster_omni"
CPU = ["sim.backend=cpu"]
CFG = GaitPriorCfg(enabled=True, frequency=2.0, amplitude=0.2, tilt=0.2, thigh_share=0.0, full_speed=0.5)


LAW, LAW_BACK = [[0.0, 0.0], [1.0, 0.1], [2.0, 0.2]], [[0.0, 0.0], [1.0, 0.3]]
FORWARD_LAW = [
    [0.0, 0.0],
    [0.011, 0.05],
    [0.056, 0.06],
    [0.179, 0.07],
    [0.725, 0.08],
    [1.005, 0.09],
    [1.174, 0.1],
    [1.426, 0.12],
    [1.524, 0.13],
    [1.698, 0.15],
    [1.92, 0.18],
    [2.05, 0.2],
    [2.183, 0.22],
    [2.437, 0.25],
]
BACKWARD_LAW = [
    [0.0, 0.0],
    [0.036, 0.14],
    [0.57, 0.15],
    [0.835, 0.16],
    [0.945, 0.17],
    [0.998, 0.18],
    [1.085, 0.19],
    [1.154, 0.22],
    [1.233, 0.24],
    [1.289, 0.26],
    [1.374, 0.3],
    [1.559, 0.35],
]
"""What `python scripts/prior_law.py` measured for caster_omni's prior (forward at tilt 0.1, backward at 0.25)."""


def _prior(cmd, mask=(0, 0, 0, 0), sin_phase=1.0, cfg=CFG):
    out = gait_prior(cfg, torch.tensor([cmd]), torch.tensor([mask], dtype=torch.float32), torch.tensor([sin_phase]))
    return out.view(4, 3)  # legs x (hip, thigh, calf)


def test_prior_is_the_nominal_pose_under_a_zero_command():
    assert torch.equal(_prior((0.0, 0.0, 0.0)), torch.zeros(4, 3))


def test_prior_tilts_the_swivel_axes_towards_the_command():
    # At a zero clock phase there is no oscillation, only posture.
    fwd, back = _prior((0.5, 0, 0), sin_phase=0.0), _prior((-0.5, 0, 0), sin_phase=0.0)
    assert (fwd[:, 2] > 0.15).all() and (back[:, 2] < -0.15).all()  # calves pitch the axes forward / back
    left = _prior((0, 0.5, 0), sin_phase=0.0)
    assert (left[:, 0] < -0.15).all()  # hips roll the axes towards +y (axis y ~ -hip)
    yaw = _prior((0, 0, 1.0), sin_phase=0.0)
    # Counter-clockwise: front feet push +y (hips negative), rear feet -y; left feet back, right forward.
    fl, fr, rl, rr = yaw
    assert fl[0] < 0 and fr[0] < 0 and rl[0] > 0 and rr[0] > 0
    assert fl[2] < 0 and rl[2] < 0 and fr[2] > 0 and rr[2] > 0


def test_prior_oscillates_only_the_driving_casters_and_splays_across_the_motion():
    a, b = _prior((0.5, 0, 0), sin_phase=1.0), _prior((0.5, 0, 0), sin_phase=0.0)
    wave = a - b
    assert wave[:, 0].tolist() == pytest.approx([0.2, -0.2, 0.2, -0.2])  # hips splay, left/right antiphase
    assert wave[:, 1:].abs().max() < 1e-6
    masked = _prior((0.5, 0, 0), mask=(0, 0, 1, 1)) - _prior((0.5, 0, 0), mask=(0, 0, 1, 1), sin_phase=0.0)
    assert masked[2:].abs().max() < 1e-6 and masked[:2, 0].abs().min() > 0.19
    side = _prior((0, 0.5, 0)) - _prior((0, 0.5, 0), sin_phase=0.0)
    assert side[:, 1].tolist() == pytest.approx([-0.2, -0.2, 0.2, 0.2])  # thighs: front/rear antiphase


def test_a_speed_law_sets_the_amplitude_of_the_forward_or_backward_push():
    """amplitude_law (forward) and amplitude_law_backward: the hip splay of a vx push is read
    from the table (interpolated, flat beyond it), tilt_backward tilts a backward push; the
    sideways part keeps amplitude x ramp, and a foot with both takes the larger."""
    cfg = GaitPriorCfg(enabled=True, amplitude=0.2, tilt=0.1, tilt_backward=0.25, thigh_share=0.0, full_speed=0.25,
                       amplitude_law=LAW, amplitude_law_backward=LAW_BACK)  # fmt: skip

    def wave(cmd):
        return _prior(cmd, cfg=cfg) - _prior(cmd, sin_phase=0.0, cfg=cfg)

    for vx, amp in ((0.5, 0.05), (1.5, 0.15), (3.0, 0.2), (-0.5, 0.15), (-2.0, 0.3)):
        assert wave((vx, 0, 0))[:, 0].tolist() == pytest.approx([amp, -amp, amp, -amp]), vx
        assert wave((vx, 0, 0))[:, 1:].abs().max() < 1e-6
    assert _prior((0.5, 0, 0), sin_phase=0.0, cfg=cfg)[:, 2].tolist() == pytest.approx([0.1] * 4)
    assert _prior((-0.5, 0, 0), sin_phase=0.0, cfg=cfg)[:, 2].tolist() == pytest.approx([-0.25] * 4)
    assert wave((0, 0.5, 0))[:, 1].tolist() == pytest.approx([-0.2, -0.2, 0.2, 0.2])  # no vx push: as before
    ux = 0.5 / np.hypot(0.5, 0.05)
    assert wave((0.5, 0.05, 0))[:, 0].abs().tolist() == pytest.approx([0.05 * ux] * 4)  # the law is larger
    assert wave((0.2, 0.1, 0))[:, 0].abs().tolist() == pytest.approx([0.08 * 0.2 / np.hypot(0.2, 0.1)] * 4)
    assert torch.equal(_prior((0.0, 0.0, 0.0), cfg=cfg), torch.zeros(4, 3))
    for bad in ([[0.0, 0.0]], [[1.0, 0.1], [0.5, 0.2]], [[0.0, -0.1], [1.0, 0.1]], [[0.0, 0.0, 1.0], [1.0, 0.1]]):
        with pytest.raises(ValueError, match="amplitude_law"):
            GaitPriorCfg(amplitude_law=bad)


def test_a_forward_push_that_brakes_a_backward_roll_takes_its_own_tilt():
    """tilt_forward_brake: a forward push tilts by it while the estimate rolls backwards
    (blended over brake_blend_speed); a forward drive and every backward push keep their
    tilts; it needs the estimate (speed feedback)."""
    kw = dict(enabled=True, amplitude=0.2, tilt=0.2, tilt_backward=0.25, thigh_share=0.0, full_speed=0.25,
              speed_feedback=1.0, command_share=0.3)  # fmt: skip
    plain, brake = GaitPriorCfg(**kw), GaitPriorCfg(**kw, tilt_forward_brake=0.02, brake_blend_speed=0.2)

    def calf(cfg, cmd, v):
        out = gait_prior(cfg, torch.tensor([cmd]), torch.zeros(1, 4), torch.tensor([0.0]), velocity=torch.tensor([v]))
        return out.view(4, 3)[:, 2].tolist()  # the calf makes all the pitch tilt at thigh_share 0

    assert calf(brake, (0.0, 0, 0), (-1.0, 0.0)) == pytest.approx([0.02] * 4)  # zero command, rolling back
    assert calf(brake, (0.0, 0, 0), (-0.1, 0.0)) == pytest.approx([0.11 * 0.1 / 0.25] * 4)  # half-way, ramp 0.4
    assert calf(plain, (0.0, 0, 0), (-1.0, 0.0)) == pytest.approx([0.2] * 4)
    same = (((1.0, 0, 0), (0.5, 0.0)), ((1.0, 0, 0), (0.0, 0.0)), ((0.0, 0, 0), (1.0, 0.0)), ((-1.0, 0, 0), (-0.5, 0)))
    for cmd, v in same:
        assert calf(brake, cmd, v) == calf(plain, cmd, v), (cmd, v)  # drives and backward pushes as before
    assert calf(brake, (0.0, 0, 0), (1.0, 0.0)) == pytest.approx([-0.25] * 4)  # braking a forward roll
    with pytest.raises(ValueError, match="speed_feedback"):
        GaitPriorCfg(tilt_forward_brake=0.02)


def test_a_backward_law_alone_leaves_the_forward_push_as_without_a_law():
    """amplitude_law_backward without amplitude_law (research/log.md run 107): a backward push
    reads its law, every other push is the prior's own amplitude x ramp, bit for bit."""
    kw = dict(enabled=True, amplitude=0.2, tilt=0.2, thigh_share=0.0, full_speed=0.25)
    plain, back = GaitPriorCfg(**kw), GaitPriorCfg(**kw, amplitude_law_backward=LAW_BACK)
    for cmd in ((0.1, 0, 0), (0.5, 0, 0), (2.0, 0.3, 0), (0.3, 0, 0.8), (0, 0.5, 0), (0, 0, -1.0), (0, 0, 0)):
        for sin in (1.0, 0.0):
            assert torch.equal(_prior(cmd, sin_phase=sin, cfg=back), _prior(cmd, sin_phase=sin, cfg=plain)), cmd
    for vx, amp in ((-0.5, 0.15), (-2.0, 0.3)):
        wave = _prior((vx, 0, 0), cfg=back) - _prior((vx, 0, 0), sin_phase=0.0, cfg=back)
        assert wave[:, 0].tolist() == pytest.approx([amp, -amp, amp, -amp]), vx


def test_an_added_law_equal_to_the_ramp_changes_nothing_and_a_larger_one_adds_its_excess():
    """amplitude_law_adds (research/log.md row 111): a foot keeps the prior's own amplitude x ramp
    of its whole push and the law adds what it gives beyond amplitude x ramp of the trunk's
    vx alone. A law equal to that ramp is then the prior without a law for every command and
    speed error (the larger-of rule is not: a sideways or turning push with some vx loses
    splay), and a larger one raises the splay by its excess."""
    kw = dict(enabled=True, amplitude=0.2, tilt=0.2, thigh_share=0.0, full_speed=0.25, speed_feedback=1.0,
              command_share=0.3)  # fmt: skip
    ramp = [[0.0, 0.0], [0.25, 0.2]]
    plain = GaitPriorCfg(**kw)
    larger_of = GaitPriorCfg(**kw, amplitude_law_backward=ramp, amplitude_law=ramp)
    added = dataclasses.replace(larger_of, amplitude_law_adds=True)
    g = torch.Generator().manual_seed(0)
    cmd = torch.rand(64, 3, generator=g) * 4.0 - 2.0
    vel = torch.rand(64, 2, generator=g) * 4.0 - 2.0
    for sin in (torch.ones(64), torch.zeros(64), torch.rand(64, generator=g) * 2 - 1):
        args = cmd, torch.zeros(64, 4), sin
        assert torch.allclose(gait_prior(added, *args, velocity=vel), gait_prior(plain, *args, velocity=vel), atol=1e-6)
    args = cmd, torch.zeros(64, 4), torch.ones(64)
    assert not torch.allclose(gait_prior(larger_of, *args, velocity=vel), gait_prior(plain, *args, velocity=vel))
    big = dataclasses.replace(
        added, speed_feedback=0.0, amplitude_law=[], amplitude_law_backward=[[0.0, 0.0], [0.25, 0.2], [1.0, 0.35]]
    )
    wave = _prior((-1.0, 0, 0), cfg=big) - _prior((-1.0, 0, 0), sin_phase=0.0, cfg=big)
    assert wave[:, 0].tolist() == pytest.approx([0.35, -0.35, 0.35, -0.35])  # 0.2 of its own + 0.15 of excess


def test_with_a_measured_speed_law_the_prior_alone_follows_the_command():
    """scripts/prior_law.py's law (research/log.md): open loop, no policy, the prior skates
    faster for a faster command (the prior without it pushes alike for every command)."""
    spec = registry.get_task(TASK)
    scen = tuple(evaluate.Scenario(f"vx{v}", ((0.0, (v, 0, 0)),), 6.0, 3.0) for v in (0.5, 1.5, -1.0))
    cfg = copy.deepcopy(spec.env_cfg)
    cfg.gait = dataclasses.replace(cfg.gait, speed_feedback=0.0, tilt=0.1, tilt_backward=0.25, lateral_gain=2.0,
                                   amplitude_law=FORWARD_LAW, amplitude_law_backward=BACKWARD_LAW)  # fmt: skip
    e = spec.env_class(evaluate.eval_env_cfg(cfg, scen))
    res = evaluate.run_scenarios(e, lambda obs: e.gait_offsets() / e.cfg.control.action_scale, scen)
    e.close()
    v = [r.mean["vx"] for r in res]
    assert 0.2 < v[0] < 0.8 and v[1] > v[0] + 0.6 and -1.3 < v[2] < -0.7, v
    assert not any(r.falls for r in res)


def test_uphill_term_raises_the_oscillation_only_when_climbing():
    """Amplitude + gain * (grade - deadband) where the trunk stands uphill along the command
    (gravity in the trunk frame pulls against it), capped; unchanged on the flat, downhill
    and without gravity when the term is off."""
    cfg = GaitPriorCfg(enabled=True, amplitude=0.2, full_speed=0.5, uphill_gain=5.0, uphill_deadband=0.02,
                       max_amplitude=0.4)  # fmt: skip

    def hip_wave(cmd, grade):
        g = torch.tensor([[-grade, 0.0, -1.0]])  # nose-up by `grade` (sine) along +x
        args = torch.tensor([cmd]), torch.zeros(1, 4)
        return float((gait_prior(cfg, *args, torch.ones(1), g) - gait_prior(cfg, *args, torch.zeros(1), g))[0, 0])

    assert hip_wave((0.5, 0, 0), 0.0) == pytest.approx(0.2)
    assert hip_wave((0.5, 0, 0), 0.02) == pytest.approx(0.2)  # inside the deadband
    assert hip_wave((0.5, 0, 0), 0.05) == pytest.approx(0.2 + 5.0 * 0.03)
    assert hip_wave((0.5, 0, 0), 0.5) == pytest.approx(0.4)  # capped
    assert hip_wave((-0.5, 0, 0), 0.05) == pytest.approx(0.2)  # backwards down the same slope
    with pytest.raises(ValueError, match="projected gravity"):
        gait_prior(cfg, torch.zeros(1, 3), torch.zeros(1, 4), torch.ones(1))
    tilted = gait_prior(
        CFG, torch.tensor([[0.5, 0, 0]]), torch.zeros(1, 4), torch.ones(1), torch.tensor([[-0.3, 0, -1]])
    )
    assert torch.equal(_prior((0.5, 0, 0)), tilted.view(4, 3))  # the term off: gravity changes nothing


def test_speed_feedback_pushes_for_the_speed_error_and_brakes_when_too_fast():
    fb = dataclasses.replace(CFG, speed_feedback=1.0, command_share=0.3)
    cmd, mask, sin = torch.tensor([[1.0, 0.0, 0.0]] * 3), torch.zeros(3, 4), torch.zeros(3)
    vel = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])  # standing, on target, too fast
    calf = gait_prior(fb, cmd, mask, sin, velocity=vel).view(3, 4, 3)[..., 2]
    # push velocity 1.3, 0.3, -0.7 m/s (full_speed 0.5): full tilt, 0.6 of it, full tilt backwards
    assert calf[0].tolist() == pytest.approx([0.2] * 4)
    assert calf[1].tolist() == pytest.approx([0.12] * 4)
    assert calf[2].tolist() == pytest.approx([-0.2] * 4)
    # without feedback the velocity is ignored; with it, it is required
    assert torch.equal(gait_prior(CFG, cmd, mask, sin, velocity=vel), gait_prior(CFG, cmd, mask, sin))
    with pytest.raises(ValueError, match="velocity"):
        gait_prior(fb, cmd, mask, sin)


@pytest.fixture(scope="module")
def env():
    e = registry.make_env(TASK, CPU, num_envs=3)
    yield e
    e.close()


def test_skating_task_observes_the_clock_and_runs_at_5ms(env):
    names = [n for n, _, _ in env.obs_layout["policy"]]
    assert names == ["commands", "mode_mask", "ang_vel", "projected_gravity", "joint_pos", "joint_vel", "actions",
                     "proprio_history", "gait_phase"]  # fmt: skip
    assert env.observation_dims()["policy"] == 49 + 50 * 42 + 2  # 50 policy steps of history
    assert env.model.opt.timestep == pytest.approx(0.005) and env.dt == pytest.approx(0.02)
    assert env.model.geom_solref[:, 0].min() >= 0.01 - 1e-9  # raised to 2 x timestep


def test_clock_phase_advances_with_policy_steps_and_restarts_with_the_episode(env):
    env.set_commands([0.5, 0.0, 0.0])
    env.reset()
    sl = slice(env.observation_dims()["policy"] - 2, None)
    for k in range(1, 6):
        obs, *_ = env.step(torch.zeros(3, 12))
        phase = 2 * np.pi * env.cfg.gait.frequency * k * env.dt
        assert obs["policy"][0, sl].tolist() == pytest.approx([np.sin(phase), np.cos(phase)], abs=1e-5)
    env.reset_idx(torch.tensor([1]))
    assert env.compute_observations()["policy"][1, sl].tolist() == pytest.approx([0.0, 1.0])


@pytest.mark.parametrize("variant", ["plain", "uphill", "law", "back_law", "back_law_adds", "yaw", "brake"])
def test_the_actor_computes_the_same_prior_from_its_observation(env, variant):
    # The actor reads the (noisy) observation, the env its own state: compare without noise.
    env.cfg.gait.uphill_gain, env.cfg.gait.uphill_deadband = (8.0, 0.0) if variant == "uphill" else (0.0, 0.06)
    env.cfg.gait.yaw_feedback, env.cfg.gait.yaw_command_share = (1.0, 0.5) if variant == "yaw" else (0.0, 1.0)
    if variant == "law":
        env.cfg.gait.amplitude_law, env.cfg.gait.amplitude_law_backward = LAW, LAW_BACK
        env.cfg.gait.tilt_backward = 0.25
    if variant == "brake":
        env.cfg.gait.tilt_forward_brake, env.cfg.gait.brake_blend_speed = 0.02, 0.05
    if variant.startswith("back_law"):
        env.cfg.gait.amplitude_law_backward = LAW_BACK
        env.cfg.gait.amplitude_law_adds = variant.endswith("adds")
    noise = env.noise_vec.clone()
    env.noise_vec.zero_()
    try:
        env.set_commands(torch.tensor([[0.7, -0.2, 0.4], [0.0, 0.4, 0.0], [-0.5, 0.0, -0.8]]))
        env.set_mode("front_wheel", torch.tensor([2]))
        for _ in range(7):
            obs, *_ = env.step(torch.zeros(3, 12))
        p = env.actor_prior()
        prior = GaitPrior(p["cfg"], p["slices"], p["action_scale"])
        assert prior.needs_velocity  # caster_omni's prior has speed feedback
        expect = env.gait_offsets() / env.cfg.control.action_scale  # fed the simulator's velocity
        velocity = env.base_lin_vel  # what the actor's estimate stands for
        assert torch.allclose(prior(obs["policy"], velocity), expect, atol=1e-5)
        assert torch.jit.script(prior)(obs["policy"], velocity).sub(expect).abs().max() < 1e-5
    finally:
        env.cfg.gait.uphill_gain, env.cfg.gait.uphill_deadband = 0.0, 0.06
        env.cfg.gait.amplitude_law, env.cfg.gait.amplitude_law_backward, env.cfg.gait.tilt_backward = [], [], None
        env.cfg.gait.amplitude_law_adds = False
        env.cfg.gait.yaw_feedback, env.cfg.gait.yaw_command_share = 0.0, 1.0
        env.cfg.gait.tilt_forward_brake, env.cfg.gait.brake_blend_speed = None, 0.2
        env.noise_vec.copy_(noise)


def test_ppo_learns_a_residual_around_the_prior(tmp_path):
    e = registry.make_env(TASK, CPU, num_envs=4)
    cfg = registry.get_task(TASK).train_cfg.for_env(e)
    cfg["num_steps_per_env"] = 8
    runner = OnPolicyRunner(e, copy.deepcopy(cfg), log_dir=str(tmp_path), device="cpu")
    actor = runner.alg.actor
    assert isinstance(actor, PriorMLPModel)
    runner.learn(num_learning_iterations=2)
    # The deterministic action is MLP + prior: zero the MLP's last layer and the prior remains.
    last = [m for m in actor.mlp if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()
    e.set_commands([0.6, 0.0, 0.0])
    obs = e.compute_observations()
    with torch.no_grad():
        estimate = actor.estimate(obs)  # the prior's speed feedback reads the actor's own estimate
        expect = gait_prior(e.cfg.gait, e.commands, e.mode_mask, torch.sin(e.gait_phase), velocity=estimate)
        assert torch.allclose(actor(obs), expect / e.cfg.control.action_scale, atol=1e-6)
        init_std = registry.get_task(TASK).train_cfg.policy.init_noise_std
        assert init_std < 0.5  # the low initial noise (docs/tasks.md)
        assert float(actor.distribution.std.mean()) == pytest.approx(init_std, rel=0.25)
    e.close()


def test_a_fixed_exploration_std_stays_put_while_ppo_learns(tmp_path):
    """policy.learn_noise_std false: the std is not a trainable parameter and stays at
    init_noise_std through PPO updates (the default learns it)."""
    e = registry.make_env(TASK, CPU, num_envs=4)
    stds = {}
    for learn in (True, False):
        train_cfg = copy.deepcopy(registry.get_task(TASK).train_cfg)
        train_cfg.policy.learn_noise_std = learn
        train_cfg.policy.noise_std_schedule = ()  # the task's schedule sets the std itself
        cfg = train_cfg.for_env(e)
        cfg["num_steps_per_env"] = 8
        runner = OnPolicyRunner(e, cfg, log_dir=str(tmp_path / str(learn)), device="cpu")
        runner.learn(num_learning_iterations=2)
        std = runner.alg.actor.distribution.std.detach()
        stds[learn] = std
        assert runner.alg.actor.distribution.std_param.requires_grad is learn
    init_std = registry.get_task(TASK).train_cfg.policy.init_noise_std
    assert torch.allclose(stds[False], torch.full_like(stds[False], init_std))
    assert not torch.allclose(stds[True], torch.full_like(stds[True], init_std))
    e.close()


def test_the_noise_std_schedule_sets_each_iterations_std(tmp_path):
    """policy.noise_std_schedule: before each iteration the std is the schedule's value at the
    number of iterations done (linear between points, held after the last); a resumed runner
    starts from the value at its own iteration. It needs the fixed std."""
    from legged_casters.learning.runner import CheckpointingRunner

    e = registry.make_env(TASK, CPU, num_envs=4)
    train_cfg = copy.deepcopy(registry.get_task(TASK).train_cfg)
    train_cfg.policy.learn_noise_std = False
    train_cfg.policy.noise_std_schedule = ((0, 0.4), (2, 0.2), (3, 0.1))
    cfg = train_cfg.for_env(e)
    cfg["num_steps_per_env"] = 8
    runner = CheckpointingRunner(e, cfg, log_dir=str(tmp_path), device="cpu", task=TASK)
    used = []
    act = runner.alg.act

    def spy(*args, **kwargs):
        used.append(round(float(runner.alg.get_policy().distribution.std_param.mean()), 6))
        return act(*args, **kwargs)

    runner.alg.act = spy
    runner.learn(num_learning_iterations=5)
    per_iteration = [used[i * 8] for i in range(5)]
    assert per_iteration == pytest.approx([0.4, 0.3, 0.2, 0.1, 0.1])
    assert all(v == per_iteration[i // 8] for i, v in enumerate(used))  # constant within an iteration
    runner.current_learning_iteration = 1  # as after loading model_1.pt
    runner.set_noise_std(runner.current_learning_iteration)
    assert float(runner.alg.get_policy().distribution.std_param.mean()) == pytest.approx(0.3)
    train_cfg.policy.learn_noise_std = True
    with pytest.raises(ConfigError, match="learn_noise_std=false"):
        train_cfg.for_env(e)
    e.close()


def _lag1(x: torch.Tensor) -> float:
    """Lag-1 autocorrelation of (steps, batch, dims) samples around their known mean 0."""
    return float((x[1:] * x[:-1]).mean() / (x * x).mean())


def test_correlated_noise_keeps_the_marginal_and_correlates_the_rollout():
    """policy.noise_correlation rho: rollout samples (no gradients) follow an AR(1) process with
    the Gaussian's own mean and std and lag-1 correlation rho; PPO's mini-batch draws (gradients
    on) are white and leave the process alone; rho 0 is white; rho outside [0, 1) is refused."""
    from legged_casters.learning.noise import CorrelatedGaussianDistribution

    torch.manual_seed(0)
    mean, std = torch.full((2000, 3), 0.5), 0.2
    out = {}
    for rho in (0.0, 0.9):
        dist = CorrelatedGaussianDistribution(3, correlation=rho, init_std=std, learn_std=False)
        draws = []
        for _ in range(200):
            with torch.inference_mode():
                dist.update(mean)
                draws.append(dist.sample())
        noise = (torch.stack(draws) - 0.5) / std
        out[rho] = noise
        assert float(noise.std()) == pytest.approx(1.0, abs=0.03)
        assert float(noise.mean()) == pytest.approx(0.0, abs=0.02)
    assert _lag1(out[0.0]) == pytest.approx(0.0, abs=0.02)
    assert _lag1(out[0.9]) == pytest.approx(0.9, abs=0.02)

    dist = CorrelatedGaussianDistribution(3, correlation=0.99, init_std=std, learn_std=False)
    with torch.inference_mode():
        dist.update(mean)
        first = dist.sample()
    state = dist._eps.clone()
    batch = torch.zeros(64, 3, requires_grad=True)
    dist.update(batch)
    minibatch_draws = torch.stack([dist.sample() for _ in range(200)]) / std
    assert abs(_lag1(minibatch_draws)) < 0.05  # white
    assert torch.equal(dist._eps, state)  # the rollout's process untouched
    with torch.inference_mode():
        dist.update(mean)
        second = dist.sample()
    assert float(((second - 0.5) - 0.99 * (first - 0.5)).std() / std) < 0.2  # continues from `first`
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError, match="correlation"):
            CorrelatedGaussianDistribution(3, correlation=bad)


def test_noise_free_fraction_keeps_the_last_rows_at_the_mean_in_the_rollout_only():
    """policy.noise_free_fraction f: in a rollout draw (no gradients) the last round(f n) rows
    are the mean exactly and the others explore with the configured std (white, or AR(1) with
    the correlation); PPO's mini-batch draws (gradients on) explore in every row; to_rsl_rl
    selects the distribution for f > 0 alone; f outside [0, 1) is refused."""
    from legged_casters.learning.noise import CorrelatedGaussianDistribution

    torch.manual_seed(0)
    mean, std = torch.full((8, 3), 0.5), 0.2
    for rho in (0.0, 0.9):
        dist = CorrelatedGaussianDistribution(3, correlation=rho, quiet_fraction=0.25, init_std=std, learn_std=False)
        for _ in range(3):
            with torch.inference_mode():
                dist.update(mean)
                draw = dist.sample()
            assert torch.equal(draw[6:], mean[6:])  # 2 of 8 rows act with the mean
            assert (draw[:6] != mean[:6]).all()
    batch = torch.full((8, 3), 0.5, requires_grad=True)
    dist.update(batch)
    assert (dist.sample()[6:] != 0.5).all()  # mini-batch draws: every row explores
    from legged_casters.train_config import TrainCfg

    cfg = TrainCfg()
    cfg.policy.noise_free_fraction = 0.25
    made = cfg.to_rsl_rl()["actor"]["distribution_cfg"]
    assert made["class_name"].endswith("CorrelatedGaussianDistribution") and made["quiet_fraction"] == 0.25
    assert made["correlation"] == 0.0
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError, match="noise-free fraction"):
            CorrelatedGaussianDistribution(3, quiet_fraction=bad)


def test_noise_correlation_selects_the_correlated_distribution(tmp_path):
    """--train-set policy.noise_correlation=0.9 trains with CorrelatedGaussianDistribution (the
    checkpoint has the same keys as with white noise, so play/export/evaluate load it); above
    the config's bound it is refused."""
    from legged_casters.config import apply_overrides
    from legged_casters.learning.noise import CorrelatedGaussianDistribution
    from legged_casters.learning.runner import CheckpointingRunner

    e = registry.make_env(TASK, CPU, num_envs=4)
    keys = {}
    for rho in (0.0, 0.9):
        train_cfg = copy.deepcopy(registry.get_task(TASK).train_cfg)
        train_cfg.policy.noise_correlation = rho
        cfg = train_cfg.for_env(e)
        cfg["num_steps_per_env"] = 4
        runner = CheckpointingRunner(e, cfg, log_dir=str(tmp_path / str(rho)), device="cpu", task=TASK)
        dist = runner.alg.get_policy().distribution
        assert isinstance(dist, CorrelatedGaussianDistribution) is (rho > 0)
        runner.learn(num_learning_iterations=1)
        keys[rho] = set(runner.alg.get_policy().state_dict())
        if rho > 0:
            assert dist._eps is not None and dist._eps.shape == (4, e.num_actions)
    assert keys[0.0] == keys[0.9]
    with pytest.raises(ConfigError, match="noise_correlation"):
        apply_overrides(copy.deepcopy(registry.get_task(TASK).train_cfg), ["policy.noise_correlation=1.0"])
    e.close()


def test_the_noise_std_schedule_can_leave_some_joints_alone(tmp_path):
    """policy.noise_std_schedule_joints: the schedule sets the std of the named joints only
    (thigh and calf here); the hips keep theirs. A name that matches no joint is refused."""
    from legged_casters.learning.runner import CheckpointingRunner

    e = registry.make_env(TASK, CPU, num_envs=4)
    train_cfg = copy.deepcopy(registry.get_task(TASK).train_cfg)
    train_cfg.policy.learn_noise_std = False
    train_cfg.policy.init_noise_std = 0.5
    train_cfg.policy.noise_std_schedule = ((0, 0.4), (2, 0.2))
    train_cfg.policy.noise_std_schedule_joints = ("thigh", "calf")
    cfg = train_cfg.for_env(e)
    cfg["num_steps_per_env"] = 8
    runner = CheckpointingRunner(e, cfg, log_dir=str(tmp_path / "a"), device="cpu", task=TASK)
    runner.learn(num_learning_iterations=2)
    std = runner.alg.get_policy().distribution.std_param.detach()
    hips = torch.tensor(["hip" in j for j in e.layout.joints])
    assert int(hips.sum()) == 4
    assert torch.allclose(std[hips], torch.full((4,), 0.5))
    assert torch.allclose(std[~hips], torch.full((8,), 0.2))
    train_cfg.policy.noise_std_schedule_joints = ("knee",)
    with pytest.raises(ConfigError, match="match none of the action joints"):
        train_cfg.for_env(e)
    train_cfg.policy.noise_std_schedule = ()
    with pytest.raises(ConfigError, match="needs a policy.noise_std_schedule"):
        train_cfg.for_env(e)
    e.close()


def test_export_carries_the_prior_and_the_bridge_rebuilds_the_clock(tmp_path):
    e = registry.make_env(TASK, CPU, num_envs=2)
    actor = export.build_actor(e, registry.get_task(TASK).train_cfg)
    e.set_commands([0.5, 0.2, 0.3])
    for _ in range(4):
        obs, *_ = e.step(torch.zeros(2, 12))
    meta = export.policy_metadata(e, TASK)
    assert meta["gait_clock"]["frequency"] == 2.0
    paths = export.export_policy(actor, meta, tmp_path)
    err = export.check_parity(actor, paths, obs["policy"])
    assert max(err.values()) < 1e-5, err
    # The bridge's observation after 4 policy steps has the env's clock phase.
    bm = load_meta(tmp_path)
    assert bm.gait_frequency == 2.0
    state = P.RobotState([1.0, 0, 0, 0], [0.0] * 3, go2.default_joint_positions(), [0.0] * 12)
    built = ObservationBuilder(bm).build(state, [0.5, 0.2, 0.3], [0, 0, 0, 0], np.zeros(12), step=4)
    assert built[-2:].tolist() == pytest.approx(obs["policy"][0, -2:].tolist(), abs=1e-5)
    # A policy that observes the clock without saying its frequency is refused.
    text = yaml.safe_load((tmp_path / "policy.yaml").read_text())
    del text["gait_clock"]
    (tmp_path / "policy.yaml").write_text(yaml.safe_dump(text))
    with pytest.raises(PolicyFormatError, match="gait_clock"):
        load_meta(tmp_path)
    e.close()


def _stop_prior(sets: list[str], cmds: torch.Tensor, held: torch.Tensor):
    """(env, observation, actor_prior() dict, GaitPrior) after the robots of a `sets` env, told
    `cmds`, held the actions `held` for two steps (so that the actions term observes them)."""
    e = registry.make_env(TASK, sets, num_envs=len(cmds))
    e.set_commands(cmds)
    for _ in range(2):
        obs, *_ = e.step(held)
    p = e.actor_prior()
    return e, obs, p, GaitPrior(p["cfg"], p["slices"], p["action_scale"])


def _assert_export_matches(e, obs, tmp_path, actor=None) -> None:
    """The exported actor (of `actor`, else a fresh one for `e`) computes what it does on `obs`."""
    actor = actor if actor is not None else export.build_actor(e, registry.get_task(TASK).train_cfg)
    paths = export.export_policy(actor, export.policy_metadata(e, TASK), tmp_path)
    err = export.check_parity(actor, paths, obs["policy"])
    assert max(err.values()) < 1e-5, err


def test_the_stop_pose_takes_over_under_a_zero_command_only(tmp_path):
    """gait.stop_pitch: where the observed command is zero the actor's whole action moves from
    the last action a share stop_rate towards the stop pose (calves +-pitch front/rear, hips
    roll x side); under any other command it is the actor's own; the export computes the same;
    the prior needs the actions slice."""
    pitch, roll, rate = 0.3, 0.1, 0.2
    e = registry.make_env(TASK, [*CPU, f"gait.stop_pitch={pitch}", f"gait.stop_roll={roll}"], num_envs=4)
    actor = export.build_actor(e, registry.get_task(TASK).train_cfg)
    e.set_commands(torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.6]]))
    for k in range(3):
        obs, *_ = e.step(torch.full((4, 12), 0.4 - 0.3 * k))
    with torch.no_grad():
        mean = actor(obs)
        actor.prior.stop_on = False
        own = actor(obs)
        actor.prior.stop_on = True
    scale = e.cfg.control.action_scale
    pose = torch.tensor([[roll * go2.leg_signs(leg)[1], 0.0, pitch * go2.leg_signs(leg)[0]] for leg in go2.LEGS])
    last = torch.full((12,), -0.2)  # the last action, as the actions term observes it
    expect = last + rate * (pose.reshape(12) / scale - last)
    for i in (0, 2):  # zero commands
        assert mean[i].tolist() == pytest.approx(expect.tolist(), abs=1e-5)
    assert torch.equal(mean[[1, 3]], own[[1, 3]])  # a drive and a turn on the spot: the actor's own
    assert not torch.allclose(own[0], expect)
    _assert_export_matches(e, obs, tmp_path, actor)
    p = e.actor_prior()
    del p["slices"]["actions"]
    with pytest.raises(ValueError, match="actions"):
        GaitPrior(p["cfg"], p["slices"], p["action_scale"])
    e.close()


def test_the_backward_stop_pose_waits_for_a_backward_roll_and_then_holds(tmp_path):
    """gait.stop_backward_speed: under a zero command the pose applies only where the velocity
    estimate rolls backwards faster than the setting, or where the last action is already
    within half the pose's distance of it (the pose held once entered); a forward roll and
    any other command keep the actor's own action; the export computes the same; without an
    estimate the prior refuses."""
    pitch, rate, speed = 0.4, 0.2, 0.15
    sets = [*CPU, f"gait.stop_pitch={pitch}", f"gait.stop_backward_speed={speed}"]
    pose = (stop_pose(pitch, 0.0) / registry.get_task(TASK).env_cfg.control.action_scale).reshape(1, 12)
    cmds = torch.zeros(6, 3)
    cmds[5, 0] = 0.5
    held = torch.zeros(6, 12)
    held[3:5] = pose  # rows 3 and 4: in the pose already (row 4 exactly, row 3 a little off)
    held[3] += 0.3
    e, obs, _, prior = _stop_prior(sets, cmds, held)
    mean = torch.full((6, 12), 0.3)
    velocity = torch.tensor([[-0.5, 0, 0], [0.5, 0, 0], [-0.1, 0, 0], [0.5, 0, 0], [0.0, 0, 0], [-0.5, 0, 0]])
    out = prior.stop(obs["policy"], mean, velocity)
    last = held.clone()
    toward = last + rate * (pose - last)
    assert torch.allclose(out[0], toward[0], atol=1e-5)  # a backward roll under a zero command
    assert torch.equal(out[1], mean[1]) and torch.equal(out[2], mean[2])  # forward, or too slow backwards
    assert torch.allclose(out[[3, 4]], toward[[3, 4]], atol=1e-5)  # held once near the pose, whatever the roll
    assert torch.equal(out[5], mean[5])  # a command
    with pytest.raises(RuntimeError, match="velocity estimate"):
        prior.stop(obs["policy"], mean, velocity[:, :0])
    _assert_export_matches(e, obs, tmp_path)
    e.close()


def test_the_brake_pose_brakes_a_backward_roll_under_any_command_but_a_backward_one(tmp_path):
    """gait.stop_brakes_commands: with stop_backward_speed the pose also applies where a
    command that does not ask to go backwards (forwards, sideways, a turn) meets a backward
    roll faster than the setting; a backward command, a slower roll and a forward roll keep
    the actor's own action; the export computes the same; it refuses without
    stop_backward_speed."""
    pitch, roll, rate, speed = 0.1, 0.3, 0.2, 0.15
    sets = [*CPU, f"gait.stop_pitch={pitch}", f"gait.stop_roll={roll}", f"gait.stop_backward_speed={speed}",
            "gait.stop_brakes_commands=true"]  # fmt: skip
    pose = (stop_pose(pitch, roll) / registry.get_task(TASK).env_cfg.control.action_scale).reshape(1, 12)
    cmds = torch.tensor([[0.5, 0, 0], [0, 0.4, 0], [0, 0, 0.8], [-0.5, 0, 0], [0.5, 0, 0], [0.5, 0, 0]])
    held = torch.full((6, 12), -0.2)
    e, obs, p, prior = _stop_prior(sets, cmds, held)
    mean = torch.full((6, 12), 0.3)
    velocity = torch.tensor([[-0.5, 0, 0]] * 4 + [[-0.1, 0, 0], [0.5, 0, 0]])
    out = prior.stop(obs["policy"], mean, velocity)
    toward = held + rate * (pose - held)
    assert torch.allclose(out[:3], toward[:3], atol=1e-5)  # forwards, sideways, a turn: brake first
    assert torch.equal(out[3:], mean[3:])  # a backward command; too slow a roll; a forward roll
    without = GaitPrior(p["cfg"], p["slices"], p["action_scale"])
    without.stop_brakes_commands = False
    assert torch.equal(without.stop(obs["policy"], mean, velocity)[:3], mean[:3])  # only zero commands
    _assert_export_matches(e, obs, tmp_path)
    cfg = copy.deepcopy(p["cfg"])
    cfg["stop_backward_speed"] = None
    with pytest.raises(ValueError, match="stop_backward_speed"):
        GaitPrior(cfg, p["slices"], p["action_scale"])
    e.close()


def test_the_rest_pose_waits_until_the_robot_is_still_and_then_holds(tmp_path):
    """gait.stop_rest_speed: under a zero command the pose applies where the velocity estimate
    is below the setting (the robot has come to rest) or the last action is already near the
    pose (held once entered); a rolling robot and any command keep the actor's own action;
    with stop_backward_speed as well, a backward roll enters it too; the export computes the
    same."""
    pitch, roll, rate, rest = 0.1, 0.3, 0.2, 0.03
    sets = [*CPU, f"gait.stop_pitch={pitch}", f"gait.stop_roll={roll}", f"gait.stop_rest_speed={rest}"]
    pose = (stop_pose(pitch, roll) / registry.get_task(TASK).env_cfg.control.action_scale).reshape(1, 12)
    cmds = torch.zeros(5, 3)
    cmds[4, 0] = 0.5
    held = torch.full((5, 12), -0.2)
    held[3] = pose  # in the pose already
    e, obs, p, prior = _stop_prior(sets, cmds, held)
    mean = torch.full((5, 12), 0.3)
    velocity = torch.tensor([[0.01, 0, 0], [0.5, 0, 0], [-0.5, 0, 0], [0.5, 0, 0], [0.0, 0, 0]])
    out = prior.stop(obs["policy"], mean, velocity)
    toward = held + rate * (pose - held)
    assert torch.allclose(out[[0, 3]], toward[[0, 3]], atol=1e-5)  # still; held once near the pose
    assert torch.equal(out[[1, 2, 4]], mean[[1, 2, 4]])  # rolling either way; a command
    cfg = copy.deepcopy(p["cfg"])
    cfg["stop_backward_speed"] = 0.15
    both = GaitPrior(cfg, p["slices"], p["action_scale"]).stop(obs["policy"], mean, velocity)
    assert torch.allclose(both[2], toward[2], atol=1e-5) and torch.equal(both[1], mean[1])  # backwards only
    _assert_export_matches(e, obs, tmp_path)
    e.close()


def test_the_prior_alone_skates_in_every_direction():
    """No learning: the prior's posture and oscillation move the robot the commanded way."""
    spec = registry.get_task(TASK)
    scen = tuple(
        evaluate.Scenario(name, ((0.0, cmd),), 4.0, 2.0)
        for name, cmd in (("fwd", (0.5, 0, 0)), ("back", (-0.5, 0, 0)), ("left", (0, 0.4, 0)), ("ccw", (0, 0, 0.8)))
    )
    cfg = copy.deepcopy(spec.env_cfg)
    cfg.gait.speed_feedback = 0.0  # the command-only prior (the feedback's own test is below)
    e = spec.env_class(evaluate.eval_env_cfg(cfg, scen))
    p = e.actor_prior()
    prior = GaitPrior(p["cfg"], p["slices"], p["action_scale"])
    res = {r.name: r for r in evaluate.run_scenarios(e, lambda obs: prior(obs["policy"], obs["policy"][:, :0]), scen)}
    e.close()
    assert res["fwd"].mean["vx"] > 0.3 and res["back"].mean["vx"] < -0.3
    assert res["left"].mean["vy"] > 0.2 and res["ccw"].mean["wz"] > 0.3


def test_the_prior_with_speed_feedback_holds_the_commanded_speed():
    """Without feedback the prior pushes equally for every command above full_speed (one
    speed); fed the simulator's trunk velocity, the same prior holds 0.3 and 0.8 m/s."""
    spec = registry.get_task(TASK)
    scen = tuple(evaluate.Scenario(f"vx{v}", ((0.0, (v, 0, 0)),), 6.0, 2.0) for v in (0.3, 0.8))
    speeds = {}
    for k in (0.0, 1.0):
        cfg = copy.deepcopy(spec.env_cfg)
        cfg.gait.speed_feedback, cfg.gait.command_share = k, 0.3
        e = spec.env_class(evaluate.eval_env_cfg(cfg, scen))
        res = evaluate.run_scenarios(e, lambda obs, e=e: e.gait_offsets() / e.cfg.control.action_scale, scen)
        speeds[k] = [r.mean["vx"] for r in res]
        e.close()
    assert abs(speeds[0.0][1] - speeds[0.0][0]) < 0.25  # one speed whatever the command
    assert speeds[1.0][0] == pytest.approx(0.3, abs=0.12) and speeds[1.0][1] == pytest.approx(0.8, abs=0.2)


def test_an_actor_whose_prior_needs_the_speed_has_an_estimator():
    e = registry.make_env(TASK, CPU + ["gait.speed_feedback=1.0"], num_envs=2)
    cfg = registry.get_task(TASK).train_cfg
    assert export.build_actor(e, cfg).prior.needs_velocity
    no_est = copy.deepcopy(cfg)
    no_est.estimator.hidden_dims = ()
    with pytest.raises(ValueError, match="estimator"):
        export.build_actor(e, no_est)
    e.close()


def test_the_downhill_hold_starts_on_the_evaluation_hill():
    """evaluate's downhill scenario starts its robot on the 3 deg descent, the others at the
    origin: with the joints held at the nominal pose the downhill robot rolls away, the
    flat one stays, and the downhill check fails for it. A flat env refuses the scenario."""
    spec = registry.get_task(TASK)
    hill = next(s for s in evaluate.SPEED if s.kind == "hill")
    scen = (evaluate.Scenario("flat", ((0.0, (0.5, 0.0, 0.0)),), 3.0, 1.0),
            evaluate.Scenario(hill.name, hill.segments, 3.0, 1.0, kind="hill", start_x=hill.start_x))  # fmt: skip
    e = spec.env_class(evaluate.eval_env_cfg(spec.env_cfg, scen))
    res = {r.name: r for r in evaluate.run_scenarios(e, lambda obs: torch.zeros(e.num_envs, 12), scen)}
    height = e.base_height.tolist()  # above the ground under each trunk: the hill's, the floor's
    assert float(e.base_pos[1, 0]) > hill.start_x and height[1] == pytest.approx(height[0], abs=0.02)
    e.close()
    assert abs(res["flat"].mean["vx"]) < 0.05 and res[hill.name].mean["vx"] > 0.3
    checks = {name: ok for name, ok, _ in evaluate.verdict(list(res.values()))}
    assert checks == {f"{hill.name}: |vx error| <= {evaluate.DOWNHILL_VX_ERROR}": False}
    flat = spec.env_class(evaluate.eval_env_cfg(spec.env_cfg, scen[:1]))
    with pytest.raises(ValueError, match="hill"):
        evaluate.run_scenarios(flat, lambda obs: torch.zeros(1, 12), scen[1:])
    flat.close()


def test_evaluation_of_a_standing_policy_reports_the_command_as_error():
    spec = registry.get_task("caster_omni_paper")
    scen = evaluate.QUICK[:3] + (evaluate.FULL[9],)  # vx +0.5, vx -0.5, vx +1.0, fig6 step
    scen = tuple(evaluate.Scenario(s.name, s.segments, 3.0 if s.kind == "track" else s.duration, 1.0, kind=s.kind)
                 for s in scen)  # fmt: skip
    e = spec.env_class(evaluate.eval_env_cfg(spec.env_cfg, scen))
    res = evaluate.run_scenarios(e, lambda obs: torch.zeros(e.num_envs, 12), scen)
    e.close()
    by = {r.name: r for r in res}
    assert by["vx +0.5"].err["vx"] == pytest.approx(0.5, abs=0.05)
    assert by["vx +1.0"].err["vx"] == pytest.approx(1.0, abs=0.05)
    assert by["fig6 step"].extra["sign_change_s"] == float("inf")
    checks = {name: ok for name, ok, _ in evaluate.verdict(res)}
    assert not checks["vx +0.5: |vx error| <= 0.15"]
    summary = evaluate.summary(res)
    assert summary["vx_error"] == pytest.approx((0.5 + 0.5 + 1.0) / 3, abs=0.05)
    # each tracking scenario on its own axis too (TensorBoard Eval/scenario/...), not the step
    assert summary["scenario/vx_+1.0"] == pytest.approx(1.0, abs=0.05)
    assert summary["scenario/vx_-0.5"] == pytest.approx(by["vx -0.5"].err["vx"])
    assert not any("fig6" in key for key in summary)


def test_bridge_rebuilds_the_whole_observation_with_clock_and_history(tmp_path):
    """Drive the env, feed its measured state to the bridge's observation builder step by
    step: the two observations agree (noise off), history and clock included."""
    # flat ground: the bridge builds projected gravity from the IMU's orientation, and on the
    # env's tilted-gravity slopes the simulator's world frame is the ground's, not gravity's
    e = registry.make_env(TASK, CPU + ["history_length=3", "noise.enabled=false", "terrain.slope_deg=0"], num_envs=1)
    actor = export.build_actor(e, registry.get_task(TASK).train_cfg)
    export.export_policy(actor, export.policy_metadata(e, TASK), tmp_path)
    bm = load_meta(tmp_path)
    assert bm.history_length == 3 and bm.history_terms[0] == "ang_vel"
    builder = ObservationBuilder(bm)
    width = e.history.shape[2]
    assert [t[0] for t in bm.obs_terms][-2:] == ["proprio_history", "gait_phase"]
    cmd = [0.6, -0.1, 0.2]
    e.set_commands(cmd)
    e.set_mode("front_wheel")
    obs = e.reset()
    torch.manual_seed(0)
    for k in range(6):
        state = P.RobotState(
            e.base_quat[0].tolist(), e.base_ang_vel[0].tolist(), e.joint_pos[0].tolist(), e.joint_vel[0].tolist()
        )
        built = builder.build(state, cmd, [0, 0, 1, 1], e.actions[0].numpy(), step=k)
        assert np.allclose(built, obs["policy"][0].numpy(), atol=1e-4), k
        history = built[-3 * width - 2 : -2].reshape(3, width)  # proprio_history, then gait_phase
        assert (np.abs(history).sum(axis=1) > 0).tolist() == [j < k for j in range(3)], k  # zeros before step 0
        obs, *_ = e.step(torch.randn(1, 12) * 0.3)
    e.close()


def test_play_feeds_the_policy_the_observation_the_bridge_builds(tmp_path, monkeypatch, capsys):
    """The history right after a reset, and at a command change. From play.py's
    first step, over the steps profile's change from standing to -0.6 m/s, robot 0's
    observation equals what the bridge builds from the same state: proprio_history at step
    k holds steps k-1, k-2, ... (all zeros at k = 0, step 0 in the newest slot at k = 1),
    as in training. And without --mode a task with modes plays four_wheel, not a draw."""
    from legged_casters.tools import play

    seen = []

    def make_policy(src, env):
        (tmp_path / "policy.yaml").write_text(export.metadata_yaml(export.policy_metadata(env, TASK)))
        meta = load_meta(tmp_path)
        assert meta.history_length == env.cfg.history_length
        builder = ObservationBuilder(meta)
        start = env.policy_obs_slices()["proprio_history"][0]
        width = env.history.shape[2]

        def policy(obs):
            k = len(seen)
            state = P.RobotState(env.base_quat[0].tolist(), env.base_ang_vel[0].tolist(),
                                 env.joint_pos[0].tolist(), env.joint_vel[0].tolist())  # fmt: skip
            built = builder.build(state, env.commands[0].tolist(), env.mode_mask[0].tolist(), env.actions[0], step=k)
            got = obs["policy"][0].numpy()
            seen.append((got[start : start + width].copy(), env.commands[0, 0].item(), env.mode_mask.tolist()))
            assert np.allclose(built, got, atol=1e-4), f"step {k}: {np.flatnonzero(~np.isclose(built, got, atol=1e-4))}"
            return torch.zeros(env.num_envs, env.num_actions)

        return policy

    monkeypatch.setattr(play, "_make_policy", make_policy)
    argv = ["--task", TASK, "--policy", "zero", "--profile", "steps", "--duration", "0.5", "--headless"]
    argv += ["--no_video", "--num_envs", "3", "--out", str(tmp_path / "play"), "--set", "noise.enabled=false"]
    argv += ["--set", "terrain.slope_deg=0"]
    assert play.main(argv) == 0, capsys.readouterr().err
    newest = [h for h, _, _ in seen]
    assert len(seen) == 25 and not newest[0].any() and newest[1].any()
    vx = [c for _, c, _ in seen]
    assert vx[4] == 0.0 and vx[5] == pytest.approx(-0.6)  # the change is inside the compared steps
    assert all(m == [[0.0] * 4] * 3 for _, _, m in seen)  # four_wheel on every robot


def test_single_axis_commands_keep_one_component():
    e = registry.make_env(
        TASK,
        CPU + ["commands.single_axis_fraction=1.0", "commands.standing_fraction=0", "commands.reverse_fraction=0"],
        num_envs=64,
    )
    e.resample_commands(torch.arange(64))
    nonzero = (e.commands != 0).sum(dim=1)
    assert (nonzero == 1).all()
    assert set((e.commands != 0).float().argmax(dim=1).tolist()) == {0, 1, 2}  # each axis gets its share
    e.close()


def test_the_shipped_policy_loads_everywhere_and_skates_forward():
    from legged_casters.tools import common

    shipped = common.shipped_policy_dir(TASK)
    assert shipped is not None, "resources/policies/caster_omni/ must hold the trained policy"
    meta = load_meta(shipped)  # the bridge accepts it
    assert meta.task == "caster_omni_sym" and meta.gait_frequency > 0  # the task whose configs trained it
    spec = registry.get_task(meta.task)
    env_cfg, _ = common.run_configs(spec, shipped)
    scen = (evaluate.Scenario("fwd", ((0.0, (0.5, 0.0, 0.0)),), 4.0, 2.0),)
    e = spec.env_class(evaluate.eval_env_cfg(env_cfg, scen))
    assert e.observation_dims()["policy"] == meta.obs_dim
    module = torch.jit.load(str(shipped / "policy.pt"))
    (res,) = evaluate.run_scenarios(e, lambda obs: module(obs["policy"]), scen)
    e.close()
    assert res.mean["vx"] > 0.25 and res.falls == 0
