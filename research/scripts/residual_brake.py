"""What does a trained actor's residual do to the prior's brake?

    python research/scripts/residual_brake.py --task caster_omni_stop --load_run <run> --checkpoint 1100

The deterministic actor of a training checkpoint (its prior inside) through the stops from
+1.5 and -1.5 m/s of `scripts/evaluate.py --scenarios stop`. Every 10 control steps after the
zero command it prints the trunk's vx and the actor's estimate, the pitch tilt (thigh + calf
target offset, rad, mean over the legs) of the prior and of the whole action, and the hip
splay (|offset|, the oscillation) of both: where the two differ, the residual changed the
prior's push.
"""

from __future__ import annotations

import argparse
import sys

import torch

from legged_casters.tools import common, evaluate
from legged_casters.tools.export import load_actor

SCENARIOS = ("stop from +1.5", "stop from -1.5")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", required=True)
    ap.add_argument("--load_run", required=True)
    ap.add_argument("--checkpoint", required=True)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    sel = common.select_checkpoint(
        evaluate.build_parser().parse_args(
            ["--task", args.task, "--load_run", args.load_run, "--checkpoint", args.checkpoint]
        ),
        None,
    )
    scen = tuple(s for s in evaluate.STOP if s.name in SCENARIOS)
    env = sel.spec.env_class(evaluate.eval_env_cfg(sel.env_cfg, scen))
    actor = load_actor(env, sel.train_cfg, sel.ckpt, sel.ckpt_path)
    rows: list[tuple[torch.Tensor, ...]] = []

    def policy(obs):
        with torch.no_grad():
            raw = torch.cat([obs[g] for g in actor.obs_groups], dim=-1)
            estimate = actor.estimate(obs)
            prior = actor.prior(raw, estimate)
            action = actor(obs)
        rows.append((env.base_lin_vel[:, 0].clone(), estimate[:, 0].clone(), prior.clone(), action.clone()))
        return action

    try:
        evaluate.run_scenarios(env, policy, scen)
    finally:
        env.close()
    scale = env.cfg.control.action_scale
    for i, s in enumerate(scen):
        switch = int(round(s.segments[1][0] / env.dt))  # the control step of the zero command
        print(f"{s.name}: t after the command (s), vx, estimate, pitch prior / action, hip prior / action (rad)")
        for k in range(switch + 5, min(len(rows), switch + 150), 10):
            vx, est, prior, action = (r[i] for r in rows[k])
            p, a = prior.view(4, 3) * scale, action.view(4, 3) * scale
            print(
                f"  {(k - switch) * env.dt:4.2f} {float(vx):+.2f} {float(est):+.2f}  "
                f"{float(p[:, 1:].sum(-1).mean()):+.3f} / {float(a[:, 1:].sum(-1).mean()):+.3f}  "
                f"{float(p[:, 0].abs().mean()):.3f} / {float(a[:, 0].abs().mean()):.3f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
