"""Can the velocity estimator see a passive roll? Its observations with and without an accelerometer.

    python research/scripts/estimator_accel.py               # about 7 min on 2 cores
    python research/scripts/estimator_accel.py --envs 128 --seconds 20 --epochs 5   # a quick look

A rolling caster robot whose legs do not move gives its joint encoders, its gyro and its
gravity direction nothing to read: the shipped estimator, trained on the flat, says 0.03 m/s
while the robot rolls down 3 deg at 1.0 m/s (`scripts/evaluate.py`, "hold 3deg"). An IMU also
has an accelerometer. This study drives the shipped policy (resources/policies/caster_omni,
deterministic actor) through caster_omni_stop's conditions (commands with a quarter zero,
ground tilted up to 6 deg in 60 % of the episodes, pushes), records the policy observation,
the trunk's true body-frame velocity and what an accelerometer in the trunk would read (the
specific force, body frame, in g, from the trunk's velocity change over each control step),
and, beside the shipped estimator's own estimate, fits two estimators of the shipped
estimator's size on the same samples:

* A: the policy observation (current terms and 1 s of history), what the estimator reads now;
* B: the same and the last 50 control steps (1 s) of the accelerometer.

It prints the held-out RMS of vx overall, for a zero command on a slope, below 0.3 m/s, and in
the first second after a standing start on a slope under a zero command (where the velocity
is the change since rest, which the accelerometer's history holds).
A research probe: the deployed actor has no accelerometer input.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from legged_casters.tools import common
from legged_casters.tools.evaluate import load_exported
from legged_casters.utils.math import quat_rotate_inverse

G = 9.81


def collect(policy_dir: Path, envs: int, seconds: float, every: int, seed: int):
    """Roll the exported policy out; returns the policy observation, the accelerometer history,
    the true velocity, whether the command is zero, the slope (deg), the env and the shipped
    estimator's estimate per kept sample."""
    _, spec, env_cfg, policy, _, _ = load_exported(policy_dir, None)
    fields = {"num_envs": envs, "sim.backend": "cpu", "sim.device": "cpu", "seed": seed,
              "terrain.slope_deg": 6.0, "terrain.slope_fraction": 0.6, "commands.standing_fraction": 0.25}  # fmt: skip
    env = spec.env_class(common.with_overrides(env_cfg, fields, "estimator_accel env"))
    try:
        obs = env.reset()
        window = env.cfg.history_length  # the accelerometer's history as long as the estimator's
        hist = torch.zeros(envs, window, 3)
        v_prev = env.base_lin_vel_world.clone()
        names = ("obs", "acc", "vel", "zero", "slope", "env", "estimate", "age")
        age = torch.zeros(envs)  # control steps since the robot's (standing) start
        keep: dict[str, list[torch.Tensor]] = {k: [] for k in names}
        steps = int(round(seconds / env.dt))
        t0 = time.time()
        for k in range(steps):
            with torch.no_grad():
                estimate = policy.estimate(obs)  # the shipped estimator's, for this observation
                obs, _, dones, _ = env.step(policy(obs))
            v = env.base_lin_vel_world.clone()
            accel = (v - v_prev) / env.dt
            force = quat_rotate_inverse(env.base_quat, accel - G * env.gravity_dir) / G
            done = dones.bool()
            force[done] = quat_rotate_inverse(env.base_quat, -env.gravity_dir)[done]  # a fresh robot at rest
            hist = torch.cat([force.unsqueeze(1), hist[:, :-1]], dim=1)
            hist[done] = force[done].unsqueeze(1).expand(-1, window, -1)
            v_prev = v
            age = torch.where(done, torch.zeros_like(age), age + 1)
            if k >= window and k % every == 0:
                keep["obs"].append(obs["policy"].clone())
                keep["acc"].append(hist.reshape(envs, -1).clone())
                keep["vel"].append(env.base_lin_vel.clone())
                keep["zero"].append((env.commands == 0).all(dim=1))
                keep["slope"].append(env.ground_slope_deg())
                keep["env"].append(torch.arange(envs))
                keep["estimate"].append(estimate)
                keep["age"].append(age.clone())
            if k % 500 == 0:
                print(f"[estimator_accel] step {k}/{steps}, {time.time() - t0:.0f} s", flush=True)
        return {k: torch.cat(v) for k, v in keep.items()}
    finally:
        env.close()


def fit(x: torch.Tensor, y: torch.Tensor, train: torch.Tensor, epochs: int, seed: int) -> torch.nn.Module:
    """An MLP (128, 64, ELU, as the shipped estimator) on normalised inputs, Adam on the MSE."""
    torch.manual_seed(seed)
    mean, std = x[train].mean(0), x[train].std(0).clamp(min=1e-3)
    net = torch.nn.Sequential(
        torch.nn.Linear(x.shape[1], 128),
        torch.nn.ELU(),
        torch.nn.Linear(128, 64),
        torch.nn.ELU(),
        torch.nn.Linear(64, 3),
    )
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    idx = train.nonzero().flatten()
    for epoch in range(epochs):
        perm = idx[torch.randperm(len(idx))]
        total = 0.0
        for b in perm.split(2048):
            loss = torch.nn.functional.mse_loss(net((x[b] - mean) / std), y[b])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += loss.item() * len(b)
        print(
            f"[estimator_accel]   epoch {epoch + 1}/{epochs}: train RMS {(total / len(idx) * 3) ** 0.5:.3f} m/s",
            flush=True,
        )
    net.eval()
    return lambda z: net((z - mean) / std)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", default="resources/policies/caster_omni")
    ap.add_argument("--envs", type=int, default=512)
    ap.add_argument("--seconds", type=float, default=40.0, help="simulated seconds per robot")
    ap.add_argument("--every", type=int, default=4, help="keep every this many control steps")
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    d = collect(Path(args.policy), args.envs, args.seconds, args.every, args.seed)
    test = d["env"] >= int(args.envs * 0.8)  # the last fifth of the robots are held out
    train = ~test
    print(f"[estimator_accel] {len(test)} samples, {int(test.sum())} held out", flush=True)
    groups = {
        "all": test,
        "zero command on >= 2 deg": test & d["zero"] & (d["slope"] >= 2.0),
        "|vx| < 0.3 m/s": test & (d["vel"][:, 0].abs() < 0.3),
        "zero command, |vx| >= 0.3 m/s": test & d["zero"] & (d["vel"][:, 0].abs() >= 0.3),
        "zero command on >= 2 deg, within 1 s of a standing start": test
        & d["zero"]
        & (d["slope"] >= 2.0)
        & (d["age"] < 50),
    }

    def cells(estimate: torch.Tensor) -> list[str]:
        err = estimate[:, 0] - d["vel"][:, 0]
        return [f"{err[m].pow(2).mean().sqrt():.3f} ({int(m.sum())})" for m in groups.values()]

    rows = [("the shipped estimator", cells(d["estimate"]))]
    for name, x in (
        ("A: policy observation", d["obs"]),
        ("B: and 1 s of accelerometer", torch.cat([d["obs"], d["acc"]], 1)),
    ):
        print(f"[estimator_accel] fitting {name} ({x.shape[1]} inputs)", flush=True)
        est = fit(x, d["vel"], train, args.epochs, args.seed)
        with torch.no_grad():
            rows.append((name, cells(torch.cat([est(x[b]) for b in torch.arange(len(x)).split(8192)]))))
    print("| estimator | " + " | ".join(f"vx RMS, {g} (samples)" for g in groups) + " |")
    print("|---|" + "---:|" * len(groups))
    for name, cells in rows:
        print(f"| {name} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
