"""train.py under torchrun with 2 CPU processes (gloo): rsl_rl's distributed PPO, which
hard-codes nccl and cuda:LOCAL_RANK, runs through CheckpointingRunner's override."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

REPO = Path(__file__).resolve().parents[1]
TASK = "go2_flat"
TINY = [
    "--task", TASK, "--num_envs", "4", "--sim_backend", "cpu", "--device", "cpu",
    "--console", "line", "--eval_every", "0",
    "--train-set", "num_steps_per_env=8",
    "--train-set", "policy.actor_hidden_dims=[32,32]",
    "--train-set", "policy.critic_hidden_dims=[32,32]",
]  # fmt: skip


CASTER = [
    "--task", "caster_omni", "--num_envs", "4", "--device", "cpu", "--console", "line", "--eval_every", "0",
    "--train-set", "num_steps_per_env=8",
    "--train-set", "policy.actor_hidden_dims=[16]",
    "--train-set", "policy.critic_hidden_dims=[16]",
    "--train-set", "estimator.hidden_dims=[16]",
    "--train-set", "select_last=0",
]  # fmt: skip


def _launch(root: Path, out: Path, tag: str, *extra: str, args: list[str] = TINY) -> str:
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nnodes=1", "--nproc_per_node=2"]
    cmd += [str(REPO / "tests" / "distributed_rank.py"), *args, "--log_root", str(root), *extra]
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


def test_the_estimator_learns_from_both_ranks(tmp_path):
    """caster_omni's actor carries a velocity estimator with its own Adam step after PPO's
    (EstimatorPPO): its gradients are averaged too, or the ranks' estimators drift apart."""
    root, out = tmp_path / "logs", tmp_path / "ranks"
    out.mkdir()
    _launch(root, out, "caster", "--max_iterations", "2", args=CASTER)
    r0, r1 = (torch.load(out / f"rank{r}_caster.pt", weights_only=True) for r in (0, 1))
    est = [k for k in r0["after"] if k.startswith("estimator.")]
    assert est, sorted(r0["after"])
    assert not all(torch.equal(r0["before"][k], r0["after"][k]) for k in est)  # the estimator learnt
    assert _same(r0["after"], r1["after"])


def test_procs_launches_one_pinned_process_per_core(tmp_path):
    """`train.py --procs 2`: torchrun with two workers, each on its own core with half the
    envs; rank 0 writes one run folder whose command.txt names the command typed."""
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("needs 2 usable cores")
    cmd = [sys.executable, str(REPO / "train.py"), *TINY[:2], "--procs", "2", "--num_envs", "8", *TINY[4:]]
    cmd += ["--log_root", str(tmp_path), "--max_iterations", "2"]
    # each process its own physics step (same 20 ms control period): process 0 at 5 ms, process 1 at 2 ms
    cmd += ["--set-per-process", "sim.timestep=[0.005,0.002]", "--set-per-process", "sim.decimation=[4,10]"]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=240)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-6000:]
    assert "2 processes on" in log and "4 envs each" in log
    cores = sorted(int(c) for c in re.findall(r"rank \d: CPU core (\d+), 1 torch thread", log))
    assert len(cores) == 2 and cores[0] != cores[1], log[-3000:]
    steps = sorted(re.findall(r"control dt 0\.020 s = (\d+ x [\d.]+ ms) physics", log))
    assert steps == ["10 x 2 ms", "4 x 5 ms"], log[-3000:]
    (run_dir,) = (tmp_path / TASK).iterdir()
    assert (run_dir / "model_2.pt").exists()
    assert "--procs 2" in (run_dir / "command.txt").read_text()
    env_yaml = yaml.safe_load((run_dir / "env.yaml").read_text())
    assert env_yaml["num_envs"] == 4  # per process
    assert (env_yaml["sim"]["timestep"], env_yaml["sim"]["decimation"]) == (0.005, 4)  # process 0's
    info = yaml.safe_load((run_dir / "run.yaml").read_text())
    assert info["processes"] == 2
    assert info["env_set_per_process"] == {"sim.timestep": [0.005, 0.002], "sim.decimation": [4, 10]}


@pytest.mark.parametrize("to_group", [True, False], ids=["ctrl_c_in_a_terminal", "kill_the_launcher"])
def test_procs_stops_like_one_process(tmp_path, to_group, stop_training):
    """A Ctrl-C in a terminal (SIGINT to the whole process group) or SIGTERM to train.py
    alone stops a --procs 2 run as a one-process run stops: exit 130 / 143, one
    "interrupted" line that names the run folder rank 0 writes, the command that continues
    (with --procs 2, which the run's per-process settings require), no traceback (torchrun's
    agent raised one under those lines) and no worker left running."""
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("needs 2 usable cores")
    cmd = [sys.executable, str(REPO / "train.py"), *TINY[:2], "--procs", "2", "--num_envs", "8", *TINY[4:]]
    cmd += ["--log_root", str(tmp_path), "--max_iterations", "5000", "--train-set", "save_interval=1"]

    def stop(proc):
        if to_group:
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGTERM)

    proc, out = stop_training(cmd, " it 3/5000", stop, start_new_session=True)
    assert proc.returncode == (130 if to_group else 143), out[-3000:]
    (run_dir,) = (tmp_path / TASK).iterdir()
    assert out.count("interrupted; newest checkpoint") == 1, out[-3000:]
    resume = f"continue with: python train.py --task {TASK} --procs 2 --resume --load_run {run_dir}\n"
    assert out.count("continue with:") == 1 and resume in out, out[-3000:]
    assert "Traceback" not in out and "death signal" not in out, out[-3000:]
    with pytest.raises(ProcessLookupError):
        os.killpg(proc.pid, 0)  # the workers are gone with the launcher


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--procs", "0"], "--procs must be at least 1"),
        (["--procs", "64"], "one process per core"),
        (["--procs", "2", "--num_envs", "5"], "does not split evenly into 2 processes"),
        (["--procs", "2", "--set-per-process", "sim.timestep=[0.005]"], "1 values for 2 process(es)"),
        (["--set-per-process", "sim.timestep=0.005"], "expected KEY=[V0,V1,...]"),
        (["--set-per-process", "sim.timestep=[0.005,0.002]"], "2 values for 1 process(es)"),
        (["--procs", "2", "--set-per-process", "sim.timestep=[0.005,0.002]"], "control period"),
    ],
)
def test_procs_bad_input(extra, message, capsys):
    from legged_casters.tools import train

    assert train.main(["--task", TASK, *extra]) == 2
    assert message in capsys.readouterr().err


def test_procs_resume_keeps_the_runs_batch(tmp_path):
    """--procs on --resume splits the run's own total (envs per process x processes), so a run
    trained by one process and resumed by two keeps its 512 x 24 batch, and back."""
    from legged_casters import registry
    from legged_casters.tools import train

    spec = registry.get_task("caster_omni")
    run = tmp_path / "caster_omni" / "2026-01-01_00-00-00_x"
    run.mkdir(parents=True)
    (run / "env.yaml").write_text("num_envs: 256\n")
    (run / "model_1.pt").write_bytes(b"")
    args = train.build_parser().parse_args(["--task", "caster_omni", "--resume", "--log_root", str(tmp_path)])
    assert train.total_envs(args, spec, None) == 256  # no run.yaml: one process
    (run / "run.yaml").write_text("task: caster_omni\nprocesses: 2\n")
    assert train.total_envs(args, spec, None) == 512
    args = train.build_parser().parse_args(["--task", "caster_omni", "--num_envs", "64"])
    assert train.total_envs(args, spec, None) == 64
    args = train.build_parser().parse_args(["--task", "caster_omni"])
    assert train.total_envs(args, spec, None) == 512


def test_procs_auto_is_two_on_the_cpu_with_two_cores(monkeypatch):
    """--procs auto (what ./setup.sh train passes): 2 processes on the CPU backend where 2 or
    more cores are usable, else 1; anything but a number or auto is refused."""
    from legged_casters.tools import train

    parse = train.build_parser().parse_args
    for cores, expect in ((1, 1), (2, 2), (16, 2)):
        monkeypatch.setattr(train, "usable_cpus", lambda c=cores: c)
        assert train.resolve_procs(parse(["--procs", "auto", "--sim_backend", "cpu", "--device", "cpu"])) == expect
    assert train.resolve_procs(parse(["--procs", "3"])) == 3
    with pytest.raises(SystemExit):
        parse(["--procs", "two"])


def test_each_process_gets_its_own_entry_and_every_entry_is_checked(tmp_path):
    """--set-per-process: process r trains with each list's entry r; a value no process may
    use, or a control period that differs between processes, fails in every process (before
    any simulation); --resume applies the run's lists (run.yaml) for each key not given anew,
    per process or by --set, and names the flags to give when the count of processes differs."""
    import argparse

    from legged_casters import registry
    from legged_casters.config import ConfigError
    from legged_casters.tools import train
    from legged_casters.tools.common import UsageError

    cfg = registry.get_task(TASK).env_cfg
    per = {"sim.timestep": [0.005, 0.002], "sim.decimation": [4, 10]}
    first, second = (train.process_env_cfg(cfg, per, r, 2) for r in (0, 1))
    assert (first.sim.timestep, first.sim.decimation) == (0.005, 4)
    assert (second.sim.timestep, second.sim.decimation) == (0.002, 10)
    with pytest.raises(ConfigError, match=r"--set-per-process \(process 1\)"):
        train.process_env_cfg(cfg, {"sim.decimation": [4, 0]}, 0, 2)  # process 0's own value is fine
    with pytest.raises(UsageError, match=r"control period .* \(20 ms, 8 ms\).*'sim.decimation=\[4,10\]'"):
        train.process_env_cfg(cfg, {"sim.timestep": [0.005, 0.002], "sim.decimation": [4, 4]}, 0, 2)

    def args(per_process=(), env_set=()):
        return argparse.Namespace(env_set_per_process=list(per_process), env_set=list(env_set))

    (tmp_path / "run.yaml").write_text(yaml.safe_dump({"processes": 2, "env_set_per_process": per}))
    assert train.per_process_for(args(), None, 2) == {}  # a new run: only what is given
    assert train.per_process_for(args(), tmp_path, 2) == per  # a resume: the run's own
    given = train.per_process_for(args(["sim.decimation=[5,10]"]), tmp_path, 2)
    assert given == {"sim.timestep": [0.005, 0.002], "sim.decimation": [5, 10]}  # one key anew, the other kept
    alike = train.per_process_for(args([], ["sim.timestep=0.004"]), tmp_path, 2)
    assert alike == {"sim.decimation": [4, 10]}  # --set makes that key alike in every process
    with pytest.raises(UsageError, match=r"2 processes with .*--set-per-process 'sim.timestep=\[0.005,0.002\]'"):
        train.per_process_for(args(), tmp_path, 1)
    assert train.per_process_for(args(["sim.timestep=[0.005]", "sim.decimation=[4]"]), tmp_path, 1) == {
        "sim.timestep": [0.005],
        "sim.decimation": [4],
    }

    # a task's default (TrainCfg.env_per_process): new runs of 2+ processes, entry r % length,
    # a key given per process or by --set is left to that; never on resume or in one process
    assert train.per_process_for(args(), None, 2, per) == per
    assert train.per_process_for(args(), None, 4, per) == {k: v + v for k, v in per.items()}
    assert train.per_process_for(args(), None, 1, per) == {}
    assert train.per_process_for(args(["sim.decimation=[5,10]"]), None, 2, per) == {
        "sim.timestep": [0.005, 0.002],
        "sim.decimation": [5, 10],
    }
    assert train.per_process_for(args([], ["sim.timestep=0.004"]), None, 2, per) == {"sim.decimation": [4, 10]}
    saved_only = {"sim.timestep": [0.005, 0.005], "sim.decimation": [4, 4]}
    (tmp_path / "run.yaml").write_text(yaml.safe_dump({"processes": 2, "env_set_per_process": saved_only}))
    assert train.per_process_for(args(), tmp_path, 2, per) == saved_only
