"""Can the skating prior alone stop the robot, in closed loop, without pitching it over?

    python research/scripts/prior_brake.py                         # the default tilt; ~20 s
    python research/scripts/prior_brake.py --forward-brake-tilts 0.02 0.06 0.1
    python research/scripts/prior_brake.py --from-speed 1.5 --vary gait.amplitude=0.2,0.3,0.42

No policy: every robot's joint targets are caster_omni's prior alone, its speed feedback fed
the simulator's trunk velocity (the estimate at its best), through the stop and reversal
scenarios of `scripts/evaluate.py --scenarios stop`. Unlike research/scripts/brake_limit.py
(a constant push until the speed first falls below the rest speed) the push here shrinks as
the robot slows, as it does under a policy. For each setting of `gait.tilt_forward_brake`
(the tilt of a forward push that brakes a backward roll; "none" = the default tilt) it prints
each scenario's measures and the times of its falls, counted from the command's change
(negative: before it, while the prior drives).

`--from-speed V`: the brake alone. Two robots start rolling at +V and -V m/s under a zero
command (no drive before it, so a setting changes only the brake); for the default settings
and each value of each `--vary KEY=V1,V2,...` (one key at a time) it prints, per direction,
when the trunk is at rest for good (|vx| below the stop checks' rest speed), the path until
then, and the times of its falls.
"""

from __future__ import annotations

import argparse
import copy
import sys

import torch

from legged_casters import registry
from legged_casters.config import apply_overrides
from legged_casters.tools import evaluate
from legged_casters.tools.evaluate import EVAL_SETTINGS, REST_SPEED


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--forward-brake-tilts", type=float, nargs="*", default=[], help="gait.tilt_forward_brake values")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="caster_omni config override")
    ap.add_argument("--from-speed", type=float, default=None, metavar="V", help="the brake alone, from +-V m/s")
    ap.add_argument("--vary", action="append", default=[], metavar="KEY=V1,V2", help="with --from-speed: values to try")
    ap.add_argument("--seconds", type=float, default=6.0, help="with --from-speed: length of each rollout")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.from_speed is not None:
        return from_speed(args)
    spec = registry.get_task("caster_omni")
    base, _ = registry.task_configs("caster_omni", args.set)
    scen = tuple(s for s in evaluate.STOP if s.kind == "brake")
    for tilt in [None, *args.forward_brake_tilts]:
        cfg = copy.deepcopy(base)
        cfg.gait.tilt_forward_brake = tilt
        env = spec.env_class(evaluate.eval_env_cfg(cfg, scen))
        lengths: list[torch.Tensor] = []

        def prior(obs, e=env, out=lengths):
            out.append(e.episode_length_buf.clone())
            return e.gait_offsets() / e.cfg.control.action_scale

        try:
            results = evaluate.run_scenarios(env, prior, scen)
        finally:
            env.close()
        steps = torch.stack(lengths)
        print(f"gait.tilt_forward_brake {'none' if tilt is None else tilt}")
        for i, (s, r) in enumerate(zip(scen, results, strict=True)):
            resets = (steps[1:, i] < steps[:-1, i]).nonzero().flatten() + 1
            switch = s.segments[1][0]  # the command's change (s)
            falls = ", ".join(f"{float(k) * env.dt - switch:+.2f}" for k in resets) or "none"
            measures = ", ".join(f"{k} {v:.2f}" for k, v in r.extra.items())
            print(f"  {s.name:22s} falls at (s from the command's change): {falls}; {measures}")
    return 0


def brake_once(overrides: list[str], speed: float, seconds: float) -> list[str]:
    """One rollout of the brake alone from +speed and -speed; a cell per direction."""
    env_cfg, _ = registry.task_configs("caster_omni", overrides)
    env_cfg = apply_overrides(
        env_cfg, {**EVAL_SETTINGS, "num_envs": 2, "episode_length_s": seconds + 5.0, "sim.backend": "cpu"}
    )
    env = registry.get_task("caster_omni").env_class(env_cfg)
    try:
        env.set_commands(torch.zeros(2, 3))
        env.set_mode("four_wheel")
        env.reset()
        qvel = env.sim.qvel.clone()
        qvel[:, 0] = torch.tensor([speed, -speed], dtype=qvel.dtype)
        qvel[:, 1] = 0.0
        env.sim.reset(None, env.sim.qpos.clone(), qvel)
        vx, falls = [], [[], []]
        for k in range(int(round(seconds / env.dt))):
            before = env.episode_length_buf.clone()
            env.step(env.gait_offsets() / env.cfg.control.action_scale)
            for i in (0, 1):
                if env.episode_length_buf[i] < before[i]:
                    falls[i].append((k + 1) * env.dt)
            vx.append(env.base_lin_vel[:, 0].clone())
    finally:
        env.close()
    v = torch.stack(vx)
    cells = []
    for i in (0, 1):
        moving = (v[:, i].abs() >= REST_SPEED).nonzero().flatten()
        if falls[i]:
            cells.append("falls at " + ", ".join(f"{t:.2f}" for t in falls[i]) + " s")
            continue
        k = 0 if len(moving) == 0 else int(moving[-1]) + 1
        if k >= len(v):
            cells.append(f"not at rest ({float(v[-1, i]):+.2f} m/s at the end)")
        else:
            cells.append(f"{k * env.dt:.2f} s, {float(v[:k, i].abs().sum()) * env.dt:.2f} m")
    return cells


def from_speed(args: argparse.Namespace) -> int:
    runs: list[tuple[str, list[str]]] = [("default", [])]
    for item in args.vary:
        key, _, values = item.partition("=")
        runs += [(f"{key}={v}", [f"{key}={v}"]) for v in values.split(",") if v]
    print(f"| setting | from +{args.from_speed:g} m/s | from -{args.from_speed:g} m/s |\n|---|---|---|")
    for name, overrides in runs:
        cells = brake_once([*args.set, *overrides], args.from_speed, args.seconds)
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
