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

A random 20 % of the same rollout is a lenient test: its windows sit between training
windows of the same robots. What speed control needs is the estimate in steady skating
under the deterministic actor, so a second table (`--steady-commands`, on by default)
runs the deterministic actor (evaluation settings: no noise, pushes or randomisation) at
constant commands for 8 s (`--steady-copies` robots each) and scores each fitted MLP on
the last 4 s: per command the mean true speed against the mean estimate on the
commanded axis (vx unless the command is sideways), and per history length one RMS of
the 3-vector error over all commands. `--no-command` leaves the command and the mode
mask (the policy observation's columns before the proprioceptive terms) out of the MLP's
input; the training's `estimator.skip_terms=[commands]` leaves out the command only.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from legged_casters import registry
from legged_casters.tools import common, export
from legged_casters.tools import evaluate as ev

STEADY_S, STEADY_FROM_S = 8.0, 4.0
"""The steady-skating test: seconds per constant command, and where its scoring window starts."""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--load_run", required=True, help="a caster_omni run folder")
    p.add_argument("--checkpoint", required=True, help="iteration or file in that run")
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--steps", type=int, default=600)
    p.add_argument("--lengths", default="1,10,25,50", help="history lengths L (policy steps)")
    p.add_argument("--epochs", type=int, default=15)
    p.add_argument("--no-command", action="store_true", help="leave the command and mode mask out of the MLP's input")
    p.add_argument(
        "--steady-commands",
        default="-2,-1,-0.5,0.5,1,1.5,2,y0.4,y-0.4",
        help="constant commands of the steady-skating test: vx values, or yV for a vy command; '' for none",
    )
    p.add_argument("--steady-copies", type=int, default=4, help="robots per steady command")
    args = p.parse_args(argv)
    lengths = [int(x) for x in args.lengths.split(",")]
    try:
        steady = [parse_steady(text) for text in args.steady_commands.split(",") if text.strip()]
    except ValueError:
        p.error(f"--steady-commands {args.steady_commands!r}: give numbers (vx) or yNUMBER (vy), comma-separated")
    if max(lengths) >= args.steps // 2:
        p.error("--steps must be more than twice the longest history length")
    torch.set_num_threads(1)
    torch.manual_seed(0)
    run = Path(args.load_run)
    spec = registry.get_task("caster_omni")
    run_cfg, train_cfg = common.run_configs(spec, run)
    env_cfg = common.with_overrides(run_cfg, {"num_envs": args.num_envs, "sim.backend": "cpu", "sim.device": "cpu"}, "")
    ckpt_path = common.find_checkpoint(run, args.checkpoint)
    ckpt = common.load_checkpoint(ckpt_path, map_location="cpu")
    env = spec.env_class(env_cfg)
    actor = export.load_actor(env, train_cfg, ckpt, ckpt_path)
    t0 = time.time()
    proprio, vel, cmds, dones = record(env, actor, args.steps, stochastic=True)
    env.close()
    print(f"[estimator_study] {args.steps} steps x {args.num_envs} robots in {time.time() - t0:.0f} s", flush=True)
    test = steady_rollout(spec, run_cfg, train_cfg, ckpt, ckpt_path, steady, args.steady_copies)
    longest = max(lengths)
    use_cmd = not args.no_command
    print("| history L (steps) | windows | RMS of the velocity error (m/s) | vx | vy | std of vx |")
    print("|---:|---:|---:|---:|---:|---:|")
    steady_rows = []
    for L in lengths:
        x, y = windows(proprio, vel, cmds, dones, L, range(longest + 1, args.steps), use_cmd)
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
        if test is not None:
            steady_rows.append((L, score_steady(net, mu, sd, test, L, steady, args.steady_copies, use_cmd)))
    if test is not None:
        print_steady(steady, steady_rows)
    return 0


def steady_axis(command) -> int:
    """The axis a steady command is scored on: 1 (vy) for a sideways command, else 0 (vx)."""
    return 1 if command[1] and not command[0] else 0


def parse_steady(text: str) -> tuple[float, float, float]:
    """'1.5' -> (1.5, 0, 0); 'y-0.4' -> (0, -0.4, 0)."""
    text = text.strip()
    return (0.0, float(text[1:]), 0.0) if text.startswith("y") else (float(text), 0.0, 0.0)


def record(env, actor, steps: int, stochastic: bool, obs=None) -> tuple[torch.Tensor, ...]:
    """Run the actor `steps` policy steps from `obs` (default: the env's current observation):
    (proprio (n, T, k), trunk velocity (n, T, 3), command and mode (n, T, c), reset after the
    step (n, T)), each from the observation it acted on."""
    cols = env.policy_obs_columns()
    start, stop, cmd_stop = cols["ang_vel"][0], cols["actions"][1], cols["ang_vel"][0]
    obs = env.get_observations() if obs is None else obs
    proprio, vel, cmds, dones = [], [], [], []
    for _ in range(steps):
        with torch.no_grad():
            act = actor(obs, stochastic_output=stochastic)
        proprio.append(obs["policy"][:, start:stop].clone())
        cmds.append(obs["policy"][:, :cmd_stop].clone())
        vel.append(env.base_lin_vel.clone())
        obs, _, done, _ = env.step(act)
        dones.append(done.clone())
    return tuple(torch.stack(x, 1) for x in (proprio, vel, cmds, dones))


def windows(proprio, vel, cmds, dones, L: int, steps, use_cmd: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """(inputs, targets) of the windows of L steps ending at each of `steps`, skipping any with a reset inside."""
    xs, ys = [], []
    n = proprio.shape[0]
    for t in steps:
        ok = ~dones[:, t - L : t].any(1)  # a reset inside the window: its history restarted
        window = proprio[:, t - L + 1 : t + 1].flip(1).reshape(n, -1)
        xs.append((torch.cat([window, cmds[:, t]], 1) if use_cmd else window)[ok])
        ys.append(vel[:, t][ok])
    return torch.cat(xs), torch.cat(ys)


def steady_rollout(spec, env_cfg, train_cfg, ckpt: dict, ckpt_path: Path, commands, copies: int):
    """The deterministic actor at each constant command (evaluation settings, four casters), or None."""
    if not commands:
        return None
    scenarios = tuple(
        ev._const(f"steady {i}", c, duration=STEADY_S, measure_from=STEADY_FROM_S, copies=copies)
        for i, c in enumerate(commands)
    )  # fmt: skip
    env = spec.env_class(ev.eval_env_cfg(env_cfg, scenarios))
    actor = export.load_actor(env, train_cfg, ckpt, ckpt_path)
    if hasattr(env, "set_mode"):
        env.set_mode("four_wheel", torch.arange(env.num_envs))
    env.set_commands(torch.zeros(env.num_envs, 3))
    obs = env.reset()
    env.commands[:] = torch.tensor([c for c in commands for _ in range(copies)], dtype=torch.float32)
    out = record(env, actor, int(round(STEADY_S / env.dt)), stochastic=False, obs=env.refresh_commands(obs))
    env.close()
    return out, env.dt


def score_steady(net, mu, sd, test, L: int, commands, copies: int, use_cmd: bool) -> list[tuple[float, float, float]]:
    """Per steady command: (mean true speed, mean estimate) on its commanded axis and the RMS of
    the 3-vector error, over the scoring window (windows with a fall inside are left out)."""
    (proprio, vel, cmds, dones), dt = test
    first = int(round(STEADY_FROM_S / dt))
    rows = []
    for i, c in enumerate(commands):
        ids = slice(i * copies, (i + 1) * copies)
        x, y = windows(proprio[ids], vel[ids], cmds[ids], dones[ids], L, range(first, proprio.shape[1]), use_cmd)
        if not len(x):
            rows.append((float("nan"),) * 3)
            continue
        with torch.no_grad():
            est = net((x - mu) / sd)
        axis = steady_axis(c)
        rms = float((est - y).pow(2).sum(1).mean().sqrt())
        rows.append((float(y[:, axis].mean()), float(est[:, axis].mean()), rms))
    return rows


def print_steady(commands, rows) -> None:
    """The steady-skating table: one row per history length, one column per command."""
    names = [f"{('vx', 'vy')[steady_axis(c)]} {c[steady_axis(c)]:+g}" for c in commands]
    print("\nSteady skating, deterministic actor (true speed / estimate on the commanded axis, m/s; RMS of the "
          "3-vector error):")  # fmt: skip
    print("| history L | RMS | " + " | ".join(names) + " |")
    print("|---:|---:|" + "---|" * len(names))
    for L, per in rows:
        rms = sum(r[2] ** 2 for r in per) / len(per)
        cells = " | ".join(f"{t:+.2f} / {e:+.2f}" for t, e, _ in per)
        print(f"| {L} | {rms**0.5:.3f} | {cells} |", flush=True)


if __name__ == "__main__":
    sys.exit(main())
