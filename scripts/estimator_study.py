"""How well can proprioception tell the trunk velocity? Regress it from L steps of history.

    python scripts/estimator_study.py --load_run logs/caster_omni/<run> --checkpoint 442
    python scripts/estimator_study.py --load_run <run> --lengths 1,10,25,50 --steps 600

Runs the run's policy (stochastic, as in training: the run's own env.yaml with its noise,
pushes and randomisation) on `--num-envs` robots for `--steps` policy steps and records
what the robot measures (the policy observation's proprioceptive terms, noise included,
and the command/mode) and the simulator's trunk velocity. Then, for each history length
L, it trains a fresh MLP ([128, 64], the estimator's size) on 80 % of the windows that
contain no reset and prints its RMS error on the other 20 %. It answers whether a longer
history (or another input) could give a better estimator before a run is spent on it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from legged_casters import registry
from legged_casters.tools import common, export


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--load_run", required=True, help="a caster_omni run folder")
    p.add_argument("--checkpoint", required=True, help="iteration or file in that run")
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--steps", type=int, default=600)
    p.add_argument("--lengths", default="1,10,25,50", help="history lengths L (policy steps)")
    p.add_argument("--epochs", type=int, default=15)
    args = p.parse_args(argv)
    lengths = [int(x) for x in args.lengths.split(",")]
    if max(lengths) >= args.steps // 2:
        p.error("--steps must be more than twice the longest history length")
    torch.set_num_threads(1)
    torch.manual_seed(0)
    run = Path(args.load_run)
    spec = registry.get_task("caster_omni")
    env_cfg, train_cfg = common.run_configs(spec, run)
    env_cfg = common.with_overrides(env_cfg, {"num_envs": args.num_envs, "sim.backend": "cpu", "sim.device": "cpu"}, "")
    ckpt_path = common.find_checkpoint(run, args.checkpoint)
    env = spec.env_class(env_cfg)
    actor = export.load_actor(env, train_cfg, common.load_checkpoint(ckpt_path, map_location="cpu"), ckpt_path)
    cols = env.policy_obs_columns()
    start, stop, cmd_stop = cols["ang_vel"][0], cols["actions"][1], cols["ang_vel"][0]
    obs = env.get_observations()
    proprio, vel, cmds, dones = [], [], [], []
    t0 = time.time()
    for _ in range(args.steps):
        with torch.no_grad():
            act = actor(obs, stochastic_output=True)
        proprio.append(obs["policy"][:, start:stop].clone())
        cmds.append(obs["policy"][:, :cmd_stop].clone())
        vel.append(env.base_lin_vel.clone())
        obs, _, done, _ = env.step(act)
        dones.append(done.clone())
    env.close()
    print(f"[estimator_study] {args.steps} steps x {args.num_envs} robots in {time.time() - t0:.0f} s", flush=True)
    proprio, vel, cmds, dones = (torch.stack(x, 1) for x in (proprio, vel, cmds, dones))
    longest = max(lengths)
    print("| history L (steps) | windows | RMS of the velocity error (m/s) | vx | vy | std of vx |")
    print("|---:|---:|---:|---:|---:|---:|")
    for L in lengths:
        xs, ys = [], []
        for t in range(longest + 1, args.steps):
            ok = ~dones[:, t - L : t].any(1)  # a reset inside the window: its history restarted
            window = proprio[:, t - L + 1 : t + 1].flip(1).reshape(args.num_envs, -1)
            xs.append(torch.cat([window, cmds[:, t]], 1)[ok])
            ys.append(vel[:, t][ok])
        x, y = torch.cat(xs), torch.cat(ys)
        idx = torch.randperm(len(x))
        train, val = idx[: int(0.8 * len(x))], idx[int(0.8 * len(x)) :]
        mu, sd = x[train].mean(0), x[train].std(0) + 1e-3
        x = (x - mu) / sd
        net = torch.nn.Sequential(
            torch.nn.Linear(x.shape[1], 128), torch.nn.ELU(), torch.nn.Linear(128, 64), torch.nn.ELU(),
            torch.nn.Linear(64, 3),
        )  # fmt: skip
        opt = torch.optim.Adam(net.parameters(), 1e-3)
        for _ in range(args.epochs):
            perm = train[torch.randperm(len(train))]
            for i in range(0, len(perm), 1024):
                j = perm[i : i + 1024]
                loss = torch.nn.functional.mse_loss(net(x[j]), y[j])
                opt.zero_grad()
                loss.backward()
                opt.step()
        with torch.no_grad():
            err = net(x[val]) - y[val]
        rms = float(err.pow(2).sum(1).mean().sqrt())
        rx, ry = (float(err[:, i].pow(2).mean().sqrt()) for i in (0, 1))
        print(f"| {L} | {len(x)} | {rms:.3f} | {rx:.3f} | {ry:.3f} | {float(y[val, 0].std()):.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
