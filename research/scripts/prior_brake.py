"""Can the skating prior alone stop the robot, in closed loop, without pitching it over?

    python research/scripts/prior_brake.py                         # the default settings; ~20 s
    python research/scripts/prior_brake.py --vary gait.tilt_forward_brake=0.02,0.06,0.1
    python research/scripts/prior_brake.py --from-speed 1.5 --vary gait.amplitude=0.2,0.3,0.42

No policy: every robot's joint targets are caster_omni's prior alone, its speed feedback fed
the simulator's trunk velocity (the estimate at its best). Unlike
research/scripts/brake_limit.py (a constant push until the speed first falls below the rest
speed) the push here shrinks as the robot slows, as it does under a policy. It runs the
default settings (with any `--set`), then each value of each `--vary KEY=V1,V2,...`, one key
at a time.

By default, through the stop and reversal scenarios of `scripts/evaluate.py --scenarios
stop` (the prior drives for 6 s, then the command changes): each scenario's measures and the
times of its falls, counted from the command's change (negative: before it, while the prior
drives; the "rest" time of a robot that fell counts the reset robot).

`--noise STD --copies N`: Gaussian noise on every action (as PPO's exploration) and N robots
per stop scenario; `--posture-rate R`: the prior's posture follows the command at most R
rad/s (a stateful probe). `--from-speed V --pose=ROLL,PITCH` (repeatable): also each held pose
(hip roll x side, calf pitch x end) in place of the prior.

`--from-speed V`: the brake alone. Two robots start rolling at +V and -V m/s in the nominal
pose under a zero command (no drive before it, so a setting changes only the brake); per
direction, when the trunk is at rest for good (|vx| below the stop checks' rest speed), the
path until then, and the times of its falls.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import torch

from legged_casters import registry
from legged_casters.envs.gait import gait_prior, stop_pose
from legged_casters.tools import evaluate
from legged_casters.tools.evaluate import REST_SPEED

TASK = "caster_omni"


def prior_policy(env, lengths: list[torch.Tensor], posture_rate: float = 0.0, noise: float = 0.0):
    """The env's prior as the policy; records each step's episode lengths (a drop: a reset).
    With `posture_rate` > 0 (rad/s) the prior's posture (its offsets with the oscillation
    left out) moves towards the new one at most that fast, the oscillation on top as it comes:
    a probe of a prior whose push reverses at a bounded rate (this script keeps the state;
    the actor has none). With `noise` > 0 each action gets Gaussian noise of that std (action
    units, as PPO's exploration adds to the actor's mean in training; seeded)."""
    gen = torch.Generator().manual_seed(0)
    state: dict[str, torch.Tensor] = {}

    def policy(obs=None):
        length = env.episode_length_buf.clone()
        offsets = env.gait_offsets()
        if posture_rate > 0.0:
            g = env.cfg.gait
            posture = gait_prior(
                g, env.commands, env.mode_mask, torch.zeros_like(env.gait_phase), env.projected_gravity,
                env.base_lin_vel, env.base_ang_vel[:, 2],
            )  # fmt: skip
            last = state.get("posture")
            if last is None:
                last = posture
            else:
                fresh = (length < state["length"]).unsqueeze(1)  # a reset robot starts from its own
                step = posture_rate * env.dt
                last = torch.where(fresh, posture, last + (posture - last).clamp(-step, step))
            state["posture"] = last
            offsets = offsets - posture + last
        state["length"] = length
        lengths.append(length)
        return with_noise(offsets / env.cfg.control.action_scale, noise, gen)

    return policy


def with_noise(action: torch.Tensor, noise: float, gen: torch.Generator) -> torch.Tensor:
    """`action` plus Gaussian noise of std `noise` (action units; none at 0), drawn from `gen`."""
    return action + noise * torch.randn(action.shape, generator=gen).to(action) if noise > 0.0 else action


def reset_times(lengths: list[torch.Tensor], i: int, dt: float) -> list[float]:
    """Times (s from the first recorded step) at which robot i was reset, i.e. fell."""
    steps = torch.stack(lengths)[:, i]
    return [float(k) * dt for k in (steps[1:] < steps[:-1]).nonzero().flatten() + 1]


def scenarios(overrides: list[str], posture_rate: float = 0.0, noise: float = 0.0, copies: int = 1) -> list[str]:
    """The stop scenarios under the prior alone, `copies` robots each (their falls joined
    by " / ", their measures averaged by the evaluation); a line per scenario."""
    env_cfg, _ = registry.task_configs(TASK, overrides)
    scen = tuple(dataclasses.replace(s, copies=copies) for s in evaluate.STOP if s.kind == "brake")
    env = registry.get_task(TASK).env_class(evaluate.eval_env_cfg(env_cfg, scen))
    lengths: list[torch.Tensor] = []
    try:
        results = evaluate.run_scenarios(env, prior_policy(env, lengths, posture_rate, noise), scen)
    finally:
        env.close()
    lines = []
    for i, (s, r) in enumerate(zip(scen, results, strict=True)):
        switch = s.segments[1][0]  # the command's change (s)
        falls = " / ".join(
            ", ".join(f"{t - switch:+.2f}" for t in reset_times(lengths, i * copies + c, env.dt)) or "none"
            for c in range(copies)
        )
        measures = ", ".join(f"{k} {v:.2f}" for k, v in r.extra.items())
        lines.append(f"  {s.name:22s} falls at (s from the command's change): {falls}; {measures}")
    return lines


def pose_policy(env, lengths: list[torch.Tensor], roll: float, pitch: float, thigh: float = 0.0, noise: float = 0.0):
    """A held pose instead of the prior: each hip offset by roll x its side (left +1), each calf
    by pitch x its end (front +1), rad; (0, 0) is the nominal pose (coasting). `noise` as in
    prior_policy."""
    gen = torch.Generator().manual_seed(0)
    action = (stop_pose(pitch, roll, thigh) / env.cfg.control.action_scale).expand(env.num_envs, 12)

    def policy(obs=None):
        lengths.append(env.episode_length_buf.clone())
        return with_noise(action, noise, gen)

    return policy


def from_speed(
    overrides: list[str],
    speed: float,
    seconds: float,
    posture_rate: float = 0.0,
    noise: float = 0.0,
    pose: tuple[float, float, float] | None = None,
) -> list[str]:
    """The brake alone from +speed and -speed m/s; a table cell per direction. With `pose`
    (roll, pitch) a held pose brakes instead of the prior (pose_policy)."""
    env_cfg, _ = registry.task_configs(TASK, overrides)
    still = evaluate.Scenario("brake alone", ((0.0, (0.0, 0.0, 0.0)),), seconds, 0.0, copies=2)
    env = registry.get_task(TASK).env_class(evaluate.eval_env_cfg(env_cfg, (still,)))
    lengths: list[torch.Tensor] = []
    if pose is None:
        policy = prior_policy(env, lengths, posture_rate, noise)
    else:  # a held pose brakes instead
        policy = pose_policy(env, lengths, *pose, noise=noise)
    vx, pitch = [], []
    try:
        env.set_commands(torch.zeros(2, 3))
        env.set_mode("four_wheel")
        env.reset()
        qvel = env.sim.qvel.clone()
        qvel[:, 0] = torch.tensor([speed, -speed], dtype=qvel.dtype)
        qvel[:, 1] = 0.0
        env.sim.reset(None, env.sim.qpos.clone(), qvel)
        for _ in range(int(round(seconds / env.dt))):
            env.step(policy())
            vx.append(env.base_lin_vel[:, 0].clone())
            pitch.append(torch.rad2deg(torch.asin(env.ground_gravity[:, 0].clamp(-1, 1))))
        lengths.append(env.episode_length_buf.clone())
    finally:
        env.close()
    v, tilt = torch.stack(vx), torch.stack(pitch)
    cells = []
    for i in (0, 1):
        falls = reset_times(lengths, i, env.dt)
        if falls:
            cells.append("falls at " + ", ".join(f"{t:.2f}" for t in falls) + " s")
            continue
        moving = (v[:, i].abs() >= REST_SPEED).nonzero().flatten()
        k = 0 if len(moving) == 0 else int(moving[-1]) + 1
        if k >= len(v):
            cells.append(f"not at rest ({float(v[-1, i]):+.2f} m/s at the end)")
        else:
            cells.append(
                f"{k * env.dt:.2f} s, {float(v[:k, i].abs().sum()) * env.dt:.2f} m, "
                f"trunk pitch {float(tilt[-int(round(1.0 / env.dt)) :, i].mean()):+.0f} deg"
            )
    return cells


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="caster_omni config override")
    ap.add_argument("--vary", action="append", default=[], metavar="KEY=V1,V2", help="values to try, one key at a time")
    ap.add_argument("--from-speed", type=float, default=None, metavar="V", help="the brake alone, from +-V m/s")
    ap.add_argument("--seconds", type=float, default=6.0, help="with --from-speed: length of each rollout")
    ap.add_argument(
        "--posture-rate", type=float, default=0.0, metavar="RAD_S", help="bound the prior's posture rate (0: off)"
    )
    ap.add_argument("--noise", type=float, default=0.0, metavar="STD", help="action noise std (action units)")
    ap.add_argument("--copies", type=int, default=1, help="robots per stop scenario (with --noise: several draws)")
    ap.add_argument(
        "--pose",
        action="append",
        default=[],
        metavar="ROLL,PITCH[,THIGH]",
        help="with --from-speed: also each held pose (hip roll x side, calf pitch and thigh x end, rad) "
        "instead of the prior",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    runs: list[tuple[str, list[str]]] = [("default", [])]
    for item in args.vary:
        key, _, values = item.partition("=")
        runs += [(f"{key}={v}", [f"{key}={v}"]) for v in values.split(",") if v]
    if args.from_speed is not None:
        print(f"| setting | from +{args.from_speed:g} m/s | from -{args.from_speed:g} m/s |\n|---|---|---|")
    for name, overrides in runs:
        if args.from_speed is None:
            lines = scenarios([*args.set, *overrides], args.posture_rate, args.noise, args.copies)
            print(name, *lines, sep="\n", flush=True)
        else:
            cells = from_speed([*args.set, *overrides], args.from_speed, args.seconds, args.posture_rate, args.noise)
            print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
    if args.from_speed is not None:
        for pose in args.pose:
            roll, pitch, thigh = ([float(x) for x in pose.split(",")] + [0.0])[:3]
            cells = from_speed(args.set, args.from_speed, args.seconds, noise=args.noise, pose=(roll, pitch, thigh))
            name = f"held pose roll {roll:g}, pitch {pitch:g}" + (f", thigh {thigh:g}" if thigh else "")
            print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
