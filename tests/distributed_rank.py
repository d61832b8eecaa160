"""One rank of tests/test_distributed.py's torchrun launch: train.py's main, with this
rank's actor saved before and after learning to $DIST_TEST_OUT/rank<RANK>_<DIST_TEST_TAG>.pt
(the test compares the ranks; nothing of this reaches the product)."""

import os
import sys

import torch

from legged_casters.tools import train

_learn = train.CheckpointingRunner.learn


def _state(runner) -> dict:
    return {k: v.detach().cpu().clone() for k, v in runner.alg.get_policy().state_dict().items()}


def learn(self, *args, **kwargs):
    before, obs = _state(self), self.env.get_observations()["policy"].detach().cpu().clone()
    try:
        _learn(self, *args, **kwargs)
    finally:  # also when --max_minutes ends the run (BudgetReached)
        record = {
            "before": before,
            "after": _state(self),
            "first_obs": obs,
            "env_seed": self.env.cfg.seed,
            "iterations": self.completed_iterations(),
            "backend": torch.distributed.get_backend(),
            "world": torch.distributed.get_world_size(),
        }
        out = os.environ["DIST_TEST_OUT"]
        torch.save(record, os.path.join(out, f"rank{os.environ['RANK']}_{os.environ['DIST_TEST_TAG']}.pt"))


train.CheckpointingRunner.learn = learn

if __name__ == "__main__":
    sys.exit(train.main(sys.argv[1:]))
