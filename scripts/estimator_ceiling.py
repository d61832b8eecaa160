"""How well can the trunk velocity be estimated from what the robot measures? An offline study.

    python scripts/estimator_ceiling.py                      # the shipped caster_omni, ~5 min on 2 cores
    python scripts/estimator_ceiling.py --policy resources/policies/caster_omni --envs 128 --seconds 20

The speed-control issue asks for a velocity estimate within 0.1 m/s RMS. The estimator
inside the actor is trained next to PPO on each rollout; this script asks what any
estimator fed the same inputs could reach with far more data and fitting, and what an
accelerometer would add. (`scripts/estimator_study.py` asks the same of history lengths,
from a training run's checkpoint; this one needs only an exported policy.)

1. Rollout: the exported policy (deterministic actor plus Gaussian action noise
   `--action-noise`, so that the data spans more than one gait) in its own env.yaml's
   env (training noise and randomisation on), commands drawn over vx [-2, 2] m/s,
   vy [-0.6, 0.6] m/s and the training's wz every `commands.resampling_time`. Recorded
   each control step: the policy observation, the trunk velocity (trunk frame, the
   target), the export's own estimate, and an ideal accelerometer: the specific force
   (dv/dt - g) in the trunk frame, from the trunk's world velocity over the control step.
2. Fits on 80 % of the robots, RMS error (m/s, 3-vector) on the other 20 %, overall and
   per speed band, leaving out the first 0.3 s of each episode:
   - `export`: the policy's own estimator, no fit;
   - `mlp`: an MLP (256, 128) on the whole policy observation (the estimator's input,
     proprioceptive history included), Adam for `--epochs` passes;
   - `mlp+acc`: the same plus the last 10 accelerometer readings;
   - `gru+acc`: a GRU (64) over each episode from its start, fed the current terms and
     the accelerometer: it may integrate the acceleration from a known start.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from legged_casters.tools import common
from legged_casters.tools import evaluate as ev
from legged_casters.utils.math import quat_rotate_inverse

BANDS = ((0.0, 0.3), (0.3, 0.8), (0.8, 1.5), (1.5, 99.0))
"""Trunk speed bands (m/s, horizontal) of the per-band RMS."""
WARMUP_S = 0.3
"""Each episode's first seconds are left out of fits and scores (the history is refilling)."""


def rollout(policy_dir: Path, envs: int, seconds: float, noise: float, seed: int) -> dict:
    task, spec, env_cfg, policy, _, _ = ev.load_exported(policy_dir, None)
    overrides = {
        "num_envs": envs, "sim.backend": "cpu", "sim.device": "cpu", "seed": seed,
        "commands.ranges.lin_vel_x": [-2.0, 2.0], "commands.ranges.lin_vel_y": [-0.6, 0.6],
        "commands.curriculum": False,
    }  # fmt: skip
    env = spec.env_class(common.with_overrides(env_cfg, overrides, "estimator_ceiling env"))
    if policy.estimate is None:
        raise SystemExit(f"{policy_dir} has no velocity estimator to compare with")
    torch.manual_seed(seed)
    obs = env.reset()
    steps = int(round(seconds / env.dt))
    up = torch.tensor([0.0, 0.0, 9.81]).expand(envs, 3)
    rec = {k: [] for k in ("obs", "vel", "est", "acc", "done")}
    prev = env.base_lin_vel_world.clone()
    t0 = time.time()
    for k in range(steps):
        with torch.no_grad():
            actions = policy(obs)
            rec["est"].append(policy.estimate(obs))
        rec["obs"].append(obs["policy"].clone())
        rec["vel"].append(env.base_lin_vel.clone())
        obs, _, dones, _ = env.step(actions + noise * torch.randn_like(actions))
        vw = env.base_lin_vel_world.clone()
        rec["acc"].append(quat_rotate_inverse(env.base_quat, (vw - prev) / env.dt + up))
        rec["done"].append(dones.clone().bool())
        prev = vw
        if (k + 1) % 250 == 0:
            print(f"[estimator_ceiling] rollout {k + 1}/{steps} steps ({time.time() - t0:.0f} s)", flush=True)
    data = {k: torch.stack(v) for k, v in rec.items()}
    data["columns"] = env.policy_obs_columns()
    data["dt"] = env.dt
    env.close()
    return data


def valid_mask(done: torch.Tensor, warmup: int) -> torch.Tensor:
    """(T, n): steps at least `warmup` steps into their episode (a reset after step k starts one at k + 1)."""
    T, n = done.shape
    since = torch.zeros(n, dtype=torch.long)
    valid = torch.zeros(T, n, dtype=torch.bool)
    for k in range(T):
        valid[k] = since >= warmup
        since = torch.where(done[k], torch.zeros_like(since), since + 1)
    return valid


def rms_table(name: str, pred: torch.Tensor, vel: torch.Tensor, mask: torch.Tensor) -> str:
    err = (pred - vel).pow(2).sum(-1)
    speed = vel[..., :2].norm(dim=-1)
    cells = []
    for lo, hi in BANDS:
        m = mask & (speed >= lo) & (speed < hi)
        cells.append(f"{float(err[m].mean().sqrt()):.3f}" if m.any() else "-")
    return f"| {name} | {float(err[mask].mean().sqrt()):.3f} | " + " | ".join(cells) + " |"


def fit_mlp(x: torch.Tensor, vel: torch.Tensor, train: torch.Tensor, epochs: int) -> torch.Tensor:
    X, Y = x[train], vel[train]
    net = torch.nn.Sequential(
        torch.nn.Linear(X.shape[1], 256), torch.nn.ELU(), torch.nn.Linear(256, 128), torch.nn.ELU(),
        torch.nn.Linear(128, 3),
    )  # fmt: skip
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    for _ in range(epochs):
        for batch in torch.randperm(len(X)).split(4096):
            loss = (net(X[batch]) - Y[batch]).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    with torch.no_grad():
        return net(x.reshape(-1, x.shape[-1])).reshape(*x.shape[:2], 3)


def fit_gru(x, vel, done, valid, n_train: int, epochs: int, chunk: int = 50) -> torch.Tensor:
    """A GRU run over the whole rollout with its state reset at each episode's start,
    trained by truncated backpropagation through `chunk` steps (state carried across)."""
    T, n, _ = x.shape
    gru, head = torch.nn.GRU(x.shape[-1], 64), torch.nn.Linear(64, 3)
    opt = torch.optim.Adam([*gru.parameters(), *head.parameters()], lr=2e-3)
    keep = (~done).float()  # 0 where an episode ended: the next step starts from a zero state

    def run(rows, train: bool) -> torch.Tensor:
        h = torch.zeros(1, len(rows), 64)
        out = []
        for s in range(0, T, chunk):
            ys = []
            for k in range(s, min(T, s + chunk)):
                y, h = gru(x[k : k + 1, rows], h)
                ys.append(head(y[0]))
                h = h * keep[k, rows].view(1, -1, 1)
            ys = torch.stack(ys)
            if train:
                m = valid[s : s + len(ys), rows]
                loss = ((ys - vel[s : s + len(ys), rows]).pow(2).sum(-1) * m).sum() / m.sum().clamp(min=1)
                opt.zero_grad()
                loss.backward()
                opt.step()
                h = h.detach()
            out.append(ys.detach())
        return torch.cat(out)

    train_rows = torch.arange(n_train)
    for _ in range(epochs):
        run(train_rows, True)
    with torch.no_grad():
        return run(torch.arange(n), False)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", type=Path, default=Path("resources/policies/caster_omni"))
    ap.add_argument("--envs", type=int, default=256)
    ap.add_argument("--seconds", type=float, default=30.0, help="rollout length (s)")
    ap.add_argument("--action-noise", type=float, default=0.15, help="std of the Gaussian noise on the actions")
    ap.add_argument("--epochs", type=int, default=30, help="MLP passes over the data")
    ap.add_argument("--gru-epochs", type=int, default=20, help="GRU passes over the rollout")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.envs < 5 or args.seconds <= 2 * WARMUP_S or min(args.epochs, args.gru_epochs) < 1:
        ap.error("--envs must be >= 5, --seconds > 0.6 and the epochs >= 1")
    torch.set_num_threads(2)
    t0 = time.time()
    d = rollout(args.policy, args.envs, args.seconds, args.action_noise, args.seed)
    obs, vel, acc, done = d["obs"], d["vel"], d["acc"], d["done"]
    T, n, _ = obs.shape
    valid = valid_mask(done, int(round(WARMUP_S / d["dt"])))
    n_train = int(0.8 * n)
    train, test = valid.clone(), valid.clone()
    train[:, n_train:] = False
    test[:, :n_train] = False
    mu, sd = obs[train].mean(0), obs[train].std(0) + 1e-2
    obs_n = (obs - mu) / sd
    acc_n = torch.where(valid.unsqueeze(-1), acc, torch.zeros_like(acc)) / 5.0
    acc_hist = torch.cat([torch.cat([torch.zeros(i, n, 3), acc_n[: T - i]]) for i in range(10)], dim=-1)
    hist = d["columns"]["proprio_history"]
    current = torch.cat([obs_n[..., : hist[0]], obs_n[..., hist[1] :]], dim=-1)
    speed = vel[..., :2].norm(dim=-1)[test]
    print(f"[estimator_ceiling] {args.policy}: {T} steps x {n} robots ({time.time() - t0:.0f} s); test samples "
          "per band: " + ", ".join(f"{lo}-{hi} m/s {float(((speed >= lo) & (speed < hi)).float().mean()):.0%}"
                                   for lo, hi in BANDS), flush=True)  # fmt: skip
    rows = [rms_table("export (the policy's estimator)", d["est"], vel, test)]
    print(rows[-1], flush=True)
    rows.append(rms_table("mlp (the estimator's input)", fit_mlp(obs_n, vel, train, args.epochs), vel, test))
    print(rows[-1], flush=True)
    both = torch.cat([obs_n, acc_hist], dim=-1)
    rows.append(rms_table("mlp+acc (+ 10 accelerometer readings)", fit_mlp(both, vel, train, args.epochs), vel, test))
    print(rows[-1], flush=True)
    seq = torch.cat([current, acc_n], dim=-1)
    gru = fit_gru(seq, vel, done, valid, n_train, args.gru_epochs)
    rows.append(rms_table("gru+acc (from the episode start)", gru, vel, test))
    print(rows[-1], flush=True)
    bands = " | ".join(f"{lo}-{hi} m/s" if hi < 99 else f">= {lo} m/s" for lo, hi in BANDS)
    print(f"\n| estimator | test RMS (m/s) | {bands} |\n|---|---:|" + "---:|" * len(BANDS))
    print("\n".join(rows))
    print(f"[estimator_ceiling] {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
