"""Start a training run from an exported actor: a research tool for fine-tuning experiments.

    python research/scripts/init_from_export.py --policy resources/policies/caster_omni_smooth \
        --donor logs/caster_omni_stop/<run>/model_800.pt --task caster_omni_stop --iteration 960 \
        --out logs/caster_omni_stop/<new run>/model_960.pt

An exported folder keeps the actor (observation normaliser, MLP, velocity estimator) but not
the critic or the optimizer. This writes a training checkpoint whose actor is the export's and
whose critic, observation normaliser count and env state (curriculum) come from a donor
checkpoint of a run on the same observation layout; the optimizers start fresh (empty Adam
moments). The run folder's env.yaml, train.yaml and run.yaml are the caller's to write; then
`python train.py --task <task> --resume --load_run <new run> --checkpoint <iteration>`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from rsl_rl.modules import EmpiricalNormalization

EPS = EmpiricalNormalization(1).eps
"""The training normaliser's eps: the export stores its std + eps as the denominator."""


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", type=Path, required=True, help="exported policy folder (policy.pt)")
    p.add_argument("--donor", type=Path, required=True, help="training checkpoint giving critic and env state")
    p.add_argument("--task", required=True, help="task name written into the checkpoint")
    p.add_argument("--iteration", type=int, required=True, help="iterations the new checkpoint counts as done")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()

    exported = torch.jit.load(str(args.policy / "policy.pt"), map_location="cpu").state_dict()
    ckpt = torch.load(args.donor, map_location="cpu", weights_only=True)
    actor = ckpt["actor_state_dict"]
    std = exported["obs_denom"] - EPS
    if torch.any(std < 0):
        raise SystemExit(f"{args.policy}: obs_denom below the normaliser's eps; not an rsl_rl normaliser")
    new = {"obs_normalizer._mean": exported["obs_mean"], "obs_normalizer._std": std, "obs_normalizer._var": std**2}
    for key, value in exported.items():
        if key.startswith(("mlp.", "estimator.net.")):
            new[key] = value
    for key, value in new.items():
        if key not in actor or actor[key].shape != value.shape:
            raise SystemExit(f"{key}: the export's {tuple(value.shape)} does not fit the donor's actor")
        actor[key] = value.clone()
    missing = [k for k in actor if k.startswith(("mlp.", "estimator.net.")) and k not in new]
    if missing:
        raise SystemExit(f"the export lacks {missing}")
    for key in ("optimizer_state_dict", "estimator_optimizer_state_dict"):
        if key in ckpt:
            ckpt[key]["state"] = {}
    ckpt["iter"] = args.iteration - 1  # rsl_rl stores the last finished iteration
    ckpt["infos"]["task"] = args.task
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(ckpt, args.out)
    print(f"wrote {args.out}: actor of {args.policy}, critic and env state of {args.donor}")


if __name__ == "__main__":
    main()
