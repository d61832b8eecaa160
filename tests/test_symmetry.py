"""Left-right mirror symmetry: the robots, the maps of actions and observations, the prior,
and PPO with symmetry.mode (legged_casters.learning.symmetry)."""

from __future__ import annotations

import copy

import mujoco
import numpy as np
import pytest
import torch

from legged_casters import registry
from legged_casters.config import ConfigError, apply_overrides
from legged_casters.envs.gait import GaitPriorCfg, gait_prior
from legged_casters.learning.symmetry import mirror, mirror_batch
from legged_casters.robot import build, go2

REFLECT = np.diag([1.0, -1.0, 1.0])

QUIET = [
    "sim.backend=cpu",
    "terrain.slope_deg=0",
    "noise.enabled=false",
    "domain_rand.randomize_friction=false",
    "domain_rand.randomize_base_mass=false",
    "domain_rand.randomize_com=false",
    "domain_rand.randomize_gains=false",
    "domain_rand.push_robots=false",
    "domain_rand.joint_damping={}",
    "domain_rand.joint_frictionloss_scale={}",
    "domain_rand.action_latency_range=[0,0]",
    "commands.resampling_time=100",
]


@pytest.mark.parametrize("feet", ["caster", "point", "wheel"])
def test_robot_is_its_own_mirror_image(feet):
    """Every leg joint's mirror (go2.mirror_joint) sits at the reflected anchor, with the
    axis that makes the sign right: rotating joint j by q and its mirror by sign * q give
    mirror-image poses. Masses and centres of mass of left and right bodies agree."""
    m = build.build_spec(feet).compile()
    d = mujoco.MjData(m)
    d.qpos[:] = m.qpos0
    d.qpos[0:3] = 0.0
    mujoco.mj_forward(m, d)
    names = [m.joint(i).name for i in range(m.njnt) if m.joint(i).name[:2] in go2.LEGS]
    assert len(names) == {"caster": 20, "point": 12, "wheel": 16}[feet]
    for name in names:
        other, sign = go2.mirror_joint(name)
        assert go2.mirror_joint(other) == (name, sign)
        np.testing.assert_allclose(d.joint(other).xanchor, REFLECT @ d.joint(name).xanchor, atol=1e-9)
        # reflecting a rotation about axis a by q gives one about REFLECT a by -q
        np.testing.assert_allclose(d.joint(other).xaxis, -sign * (REFLECT @ d.joint(name).xaxis), atol=1e-9)
    for i in range(m.nbody):
        name = m.body(i).name
        if name[:2] in go2.LEGS:
            other = name[0] + ("R" if name[1] == "L" else "L") + name[2:]
            assert m.body(other).mass[0] == pytest.approx(m.body(name).mass[0])
            np.testing.assert_allclose(d.body(other).xipos, REFLECT @ d.body(name).xipos, atol=1e-9)


def test_mirror_joint_rejects_other_names():
    with pytest.raises(ValueError, match="not a Go2 leg joint"):
        go2.mirror_joint("trunk_joint")


def _mirror_prior_inputs(cmd, mask, vel):
    legs = go2.mirror_legs()
    return cmd * torch.tensor([1.0, -1.0, -1.0]), mask[:, legs], vel * torch.tensor([1.0, -1.0, 1.0])


def test_gait_prior_is_mirror_equivariant():
    """The prior inside caster_omni's actor: the mirrored command (mask, velocity estimate)
    gives the mirrored joint offsets, so a symmetric MLP plus the prior is symmetric."""
    env_like = type("E", (), {"layout": go2.action_layout("caster")})
    from legged_casters.envs.base import LeggedEnv

    index, sign = LeggedEnv.action_mirror(env_like)
    gen = torch.Generator().manual_seed(0)
    n = 64
    cmd = (torch.rand(n, 3, generator=gen) - 0.5) * 4.0
    mask = (torch.rand(n, 4, generator=gen) < 0.3).float()
    vel = (torch.rand(n, 3, generator=gen) - 0.5) * 3.0
    sin_phase = torch.rand(n, generator=gen) * 2 - 1
    yaw = (torch.rand(n, generator=gen) - 0.5) * 3.0  # the gyro's yaw rate: flips in the mirror image
    cfg = GaitPriorCfg(enabled=True, tilt=0.2, tilt_backward=0.3, speed_feedback=1.0, command_share=0.3,
                       yaw_feedback=1.0, yaw_command_share=0.5)  # fmt: skip
    out = gait_prior(cfg, cmd, mask, sin_phase, velocity=vel, yaw_rate=yaw)
    cmd_m, mask_m, vel_m = _mirror_prior_inputs(cmd, mask, vel)
    out_m = gait_prior(cfg, cmd_m, mask_m, sin_phase, velocity=vel_m, yaw_rate=-yaw)
    torch.testing.assert_close(out_m, mirror(out, torch.tensor(index), torch.tensor(sign)), atol=1e-6, rtol=0)


def mirror_state(model, x: torch.Tensor, kind: str) -> torch.Tensor:
    """The mirror image of a (1, nq) qpos or (1, nv) qvel of a Go2 model: the free joint
    reflected (position y, the quaternion's x and z; linear velocity y, body rates x and z),
    each leg joint moved to its mirror with go2.mirror_joint's sign."""
    out = x.clone()
    if kind == "qpos":
        out[0, 1] = -x[0, 1]
        out[0, 4] = -x[0, 4]
        out[0, 6] = -x[0, 6]
    else:
        out[0, 1] = -x[0, 1]
        out[0, 3] = -x[0, 3]
        out[0, 5] = -x[0, 5]
    for i in range(model.njnt):
        name = model.joint(i).name
        if name[:2] not in go2.LEGS:
            continue
        other, sign = go2.mirror_joint(name)
        adr = "qposadr" if kind == "qpos" else "dofadr"
        out[0, getattr(model.joint(other), adr)[0]] = sign * x[0, getattr(model.joint(name), adr)[0]]
    return out


def test_caster_omni_mirrored_twin_observes_the_mirror_image():
    """Two caster robots start in mirror-image states (a reset's random pose, moving); one
    gets commands and actions, the other their mirror images. For 1 s of skating, every policy observation of the
    second (history and clock included) is the mirror map of the first's, and so are the
    swivel states the critic sees."""
    env = registry.make_env("caster_omni", QUIET, num_envs=2)
    env.set_mode("four_wheel")
    qpos, qvel = env.sim.qpos[0:1].clone(), env.sim.qvel[0:1].clone()  # a reset's random pose
    qvel[0, 0:3] = torch.tensor([0.3, 0.2, 0.0])
    qvel[0, 3:6] = torch.tensor([0.1, -0.2, 0.3])
    env.sim.reset([0, 1], torch.cat([qpos, mirror_state(env.model, qpos, "qpos")]),
                  torch.cat([qvel, mirror_state(env.model, qvel, "qvel")]))  # fmt: skip
    env._refresh_state()
    env.commands[0] = torch.tensor([0.6, 0.3, 0.5])
    env.commands[1] = torch.tensor([0.6, -0.3, -0.5])
    env.episode_length_buf[:] = 0
    env.gait_phase[:] = 0.0
    env.history[:] = 0.0
    env.actions[:] = 0.0
    maps = env.mirror_maps()
    assert maps["critic"] is None  # caster_zaxis is a world-frame vector
    pol_index, pol_sign = maps["policy"]
    act_index, act_sign = (torch.tensor(v) for v in env.action_mirror())
    gen = torch.Generator().manual_seed(1)
    swivel = env.obs_layout["critic"]
    worst = 0.0
    for step in range(50):
        # the skating prior of robot 0 (what caster_omni's actor adds to its MLP) and some noise
        a = env.gait_offsets()[0] / env.cfg.control.action_scale + 0.3 * torch.randn(12, generator=gen)
        obs, _, dones, _ = env.step(torch.stack([a, mirror(a[None], act_index, act_sign)[0]]))
        assert not dones.any(), step
        pol = obs["policy"]
        err = (pol[1] - mirror(pol[0:1], pol_index, pol_sign)[0]).abs()
        worst = max(worst, err.max().item())
        assert err.max().item() < 1e-4, (step, err.argmax().item())
        crit = obs["critic"]
        start = sum(dim for term, dim, _ in swivel[:1])  # caster_zaxis first, then swivel_pos, swivel_vel
        assert [t for t, _, _ in swivel[:3]] == ["caster_zaxis", "swivel_pos", "swivel_vel"]
        sp0, sp1 = crit[0, start : start + 4], crit[1, start : start + 4]
        torch.testing.assert_close(sp1, -sp0[go2.mirror_legs()], atol=1e-4, rtol=0)
    assert env.base_lin_vel[0, 0] > 0.1  # it skated
    print("largest mirror mismatch", worst)


def test_mirror_batch_appends_mirror_images():
    env = registry.make_env("caster_omni", ["sim.backend=cpu"], num_envs=3)
    obs = env.get_observations()
    actions = torch.randn(3, 12)
    obs2, actions2 = mirror_batch(env, obs, actions)
    assert obs2.batch_size[0] == 6 and actions2.shape == (6, 12)
    torch.testing.assert_close(obs2[:3]["policy"], obs["policy"])
    index, sign = env.mirror_maps()["policy"]
    torch.testing.assert_close(obs2[3:]["policy"], mirror(obs["policy"], index, sign))
    # twice mirrored is the original
    twice, twice_a = mirror_batch(env, obs2[3:], actions2[3:])
    torch.testing.assert_close(twice[3:]["policy"], obs["policy"])
    torch.testing.assert_close(twice_a[3:], actions)
    # a group without a map passes unmirrored
    torch.testing.assert_close(obs2[3:]["critic"], obs["critic"])
    assert mirror_batch(env, None, actions)[0] is None


def test_symmetry_config_checks_the_task():
    env = registry.make_env("caster_omni", ["sim.backend=cpu"], num_envs=2)
    _, cfg = registry.task_configs("caster_omni", train_overrides=["symmetry.mode=augment"])
    with pytest.raises(ConfigError, match=r"'critic' observation terms \['caster_zaxis', 'lin_vel'\] have no mirror"):
        cfg.for_env(env)
    cfg.symmetry.mode = "loss"
    rsl = cfg.for_env(env)
    sym = rsl["algorithm"]["symmetry_cfg"]
    assert sym["use_mirror_loss"] and not sym["use_data_augmentation"]
    cfg.symmetry.mode = "log"
    sym = cfg.for_env(env)["algorithm"]["symmetry_cfg"]
    assert not sym["use_mirror_loss"] and not sym["use_data_augmentation"]
    cfg.symmetry.mode = "none"
    assert "symmetry_cfg" not in cfg.for_env(env)["algorithm"]


@pytest.mark.parametrize("task", ["go2_flat", "go2_wheel_flat"])
def test_point_foot_and_wheel_tasks_mirror_every_group(task):
    """Their observations are all in the trunk frame or per leg: "augment" is allowed."""
    env = registry.make_env(task, ["sim.backend=cpu"], num_envs=2)
    maps = env.mirror_maps()
    assert maps["policy"] is not None and maps["critic"] is not None
    _, cfg = registry.task_configs(task, train_overrides=["symmetry.mode=both"])
    sym = cfg.for_env(env)["algorithm"]["symmetry_cfg"]
    assert sym["use_data_augmentation"] and sym["use_mirror_loss"]
    obs = env.get_observations()
    twice, _ = mirror_batch(env, mirror_batch(env, obs)[0][2:])
    torch.testing.assert_close(twice[2:]["critic"], obs["critic"])


def _train_two_iterations(tmp_path, mode: str, name: str) -> tuple[dict, list[float]]:
    from legged_casters.learning.runner import CheckpointingRunner

    torch.manual_seed(0)
    env = registry.make_env("caster_omni", ["sim.backend=cpu", "seed=3"], num_envs=4)
    _, train_cfg = registry.task_configs("caster_omni", train_overrides=[f"symmetry.mode={mode}"])
    cfg = train_cfg.for_env(env)
    cfg["num_steps_per_env"] = 8
    runner = CheckpointingRunner(env, cfg, log_dir=str(tmp_path / name), device="cpu", task="caster_omni")
    losses = []
    update = runner.alg.update

    def spy():
        out = update()
        losses.append(out.get("symmetry"))
        return out

    runner.alg.update = spy
    runner.learn(num_learning_iterations=2)
    env.close()
    return {k: v.clone() for k, v in runner.alg.actor.state_dict().items()}, losses


def test_symmetry_log_measures_without_learning_and_loss_learns(tmp_path):
    """mode=log reports the mirror loss and trains exactly as mode=none; mode=loss trains
    differently (its gradient reaches the actor)."""
    off, off_losses = _train_two_iterations(tmp_path, "none", "none")
    logged, log_losses = _train_two_iterations(tmp_path, "log", "log")
    learnt, loss_losses = _train_two_iterations(tmp_path, "loss", "loss")
    assert off_losses == [None, None]
    assert all(v is not None and v > 0.0 for v in log_losses + loss_losses)
    for key in off:
        torch.testing.assert_close(logged[key], off[key], atol=0, rtol=0)
    assert any(not torch.equal(learnt[key], off[key]) for key in off)


def test_evaluate_symmetrise_makes_any_policy_mirror_equivariant():
    """evaluate.py --symmetrise: a one-sided policy, averaged with its mirror image, acts on
    the mirrored observation exactly as the mirror image of its action."""
    from legged_casters.tools.evaluate import symmetrised

    env = registry.make_env("caster_omni", ["sim.backend=cpu"], num_envs=3)
    obs = env.get_observations()
    obs["policy"] = obs["policy"] + 0.3 * torch.randn_like(obs["policy"])  # not the mirror-symmetric reset
    torch.manual_seed(0)
    layer = torch.nn.Linear(obs["policy"].shape[1], 12)
    one_sided = lambda o: layer(o["policy"])  # noqa: E731
    sym = symmetrised(one_sided, env)
    mirrored, _ = mirror_batch(env, obs, None)
    mirrored = mirrored[3:]
    index, sign = (torch.tensor(v) for v in env.action_mirror())
    with torch.no_grad():
        assert not torch.allclose(one_sided(mirrored), mirror(one_sided(obs), index, sign), atol=1e-3)
        torch.testing.assert_close(sym(mirrored), mirror(sym(obs), index, sign))
    env.close()


def test_symmetry_estimator_mirrors_the_estimators_samples_and_needs_an_estimator():
    """symmetry.estimator: each of the estimator's regression mini-batches holds every sample
    and then its mirror image, target included (vy flips), with or without a symmetry mode;
    without an estimator it is refused."""
    from legged_casters.learning.estimator import TARGET_GROUP
    from legged_casters.learning.runner import CheckpointingRunner

    env = registry.make_env("caster_omni", ["sim.backend=cpu", "seed=3"], num_envs=4)
    _, cfg = registry.task_configs("caster_omni", train_overrides=["symmetry.estimator=true", "symmetry.mode=none"])
    no_estimator = copy.deepcopy(cfg)
    no_estimator.estimator.hidden_dims = ()
    with pytest.raises(ConfigError, match="symmetry.estimator=true .* needs the estimator"):
        no_estimator.for_env(env)
    rsl = cfg.for_env(env)  # with symmetry.mode none: the actor's PPO is left as it is
    assert "symmetry_cfg" not in rsl["algorithm"]
    assert rsl["algorithm"]["estimator_mirror"] is True
    rsl["num_steps_per_env"] = 8
    runner = CheckpointingRunner(env, rsl, log_dir=None, device="cpu", task="caster_omni")
    alg = runner.alg
    for _ in range(8):  # a rollout in storage, moving
        with torch.no_grad():
            obs, rew, dones, extras = env.step(alg.act(env.get_observations()))
            alg.process_env_step(obs, rew, dones, extras)
    seen = []
    estimate = alg._raw_actor.estimate
    alg._raw_actor.estimate = lambda o: (seen.append(o.clone()), estimate(o))[1]
    alg.update_estimator()
    assert seen
    for batch in seen:
        half = batch.batch_size[0] // 2
        assert batch.batch_size[0] == 2 * half
        torch.testing.assert_close(batch[half:], mirror_batch(env, batch[:half])[0][half:])
        target = batch[TARGET_GROUP]
        torch.testing.assert_close(target[half:, 1], -target[:half, 1])
        torch.testing.assert_close(target[half:, [0, 2]], target[:half, [0, 2]])
    env.close()


def test_symmetry_exact_actor_is_mirror_equivariant_trained_and_exported(tmp_path):
    """symmetry.mode=exact: the actor and its estimate are exact mirror images of themselves
    for any weights and normaliser (the same actor without the maps is not), a checkpoint of
    the plain actor loads into it, PPO trains it, and TorchScript and ONNX compute the same."""
    import onnxruntime as ort

    from legged_casters.learning.estimator import TARGET_GROUP
    from legged_casters.learning.runner import CheckpointingRunner
    from legged_casters.tools import export

    env = registry.make_env("caster_omni", ["sim.backend=cpu", "seed=5"], num_envs=4)
    _, cfg = registry.task_configs("caster_omni", train_overrides=["symmetry.mode=exact"])
    both = copy.deepcopy(cfg)
    both.symmetry.estimator = True
    with pytest.raises(ConfigError, match="leave out symmetry.estimator"):
        both.for_env(env)
    point = registry.make_env("go2_flat", ["sim.backend=cpu"], num_envs=1)
    with pytest.raises(ConfigError, match="exact needs an actor with a prior"):
        registry.task_configs("go2_flat", train_overrides=["symmetry.mode=exact"])[1].for_env(point)
    point.close()
    rsl = cfg.for_env(env)
    assert "symmetry_cfg" not in rsl["algorithm"]
    assert set(rsl["actor"]["mirror"]) == {"observation", "action", "estimate"}
    plain_cfg = copy.deepcopy(cfg)
    plain_cfg.symmetry.mode = "none"
    torch.manual_seed(0)
    plain = export.build_actor(env, plain_cfg)
    actor = export.build_actor(env, cfg)
    obs = env.get_observations()
    obs["policy"] = obs["policy"] + 0.3 * torch.randn_like(obs["policy"])  # not the mirror-symmetric reset
    with torch.no_grad():
        plain.obs_normalizer.update(obs["policy"] + 0.5)  # a normaliser that is not symmetric either
        plain.eval()
        actor.load_state_dict(plain.state_dict(), strict=True)
        actor.eval()
    mirrored = mirror_batch(env, obs, None)[0][4:]
    action = [torch.tensor(v) for v in env.action_mirror()]
    target = env.mirror_maps()[TARGET_GROUP]
    with torch.no_grad():
        assert not torch.allclose(plain(mirrored), mirror(plain(obs), *action), atol=1e-3)
        torch.testing.assert_close(actor(mirrored), mirror(actor(obs), *action))
        torch.testing.assert_close(actor.estimate(mirrored), mirror(actor.estimate(obs), *target))
        meta = export.policy_metadata(env, "caster_omni", actor)
        assert meta["symmetry"]["mode"] == "exact"  # policy.yaml says so
        assert "symmetry" not in export.policy_metadata(env, "caster_omni", plain)
        paths = export.export_policy(actor, meta, tmp_path)
        module = torch.jit.load(str(paths["torchscript"]))
        torch.testing.assert_close(module(obs["policy"]), actor(obs), atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(module.estimate(obs["policy"]), actor.estimate(obs), atol=1e-5, rtol=1e-5)
    (out,) = ort.InferenceSession(str(paths["onnx"])).run(None, {"obs": obs["policy"].numpy()})
    np.testing.assert_allclose(out, actor(obs).detach().numpy(), atol=1e-5)
    rsl["num_steps_per_env"] = 8
    runner = CheckpointingRunner(env, rsl, log_dir=None, device="cpu", task="caster_omni")
    runner.logger.log = lambda **kw: None
    before = copy.deepcopy(runner.alg._raw_actor.state_dict())
    runner.learn(num_learning_iterations=1)
    trained = runner.alg._raw_actor
    assert trained.mirrored and any(not torch.equal(before[k], v) for k, v in trained.state_dict().items())
    with torch.no_grad():
        trained.eval()
        torch.testing.assert_close(trained(mirrored), mirror(trained(obs), *action))
    env.close()


def test_shipped_symmetric_policy_mirrors_its_action_and_says_so():
    """resources/policies/caster_omni (symmetry.mode=exact): the shipped TorchScript and ONNX files
    give the mirrored observation exactly the mirrored action, and policy.yaml says the network is
    symmetric."""
    import onnxruntime as ort
    import yaml

    from legged_casters.tools import common
    from legged_casters.tools import evaluate as ev

    torch.manual_seed(0)
    cases = (("caster_omni", True),)
    for name, symmetric in cases:
        folder = common.SHIPPED_POLICIES / name
        meta = yaml.safe_load((folder / "policy.yaml").read_text())
        assert ("symmetry" in meta) == symmetric
        _, spec, env_cfg, policy, _, _ = ev.load_exported(folder, None)
        env = spec.env_class(apply_overrides(env_cfg, ["sim.backend=cpu", "noise.enabled=false", "num_envs=3"]))
        obs = env.get_observations()
        obs["policy"] = obs["policy"] + 0.3 * torch.randn_like(obs["policy"])
        mirrored = mirror_batch(env, obs, None)[0][3:]
        index, sign = (torch.tensor(v) for v in env.action_mirror())
        with torch.no_grad():
            same = torch.allclose(policy(mirrored), mirror(policy(obs), index, sign), atol=1e-5)
        assert same == symmetric
        if symmetric:
            session = ort.InferenceSession(str(folder / "policy.onnx"))
            (a,) = session.run(None, {"obs": obs["policy"].numpy()})
            (b,) = session.run(None, {"obs": mirrored["policy"].numpy()})
            np.testing.assert_allclose(b, mirror(torch.from_numpy(a), index, sign).numpy(), atol=1e-5)
        env.close()
