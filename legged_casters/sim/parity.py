"""MuJoCo Warp against MuJoCo C on the same starts and PD targets: the measures of the
backend parity test (tests/test_sim_backends.py), shared with the GPU check
(dev/gpu_loan/gpu_check.py, the lent-GPU check), which runs them with Warp on CUDA."""

from __future__ import annotations

import mujoco
import torch

from legged_casters.robot import go2
from legged_casters.sim.base import make_backend

DECIMATION = 10
BOUNDS = {
    "trunk_pos": 1e-5,
    "trunk_quat": 1e-5,
    "joint_pos": 5e-5,
    "joint_vel": 2e-3,
    "qpos": 1e-3,
    "qvel": 2e-2,
}
"""Largest |Warp - C| accepted over 25 control steps of the caster robot (4 envs, targets
nominal + N(0, 0.05 rad)): >= 20x what was measured with Warp on the CPU device."""


def joint_addresses(m: mujoco.MjModel, joints, kind: str) -> list[int]:
    table = m.jnt_qposadr if kind == "q" else m.jnt_dofadr
    return [int(table[m.joint(j).id]) for j in joints]


def perturbed_stand(m: mujoco.MjModel, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The "stand" keyframe with joint angles + N(0, 0.01 rad) and joint velocities N(0, 0.05 rad/s)."""
    g = torch.Generator().manual_seed(seed)
    qpos = torch.from_numpy(m.key_qpos[0].copy()).repeat(n, 1)
    qvel = torch.zeros(n, m.nv, dtype=torch.float64)
    qpos[:, joint_addresses(m, go2.ACTUATED_JOINTS, "q")] += 0.01 * torch.randn(n, 12, generator=g, dtype=torch.float64)
    qvel[:, joint_addresses(m, go2.ACTUATED_JOINTS, "v")] = 0.05 * torch.randn(n, 12, generator=g, dtype=torch.float64)
    return qpos, qvel


def random_targets(steps: int, n: int, std: float, seed: int) -> torch.Tensor:
    """(steps, n, 12) PD targets: the nominal pose + N(0, std)."""
    g = torch.Generator().manual_seed(seed)
    nominal = torch.tensor(go2.default_joint_positions(), dtype=torch.float64)
    return nominal + std * torch.randn(steps, n, 12, generator=g, dtype=torch.float64)


def rollout(backend, qpos, qvel, targets) -> tuple[torch.Tensor, torch.Tensor]:
    """(steps + 1, n, nq) positions and (steps + 1, n, nv) velocities, float64 on the CPU."""
    backend.reset(None, qpos, qvel)
    qs, vs = [backend.qpos.double().cpu().clone()], [backend.qvel.double().cpu().clone()]
    for ctrl in targets:
        backend.step(ctrl.to(backend.device, backend.ctrl.dtype))
        qs.append(backend.qpos.double().cpu().clone())
        vs.append(backend.qvel.double().cpu().clone())
    return torch.stack(qs), torch.stack(vs)


def parity_errors(
    model: mujoco.MjModel, n: int = 4, steps: int = 25, warp_device: str = "cpu", std: float = 0.05
) -> dict[str, float]:
    """Roll both backends from the same perturbed stand (seed 0) with the same random
    targets (seed 3); return the largest |difference| of each measure in BOUNDS, plus
    `moved` (how far the C trajectory's joints went: the robots are not standing still),
    `finite` (both trajectories finite), `contact_overflow` (Warp's buffers ran out),
    `worlds_outside` (how many of the n robots exceed any bound) and `worst_dof` (the
    joint whose velocity differs most, with the robot it does so in)."""
    qpos, qvel = perturbed_stand(model, n, seed=0)
    targets = random_targets(steps, n, std, seed=3)
    cpu = make_backend("cpu", model, n, DECIMATION)
    try:
        qc, vc = rollout(cpu, qpos, qvel, targets)
    finally:
        cpu.close()
    warp = make_backend("warp", model, n, DECIMATION, warp_device)
    try:
        qw, vw = rollout(warp, qpos, qvel, targets)
        overflow = bool(warp.contact_overflow())
    finally:
        warp.close()
    qa = joint_addresses(model, go2.ACTUATED_JOINTS, "q")
    va = joint_addresses(model, go2.ACTUATED_JOINTS, "v")
    dq, dv = (qc - qw).abs(), (vc - vw).abs()
    per_world = {  # (n,) largest difference of each measure in each robot
        "trunk_pos": dq[:, :, 0:3].amax(dim=(0, 2)),
        "trunk_quat": dq[:, :, 3:7].amax(dim=(0, 2)),
        "joint_pos": dq[:, :, qa].amax(dim=(0, 2)),
        "joint_vel": dv[:, :, va].amax(dim=(0, 2)),
        "qpos": dq.amax(dim=(0, 2)),
        "qvel": dv.amax(dim=(0, 2)),
    }
    outside = torch.zeros(n, dtype=torch.bool)
    for name, bound in BOUNDS.items():
        outside |= per_world[name] >= bound
    world = int(per_world["qvel"].argmax())
    dof = int(dv[:, world].amax(dim=0).argmax())
    joint = int(model.dof_jntid[dof])
    return {
        **{name: float(per_world[name].max()) for name in BOUNDS},
        "moved": float((qc[:, :, qa] - qc[0, :, qa]).abs().max()),
        "finite": bool(torch.isfinite(qc).all() and torch.isfinite(qw).all()),
        "contact_overflow": overflow,
        "worlds_outside": int(outside.sum()),
        "worst_dof": f"{model.joint(joint).name} (robot {world})",
    }
