"""Can the skating prior alone stop the robot, in closed loop, without pitching it over?

    python research/scripts/prior_brake.py                         # the default tilt; ~20 s
    python research/scripts/prior_brake.py --forward-brake-tilts 0.02 0.06 0.1

No policy: every robot's joint targets are caster_omni's prior alone, its speed feedback fed
the simulator's trunk velocity (the estimate at its best), through the stop and reversal
scenarios of `scripts/evaluate.py --scenarios stop`. Unlike research/scripts/brake_limit.py
(a constant push until the speed first falls below the rest speed) the push here shrinks as
the robot slows, as it does under a policy. For each setting of `gait.tilt_forward_brake`
(the tilt of a forward push that brakes a backward roll; "none" = the default tilt) it prints
each scenario's measures and the times of its falls, counted from the command's change
(negative: before it, while the prior drives).
"""

from __future__ import annotations

import argparse
import copy
import sys

import torch

from legged_casters import registry
from legged_casters.tools import evaluate


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--forward-brake-tilts", type=float, nargs="*", default=[], help="gait.tilt_forward_brake values")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="caster_omni config override")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
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


if __name__ == "__main__":
    sys.exit(main())
