"""cot: the paper's Table II on our simulator: mechanical cost of transport of the three
robots at one commanded speed on flat ground, measured the same way.

    python scripts/cot.py                      # the shipped policies of go2_flat, caster_omni, go2_wheel_flat
    python scripts/cot.py --speed 1.0 --point logs/go2_flat/<run>/exported

Each policy runs from a standing start under a constant forward command (noise,
randomisation and pushes off, as in scripts/evaluate.py); over the window after the
robot reached speed, COT = positive mechanical work of all actuated joints (wheels
included; every physics step) / (weight x distance), the paper's formula. Ratios are
against the point-foot robot measured in the same run.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from legged_casters.tools import common, evaluate
from legged_casters.tools.common import UsageError

PROG = "cot.py"
ROBOTS = (
    ("point", "go2_flat", "point feet (trot)", 0.648),
    ("caster", "caster_omni", "passive casters (ours)", 0.0705),
    ("wheel", "go2_wheel_flat", "driving wheels", 0.0637),
)
"""(flag, task, robot, the paper's COT_mech in Table II)."""


def measure(policy_dir: Path, speed: float, duration: float, settle: float) -> dict:
    task, spec, env_cfg, policy, label, dim = evaluate.load_exported(policy_dir, None)
    scenario = evaluate.Scenario(f"vx {speed:+.1f}", ((0.0, (speed, 0.0, 0.0)),), duration, settle)
    env = spec.env_class(evaluate.eval_env_cfg(env_cfg, (scenario,)))
    try:
        if dim is not None and dim != env.observation_dims()["policy"]:
            raise common.CheckpointError(f"{label} expects {dim} observations; {task} gives another layout")
        (r,) = evaluate.run_scenarios(env, policy, (scenario,))
    finally:
        env.close()
    return {"task": task, "speed": r.mean["vx"], "power": r.extra["power_w"], "cot": r.extra["cot"], "falls": r.falls}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--speed", type=float, default=1.0, help="commanded forward speed, m/s (default: 1.0)")
    p.add_argument("--duration", type=float, default=12.0, help="seconds per robot (default: 12)")
    p.add_argument("--settle", type=float, default=4.0, help="seconds before the measurement starts (default: 4)")
    for flag, task, _, _ in ROBOTS:
        p.add_argument(f"--{flag}", help=f"exported {task} policy folder (default: resources/policies/{task})")
    args = p.parse_args(argv)

    def body() -> int:
        if not 0.0 < args.settle < args.duration:
            raise UsageError("--settle must be positive and shorter than --duration")
        rows = []
        for flag, task, robot, paper in ROBOTS:
            given = getattr(args, flag)
            path = Path(given).expanduser() if given else common.shipped_policy_dir(task)
            if path is None:
                print(f"[{PROG}] no {task} policy (none shipped; pass --{flag} DIR): skipped", file=sys.stderr)
                continue
            rows.append((robot, paper, path, measure(path, args.speed, args.duration, args.settle)))
        if not rows:
            raise UsageError("no policy to measure")
        ref = next((m for robot, _, _, m in rows if robot.startswith("point")), None)
        print(
            f"COT_mech at a {args.speed:.1f} m/s forward command, flat ground, {args.settle:.0f}-{args.duration:.0f} s:"
        )
        print("| robot | policy | mean speed (m/s) | mean power (W) | COT (ours) | vs point feet | COT (paper) | "
              "paper vs point feet | falls |")  # fmt: skip
        print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
        for robot, paper, path, m in rows:
            ours = f"{100 * (m['cot'] / ref['cot'] - 1):+.1f} %" if ref else "-"
            theirs = f"{100 * (paper / 0.648 - 1):+.1f} %"
            shown = path.resolve().relative_to(Path.cwd()) if path.resolve().is_relative_to(Path.cwd()) else path
            print(
                f"| {robot} | `{shown}` | {m['speed']:.2f} | {m['power']:.1f} | {m['cot']:.3f} | {ours} | "
                f"{paper} | {theirs} | {m['falls']} |"
            )
        return common.EXIT_OK

    return common.run_cli(body, PROG)


if __name__ == "__main__":
    sys.exit(main())
