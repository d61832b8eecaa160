"""caster_omni's velocity estimator: where it reads, what the actor and critic read, that it
learns the trunk velocity next to PPO, and that the export carries it."""

import copy

import numpy as np
import onnxruntime as ort
import pytest
import torch
from rsl_rl.runners import OnPolicyRunner

from legged_casters import registry
from legged_casters.learning.estimator import TARGET_GROUP, EstimatorPPO
from legged_casters.learning.models import ColumnsMLPModel, PriorMLPModel
from legged_casters.tools import export

TASK = "caster_omni"
CPU = ["sim.backend=cpu"]


@pytest.fixture(scope="module")
def env():
    e = registry.make_env(TASK, CPU, num_envs=8)
    e.set_commands([0.6, 0.0, 0.3])
    for _ in range(12):  # a history that is not all zeros
        e.step(torch.randn(8, 12) * 0.3)
    yield e
    e.close()


def _perturb(obs, columns, amount=1.0):
    out = obs.clone()
    start, stop = columns
    out["policy"][:, start:stop] += amount
    return out


def test_the_actor_reads_the_history_only_through_the_estimate(env):
    actor = export.build_actor(env, registry.get_task(TASK).train_cfg)
    assert isinstance(actor, PriorMLPModel) and actor.estimator is not None
    cols = env.policy_obs_columns()
    hist = cols["proprio_history"]
    first = [m for m in actor.mlp if isinstance(m, torch.nn.Linear)][0]
    assert first.in_features == env.observation_dims()["policy"] - (hist[1] - hist[0]) + 3
    obs = env.get_observations()
    with torch.no_grad():
        base = actor(obs)
        assert not torch.allclose(actor(_perturb(obs, hist)), base)  # through the estimate
        assert not torch.allclose(actor.estimate(_perturb(obs, hist)), actor.estimate(obs))
        last = [m for m in actor.estimator.net if isinstance(m, torch.nn.Linear)][-1]
        last.weight.zero_()  # a constant estimate: the history no longer matters to the action
        base = actor(obs)
        assert torch.allclose(actor(_perturb(obs, hist)), base)
        assert not torch.allclose(actor(_perturb(obs, cols["joint_vel"])), base)  # the current terms do


def test_the_critic_skips_the_history(env):
    cfg = registry.get_task(TASK).train_cfg.for_env(env)
    assert cfg["critic"]["class_name"].endswith("ColumnsMLPModel")
    runner = OnPolicyRunner(env, copy.deepcopy(cfg), log_dir=None, device="cpu")
    critic = runner.alg.critic
    assert isinstance(critic, ColumnsMLPModel)
    hist = env.policy_obs_columns()["proprio_history"]
    obs = env.get_observations()
    with torch.no_grad():
        assert torch.allclose(critic(_perturb(obs, hist)), critic(obs))
        assert not torch.allclose(critic(_perturb(obs, env.policy_obs_columns()["joint_vel"])), critic(obs))


def test_the_estimator_learns_the_trunk_velocity_from_a_rollout():
    e = registry.make_env(TASK, CPU, num_envs=16)
    cfg = registry.get_task(TASK).train_cfg.for_env(e)
    cfg["num_steps_per_env"] = 24
    runner = OnPolicyRunner(e, copy.deepcopy(cfg), log_dir=None, device="cpu")
    runner.logger.log = lambda **kw: None
    alg = runner.alg
    assert isinstance(alg, EstimatorPPO)
    runner.learn(num_learning_iterations=1)
    obs = alg.storage.observations.flatten(0, 1)
    target = obs[TARGET_GROUP]
    assert target.shape[1] == 3 and target.abs().max() > 0.05  # the trunk moves

    def mse() -> float:
        with torch.no_grad():
            return float(torch.nn.functional.mse_loss(alg.actor.estimate(obs), target))

    before = mse()
    for _ in range(40):
        alg.update_estimator()
    after = mse()
    assert after < 0.3 * before, (before, after)
    saved = alg.save()
    assert "estimator_optimizer_state_dict" in saved
    e.close()


def test_export_carries_the_estimator(env, tmp_path):
    actor = export.build_actor(env, registry.get_task(TASK).train_cfg)
    with torch.no_grad():  # a normaliser that is not the identity
        actor.obs_normalizer.update(env.get_observations()["policy"])
    meta = export.policy_metadata(env, TASK, actor)
    assert meta["estimator"]["output"] == "base_lin_vel"
    paths = export.export_policy(actor.eval(), meta, tmp_path)
    obs = env.get_observations()
    module = torch.jit.load(str(paths["torchscript"]))
    with torch.no_grad():
        expect = actor(obs)
        assert torch.allclose(module(obs["policy"]), expect, atol=1e-5)
        assert torch.allclose(module.estimate(obs["policy"]), actor.estimate(obs), atol=1e-5)
    sess = ort.InferenceSession(str(paths["onnx"]))
    (out,) = sess.run(None, {"obs": obs["policy"].numpy()})
    assert np.allclose(out, expect.numpy(), atol=1e-5)


def test_an_estimator_that_skips_the_command_never_reads_it_trained_or_exported(env, tmp_path):
    train_cfg = copy.deepcopy(registry.get_task(TASK).train_cfg)
    train_cfg.estimator.skip_terms = ("commands",)
    actor = export.build_actor(env, train_cfg)
    with torch.no_grad():
        actor.obs_normalizer.update(env.get_observations()["policy"])
    cols = env.policy_obs_columns()
    obs = env.get_observations()
    with torch.no_grad():
        assert torch.equal(actor.estimate(_perturb(obs, cols["commands"])), actor.estimate(obs))
        assert not torch.allclose(actor.estimate(_perturb(obs, cols["joint_vel"])), actor.estimate(obs))
        assert not torch.allclose(actor(_perturb(obs, cols["commands"])), actor(obs))  # the MLP and prior still do
    meta = export.policy_metadata(env, TASK, actor)
    assert "except commands" in meta["estimator"]["input"]
    paths = export.export_policy(actor.eval(), meta, tmp_path)
    module = torch.jit.load(str(paths["torchscript"]))
    moved = _perturb(obs, cols["commands"])["policy"]
    with torch.no_grad():
        assert torch.allclose(module.estimate(moved), module.estimate(obs["policy"]))
        assert torch.allclose(module(moved), actor(_perturb(obs, cols["commands"])), atol=1e-5)
    sess = ort.InferenceSession(str(paths["onnx"]))
    (out,) = sess.run(None, {"obs": moved.numpy()})
    assert np.allclose(out, actor(_perturb(obs, cols["commands"])).detach().numpy(), atol=1e-5)
    train_cfg.estimator.skip_terms = ("speed",)
    with pytest.raises(ValueError, match="estimator.skip_terms.*not policy observation terms"):
        train_cfg.for_env(env)


def test_the_history_holds_the_observation_as_the_policy_saw_it():
    """With observation noise on, the newest history slot is the previous observation's
    (noisy) proprioceptive terms, not the clean state."""
    e = registry.make_env(TASK, CPU + ["noise.level=1.0"], num_envs=4)
    cols = e.policy_obs_columns()
    start, stop = cols["ang_vel"][0], cols["actions"][1]
    hist = cols["proprio_history"]
    e.set_commands([0.5, 0.0, 0.0])
    obs = e.get_observations()
    for _ in range(3):
        prev = obs["policy"][:, start:stop].clone()
        obs, *_ = e.step(torch.zeros(4, 12))
        newest = obs["policy"][:, hist[0] : hist[0] + (stop - start)]
        assert torch.allclose(newest, prev)
    clean = e._proprio()
    assert not torch.allclose(obs["policy"][:, start:stop], clean)  # the noise is there to be kept
    e.close()


def test_speed_set_checks_slalom_ramp_and_sweep_bars():
    """The speed sweep's verdict (the speed sweep's bars) from results: a stand-still robot fails
    the slalom and the ramp; errors at the bar pass, above it fail."""
    from legged_casters.tools import evaluate as ev

    by = {s.name: s for s in ev.SPEED}
    scen = (by["vy slalom"], by["fig9 ramp"])
    e = registry.make_env(TASK, CPU, num_envs=1)
    cfg = ev.eval_env_cfg(e.cfg, scen)
    e.close()
    e = registry.get_task(TASK).env_class(cfg)
    zero = torch.zeros(e.num_envs, 12)
    slalom, ramp = ev.run_scenarios(e, lambda obs: zero, scen)
    e.close()
    assert slalom.extra["swing_m"] < 0.1 and ramp.extra["best_2s_backward"] < 0.2  # it stands
    checks = {name: ok for name, ok, _ in ev.verdict([slalom, ramp])}
    assert checks == {
        "vy slalom: lateral swing 0.3-0.6 m": False,
        "vy slalom: heading change < 30.0 deg": True,
        "fig9 ramp: best 2-s backward speed >= 2.0 m/s": False,
    }

    def track(name, cmd, err):
        r = ev.ScenarioResult(name, "track", cmd)
        r.err = {"vx": err, "vy": err, "wz": 0.0}
        r.extra["est_rms"] = err
        return r

    results = [track("vx +1.50", (1.5, 0, 0), 0.15), track("vx -2.00", (-2.0, 0, 0), 0.31),
               track("vy +0.40", (0, 0.4, 0), 0.09), track("vy -0.60", (0, -0.6, 0), 0.5)]  # fmt: skip
    checks = {name: ok for name, ok, _ in ev.verdict(results)}
    assert checks["vx +1.50: |vx error| <= 0.15"] and not checks["vx -2.00: |vx error| <= 0.3"]
    assert checks["vy +0.40: |vy error| <= 0.1"] and not any(k.startswith("vy -0.60") for k in checks)
    assert not checks["estimator RMS error <= 0.1 m/s (worst flat scenario)"]


@pytest.mark.parametrize("name, history, reads_command, task", [("caster_omni", 50, False, "caster_omni_sym")])
def test_the_shipped_estimator_policy_loads_everywhere_and_estimates_its_speed(name, history, reads_command, task):
    from legged_casters.deploy.policy import load_meta
    from legged_casters.tools import common
    from legged_casters.tools import evaluate as ev

    shipped = common.SHIPPED_POLICIES / name
    meta = load_meta(shipped)  # the bridge accepts it
    assert meta.task == task and meta.history_length == history
    loaded_task, spec, env_cfg, policy, _, dim = ev.load_exported(shipped, None)
    assert loaded_task == task and policy.estimate is not None
    assert env_cfg.gait.speed_feedback == 1.0  # its prior reads the estimate
    scen = (ev.Scenario("fwd", ((0.0, (0.5, 0.0, 0.0)),), 5.0, 3.0),)
    e = spec.env_class(ev.eval_env_cfg(env_cfg, scen))
    assert e.observation_dims()["policy"] == dim == meta.obs_dim
    (res,) = ev.run_scenarios(e, policy, scen, estimator=policy.estimate, command_gain=True)
    e.close()
    assert abs(res.mean["vx"] - 0.5) < 0.15 and res.falls == 0  # it holds the commanded 0.5 m/s
    assert res.extra["est_rms"] < 0.2  # and knows how fast it goes
    assert abs(res.extra["est_vx"] - res.mean["vx"]) < res.extra["est_rms"] + 0.02  # its mean within its RMS
    if reads_command:
        assert 0.02 < res.extra["est_cmd_gain"] < 0.5  # partly from the command it reads (research/log.md)
    else:  # estimator.skip_terms [commands]: the command cannot move its estimate
        assert res.extra["est_cmd_gain"] == 0.0


def _load_study():
    import importlib.util
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "estimator_study.py"
    spec = importlib.util.spec_from_file_location("estimator_study", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["estimator_study"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_estimator_study_windows_are_newest_first_and_skip_resets():
    study = _load_study()
    n, steps, k = 2, 6, 1
    proprio = torch.arange(steps, dtype=torch.float32).reshape(1, steps, k).repeat(n, 1, 1)  # value = step
    vel = proprio.repeat(1, 1, 3)
    cmds = torch.full((n, steps, 1), 9.0)
    dones = torch.zeros(n, steps, dtype=torch.bool)
    dones[1, 1] = True  # robot 1 reset after step 1: its windows that reach back over it are left out
    x, y = study.windows(proprio, vel, cmds, dones, 3, range(3, steps), use_cmd=True)
    # step by step, robots in order: robot 0 ends windows at 3, 4 and 5; robot 1 only at 5 (steps 3-5)
    assert x.tolist() == [[3, 2, 1, 9], [4, 3, 2, 9], [5, 4, 3, 9], [5, 4, 3, 9]]
    assert y[:, 0].tolist() == [3, 4, 5, 5]
    x, _ = study.windows(proprio, vel, cmds, dones, 3, range(5, steps), use_cmd=False)
    assert x.tolist() == [[5, 4, 3], [5, 4, 3]]


def test_estimator_study_steady_commands():
    study = _load_study()
    assert study.parse_steady("1.5") == (1.5, 0.0, 0.0)
    assert study.parse_steady(" y-0.4") == (0.0, -0.4, 0.0)
    with pytest.raises(ValueError):
        study.parse_steady("fast")
    with pytest.raises(SystemExit):  # a usage error before anything runs
        study.main(["--load_run", "x", "--checkpoint", "1", "--steady-commands", "1,fast"])


def test_pose_imitation_pulls_the_networks_own_mean_to_the_held_stop_pose():
    """policy.stop_pose_imitation: where the stop pose holds (a zero command, the last action
    near the pose), PPO gives the MLP no gradient; the imitation pass's loss is the gap
    between the network's own mean and the posed action over those samples, and its steps
    close it. Without the pose or without the estimator it refuses."""
    from legged_casters.config import ConfigError
    from legged_casters.envs.gait import stop_pose

    sets = [*CPU, "gait.stop_pitch=0.4"]
    e = registry.make_env(TASK, sets, num_envs=16)
    pose = (stop_pose(0.4, 0.0) / e.cfg.control.action_scale).reshape(1, 12)
    train = copy.deepcopy(registry.get_task(TASK).train_cfg)
    train.policy.stop_pose_imitation = 1e-2
    cfg = train.for_env(e)
    cfg["num_steps_per_env"] = 8
    runner = OnPolicyRunner(e, copy.deepcopy(cfg), log_dir=None, device="cpu")
    alg = runner.alg
    commands = torch.zeros(16, 3)
    commands[8:, 0] = 0.5  # half the robots have a command: never posed
    e.set_commands(commands)
    e.step(pose.expand(16, 12).clone())  # the last action is the pose: it holds under the zero command
    obs = e.get_observations()
    alg.train_mode()
    for _ in range(8):
        with torch.no_grad():
            actions = alg.act(obs)
        assert actions.shape == (16, 12)
        obs, rewards, dones, extras = e.step(pose.expand(16, 12).clone())  # stay in the pose whatever was sampled
        e.set_commands(commands)
        alg.process_env_step(obs, rewards, dones, extras)
    batch = alg.storage.observations.flatten(0, 1)

    def gap() -> tuple[float, int]:
        with torch.no_grad():
            own, posed = alg.actor.means(batch)
        held = (own != posed).any(dim=1)
        return float((own - posed)[held].pow(2).mean()), int(held.sum())

    before, n = gap()
    assert n == 8 * 8  # every zero-command robot at every step
    losses = [alg.update_pose_imitation() for _ in range(30)]
    after, _ = gap()
    assert losses[-1] < 0.5 * losses[0]
    assert after < 0.2 * before, (before, after)
    e.close()

    plain = registry.make_env(TASK, CPU, num_envs=4)  # no stop pose: nothing to imitate
    with pytest.raises(ValueError, match="stop_pitch"):
        OnPolicyRunner(plain, copy.deepcopy(train.for_env(plain)), log_dir=None, device="cpu")
    train.estimator.hidden_dims = ()
    with pytest.raises(ConfigError, match="estimator"):
        train.to_rsl_rl()
    plain.close()
