"""The skating prior alone (no policy) through the speed sweep, with and without speed feedback.

    python scripts/prior_sweep.py                              # k = 0 and k = 1 (c = 0.3); ~1 min on 2 cores
    python scripts/prior_sweep.py --feedback 0 1 2 --command-share 0.2
    python scripts/prior_sweep.py --feedback 0 --set gait.tilt=0.1 --set 'gait.amplitude_law=[[0, 0], [1, 0.09]]'
    python scripts/prior_sweep.py --turn --feedback 1 --set gait.yaw_feedback=1 --set gait.yaw_command_share=0.5

Every robot's joint targets are caster_omni's prior alone (what the actor adds its
residual to), in the evaluation setting (no noise, pushes or randomisation), through
the vx and vy scenarios of `scripts/evaluate.py --scenarios speed`. With speed
feedback (`gait.speed_feedback` k > 0) the prior reads the simulator's trunk velocity
where the actor reads its estimate, so this is the feedback law at its best. Prints
one row per scenario: the mean velocity along the commanded axis over the scenario's
window for each k, F where the robot fell. `--turn`: turning commands instead (on the
spot, and while skating forwards or backwards, the mixed ones being commands that
trained policies fell under), each cell the mean vx / wz; with yaw feedback
(`gait.yaw_feedback`) the prior reads the simulator's yaw rate, as the actor reads its gyro.
"""

from __future__ import annotations

import argparse
import copy
import sys

import torch

from legged_casters import registry
from legged_casters.tools import evaluate

TURN = tuple(
    evaluate.Scenario(name, ((0.0, cmd),), 8.0, 3.0)
    for name, cmd in (
        ("wz +0.4", (0.0, 0.0, 0.4)),
        ("wz +0.8", (0.0, 0.0, 0.8)),
        ("vx +0.5, wz +0.6", (0.5, 0.0, 0.6)),
        ("vx -0.5, wz -0.6", (-0.5, 0.0, -0.6)),
        ("vx +0.59, vy -0.30, wz +0.91", (0.59, -0.30, 0.91)),
        ("vx -0.9, vy -0.24, wz +0.68", (-0.9, -0.24, 0.68)),
    )
)
"""Turning on the spot and while skating; the last two are commands run 57's policy fell under."""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--feedback", type=float, nargs="+", default=[0.0, 1.0], help="gait.speed_feedback values")
    ap.add_argument("--command-share", type=float, default=0.3, help="gait.command_share with feedback")
    ap.add_argument("--turn", action="store_true", help="turning commands (cells: mean vx / wz) instead of the sweep")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="caster_omni config override")
    args = ap.parse_args(argv)
    if any(k < 0 for k in args.feedback) or args.command_share < 0:
        ap.error("--feedback and --command-share must be >= 0")
    torch.set_num_threads(1)
    spec = registry.get_task("caster_omni")
    env_cfg, _ = registry.task_configs("caster_omni", args.set)
    scen = TURN if args.turn else tuple(s for s in evaluate.SPEED if s.kind == "track")
    rows: dict[str, list[str]] = {s.name: [] for s in scen}
    for k in args.feedback:
        cfg = copy.deepcopy(env_cfg)
        cfg.gait.speed_feedback, cfg.gait.command_share = k, (args.command_share if k > 0 else 1.0)
        env = spec.env_class(evaluate.eval_env_cfg(cfg, scen))
        try:
            res = evaluate.run_scenarios(env, lambda obs, e=env: e.gait_offsets() / e.cfg.control.action_scale, scen)
        finally:
            env.close()
        for s, r in zip(scen, res, strict=True):
            if args.turn:
                cell = f"{r.mean['vx']:+.2f} / {r.mean['wz']:+.2f}"
            else:
                cell = f"{r.mean['vx' if s.segments[0][1][0] != 0.0 else 'vy']:+.2f}"
            rows[s.name].append(cell + (" F" if r.falls else ""))
        print(f"[prior_sweep] k = {k:g} done", flush=True)
    head = [f"k = {k:g}" + (f", c = {args.command_share:g}" if k > 0 else "") for k in args.feedback]
    print("\n| command | " + " | ".join(head) + " |")
    print("|---|" + "---:|" * len(head))
    for name, cells in rows.items():
        print(f"| {name} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
