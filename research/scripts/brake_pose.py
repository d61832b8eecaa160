"""The shipped caster policy with a held brake pose under a zero command (a probe, no training).

    python research/scripts/brake_pose.py --pitch 0.2                # the pose replaces the policy at 0
    python research/scripts/brake_pose.py --pitch 0.2 --blend 0.3    # ... blended in over 0.3 s
    python research/scripts/brake_pose.py --pitch 0 --roll 0         # the nominal pose at 0 (coasting)

research/scripts/prior_brake.py --from-speed found that a held pose whose front calves
extend and rear calves flex (`pitch` rad each, the front and rear casters' swivel axes
leaning opposite ways) brakes a roll in either direction without any oscillation. This runs
`scripts/evaluate.py --scenarios stop` on the shipped export with one change: while a
robot's command is zero its action becomes that pose (each hip `roll` x its side, each calf
`pitch` x its end, rad), blended in linearly over `--blend` s from the moment the command
became zero. It prints the evaluation's stop table and its verdict lines.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from legged_casters import registry
from legged_casters.envs.gait import stop_pose
from legged_casters.tools import evaluate

POLICY = Path(__file__).resolve().parents[2] / "resources" / "policies" / "caster_omni"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pitch", type=float, default=0.2, help="calf offset x end (front +1), rad")
    ap.add_argument("--roll", type=float, default=0.0, help="hip offset x side (left +1), rad")
    ap.add_argument("--blend", type=float, default=0.0, help="s over which the pose replaces the policy")
    ap.add_argument("--add", action="store_true", help="add the pose to the policy's action instead")
    ap.add_argument("--policy", type=Path, default=POLICY)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    task, _, env_cfg, policy, _, _ = evaluate.load_exported(args.policy, None)
    scen = evaluate.STOP
    env = registry.get_task(task).env_class(evaluate.eval_env_cfg(env_cfg, scen))
    pose = stop_pose(args.pitch, args.roll) / env.cfg.control.action_scale  # (12,): broadcast over the robots
    since = torch.zeros(env.num_envs)  # s since the command became zero

    def braked(obs):
        action = policy(obs)
        zero = env.commands.abs().sum(dim=1).cpu() == 0.0
        since[:] = torch.where(zero, since + env.dt, torch.zeros_like(since))
        w = (since / args.blend).clamp(max=1.0) if args.blend > 0 else zero.float()
        w = (w * zero.float()).unsqueeze(1).to(action)
        target = action + pose.to(action) if args.add else pose.to(action)
        return (1 - w) * action + w * target

    try:
        results = evaluate.run_scenarios(env, braked, scen)
    finally:
        env.close()
    print(evaluate.format_table(results))
    for check, ok, text in evaluate.verdict(results, task):
        print(f"{'pass' if ok else 'FAIL'}  {check}: {text}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
