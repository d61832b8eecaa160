"""Throughput of the simulation backends against the raw `mujoco.rollout` ceiling.

    PYTHONPATH=. python scripts/bench_sim.py                       # defaults below
    PYTHONPATH=. python scripts/bench_sim.py --backends cpu --cpu-envs 64,256

For each backend and num_envs: reset all envs to the "stand" keyframe, then time
at least `--steps` control steps (and at least `--min-time` s) with random PD
targets (nominal pose + N(0, action_std)), resetting all envs every `--reset-every`
control steps (resets are not timed). The ceiling is `mujoco.rollout` on the same
number of envs with constant (nominal) controls, all threads, calls of
steps * decimation physics steps (repeated for `--min-time` s), no outputs copied:
the physics alone. Reported: physics world-steps/s, control steps/s (env-steps/s,
i.e. world-steps/s divided by decimation) and backend / ceiling.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time

import mujoco
import mujoco.rollout
import numpy as np
import torch

from legged_casters.robot import go2
from legged_casters.robot.build import MODEL_FILES
from legged_casters.sim.base import make_backend, physics_model, usable_cpus


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x]


def ceiling(model: mujoco.MjModel, num_envs: int, nstep: int, min_time: float, *, call_pattern: bool = False) -> float:
    """Physics world-steps per second of a bare multi-threaded rollout of the stand keyframe.

    `call_pattern=True` makes the calls the CPU backend makes (legged_casters/sim/cpu.py):
    one model copy per env, `nstep` steps per call, every substep's state and sensor
    values written out, a warmstart passed in. The states stay the standing ones, so
    what this adds to the plain ceiling is the cost of the way the env calls the
    simulator, not of what its robots do.
    """
    nthread = usable_cpus()  # as many threads as the CPU backend's pool
    data = [mujoco.MjData(model) for _ in range(nthread)]
    d0 = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, d0, 0)
    state0 = np.empty(mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS))
    mujoco.mj_getState(model, d0, state0, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    initial = np.tile(state0, (num_envs, 1))
    control = np.tile(model.key_ctrl[0], (num_envs, nstep, 1))
    outputs = {}
    if call_pattern:
        models = [copy.copy(model) for _ in range(num_envs)]
        outputs = {
            "state": np.empty((num_envs, nstep, state0.size)),
            "sensordata": np.empty((num_envs, nstep, model.nsensordata)),
            "initial_warmstart": np.zeros((num_envs, model.nv)),
        }
    else:
        models = [model] * num_envs
    with mujoco.rollout.Rollout(nthread=nthread) as pool:
        pool.rollout(models, data, initial[:, :], control[:, :1], nstep=1)  # warm the pool
        calls, t0 = 0, time.perf_counter()
        while calls == 0 or time.perf_counter() - t0 < min_time:
            pool.rollout(models, data, initial, control, skip_checks=True, nstep=nstep, **outputs)
            calls += 1
        elapsed = time.perf_counter() - t0
    return calls * num_envs * nstep / elapsed


def bench_backend(kind: str, model, num_envs: int, args, device: str) -> tuple[float, float]:
    """(physics world-steps/s, control env-steps/s) of one backend."""
    t0 = time.perf_counter()
    backend = make_backend(kind, model, num_envs, args.decimation, device)
    dev = backend.device
    q0 = torch.as_tensor(model.key_qpos[0], device=dev).repeat(num_envs, 1)
    v0 = torch.zeros(num_envs, model.nv, device=dev)
    nominal = torch.as_tensor(go2.default_joint_positions(), device=dev)
    gen = torch.Generator(device=dev).manual_seed(0)

    def targets() -> torch.Tensor:
        noise = torch.randn(num_envs, model.nu, generator=gen, device=dev)
        return (nominal + args.action_std * noise).to(backend.ctrl.dtype)

    backend.reset(None, q0, v0)
    for _ in range(args.warmup):  # Warp compiles kernels / captures graphs here
        backend.step(targets())
    print(f"    setup + {args.warmup} warm-up steps: {time.perf_counter() - t0:.1f} s", flush=True)
    elapsed = 0.0
    unstable = torch.zeros(num_envs, dtype=torch.bool, device=dev)
    i = 0
    while i < args.steps or elapsed < args.min_time:
        if i % args.reset_every == 0:
            backend.reset(None, q0, v0)
        ctrl = targets()
        if dev.type == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        backend.step(ctrl)
        if dev.type == "cuda":
            torch.cuda.synchronize()
        elapsed += time.perf_counter() - t
        unstable |= ~torch.isfinite(backend.qvel).all(dim=1) | (backend.qvel.abs().amax(dim=1) > 1e3)
        i += 1
        if i % max(1, args.steps // 4) == 0:
            print(f"    {i} control steps, {elapsed:.1f} s", flush=True)
    print(f"    envs that diverged (|qvel| > 1e3 or non-finite) at some step: {int(unstable.sum())}/{num_envs}")
    backend.close()
    control_rate = num_envs * i / elapsed
    return control_rate * args.decimation, control_rate


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--backends", default="cpu,warp")
    p.add_argument("--feet", default="caster", choices=tuple(MODEL_FILES))
    p.add_argument("--cpu-envs", type=_ints, default=[64, 256, 1024, 4096])
    p.add_argument("--warp-envs", type=_ints, default=None, help="default: 1024,4096,16384 on CUDA, 8 on CPU")
    p.add_argument("--decimation", type=int, default=10)
    p.add_argument("--steps", type=int, default=20, help="timed control steps per configuration")
    p.add_argument("--warp-cpu-steps", type=int, default=5, help="timed control steps for Warp on the CPU device")
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--min-time", type=float, default=1.0, help="s; each measurement runs at least this long")
    p.add_argument("--reset-every", type=int, default=25)
    p.add_argument("--action-std", type=float, default=0.05, help="rad, around the nominal pose")
    p.add_argument("--skip-warp-on-cpu", action="store_true")
    p.add_argument(
        "--impratio",
        type=float,
        default=None,
        help="override opt.impratio (to compare contact settings)",
    )
    args = p.parse_args(argv)

    model = physics_model(MODEL_FILES[args.feet])
    if args.impratio is not None:
        model.opt.impratio = args.impratio
    cuda = torch.cuda.is_available()
    print(
        f"model {args.feet}: nq={model.nq} nv={model.nv} nu={model.nu}, dt={model.opt.timestep} s, "
        f"impratio {model.opt.impratio:g}, decimation {args.decimation}; {usable_cpus()} CPU threads; CUDA: {cuda}",
        flush=True,
    )
    rows = []
    for kind in args.backends.split(","):
        if kind == "cpu":
            envs, device, steps = args.cpu_envs, "cpu", args.steps
        elif kind == "warp":
            if not cuda and args.skip_warp_on_cpu:
                print("warp: skipped (no CUDA, --skip-warp-on-cpu)", flush=True)
                continue
            envs = args.warp_envs or ([1024, 4096, 16384] if cuda else [8])
            device = "cuda:0" if cuda else "cpu"
            steps = args.steps if cuda else args.warp_cpu_steps
        else:
            raise SystemExit(f"unknown backend {kind!r}")
        for n in envs:
            print(f"[{kind} on {device}] num_envs={n}", flush=True)
            sub = argparse.Namespace(**{**vars(args), "steps": steps})
            phys, ctrl = bench_backend(kind, model, n, sub, device)
            print(f"    ceiling: rollout of {n} envs x {steps * args.decimation} steps", flush=True)
            ceil = ceiling(model, n, steps * args.decimation, args.min_time)
            rows.append((f"{kind} ({device})", n, phys, ctrl, ceil / args.decimation, ctrl / (ceil / args.decimation)))

    cols = ("physics steps/s", "control steps/s", "ceiling ctrl/s")
    header = f"{'backend':<14} {'envs':>6} {cols[0]:>16} {cols[1]:>16} {cols[2]:>15} {'ratio':>6}"
    print("\n" + header)
    print("-" * len(header))
    for name, n, phys, ctrl, ceil, ratio in rows:
        print(f"{name:<14} {n:>6} {phys:>16,.0f} {ctrl:>16,.0f} {ceil:>15,.0f} {ratio:>6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
