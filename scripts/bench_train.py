"""Where a training iteration's time goes, against the physics ceiling measured in the same run.

    python scripts/bench_train.py                                  # caster_omni, its defaults, 8 iterations
    python scripts/bench_train.py --iterations 12 --torch-threads 1
    python scripts/bench_train.py --train-set policy.actor_hidden_dims=[512,256,128]

Three phases, one process, the task's default env count and backend:

1. **Ceilings.** (a) `standing`: a bare multi-threaded `mujoco.rollout` of the nominal
   model from the stand keyframe with constant controls (scripts/bench_sim.py's
   ceiling, what `scripts/bench_env.py` divides by). (b) `call pattern`: the same
   standing robots stepped the way the CPU backend calls the simulator (a model copy per
   env, `decimation` steps per call, every substep's state and sensors written out), so
   (a) / (b) is what the env's use of `mujoco.rollout` costs before any robot moves.
   (c) `same work`: the time the env's
   own `mujoco.rollout` calls take inside phases 2 and 3, i.e. the simulator alone on
   exactly the states and controls the env produced (robots in motion have more
   contacts and solver iterations than standing ones, so (c) is the fair ceiling).
2. **Env alone**: `env.step` with random actions (N(0, 0.5)) for `--env-seconds`.
3. **Training**: rsl_rl's OnPolicyRunner with the task's train config (as train.py
   builds it, no log folder) for `--iterations` iterations; the first `--warmup` are
   not counted. Collection is split into physics, the env's Python work and the
   policy (inference, storage); the update is PPO's. The periodic deterministic
   evaluation (train.py --eval_every, default 25) is timed once and its share of a
   training run at that period is added.

Every rate is env steps per second (one env step = one policy step of one robot =
`decimation` physics steps) and every ratio is against the ceilings of this run.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from rsl_rl.runners import OnPolicyRunner

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sim import ceiling  # noqa: E402

from legged_casters import registry  # noqa: E402
from legged_casters.envs.base import set_timestep  # noqa: E402
from legged_casters.robot.build import MODEL_FILES  # noqa: E402
from legged_casters.sim.base import physics_model  # noqa: E402
from legged_casters.tools import common  # noqa: E402


class Timer:
    """Accumulated wall time of a wrapped callable."""

    def __init__(self, fn):
        self.fn, self.seconds, self.calls = fn, 0.0, 0

    def __call__(self, *args, **kwargs):
        t0 = time.perf_counter()
        try:
            return self.fn(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - t0
            self.calls += 1

    def reset(self) -> None:
        self.seconds, self.calls = 0.0, 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="caster_omni")
    p.add_argument("--num-envs", type=int, help="default: the env's (512 on the CPU backend)")
    p.add_argument("--iterations", type=int, default=8, help="training iterations timed (after --warmup)")
    p.add_argument("--warmup", type=int, default=2, help="training iterations run first and not counted")
    p.add_argument("--env-seconds", type=float, default=8.0, help="seconds of env-alone stepping")
    p.add_argument("--torch-threads", type=int, help="as train.py --torch_threads (default: train.py's)")
    p.add_argument("--eval-every", type=int, default=25, help="train.py's --eval_every, for the evaluation share")
    p.add_argument("--set", dest="env_set", action="append", default=[], metavar="KEY=VALUE", help="env override")
    p.add_argument("--train-set", action="append", default=[], metavar="KEY=VALUE", help="train config override")
    args = p.parse_args(argv)

    spec = registry.get_task(args.task)
    env_set = list(args.env_set) + ([f"num_envs={args.num_envs}"] if args.num_envs else [])
    env_cfg, train_cfg = registry.task_configs(args.task, env_set, args.train_set)
    common.limit_cpu_threads("cpu", args.torch_threads)
    print(f"[bench_train] {args.task}, torch threads {torch.get_num_threads()}", flush=True)

    env = spec.env_class(env_cfg)
    n, dec = env.num_envs, env.cfg.sim.decimation
    physics = Timer(env.sim.step)
    env.sim.step = physics
    env_step = Timer(env.step)

    # --- 1a. the standing ceiling ------------------------------------------------------------
    model = physics_model(MODEL_FILES[env_cfg.robot])
    if env_cfg.sim.timestep is not None:
        set_timestep(model, env_cfg.sim.timestep)
    standing = ceiling(model, n, 20 * dec, 3.0) / dec
    print(f"[bench_train] standing ceiling: {standing:,.0f} env steps/s ({n} envs)", flush=True)
    pattern = ceiling(model, n, dec, 3.0, call_pattern=True) / dec
    print(f"[bench_train] the env's call pattern, standing: {pattern:,.0f} env steps/s", flush=True)

    # --- 2. env alone ------------------------------------------------------------------------
    gen = torch.Generator().manual_seed(0)
    for _ in range(3):
        env.step(torch.randn(n, env.num_actions, generator=gen) * 0.5)
    physics.reset()
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < args.env_seconds:
        env_step(torch.randn(n, env.num_actions, generator=gen) * 0.5)
        steps += 1
    env_wall = time.perf_counter() - t0
    env_rate = n * steps / env_wall
    env_ceiling = n * steps / physics.seconds
    print(
        f"[bench_train] env alone: {env_rate:,.0f} env steps/s; its physics alone {env_ceiling:,.0f} "
        f"({physics.seconds / env_wall:.0%} of the time)",
        flush=True,
    )

    # --- 3. training -------------------------------------------------------------------------
    env.reset()
    cfg = train_cfg.for_env(env)
    runner = OnPolicyRunner(env, cfg, log_dir=None, device="cpu")
    env.step = env_step  # the runner steps the env through this wrapper
    rows: list[dict] = []

    def log(**kw):  # replaces rsl_rl's console report: the numbers are collected here
        rows.append(
            {
                "collect": kw["collect_time"],
                "learn": kw["learn_time"],
                "physics": physics.seconds,
                "env": env_step.seconds,
            }
        )
        physics.reset()
        env_step.reset()

    runner.logger.log = log
    physics.reset()
    env_step.reset()
    total = args.warmup + args.iterations
    print(f"[bench_train] training {total} iterations ({args.warmup} not counted) ...", flush=True)
    runner.learn(num_learning_iterations=total, init_at_random_ep_len=True)
    timed = rows[args.warmup :]
    steps_per_it = cfg["num_steps_per_env"] * n

    def mean(key: str) -> float:
        return statistics.mean(r[key] for r in timed)

    collect, learn, phys, env_total = mean("collect"), mean("learn"), mean("physics"), mean("env")

    eval_s = 0.0
    if args.eval_every:
        from legged_casters.tools.evaluate import DeterministicEval

        evaluator = DeterministicEval(spec, env_cfg)
        t0 = time.perf_counter()
        evaluator(runner.alg.get_policy())
        eval_s = time.perf_counter() - t0
        evaluator.close()
    eval_per_it = eval_s / args.eval_every if args.eval_every else 0.0
    it_time = collect + learn + eval_per_it
    train_rate = steps_per_it / it_time
    same_work = steps_per_it / phys  # the rollout calls of training's own collection

    print()
    print(f"caster physics ceilings ({n} envs, decimation {dec}, torch threads {torch.get_num_threads()}):")
    print(f"  standing, constant control:          {standing:>10,.0f} env steps/s")
    print(f"  the env's call pattern, standing:    {pattern:>10,.0f} env steps/s "
          f"({pattern / standing:.2f}: a model per env, {dec} steps per call, outputs)")  # fmt: skip
    print(f"  same work (the env's rollout calls): {env_ceiling:>10,.0f} env steps/s (env alone, random actions)")
    print(f"                                       {same_work:>10,.0f} env steps/s (training's collection)")
    print()
    print("| measured | env steps/s | vs standing ceiling | vs call-pattern ceiling | vs same-work ceiling |")
    print("|---|---:|---:|---:|---:|")
    rows_out = [
        ("env alone (random actions)", env_rate, env_ceiling),
        ("collection only", steps_per_it / collect, same_work),
        ("training (collection + update + evaluation)", train_rate, same_work),
    ]
    for name, rate, work in rows_out:
        print(f"| {name} | {rate:,.0f} | {rate / standing:.2f} | {rate / pattern:.2f} | {rate / work:.2f} |")
    print()
    print(f"where one training iteration's {it_time:.2f} s go ({steps_per_it:,} env steps):")
    parts = [
        ("physics (mujoco.rollout)", phys),
        ("env Python work (obs, rewards, resets)", env_total - phys),
        ("policy inference + storage", collect - env_total),
        ("PPO update", learn),
        (f"evaluation ({eval_s:.1f} s every {args.eval_every} it)", eval_per_it),
    ]
    print("| part | s/it | share |")
    print("|---|---:|---:|")
    for name, seconds in parts:
        print(f"| {name} | {seconds:.3f} | {seconds / it_time:.0%} |")
    env.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
