"""Probes of the stop pose's rules, run through scripts/evaluate.py without changing the code.

    python research/scripts/stop_probe.py --true-gate -- --task caster_omni_stop --load_run <run> --scenarios stop
    python research/scripts/stop_probe.py --blend 0.15 -- --task caster_omni_stop --load_run <run> --scenarios stop
    python research/scripts/stop_probe.py --damp-thigh -0.2 -- --task caster_omni_stop --load_run <run> --scenarios stop

Each option replaces `GaitPrior.stop` (legged_casters/envs/gait.py) for this process only, so
the run's own env.yaml (stop_pitch, stop_roll, stop_backward_speed, stop_rest_speed) still
decides where the pose holds; the arguments after `--` go to scripts/evaluate.py unchanged.

* --true-gate: the rules read the trunk's true velocity instead of the actor's estimate (the
  network and the prior still read the estimate): what the gate would do with a perfect one.
* --blend A: where the pose holds, the action moves a share A from the pose's towards the
  network's own action (prior and MLP).
* --damp-thigh K: where the pose holds, each thigh's target gets K x the trunk's pitch rate
  (rad per rad/s; front legs +, rear legs -, the leg-end pattern of the pose's calves).
"""

from __future__ import annotations

import argparse
import sys

import torch

from legged_casters.envs import gait
from legged_casters.envs.base import LeggedEnv
from legged_casters.tools import evaluate


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ours, rest = (argv[: argv.index("--")], argv[argv.index("--") + 1 :]) if "--" in argv else (argv, [])
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--true-gate", action="store_true")
    ap.add_argument("--blend", type=float, default=0.0)
    ap.add_argument("--damp-thigh", type=float, default=0.0)
    args = ap.parse_args(ours)
    current: dict[str, LeggedEnv] = {}
    if args.true_gate:
        step, reset = LeggedEnv.step, LeggedEnv.reset

        def remember_step(self, actions):
            current["env"] = self
            return step(self, actions)

        def remember_reset(self):
            current["env"] = self
            return reset(self)

        LeggedEnv.step, LeggedEnv.reset = remember_step, remember_reset
    stop = gait.GaitPrior.stop

    def probed(self, obs: torch.Tensor, mean: torch.Tensor, velocity: torch.Tensor) -> torch.Tensor:
        env = current.get("env")
        if env is not None and env.num_envs == obs.shape[0]:
            velocity = env.base_lin_vel.to(velocity.dtype)
        out = stop(self, obs, mean, velocity)
        posed = (out != mean).any(dim=1, keepdim=True)
        if args.blend:
            out = torch.where(posed, out + args.blend * (mean - out), out)
        if args.damp_thigh:
            pitch_rate = obs[:, self.yaw_col - 1 : self.yaw_col] / self.gyro_scale
            thighs = gait.stop_pose(0.0, 0.0, thigh=1.0)  # each thigh x its leg's end (front +1)
            add = args.damp_thigh * pitch_rate * thighs / self.action_scale
            out = torch.where(posed, out + add, out)
        return out

    gait.GaitPrior.stop = probed
    return evaluate.main(rest)


if __name__ == "__main__":
    sys.exit(main())
