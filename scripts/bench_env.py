"""Env steps per second of the registered tasks against the physics ceiling.

    python scripts/bench_env.py                                   # both tasks, CPU backend, several sizes
    python scripts/bench_env.py --tasks caster_omni --num-envs 256,1024 --backends cpu,warp

One env step = a policy step: random actions, `decimation` physics steps, every
observation, reward term, termination check and the resets they trigger. The
ceiling is a bare multi-threaded `mujoco.rollout` of the same model and env count
with constant controls (scripts/bench_sim.py), divided by the decimation.
"""

from __future__ import annotations

import argparse
import sys
import time

import torch

from legged_casters import registry
from legged_casters.envs.base import set_timestep
from legged_casters.robot.build import MODEL_FILES
from legged_casters.sim.base import physics_model

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from bench_sim import ceiling  # noqa: E402


def bench(task: str, backend: str, num_envs: int, min_time: float, steps: int) -> tuple[float, int]:
    env = registry.make_env(task, [f"sim.backend={backend}"], num_envs=num_envs)
    gen = torch.Generator(device=env.device).manual_seed(0)
    actions = lambda: torch.randn(num_envs, env.num_actions, generator=gen, device=env.device) * 0.5  # noqa: E731
    for _ in range(3):
        env.step(actions())
    done, n, t0 = 0, 0, time.perf_counter()
    while n < steps or time.perf_counter() - t0 < min_time:
        _, _, dones, _ = env.step(actions())
        done += int(dones.sum())
        n += 1
    if env.device.type == "cuda":
        torch.cuda.synchronize()
    rate = num_envs * n / (time.perf_counter() - t0)
    env.close()
    return rate, done


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", default="go2_flat,caster_omni")
    p.add_argument("--backends", default="cpu")
    p.add_argument("--num-envs", default="64,256,1024,2048")
    p.add_argument("--min-time", type=float, default=3.0, help="seconds per measurement")
    p.add_argument("--steps", type=int, default=20)
    args = p.parse_args(argv)
    sizes = [int(x) for x in args.num_envs.split(",")]
    rows = []
    for task in args.tasks.split(","):
        spec = registry.get_task(task)
        model = physics_model(MODEL_FILES[spec.env_cfg.robot])
        if spec.env_cfg.sim.timestep is not None:  # the task's physics step (caster_omni: 5 ms)
            set_timestep(model, spec.env_cfg.sim.timestep)
        decimation = spec.env_cfg.sim.decimation
        for backend in args.backends.split(","):
            for n in sizes:
                print(f"{task} {backend} {n} envs ...", flush=True)
                rate, resets = bench(task, backend, n, args.min_time, args.steps)
                ceil = ceiling(model, n, 20 * decimation, args.min_time) / decimation
                rows.append((task, backend, n, rate, ceil, resets))
                print(f"  {rate:,.0f} env steps/s, ceiling {ceil:,.0f}, ratio {rate / ceil:.2f}, resets {resets}")
    print("\n| task | backend | envs | env steps/s | ceiling steps/s | ratio |")
    print("|---|---|---:|---:|---:|---:|")
    for task, backend, n, rate, ceil, _ in rows:
        print(f"| {task} | {backend} | {n} | {rate:,.0f} | {ceil:,.0f} | {rate / ceil:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
