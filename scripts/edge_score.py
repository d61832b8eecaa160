"""What an exported policy scores under the "edge" command curriculum, in training conditions.

    python scripts/edge_score.py --policy resources/policies/caster_omni --std 0.2   # ~1 min

Runs the policy's TorchScript actor (its mean action plus Gaussian noise of `--std`, in
action units, as a stochastic policy acts in training) on `--num-envs` robots of its task
with the task's training settings (observation noise, pushes, randomisation, random
commands) and `commands.curriculum_mode=edge`, for `--periods` curriculum periods (one
episode length each), and prints the mean vx tracking judged at each end of the vx range
and the range after each period. It is how caster_omni's `curriculum_threshold` was
chosen (research/log.md).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from legged_casters import registry
from legged_casters.deploy.policy import load_meta


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", required=True, help="an export folder (policy.yaml, policy.pt)")
    ap.add_argument("--std", type=float, default=0.2, help="exploration noise std, action units")
    ap.add_argument("--num-envs", type=int, default=256)
    ap.add_argument("--periods", type=int, default=2)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="env config override")
    args = ap.parse_args(argv)
    if args.std < 0 or args.num_envs < 1 or args.periods < 1:
        ap.error("--std must be >= 0, --num-envs and --periods >= 1")
    folder = Path(args.policy)
    meta = load_meta(folder / "policy.yaml")
    torch.set_num_threads(1)
    torch.manual_seed(0)
    actor = torch.jit.load(str(folder / meta.files["torchscript"]), map_location="cpu")
    env = registry.make_env(
        meta.task, ["sim.backend=cpu", "commands.curriculum=true", "commands.curriculum_mode=edge", *args.set],
        num_envs=args.num_envs,
    )  # fmt: skip
    obs = env.get_observations()
    t0 = time.time()
    try:
        for k in range(args.periods * env.max_episode_length):
            with torch.no_grad():
                act = actor(obs["policy"])
            obs, _, _, _ = env.step(act + args.std * torch.randn_like(act))
            if (k + 1) % env.max_episode_length == 0:
                back, fwd = env.edge_tracking
                lo, hi = env.command_ranges["lin_vel_x"]
                print(
                    f"[edge_score] period {(k + 1) // env.max_episode_length}: vx tracking at the backward end "
                    f"{back:.3f}, forward end {fwd:.3f}; vx range now [{lo:g}, {hi:g}] ({time.time() - t0:.0f} s)",
                    flush=True,
                )
    finally:
        env.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
