"""train.py under torchrun with 2 CPU processes (gloo): rsl_rl's distributed PPO, which
hard-codes nccl and cuda:LOCAL_RANK, runs through CheckpointingRunner's override."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
TASK = "go2_flat"
TINY = [
    "--task", TASK, "--num_envs", "4", "--sim_backend", "cpu", "--device", "cpu",
    "--console", "line", "--eval_every", "0",
    "--train-set", "num_steps_per_env=8",
    "--train-set", "policy.actor_hidden_dims=[32,32]",
    "--train-set", "policy.critic_hidden_dims=[32,32]",
]  # fmt: skip


def _launch(root: Path, out: Path, tag: str, *extra: str) -> str:
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nnodes=1", "--nproc_per_node=2"]
    cmd += [str(REPO / "tests" / "distributed_rank.py"), *TINY, "--log_root", str(root), *extra]
    env = {**os.environ, "DIST_TEST_OUT": str(out), "DIST_TEST_TAG": tag, "OMP_NUM_THREADS": "1"}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=240)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-6000:]
    return log


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root, out = tmp_path_factory.mktemp("logs"), tmp_path_factory.mktemp("ranks")
    first = _launch(root, out, "first", "--max_iterations", "2")
    # the resume also runs out of a tiny wall budget: rank 0 decides, both ranks stop after one iteration
    resumed = _launch(root, out, "resume", "--resume", "--max_iterations", "5", "--max_minutes", "0.0001")
    ranks = {
        (tag, r): torch.load(out / f"rank{r}_{tag}.pt", weights_only=True)
        for tag in ("first", "resume")
        for r in (0, 1)
    }
    return root, ranks, first, resumed


def test_both_ranks_step_their_own_envs(runs):
    _, ranks, _, _ = runs
    r0, r1 = ranks["first", 0], ranks["first", 1]
    assert (r0["backend"], r0["world"]) == ("gloo", 2)
    assert r1["env_seed"] == r0["env_seed"] + 1
    assert not torch.equal(r0["first_obs"], r1["first_obs"])  # different draws, different data


def test_gradients_are_averaged(runs):
    """The ranks start from different initial weights (torch seeded with seed + rank) and
    learn from different data; rank 0's weights are broadcast, and only averaged
    gradients keep the actors equal after the updates."""
    _, ranks, _, _ = runs
    r0, r1 = ranks["first", 0], ranks["first", 1]
    assert not _same(r0["before"], r1["before"])
    assert _same(r0["after"], r1["after"])
    assert not _same(r0["after"], r0["before"])  # the updates changed the actor
    assert r0["iterations"] == r1["iterations"] == 2


def test_only_rank_0_writes_the_run(runs):
    root, ranks, _, _ = runs
    (run_dir,) = (root / TASK).iterdir()
    names = sorted(p.name for p in run_dir.iterdir())
    assert "model_2.pt" in names and "model_3.pt" in names and "model_4.pt" not in names
    assert names.count("command.txt") == 1
    saved = torch.load(run_dir / "model_2.pt", weights_only=True)["actor_state_dict"]
    assert _same(saved, ranks["first", 1]["after"])  # rank 0's checkpoint holds the common weights


def test_resume_with_two_processes(runs):
    root, ranks, _, resumed = runs
    (run_dir,) = (root / TASK).iterdir()
    r0, r1 = ranks["resume", 0], ranks["resume", 1]
    assert r0["iterations"] == r1["iterations"] == 3
    first = torch.load(run_dir / "model_2.pt", weights_only=True)["actor_state_dict"]
    assert _same(r0["before"], first) and _same(r1["before"], first)  # both ranks loaded the checkpoint
    assert _same(r0["after"], r1["after"])
    final = torch.load(run_dir / "model_3.pt", weights_only=True)["actor_state_dict"]
    assert _same(final, r0["after"])
    assert "resumed" in resumed and "stopped after iteration 3" in resumed
