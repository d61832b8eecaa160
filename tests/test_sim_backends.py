"""Tests of the simulation backends (legged_casters.sim): CPU (MuJoCo C rollout) and
MuJoCo Warp (here on Warp's CPU device; the first run compiles kernels, ~40 s, then
they are cached).

All tests use the committed caster robot. (An earlier contact setting, elliptic
cones with impratio 10, made it diverge under small random targets: wheels spun up
to 1e3-1e12 rad/s. Chaotic trajectories cannot be compared across backends; the
pyramidal cone now committed keeps them bounded.)
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

from legged_casters.robot import go2
from legged_casters.robot.build import MODEL_FILES
from legged_casters.sim.base import RANDOMIZABLE_FIELDS, make_backend, physics_model
from legged_casters.sim.cpu import CpuBackend
from legged_casters.sim.parity import BOUNDS, parity_errors
from legged_casters.sim.parity import joint_addresses as _adr
from legged_casters.sim.parity import perturbed_stand as _perturbed_stand
from legged_casters.sim.parity import random_targets as _targets
from legged_casters.sim.parity import rollout as _rollout

DECIMATION = 10
BACKENDS = ("cpu", "warp")


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return physics_model(MODEL_FILES["caster"])


def _tiled(m: mujoco.MjModel, name: str, n: int) -> torch.Tensor:
    """The nominal value of model field `name`, repeated for n envs."""
    value = torch.from_numpy(np.array(getattr(m, name), dtype=np.float64))
    return value.unsqueeze(0).repeat(n, *[1] * value.ndim)


def test_factory_rejects_unknown_kind(model):
    with pytest.raises(ValueError, match="auto, cpu, warp"):
        make_backend("gpu", model, 2, DECIMATION)


def test_factory_auto_is_cpu_without_cuda(model, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    backend = make_backend("auto", model, 2, DECIMATION)
    assert isinstance(backend, CpuBackend)
    backend.close()


def test_cpu_backend_matches_mj_step(model):
    """The rollout plumbing (state layout, constant control per substep) reproduces a
    plain mj_step loop, up to the solver warmstart (the backend approximates mj_step's
    qacc_warmstart, so Newton stops at its tolerance from a slightly different start).
    Measured: qpos within 2e-5, qvel within 5e-5 after 10 control steps."""
    n, steps = 3, 10
    qpos, qvel = _perturbed_stand(model, n, seed=1)
    targets = _targets(steps, n, 0.1, seed=2)
    backend = make_backend("cpu", model, n, DECIMATION)
    q, v = _rollout(backend, qpos, qvel, targets)
    for env in range(n):
        d = mujoco.MjData(model)
        d.qpos[:], d.qvel[:] = qpos[env].numpy(), qvel[env].numpy()
        for t in range(steps):
            d.ctrl[:] = targets[t, env].numpy()
            for _ in range(DECIMATION):
                mujoco.mj_step(model, d)
        np.testing.assert_allclose(q[-1, env].numpy(), d.qpos, atol=2e-4, rtol=0)
        np.testing.assert_allclose(v[-1, env].numpy(), d.qvel, atol=1e-3, rtol=0)
    backend.close()


def test_cpu_warp_parity(model):
    """Same perturbed stand and the same random PD targets (nominal + N(0, 0.05 rad))
    through both backends, 25 control steps (0.5 s). Measured maxima over 4 envs
    (float32 Warp vs float64 C, ls_iterations 30): trunk position 2.4e-7 m, trunk
    quaternion 1.7e-7, actuated joint angles 1.1e-6 rad, their velocities 7.8e-5
    rad/s, all qpos (including swivel and wheel angles) 2.2e-5, all qvel 9.1e-4.
    Asserted with a margin of >= 20x. Beyond ~40 steps the contact dynamics amplify
    float32 round-off (joint velocities differ by 0.3 rad/s at step 50)."""
    err = parity_errors(model, n=4, steps=25, warp_device="cpu")
    assert not err["contact_overflow"]
    # the trajectories move: the targets are tracked, the test is not comparing two still robots
    assert err["moved"] > 0.02
    assert err["finite"]
    for name, bound in BOUNDS.items():
        assert err[name] < bound, f"{name}: |warp - cpu| up to {err[name]:.2e}, bound {bound:.0e}"
    assert err["worlds_outside"] == 0
    assert err["worst_dof"].endswith(")") and "robot " in err["worst_dof"]


@pytest.mark.parametrize("kind", BACKENDS)
def test_reset_selected_envs(model, kind):
    n = 4
    backend = make_backend(kind, model, n, DECIMATION, "cpu")
    qpos, qvel = _perturbed_stand(model, n, seed=4)
    backend.reset(None, qpos, qvel)
    for ctrl in _targets(3, n, 0.1, seed=5):
        backend.step(ctrl.to(backend.ctrl.dtype))
    before_q = backend.qpos.clone()
    before_v = backend.qvel.clone()
    before_s = backend.sensordata.clone()

    ids = torch.tensor([1, 3])
    new_q, new_v = _perturbed_stand(model, 2, seed=6)
    new_v[:, 0] = 0.3  # a forward trunk velocity, distinguishable from the stepped state
    backend.reset(ids, new_q, new_v)

    tol = 1e-6 if kind == "warp" else 0.0
    torch.testing.assert_close(backend.qpos[ids].double(), new_q, atol=tol, rtol=0)
    torch.testing.assert_close(backend.qvel[ids].double(), new_v, atol=tol, rtol=0)
    others = torch.tensor([0, 2])
    assert torch.equal(backend.qpos[others], before_q[others])
    assert torch.equal(backend.qvel[others], before_v[others])
    assert torch.equal(backend.sensordata[others], before_s[others])
    assert not torch.equal(backend.qpos[ids], before_q[ids])

    # forward ran for the reset envs: their sensors describe the new state
    for row, env in enumerate(ids.tolist()):
        d = mujoco.MjData(model)
        d.qpos[:], d.qvel[:] = new_q[row].numpy(), new_v[row].numpy()
        d.ctrl[:] = backend.ctrl[env].double().numpy()
        mujoco.mj_forward(model, d)
        for name in ("FL_thigh_joint_pos", "trunk_pos", "imu_quat", "trunk_linvel_world", "imu_gyro"):
            adr = model.sensor(name).adr[0]
            dim = model.sensor(name).dim[0]
            np.testing.assert_allclose(
                backend.sensor(name)[env].double().numpy(), d.sensordata[adr : adr + dim], atol=1e-5
            )
    backend.close()


@pytest.mark.parametrize("kind", BACKENDS)
def test_randomised_fields_land_per_env(model, kind):
    n = 4
    backend = make_backend(kind, model, n, DECIMATION, "cpu")
    g = torch.Generator().manual_seed(7)
    # read back: every field, different values per env
    written = {}
    for name in RANDOMIZABLE_FIELDS:
        nominal = torch.from_numpy(np.array(getattr(model, name), dtype=np.float64))
        scale = 1.0 + 0.2 * torch.rand(n, *nominal.shape, generator=g, dtype=torch.float64)
        written[name] = nominal * scale
        backend.set_model_field(name, None, written[name])
    for name, values in written.items():
        got = backend.get_model_field(name).double()
        assert got.shape == (n, *getattr(model, name).shape)
        torch.testing.assert_close(got, values, atol=1e-6, rtol=1e-6)
        assert not torch.equal(got[0], got[1])
    # setting a subset leaves the other envs alone
    friction = backend.get_model_field("geom_friction").double()
    backend.set_model_field("geom_friction", [2], torch.full((1, model.ngeom, 3), 0.3, dtype=torch.float64))
    after = backend.get_model_field("geom_friction").double()
    assert torch.equal(after[[0, 1, 3]], friction[[0, 1, 3]])
    assert torch.allclose(after[2], torch.full_like(after[2], 0.3))

    # physics: envs 0 and 2 nominal, env 1 with soft PD gains, env 3 with a heavier trunk
    for name in RANDOMIZABLE_FIELDS:
        backend.set_model_field(name, None, _tiled(model, name, n))
    gain, bias = _tiled(model, "actuator_gainprm", n), _tiled(model, "actuator_biasprm", n)
    kp, kd = 15.0, 0.3
    gain[1, :, 0], bias[1, :, 1], bias[1, :, 2] = kp, -kp, -kd
    backend.set_model_field("actuator_gainprm", None, gain)
    backend.set_model_field("actuator_biasprm", None, bias)
    trunk = model.body(go2.TRUNK_BODY).id
    mass = _tiled(model, "body_mass", n)
    mass[3, trunk] += 4.0
    backend.set_model_field("body_mass", [3], mass[3:4])

    qpos = torch.from_numpy(model.key_qpos[0].copy()).repeat(n, 1)
    backend.reset(None, qpos, torch.zeros(n, model.nv, dtype=torch.float64))
    ctrl = torch.tensor(go2.default_joint_positions(), dtype=torch.float64).repeat(n, 1)
    ctrl[:, [1, 4, 7, 10]] += 0.3  # thighs forward: a step response of the PD loop
    traj = []
    for _ in range(10):
        backend.step(ctrl.to(backend.ctrl.dtype))
        traj.append(backend.qpos.double().clone())
    traj = torch.stack(traj)
    qa = _adr(model, go2.ACTUATED_JOINTS, "q")
    assert (traj[:, 0] - traj[:, 2]).abs().max() < 1e-5  # identical parameters, identical physics
    assert (traj[:, 0][:, qa] - traj[:, 1][:, qa]).abs().max() > 0.02  # soft gains: a different response
    assert traj[-1, 3, 2] < traj[-1, 0, 2] - 1e-3  # the heavy trunk sags lower on the PD legs
    backend.close()


@pytest.mark.parametrize("kind", BACKENDS)
def test_push_acts_for_one_step(model, kind):
    n = 2
    backend = make_backend(kind, model, n, DECIMATION, "cpu")
    backend.reset(None, torch.from_numpy(model.key_qpos[0].copy()).repeat(n, 1), torch.zeros(n, model.nv))
    ctrl = torch.tensor(go2.default_joint_positions()).repeat(n, 1).to(backend.ctrl.dtype)
    backend.apply_force([1], go2.TRUNK_BODY, torch.tensor([[0.0, 60.0, 0.0]]))
    backend.step(ctrl)
    vy = backend.sensor("trunk_linvel_world")[:, 1].double()
    assert abs(vy[0]) < 0.01
    assert vy[1] > 0.05  # 60 N on ~15 kg for 0.02 s: ~0.08 m/s before friction
    backend.step(ctrl)
    backend.step(ctrl)
    vy_later = backend.qvel[:, 1].double()
    assert vy_later[1] < vy[1]  # the force was cleared: the push decays
    backend.close()


@pytest.mark.parametrize("kind", BACKENDS)
def test_gravity_per_env_tilts_only_that_env(model, kind):
    # The same stand in three worlds: gravity straight down, and tilted 5 deg towards +x and
    # towards -y. The tilted worlds roll downhill, the straight one stays.
    n = 3
    backend = make_backend(kind, model, n, DECIMATION, "cpu")
    backend.reset(None, torch.from_numpy(model.key_qpos[0].copy()).repeat(n, 1), torch.zeros(n, model.nv))
    g, a = 9.81, np.radians(5.0)
    tilted = [[g * np.sin(a), 0.0, -g * np.cos(a)], [0.0, -g * np.sin(a), -g * np.cos(a)]]
    backend.set_gravity([1, 2], torch.tensor(tilted))
    with pytest.raises(ValueError, match="gravity"):
        backend.set_gravity([0], torch.zeros(2, 3))
    ctrl = torch.tensor(go2.default_joint_positions()).repeat(n, 1).to(backend.ctrl.dtype)
    start = backend.qpos[:, 0:2].double().clone()
    for _ in range(25):  # 0.5 s
        backend.step(ctrl)
    moved = backend.qpos[:, 0:2].double() - start
    assert moved[0].abs().max() < 0.01
    assert moved[1, 0] > 0.05 and abs(moved[1, 1]) < 0.02
    assert moved[2, 1] < -0.005  # sideways the casters roll less freely, but downhill
    backend.close()


@pytest.mark.parametrize("kind", BACKENDS)
def test_action_latency_holds_the_previous_targets(model, kind):
    """step(ctrl, held, held_steps): env i applies held[i] for its first held_steps[i]
    substeps, then ctrl[i]. 0 substeps is a plain step with ctrl, `decimation` substeps a
    plain step with held, and in between differs from both; on the CPU backend it also
    matches an mj_step loop that switches targets after that many substeps."""
    n = 3
    qpos, qvel = _perturbed_stand(model, n, seed=3)
    held, ctrl = _targets(2, n, 0.15, seed=4)

    def one_step(targets, **latency) -> torch.Tensor:
        backend = make_backend(kind, model, n, DECIMATION, "cpu")
        backend.reset(None, qpos.to(backend.qpos.dtype), qvel.to(backend.qvel.dtype))
        if latency:
            latency["held"] = latency["held"].to(backend.ctrl.dtype)
        backend.step(targets.to(backend.ctrl.dtype), **latency)
        q = backend.qpos.clone().double()
        backend.close()
        return q

    with_ctrl, with_held = one_step(ctrl), one_step(held)
    q = one_step(ctrl, held=held, held_steps=torch.tensor([0, DECIMATION, 4]))
    torch.testing.assert_close(q[0], with_ctrl[0], atol=1e-9, rtol=0)
    torch.testing.assert_close(q[1], with_held[1], atol=1e-9, rtol=0)
    joints = _adr(model, go2.ACTUATED_JOINTS, "q")
    assert (q[2, joints] - with_ctrl[2, joints]).abs().max() > 1e-4
    assert (q[2, joints] - with_held[2, joints]).abs().max() > 1e-4
    if kind == "cpu":
        d = mujoco.MjData(model)
        d.qpos[:], d.qvel[:] = qpos[2].numpy(), qvel[2].numpy()
        for k in range(DECIMATION):
            d.ctrl[:] = (held if k < 4 else ctrl)[2].numpy()
            mujoco.mj_step(model, d)
        np.testing.assert_allclose(q[2].numpy(), d.qpos, atol=2e-4, rtol=0)


@pytest.mark.parametrize("kind", BACKENDS)
def test_delayed_state_is_the_state_that_many_substeps_back(model, kind):
    """delayed_state(steps) after keep_substep_states(): 0 gives the current state, `decimation`
    the state the step began from, and k in between the state after decimation - k substeps
    (what a backend stepping only that many substeps reaches). Without keep_substep_states a
    delay is refused, and a step count outside [0, decimation] too."""
    n, lag = 3, 4
    qpos, qvel = _perturbed_stand(model, n, seed=5)
    (ctrl,) = _targets(1, n, 0.15, seed=6)

    def stepped(decimation: int, keep: bool):
        backend = make_backend(kind, model, n, decimation, "cpu")
        if keep:
            backend.keep_substep_states()
        backend.reset(None, qpos.to(backend.qpos.dtype), qvel.to(backend.qvel.dtype))
        backend.step(ctrl.to(backend.ctrl.dtype))
        return backend

    backend = stepped(DECIMATION, keep=True)
    q, v = backend.delayed_state(torch.tensor([0, DECIMATION, lag]))
    torch.testing.assert_close(q[0], backend.qpos[0])
    torch.testing.assert_close(v[0], backend.qvel[0])
    torch.testing.assert_close(q[1].double(), qpos[1], atol=1e-6, rtol=0)
    torch.testing.assert_close(v[1].double(), qvel[1], atol=1e-6, rtol=0)
    shorter = stepped(DECIMATION - lag, keep=False)
    torch.testing.assert_close(q[2], shorter.qpos[2], atol=1e-6, rtol=0)
    torch.testing.assert_close(v[2], shorter.qvel[2], atol=1e-4, rtol=0)
    assert (q[2] - backend.qpos[2]).abs().max() > 1e-4  # the lag is not the present
    with pytest.raises(ValueError, match=r"\[0, 10\]"):
        backend.delayed_state(torch.tensor([0, DECIMATION + 1, 0]))
    shorter.close()
    plain = stepped(DECIMATION, keep=False)
    with pytest.raises(RuntimeError, match="keep_substep_states"):
        plain.delayed_state(torch.tensor([0, 1, 0]))
    q0, _ = plain.delayed_state(torch.zeros(n, dtype=torch.long))
    torch.testing.assert_close(q0, plain.qpos)
    for b in (backend, plain):
        b.close()
