"""train.py / play.py / export.py end to end on the CPU backend: a tiny training run,
resume, export with parity, headless play; and the errors users get for bad input."""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
import yaml

from legged_casters import registry
from legged_casters.config import load_yaml
from legged_casters.learning import progress
from legged_casters.robot import go2
from legged_casters.tools import common, export, play, render, train

REPO = Path(__file__).resolve().parents[1]
TASK = "go2_flat"
NUM_ENVS, STEPS = 4, 8
SMALL = [
    "--train-set",
    f"num_steps_per_env={STEPS}",
    "--train-set",
    "save_interval=1",
    "--train-set",
    "policy.actor_hidden_dims=[64,64]",
    "--train-set",
    "policy.critic_hidden_dims=[64,64]",
    "--console",
    "line",
]
UPDATES_PER_IT = 5 * 4  # PPO epochs x mini-batches of the default train config


def _train(root: Path, *extra: str) -> tuple[int, str]:
    argv = ["--task", TASK, "--num_envs", str(NUM_ENVS), "--sim_backend", "cpu", "--log_root", str(root), *extra]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = train.main(argv)
    return rc, out.getvalue()


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A 2-iteration run, then resumed for 1 more iteration. Returns (root, run_dir, outputs)."""
    root = tmp_path_factory.mktemp("logs")
    rc, out1 = _train(
        root, "--max_iterations", "2", "--run_name", "tiny", "--set", "commands.ranges.lin_vel_y=[-0.4,0.4]", *SMALL
    )
    assert rc == 0, out1
    (run_dir,) = (root / TASK).iterdir()
    # Snapshot of the first invocation's last checkpoint, before the resume adds model_3.
    first = torch.load(run_dir / "model_2.pt", weights_only=True)
    # A curriculum state the resumed env must pick up from the checkpoint.
    first["infos"]["env_state"]["command_ranges"]["lin_vel_x"] = [-1.5, 1.5]
    torch.save(first, run_dir / "model_2.pt")
    rc, out2 = _train(root, "--resume", "--max_iterations", "1")
    assert rc == 0, out2
    return root, run_dir, first, out1, out2


@pytest.fixture(autouse=False)
def no_simulation(monkeypatch):
    """Fail the test if any env (and so any simulation) is constructed."""

    def boom(self, cfg):
        raise AssertionError("a simulation was started")

    monkeypatch.setattr(registry.get_task(TASK).env_class, "__init__", boom)


# --- training, resume ---------------------------------------------------------------------------
def test_run_folder_holds_checkpoints_configs_git_state_and_events(run):
    root, run_dir, _, out1, _ = run
    assert run_dir.parent == root / TASK and run_dir.name.endswith("_tiny")
    assert common.RUN_DIR_RE.match(run_dir.name)
    names = {p.name for p in run_dir.iterdir()}
    # One convention: model_<n>.pt is the policy after n iterations ("it n/total").
    assert {"model_1.pt", "model_2.pt", "model_3.pt", "env.yaml", "train.yaml", "run.yaml"} <= names
    assert "model_0.pt" not in names
    assert {"git.yaml", "git.diff", "command.txt"} <= names
    assert any(n.startswith("events.out.tfevents") for n in names)
    assert not [n for n in names if n.endswith(".tmp")]
    env_cfg = load_yaml(type(registry.get_task(TASK).env_cfg), run_dir / "env.yaml")
    assert env_cfg.num_envs == NUM_ENVS and env_cfg.sim.backend == "cpu"
    assert env_cfg.commands.ranges.lin_vel_y == (-0.4, 0.4)  # --set landed in the run's config
    train_cfg = load_yaml(type(registry.get_task(TASK).train_cfg), run_dir / "train.yaml")
    assert train_cfg.num_steps_per_env == STEPS and train_cfg.policy.actor_hidden_dims == (64, 64)
    git = yaml.safe_load((run_dir / "git.yaml").read_text())
    assert len(git["commit"]) == 40 and isinstance(git["dirty"], bool)
    commands = (run_dir / "command.txt").read_text()
    assert commands.count("train.py") == 2 and "--resume" in commands  # first invocation and the resume
    assert yaml.safe_load((run_dir / "run.yaml").read_text())["task"] == TASK
    # One progress line per iteration, with throughput and ETA.
    lines = [line for line in out1.splitlines() if line.startswith(f"[{TASK}] it ")]
    assert len(lines) == 2 and "steps/s" in lines[0] and "ETA" in lines[0] and "mean reward" in lines[0]
    assert lines[0].startswith(f"[{TASK}] it 1/2 ") and lines[1].startswith(f"[{TASK}] it 2/2 ")
    assert "Learning iteration" not in out1  # --console line: only the progress line
    # The deterministic evaluation runs on the first and the last iteration (and every 25th).
    assert all("eval |err| vx" in line and "falls" in line for line in lines)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"Eval/vx_error", "Eval/vy_error", "Eval/wz_error", "Eval/falls", "Eval/time_share"} <= tags
    assert {"Eval/scenario/wz_+0.8", "Eval/scenario/wz_-0.8", "Eval/scenario/vx_+0.5"} <= tags  # each way
    assert {f"Noise/std_{j}" for j in go2.ACTUATED_JOINTS} <= tags
    # The best-evaluated policy so far is kept as model_best.pt, reachable as --checkpoint best.
    best = common.find_checkpoint(run_dir, "best")
    assert best.name == "model_best.pt"
    saved = torch.load(best, weights_only=True)
    score = progress.eval_score(saved["infos"]["eval"])
    assert saved["infos"]["eval_score"] == pytest.approx(score)
    assert score == pytest.approx(min(e.value for e in events.Scalars("Eval/score")), rel=1e-5)


def test_checkpoints_load_weights_only_and_carry_env_state(run):
    _, run_dir, _, _, _ = run
    ckpt = torch.load(run_dir / "model_1.pt", weights_only=True)
    assert ckpt["iter"] == 0  # rsl_rl's own field: the index (from 0) of the last iteration done
    assert ckpt["infos"]["task"] == TASK
    assert ckpt["infos"]["env_state"]["command_ranges"]["lin_vel_x"] == [-1.0, 1.0]
    assert {"actor_state_dict", "critic_state_dict", "optimizer_state_dict"} <= set(ckpt)


def test_resume_continues_iterations_optimizer_normaliser_and_curriculum(run):
    _, run_dir, first, _, out2 = run
    resumed = torch.load(run_dir / "model_3.pt", weights_only=True)
    assert resumed["iter"] == 2  # iterations 1, 2, then 3: numbering continues, nothing overwritten
    assert f"resumed {run_dir / 'model_2.pt'} after 2 iterations" in out2
    assert f"[{TASK}] it 3/3 " in out2
    assert "Learning iteration 3/3" in out2  # rsl_rl's block report (the default) counts the same way
    # Adam's step count continues from the checkpoint's (a fresh optimizer would restart at one iteration's).
    steps_before = max(s["step"].item() for s in first["optimizer_state_dict"]["state"].values())
    steps_after = max(s["step"].item() for s in resumed["optimizer_state_dict"]["state"].values())
    assert steps_before == 2 * UPDATES_PER_IT and steps_after == 3 * UPDATES_PER_IT
    # The observation normaliser keeps counting samples.
    count = "obs_normalizer.count"
    assert resumed["actor_state_dict"][count] == first["actor_state_dict"][count] + NUM_ENVS * STEPS
    # The curriculum state in the checkpoint was restored into the env and saved again.
    assert resumed["infos"]["env_state"]["command_ranges"]["lin_vel_x"] == [-1.5, 1.5]
    assert len(list(run_dir.glob("git_resume_*.yaml"))) == 1


def test_atomic_save_never_leaves_a_half_written_newest_file(tmp_path, monkeypatch):
    path = tmp_path / "model_5.pt"
    common.save_checkpoint_atomic({"w": torch.ones(3)}, path)
    real_save = torch.save

    def dying_save(obj, f, *a, **kw):
        f.write(b"PK\x03\x04 half a checkpoint")
        raise KeyboardInterrupt  # killed while writing

    monkeypatch.setattr(torch, "save", dying_save)
    with pytest.raises(KeyboardInterrupt):
        common.save_checkpoint_atomic({"w": torch.zeros(3)}, path)
    monkeypatch.setattr(torch, "save", real_save)
    assert torch.equal(torch.load(path, weights_only=True)["w"], torch.ones(3))
    assert [p.name for p in tmp_path.iterdir()] == ["model_5.pt"]
    # A temporary file is never taken for a checkpoint.
    (tmp_path / ".model_9.pt.abc.tmp").write_bytes(b"junk")
    assert common.find_checkpoint(tmp_path, None) == path


def test_newest_checkpoint_is_by_iteration_number(tmp_path):
    for it in (2, 10, 9):
        (tmp_path / f"model_{it}.pt").write_bytes(b"x")
    assert common.find_checkpoint(tmp_path, None).name == "model_10.pt"
    assert common.find_checkpoint(tmp_path, "9").name == "model_9.pt"
    assert common.find_checkpoint(tmp_path, "model_2.pt").name == "model_2.pt"


# --- export ------------------------------------------------------------------------------------------
SCHEMA_KEYS = [
    "format_version",
    "task",
    "robot",
    "joint_names",
    "joint_control",
    "default_joint_pos",
    "action_scale",
    "clip_actions",
    "kp",
    "kd",
    "torque_limits",
    "joint_pos_limits",
    "control_dt",
    "physics_dt",
    "observation",
    "propulsion_modes",
    "files",
    "onnx",
]


@pytest.fixture(scope="module")
def exported(run, tmp_path_factory):
    root, run_dir, _, _, _ = run
    out = tmp_path_factory.mktemp("exported")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = export.main(["--task", TASK, "--log_root", str(root), "--out", str(out)])
    assert rc == 0, buf.getvalue()
    return out, buf.getvalue()


def test_export_writes_single_file_onnx_torchscript_and_the_deployment_yaml(exported):
    out, log = exported
    names = sorted(p.name for p in out.iterdir())
    assert names == ["env.yaml", "policy.onnx", "policy.pt", "policy.yaml", "train.yaml"]
    meta = yaml.safe_load((out / "policy.yaml").read_text())
    assert list(meta) == SCHEMA_KEYS
    assert meta["format_version"] == 1 and meta["task"] == TASK and meta["robot"] == "point"
    assert meta["joint_names"] == list(go2.ACTUATED_JOINTS)
    assert meta["default_joint_pos"] == pytest.approx(go2.default_joint_positions())
    assert meta["kp"] == go2.kp() and meta["kd"] == go2.kd() and meta["torque_limits"] == go2.torque_limits()
    assert meta["joint_pos_limits"] == [list(r) for r in go2.joint_ranges()]
    assert meta["control_dt"] == pytest.approx(0.02) and meta["physics_dt"] == pytest.approx(0.002)
    assert meta["action_scale"] == 0.25 and meta["clip_actions"] == 100.0
    terms = meta["observation"]["terms"]
    assert [t["name"] for t in terms] == list(registry.get_task(TASK).env_class.OBSERVATIONS["policy"])
    assert sum(t["dim"] for t in terms) == meta["observation"]["dim"] == 48
    assert {t["name"]: t["scale"] for t in terms}["ang_vel"] == 0.25
    assert meta["propulsion_modes"] == {}  # go2_flat has no modes
    assert meta["files"] == {"onnx": "policy.onnx", "torchscript": "policy.pt"}
    assert meta["onnx"] == {"input": "obs", "output": "actions"}
    model = onnx.load(str(out / "policy.onnx"))
    props = {p.key: p.value for p in model.metadata_props}
    assert yaml.safe_load(props["policy.yaml"]) == meta
    (inp,), (outp,) = model.graph.input, model.graph.output
    assert inp.name == "obs" and outp.name == "actions"
    assert inp.type.tensor_type.shape.dim[0].dim_param  # dynamic batch axis
    assert inp.type.tensor_type.shape.dim[1].dim_value == 48
    assert "parity" in log


def test_exported_files_match_the_training_actor_on_real_observations(run, exported):
    """Training actor (rsl_rl MLPModel, deterministic, normaliser on), TorchScript and
    onnxruntime agree within 1e-5 on observations of a rollout, batch > 1."""
    root, run_dir, _, _, _ = run
    out, _ = exported
    sel = common.select_checkpoint(_sel_args(root, load_run=str(run_dir)), None)
    env = common.make_eval_env(sel, num_envs=6, overrides=[])
    actor = export.load_actor(env, sel.train_cfg, sel.ckpt, sel.ckpt_path)
    assert actor.obs_normalizer.count > 0  # a trained normaliser, not the identity
    torch.manual_seed(3)
    for _ in range(15):
        obs, *_ = env.step(torch.randn(6, 12) * 0.5)
    paths = {"torchscript": out / "policy.pt", "onnx": out / "policy.onnx"}
    err = export.check_parity(actor, paths, obs["policy"])
    assert err["torchscript"] < 1e-5 and err["onnx"] < 1e-5, err
    err1 = export.check_parity(actor, paths, obs["policy"][:1])  # batch 1 through the dynamic axis
    assert max(err1.values()) < 1e-5
    env.close()


def _sel_args(root, **kw):
    import argparse

    base = {"task": TASK, "experiment_name": None, "load_run": None, "checkpoint": None, "log_root": str(root)}
    return argparse.Namespace(**{**base, **kw})


# --- play ----------------------------------------------------------------------------------------------
def test_headless_play_writes_a_video_and_plots(run, tmp_path):
    root, _, _, _, _ = run
    backend, errors = render.probe_gl_backend()
    if backend is None:
        pytest.skip(f"no offscreen OpenGL here: {errors}")
    out = tmp_path / "play"
    argv = ["--task", TASK, "--log_root", str(root), "--headless", "--duration", "1.0", "--fps", "10"]
    argv += ["--width", "160", "--height", "120", "--fast_render", "--out", str(out)]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert play.main(argv) == 0, buf.getvalue()
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        "model_3_steps.mp4",
        "model_3_steps_data.npz",
        "model_3_steps_joints.png",
        "model_3_steps_velocity.png",
    ]
    import imageio.v2 as imageio

    frames = [f for f in imageio.get_reader(str(out / "model_3_steps.mp4")).iter_data()]
    assert len(frames) == 10 and frames[0].shape == (120, 160, 3)
    assert np.std(frames[5]) > 5  # a picture, not a blank frame
    data = np.load(out / "model_3_steps_data.npz")
    assert data["t"].shape == (50,) and data["measured"].shape == (50, 3) and data["joint_pos"].shape == (50, 12)
    # steps profile: stand, then -0.6 m/s, then +0.6 m/s
    assert data["command"][0, 0] == 0 and data["command"][25, 0] == pytest.approx(-0.6)
    assert data["command"][-1, 0] == pytest.approx(0.6)


def test_play_runs_an_exported_onnx_policy(exported, tmp_path):
    out, _ = exported
    argv = ["--policy", str(out / "policy.onnx"), "--no_video", "--headless", "--profile", "slalom"]
    argv += ["--duration", "0.5", "--num_envs", "1", "--out", str(tmp_path)]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert play.main(argv) == 0, buf.getvalue()
    assert (tmp_path / "policy_slalom_velocity.png").is_file()
    data = np.load(tmp_path / "policy_slalom_data.npz")
    assert data["command"][0, 1] == pytest.approx(0.4)  # slalom starts to the left


def test_play_takes_an_export_folder_like_evaluate_and_the_bridge(exported, tmp_path):
    out, _ = exported
    argv = ["--policy", str(out), "--no_video", "--headless", "--duration", "0.2", "--num_envs", "1"]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert play.main([*argv, "--out", str(tmp_path)]) == 0, buf.getvalue()
    assert any(tmp_path.glob("policy_*_velocity.png"))


def test_a_task_without_runs_plays_its_shipped_policy_under_the_folders_task(tmp_path):
    """play.py with no run under the log root plays the shipped caster_omni folder, under the
    task its policy.yaml names (caster_omni_sym, whose configs it was trained with)."""
    argv = ["--log_root", str(tmp_path), "--no_video", "--headless"]
    argv += ["--duration", "0.2", "--num_envs", "1", "--out", str(tmp_path / "out")]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert play.main(argv) == 0, buf.getvalue()
    assert "playing the shipped policy" in buf.getvalue() and "caster_omni_sym" in buf.getvalue()
    assert any((tmp_path / "out").glob("policy_*_velocity.png"))


# --- bad input fails before any simulation ----------------------------------------------------------------
@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--task", "nope"], "unknown task 'nope'; known tasks: "),
        (["--set", "commands.nope=1"], "unknown config field 'commands.nope'"),
        (["--set", "control.action_scale=fast"], "expected a number"),
        (["--set", "num_envs=0"], "below the minimum"),
        (["--set", "commands.ranges.lin_vel_x=[1]"], "expected 2 values"),
        (["--set", "noequals"], "must look like name.path=value"),
        (["--train-set", "algorithm.gamma=2"], "above the maximum"),
        (["--train-set", "policy.activation=swish"], "is not allowed"),
        (["--num_envs", "0"], "--num_envs must be at least 1"),
        (["--load_run", "x"], "add --resume"),
        (["--device", "tpu"], "--device"),
    ],
)
def test_bad_train_flags_exit_2_with_what_is_allowed(no_simulation, tmp_path, capsys, argv, message):
    assert train.main([*argv, "--log_root", str(tmp_path)]) == common.EXIT_USAGE
    assert message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # no run folder either


def test_bad_backend_is_refused_by_the_parser(no_simulation, capsys):
    with pytest.raises(SystemExit) as exc:
        train.main(["--sim_backend", "gpu"])
    assert exc.value.code == common.EXIT_USAGE
    err = capsys.readouterr().err
    assert "invalid choice: 'gpu'" in err and "'auto', 'cpu', 'warp'" in err


def test_cuda_device_without_cuda_is_refused(no_simulation, tmp_path, capsys):
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    assert train.main(["--device", "cuda", "--log_root", str(tmp_path)]) == common.EXIT_USAGE
    assert "CUDA is not available" in capsys.readouterr().err


def test_resume_without_runs_or_with_a_missing_checkpoint(run, no_simulation, tmp_path, capsys):
    assert train.main(["--task", TASK, "--resume", "--log_root", str(tmp_path)]) == common.EXIT_USAGE
    assert "no run with a checkpoint under" in capsys.readouterr().err
    root, run_dir, _, _, _ = run
    argv = ["--task", TASK, "--resume", "--log_root", str(root)]
    assert train.main([*argv, "--checkpoint", "99"]) == common.EXIT_USAGE
    assert "checkpoints there: model_1.pt, model_2.pt, model_3.pt" in capsys.readouterr().err
    assert train.main([*argv, "--load_run", "nope"]) == common.EXIT_USAGE
    assert f"runs there: {run_dir.name}" in capsys.readouterr().err


def test_corrupt_or_truncated_checkpoints_give_a_clear_error(run, no_simulation, tmp_path, capsys):
    _, run_dir, _, _, _ = run
    copy = tmp_path / TASK / run_dir.name
    shutil.copytree(run_dir, copy)
    newest = copy / "model_3.pt"
    good = newest.read_bytes()
    for bad in (good[: len(good) // 2], b"not a checkpoint at all"):
        newest.write_bytes(bad)
        assert train.main(["--task", TASK, "--resume", "--log_root", str(tmp_path)]) == common.EXIT_FAILURE
        err = capsys.readouterr().err
        assert f"checkpoint {newest} cannot be read" in err and "corrupt" in err
        assert export.main(["--task", TASK, "--log_root", str(tmp_path)]) == common.EXIT_FAILURE
        assert "cannot be read" in capsys.readouterr().err


def test_play_flags_are_checked_before_the_simulation(no_simulation, tmp_path, capsys):
    argv = ["--task", TASK, "--log_root", str(tmp_path), "--headless"]
    assert play.main([*argv, "--policy", "zero", "--profile", "modes"]) == common.EXIT_USAGE
    assert "needs a task with propulsion modes" in capsys.readouterr().err
    # nothing trained under this root, and a checkpoint asked for (no fallback to a shipped policy)
    assert play.main([*argv, "--checkpoint", "5"]) == common.EXIT_USAGE
    assert "no run with a checkpoint" in capsys.readouterr().err
    assert play.main([*argv, "--policy", str(tmp_path / "missing.onnx")]) == common.EXIT_USAGE
    assert "no such file" in capsys.readouterr().err
    assert play.main([*argv, "--policy", "zero", "--set", "rewards.nope.x=1"]) == common.EXIT_USAGE
    assert "unknown config field" in capsys.readouterr().err
    assert play.main([*argv, "--policy", "zero", "--mode", "four_wheel"]) == common.EXIT_USAGE
    assert "--mode needs a task with propulsion modes; go2_flat has none" in capsys.readouterr().err
    caster = ["--task", "caster_omni", "--log_root", str(tmp_path), "--headless", "--policy", "zero"]
    assert play.main([*caster, "--mode", "sideways"]) == common.EXIT_USAGE
    assert "known: four_wheel, front_wheel, rear_wheel" in capsys.readouterr().err
    assert play.main([*caster, "--profile", "modes", "--mode", "rear_wheel"]) == common.EXIT_USAGE
    assert "leave --mode out" in capsys.readouterr().err
    # the steps profile runs its own commands: a --cmd given beside it would be ignored
    assert play.main([*caster, "--profile", "steps", "--cmd", "-1", "0", "0"]) == common.EXIT_USAGE
    assert "does not read --cmd" in capsys.readouterr().err


def test_play_cmd_alone_holds_that_command_and_no_flags_run_the_steps():
    """--cmd without --profile selects the constant profile (it used to be ignored under the
    default steps profile); with neither, the steps profile and the default command."""
    parser = play.build_parser()
    for argv, profile, cmd in (
        (["--cmd", "-1", "0", "0"], "constant", (-1.0, 0.0, 0.0)),
        ([], "steps", play.DEFAULT_CMD),
        (["--profile", "slalom"], "slalom", play.DEFAULT_CMD),
        (["--profile", "constant"], "constant", play.DEFAULT_CMD),
    ):
        args = parser.parse_args(argv)
        play.resolve_profile(args)
        assert (args.profile, tuple(args.cmd)) == (profile, cmd), argv


def test_default_task_prefers_caster_omni():
    tasks = registry.list_tasks()
    assert common.default_task() == ("caster_omni" if "caster_omni" in tasks else tasks[0])


def test_entry_point_exit_code_and_message():
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run(
        [sys.executable, str(REPO / "train.py"), "--task", "nope"], capture_output=True, text=True, env=env, timeout=120
    )
    assert out.returncode == 2
    assert "train.py: error: unknown task 'nope'; known tasks: " in out.stderr and TASK in out.stderr


# --- a task with propulsion modes and casters ------------------------------------------------------------
CASTER = "caster_omni"
needs_caster = pytest.mark.skipif(CASTER not in registry.list_tasks(), reason="caster_omni is not registered")


@needs_caster
def test_caster_task_metadata_lists_its_modes_and_observation_layout():
    env = registry.make_env("caster_omni_paper", ["sim.backend=cpu"], num_envs=1)
    meta = export.policy_metadata(env, "caster_omni_paper")
    env.close()
    assert meta["robot"] == "caster"
    terms = [(t["name"], t["dim"]) for t in meta["observation"]["terms"]]
    assert terms == [
        ("commands", 3),
        ("mode_mask", 4),
        ("ang_vel", 3),
        ("projected_gravity", 3),
        ("joint_pos", 12),
        ("joint_vel", 12),
        ("actions", 12),
    ]
    assert meta["observation"]["dim"] == 49
    assert meta["propulsion_modes"] == {
        "four_wheel": [0, 0, 0, 0],
        "front_wheel": [0, 0, 1, 1],
        "rear_wheel": [1, 1, 0, 0],
    }
    assert yaml.safe_load(export.metadata_yaml(meta)) == meta


@needs_caster
def test_modes_profile_switches_4wd_fwd_rwd_and_plots_the_casters(tmp_path):
    argv = ["--task", CASTER, "--policy", "zero", "--profile", "modes", "--duration", "0.6", "--num_envs", "1"]
    argv += ["--headless", "--no_video", "--out", str(tmp_path)]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert play.main(argv) == 0, buf.getvalue()
    assert (tmp_path / "zero_modes_casters.png").is_file()
    data = np.load(tmp_path / "zero_modes_data.npz")
    assert data["phi"].shape == (30, 4) and data["theta_diffz"].shape == (30, 4)
    masks = [tuple(int(v) for v in row) for row in data["mode"]]
    assert list(dict.fromkeys(masks)) == [(0, 0, 0, 0), (0, 0, 1, 1), (1, 1, 0, 0)]
    assert masks[0] == (0, 0, 0, 0) and masks[-1] == (1, 1, 0, 0)
    if "env_mode" in data:  # the env took each mode (and kept it through resets)
        assert np.array_equal(data["env_mode"], data["mode"])


@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="needs xvfb-run (Debian package xvfb)")
def test_viewer_runs_under_a_virtual_display(exported, tmp_path):
    out, _ = exported
    cmd = ["xvfb-run", "-a", "-s", "-screen 0 800x600x24", sys.executable, str(REPO / "play.py")]
    cmd += [
        "--policy",
        str(out / "policy.pt"),
        "--viewer",
        "--duration",
        "0.4",
        "--num_envs",
        "1",
        "--out",
        str(tmp_path),
    ]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("DISPLAY", None)
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=180)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "profile steps: 20 steps" in res.stdout
    assert (tmp_path / "policy_steps_velocity.png").is_file() and not list(tmp_path.glob("*.mp4"))


# --- rough edges a new user hit ------------------------------------------------------------------
def test_play_and_evaluate_take_a_training_checkpoint_as_policy(run, tmp_path):
    """A training checkpoint given to --policy is played from its run, not called corrupt."""
    _, run_dir, _, _, _ = run
    argv = ["--policy", str(run_dir / "model_3.pt"), "--no_video", "--headless", "--profile", "constant"]
    argv += ["--duration", "0.2", "--num_envs", "1", "--out", str(tmp_path)]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert play.main(argv) == 0, buf.getvalue()
    assert "is a training checkpoint: playing it from its run" in buf.getvalue()
    assert (tmp_path / "model_3_constant_data.npz").is_file()
    assert f"wrote {tmp_path / 'model_3_constant_data.npz'}" in buf.getvalue()  # the data file is listed too


def test_corrupt_checkpoint_message_is_ours_and_verbose_adds_the_loaders(run, no_simulation, tmp_path, capsys):
    _, run_dir, _, _, _ = run
    copy = tmp_path / TASK / run_dir.name
    shutil.copytree(run_dir, copy)
    (copy / "model_3.pt").write_bytes((copy / "model_3.pt").read_bytes()[:1000])
    argv = ["--task", TASK, "--log_root", str(tmp_path)]
    assert export.main(argv) == common.EXIT_FAILURE
    err = capsys.readouterr().err
    assert "is corrupt" in err and "pick another with --checkpoint" in err and "--verbose" in err
    assert "PytorchStreamReader" not in err and "likelihood" not in err  # no torch text cut mid-sentence
    assert export.main([*argv, "--verbose"]) == common.EXIT_FAILURE
    assert "the loader said:" in capsys.readouterr().err


def test_renamed_run_folders_are_found_by_contents_newest_first(run, tmp_path):
    _, run_dir, _, _, _ = run
    exp = tmp_path / TASK
    older, newer = exp / "zz_my_old_run", exp / "aa_renamed"
    shutil.copytree(run_dir, older)
    shutil.copytree(run_dir, newer)
    for path, created in ((older, "2020-01-01T00:00:00"), (newer, "2030-01-01T00:00:00")):
        info = yaml.safe_load((path / common.RUN_FILE).read_text())
        info["created"] = created
        (path / common.RUN_FILE).write_text(yaml.safe_dump(info))
    (exp / "notes").mkdir()  # a folder without run.yaml or checkpoints is not a run
    assert common.list_runs(tmp_path, TASK) == [older, newer]
    assert common.find_run(tmp_path, TASK, None) == newer


def test_help_states_each_default_once():
    for parser in (train.build_parser(), play.build_parser(), export.build_parser()):
        text = parser.format_help()
        assert "(default: None)" not in text and "(default: [])" not in text
        formatter = parser._get_formatter()
        for action in parser._actions:
            assert formatter._get_help_string(action).count("(default:") <= 1, action.option_strings
    text = play.build_parser().format_help()
    assert "video width in pixels (default: 640)" in " ".join(text.split())


def test_watch_hint_names_the_resumed_runs_own_folder(run, tmp_path):
    _, run_dir, _, _, _ = run
    copy = tmp_path / "elsewhere" / run_dir.name
    shutil.copytree(run_dir, copy)
    rc, out = _train(tmp_path / "default_root", "--resume", "--load_run", str(copy), "--max_iterations", "1")
    assert rc == 0, out
    assert f"watch: tensorboard --logdir {copy} " in out
    assert not (copy / "git").exists()  # rsl_rl's empty git/ folder is not made (git.yaml/git.diff are ours)


def test_play_of_a_runs_export_writes_next_to_the_run_not_into_the_export(run, tmp_path):
    root, run_dir, _, _, _ = run
    copy = tmp_path / TASK / run_dir.name
    shutil.copytree(run_dir, copy)
    with contextlib.redirect_stdout(io.StringIO()):
        assert export.main(["--task", TASK, "--log_root", str(tmp_path), "--load_run", str(copy)]) == 0
    before = sorted(p.name for p in (copy / "exported").iterdir())
    argv = ["--policy", str(copy / "exported" / "policy.onnx"), "--no_video", "--headless", "--duration", "0.2"]
    argv += ["--num_envs", "1", "--log_root", str(tmp_path)]
    with contextlib.redirect_stdout(io.StringIO()):
        assert play.main(argv) == 0
    assert sorted(p.name for p in (copy / "exported").iterdir()) == before
    assert (copy / "play" / "policy_steps_data.npz").is_file()


def test_each_shipped_policy_played_gets_its_own_output_folder(tmp_path):
    """The shipped caster_omni and a copy of it under another name both name caster_omni_sym
    as their task: playing one must not overwrite the other's plots, and nothing is written
    into resources/."""
    copy = tmp_path / "mine"
    shutil.copytree(common.SHIPPED_POLICIES / "caster_omni", copy)
    outs = []
    for folder in (common.SHIPPED_POLICIES / "caster_omni", copy):
        args = play.build_parser().parse_args(["--policy", str(folder), "--log_root", str(tmp_path)])
        with contextlib.redirect_stdout(io.StringIO()):
            source = play._resolve_source(args, None)
        assert source.task == "caster_omni_sym"
        outs.append(source.out_dir)
    assert outs == [tmp_path / "caster_omni_sym" / "play_caster_omni", tmp_path / "caster_omni_sym" / "play_mine"]


def _train_cmd(root: Path, *extra: str) -> list[str]:
    """train.py as a user starts it, small, 200 iterations under `root`."""
    return [sys.executable, "train.py", "--task", TASK, "--num_envs", str(NUM_ENVS), "--sim_backend", "cpu",
            "--log_root", str(root), "--max_iterations", "200", "--console", "line", *SMALL, *extra]  # fmt: skip


def test_kill_stops_training_like_ctrl_c(tmp_path, stop_training):
    """SIGTERM (and SIGINT to a process started in the background, which would otherwise
    ignore it) ends training with the newest checkpoint and the command that continues."""
    for sig in (signal.SIGTERM, signal.SIGINT):
        # started as a shell script's `train.py &` would be: SIGINT ignored
        proc, out = stop_training(_train_cmd(tmp_path), " it 2/200", lambda p, sig=sig: p.send_signal(sig),
                                  preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))  # fmt: skip
        assert proc.returncode == 130, out[-2000:]
        assert "interrupted; newest checkpoint" in out and "--resume --load_run" in out


def test_a_stop_before_the_first_checkpoint_offers_no_resume(tmp_path, stop_training):
    """Stopped before anything was saved, train.py says there is nothing to continue from
    instead of a --resume command that would fail."""
    cmd = _train_cmd(tmp_path, "--train-set", "save_interval=1000")
    proc, out = stop_training(cmd, " it 2/200", lambda p: p.send_signal(signal.SIGTERM))
    assert proc.returncode == 130, out[-2000:]
    assert "interrupted before the first checkpoint (saved every 1000 iterations)" in out, out[-2000:]
    assert "no model_<iteration>.pt to continue from" in out and "--resume" not in out
    assert not list(tmp_path.rglob("model_[0-9]*.pt"))  # (model_best.pt may exist: an evaluation, not a state)


@needs_caster
def test_play_tells_a_time_limit_reset_from_a_fall(tmp_path):
    """A reset at the episode's time limit is not a fall: the data marks it (time_out) and the
    summary line counts it apart; the standing zero policy never falls."""
    argv = ["--task", CASTER, "--policy", "zero", "--profile", "constant", "--duration", "0.5", "--num_envs", "1"]
    argv += ["--set", "episode_length_s=0.2", "--headless", "--no_video", "--out", str(tmp_path)]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert play.main(argv) == 0, buf.getvalue()
    data = np.load(tmp_path / "zero_constant_data.npz")
    assert data["done"].sum() == 2 and np.array_equal(data["time_out"], data["done"])
    assert "robot 0 resets 2 (0 falls, 2 at the episode's time limit)" in buf.getvalue()


def _verdict_of(out: str) -> tuple[str, list[str]]:
    """'X/Y' and the measured values of the FAIL lines of one evaluate.py output."""
    passed = out.split("verdict: ")[1].split(" checks")[0]
    fails = [line.rsplit("(measured ", 1)[1].rstrip(")") for line in out.splitlines() if line.startswith("FAIL  ")]
    return passed, fails


def _quick_evaluation(root: Path, run_dir: Path):
    """evaluate.py on `run_dir`'s quick scenarios: ev(*argv) -> (exit code, stdout)."""
    from legged_casters.tools import evaluate

    def ev(*argv):
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            rc = evaluate.main(["--log_root", str(root), "--load_run", str(run_dir), "--scenarios", "quick", *argv])
        return rc, buf.getvalue()

    return ev


def test_evaluate_ranks_checkpoints_as_each_evaluates_alone(run):
    """evaluate.py --checkpoints: each checkpoint's line agrees with `--checkpoint N` alone
    (checks passed, the failed checks' measurements), the table is ordered by falls, then
    checks passed, then the newest, and 'all' lists every saved checkpoint once."""

    root, run_dir, _, _, _ = run
    ev = _quick_evaluation(root, run_dir)

    rc, ranked = ev("--checkpoints", "3,1,3")
    assert rc == 0, ranked
    table = [line for line in ranked.splitlines() if line.startswith("| ") and "model_" in line]
    assert len(table) == 2  # 3 given twice: evaluated once
    rows = {}
    for line in table:
        cells = [c.strip() for c in line.strip("|").split("|")]
        rows[cells[1]] = (int(cells[0]), int(cells[2]), cells[3], int(cells[4]), cells[5])
    for it in (1, 3):
        rc, alone = ev("--checkpoint", str(it))
        assert rc == 0, alone
        passed, fails = _verdict_of(alone)
        _, iteration, r_passed, _, failed = rows[f"model_{it}.pt"]
        assert (iteration, r_passed) == (it, passed)
        got = [] if failed == "-" else failed.split("; ")
        assert len(got) == len(fails) and all(g.endswith(" " + f) for g, f in zip(got, fails, strict=True))
    order = sorted(rows.values(), key=lambda r: r[0])
    keys = [(r[3], -int(r[2].split("/")[0]), -r[1]) for r in order]
    assert keys == sorted(keys)
    assert "first by this evaluation: " + min(rows, key=lambda k: rows[k][0]) in ranked

    rc, parallel = ev("--checkpoints", "3,1,3", "--jobs", "2")  # two processes: the same table
    assert rc == 0, parallel
    assert [ln for ln in parallel.splitlines() if ln.startswith("| ") and "model_" in ln] == table

    rc, selected = ev("--checkpoints", "3,1", "--select")
    assert rc == 0, selected
    first = min(rows, key=lambda k: rows[k][0])
    assert yaml.safe_load((run_dir / common.SELECTED_FILE).read_text())["file"] == first
    assert common.find_checkpoint(run_dir, None).name == first
    (run_dir / common.SELECTED_FILE).unlink()  # the other tests load the newest

    rc, everything = ev("--checkpoints", "all")
    assert rc == 0, everything
    listed = [
        line.split(" ")[2]
        for line in everything.splitlines()
        if line.startswith("[evaluate.py] ") and "/" in line.split(" ")[1]
    ]
    saved = sorted((p.name for p in run_dir.glob("model_*.pt")), key=lambda n: (n == "model_best.pt", len(n), n))
    assert listed == saved


def _tolerance_rows(out: str) -> dict[str, tuple[float, float, int, str]]:
    """{condition: (largest change m/s, rad/s, falls, within)} from the tolerance table."""
    head = out.index("| condition | largest change, m/s")
    rows = {}
    for line in out[head:].splitlines()[2:]:
        if not line.startswith("| "):
            break
        name, lin, ang, falls, within = (c.strip() for c in line.strip("|").split("|"))
        rows[name] = (float(lin.split()[0]), float(ang.split()[0]), int(falls), within)
    return rows


@pytest.fixture(scope="module")
def run_5ms(tmp_path_factory):
    """A 2-iteration run at 5 ms physics (decimation 4, the 20 ms control period): a task
    config that sets sim.timestep, as --physics-dt and --robot-clock need."""
    root = tmp_path_factory.mktemp("logs5ms")
    rc, out = _train(root, "--max_iterations", "2", "--set", "sim.timestep=0.005", "--set", "sim.decimation=4", *SMALL)
    assert rc == 0, out
    (run_dir,) = (root / TASK).iterdir()
    return root, run_dir


def test_evaluate_ranks_checkpoints_against_the_robot_clock_bar(run_5ms):
    """evaluate.py --checkpoints --robot-clock: each checkpoint's row holds what
    `--checkpoint N --robot-clock` alone prints (checks at 5 ms, falls per condition, the
    largest change of an error check under 2 ms or 20 ms latency, within the bar or not),
    and the table is ordered by falls at 5 ms, the bar, all falls, checks and the newest."""
    from legged_casters.tools import evaluate

    root, run_dir = run_5ms
    ev = _quick_evaluation(root, run_dir)

    rc, ranked = ev("--checkpoints", "1,2", "--robot-clock")
    assert rc == 0, ranked
    head = ranked.index("| rank | checkpoint |")
    table = [line for line in ranked[head:].splitlines()[2:] if line.startswith("| ")]
    assert len(table) == 2
    rows = {}
    for line in table:
        k, file, iteration, passed, falls, *changes, within = (c.strip() for c in line.strip("|").split("|"))
        rows[file] = (int(k), int(iteration), passed, [int(f) for f in falls.split(" / ")], changes, within)
    for it in (1, 2):
        rc, alone = ev("--checkpoint", str(it), "--robot-clock")
        assert rc == 0, alone
        assert alone.count("verdict: ") == 3  # 5 ms, 2 ms, 20 ms latency: nothing else
        tol = _tolerance_rows(alone)
        assert list(tol) == list(evaluate.ROBOT_CLOCK)
        _, iteration, passed, falls, changes, within = rows[f"model_{it}.pt"]
        assert (iteration, passed) == (it, _verdict_of(alone)[0])
        assert falls == [t[2] for t in tol.values()]
        others = list(tol.values())[1:]
        assert len(changes) == len(others) == 2
        for cell, (lin, ang, _, ok) in zip(changes, others, strict=True):
            m = re.fullmatch(r"([+-][\d.]+) \(.*\); ([+-][\d.]+) \(.*\): (yes|no)", cell)
            assert m, cell
            assert (float(m.group(1)), float(m.group(2)), m.group(3)) == (lin, ang, ok)
        assert within == ("yes" if all(t[3] == "yes" for t in others) else "no")
    order = sorted(rows.values(), key=lambda r: r[0])
    keys = [(r[3][0], r[5] != "yes", sum(r[3]), -int(r[2].split("/")[0]), -r[1]) for r in order]
    assert keys == sorted(keys)
    assert "first by the robot-clock bar: " + min(rows, key=lambda k: rows[k][0]) in ranked


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--checkpoints", "two"], "'two' is neither an iteration, 'best' nor 'all'"),
        (["--checkpoints", ",,"], "give iterations and 'best'"),
        (["--checkpoints", "99"], "not found in"),
        (["--checkpoints", "1", "--checkpoint", "2"], "leave out --checkpoint"),
        (["--checkpoints", "1", "--sim2sim"], "leave out --sim2sim"),
        (["--checkpoints", "1", "--seeds", "0-1"], "leave out --seeds"),
        (["--sim2sim", "--robot-clock"], "not both"),
        (["--robot-clock", "--checkpoint", "1"], "needs a task whose config sets sim.timestep"),
        (["--robot-clock", "--physics-dt", "0.002"], "runs its own conditions"),
        (["--sim2sim", "--observation-delay-ms", "10"], "leave out --physics-dt, --action-latency-ms, --observation"),
        (["--checkpoints", "1", "--robot-clock", "--seeds", "x"], "expected seeds >= 0"),
        (["--seeds", "0-1", "--seed", "3"], "not both"),
        (["--seeds", "x"], "expected seeds >= 0"),
    ],
)
def test_evaluate_checkpoints_bad_input_exits_2(run, capsys, argv, message):
    from legged_casters.tools import evaluate

    root, run_dir, _, _, _ = run
    assert evaluate.main(["--log_root", str(root), "--load_run", str(run_dir), *argv]) == 2
    assert message in capsys.readouterr().err


def test_is_training_checkpoint_tells_exports_apart_without_warning(tmp_path):
    """play.py/evaluate.py ask whether a .pt is a training checkpoint: an exported TorchScript
    policy answers no from its archive alone (no TorchScript-dispatch warning), a training
    checkpoint yes, a damaged file no; load_checkpoint says which an exported file is."""
    ckpt = tmp_path / "model_1.pt"
    torch.save(dict.fromkeys(common.REQUIRED_CHECKPOINT_KEYS, 1), ckpt)
    damaged = tmp_path / "model_2.pt"
    damaged.write_bytes(b"not a checkpoint")
    exported = common.SHIPPED_POLICIES / "caster_omni" / "policy.pt"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert common.is_training_checkpoint(exported) is False
    assert [str(w.message) for w in caught] == []
    assert common.is_training_checkpoint(ckpt) is True
    assert common.is_training_checkpoint(damaged) is False
    with pytest.raises(common.CheckpointError, match="exported TorchScript policy"):
        common.load_checkpoint(exported)


def test_brake_measures_time_and_path_to_rest_and_to_the_zero_crossing():
    from legged_casters.tools import evaluate

    dt = 0.02
    k_cmd = int(round(evaluate.BRAKE_AT_S / dt))
    steps = k_cmd + 300
    # 1.5 m/s until the stop, then a linear brake to zero over 1.0 s, a wobble back to 0.15
    # at 1.5 s (not at rest for good yet), then still.
    vx = torch.full((steps,), 1.5)
    t = torch.arange(300) * dt
    vx[k_cmd:] = (1.5 * (1.0 - t / 1.0)).clamp(min=0.0)
    vx[k_cmd + 75] = 0.15
    xy = torch.zeros(steps, 2)
    xy[:, 0] = torch.cumsum(vx, 0) * dt
    stop = evaluate._brake("stop", 1.5, 0.0)
    out = evaluate._brake_measures(stop, vx, xy, steps, dt)
    assert out["v_at_cmd"] == pytest.approx(1.5)
    assert out["rest_s"] == pytest.approx(76 * dt)  # the wobble at step 75 is the last |vx| >= 0.1
    assert out["rest_m"] == pytest.approx(float(xy[k_cmd + 75, 0] - xy[k_cmd - 1, 0]), abs=1e-5)
    never = evaluate._brake_measures(stop, torch.full((steps,), 0.5), xy, steps, dt)
    assert never["rest_s"] == math.inf
    reverse = evaluate._brake("reverse", 1.5, -0.5)
    out = evaluate._brake_measures(reverse, vx - 0.5, xy, steps, dt)
    assert out["cross_s"] == pytest.approx(float((vx[k_cmd:] - 0.5 < 0).nonzero()[0] + 1) * dt)
    checks = evaluate.verdict([
        evaluate.ScenarioResult("stop from +1.5", "brake", (0, 0, 0), extra={"rest_s": 1.9, "rest_m": 1.6}),
        evaluate.ScenarioResult("hold flat", "hold", (0, 0, 0), extra={"max_drift_m": 0.05, "max_turn_deg": 6.0}),
        evaluate.ScenarioResult("hold 5deg", "hold", (0, 0, 0), falls=1, slope_deg=5.0,
                                extra={"max_drift_m": 0.0, "max_turn_deg": 0.0}),
        evaluate.ScenarioResult("reverse -2.0 to +0.5", "brake", (0.5, 0, 0), falls=1, extra={"cross_s": 1.1}),
    ])  # fmt: skip
    assert [ok for _, ok, _ in checks] == [False, False, False, False]  # 1.6 m > 1.5 m; 6 deg > 5 deg; a fall on 5 deg
    assert checks[2][2] == "1.10 s (1 fall)"  # in time, but fell: the measurement says why it fails


def test_a_start_after_a_stop_passes_on_its_own_axis_without_a_fall():
    from legged_casters.tools import evaluate

    s = evaluate._go_again(1.0, (0.0, 0.4, 0.0))
    start = 4.0 + evaluate.GO_STOPPED_S
    assert [t for t, _ in s.segments] == [0.0, 4.0, start] and s.command(start - 0.01) == (0.0, 0.0, 0.0)
    assert (s.measure_from, s.duration) == (start + evaluate.GO_WINDOW_S[0], start + evaluate.GO_WINDOW_S[1])
    assert evaluate._go_again(0.0, (0.5, 0.0, 0.0)).segments == ((0.0, (0.0, 0.0, 0.0)), (1.0, (0.5, 0.0, 0.0)))

    def go(cmd, err, falls=0):
        errors = dict(zip(("vx", "vy", "wz"), err, strict=True))
        return evaluate.ScenarioResult("go", "go", cmd, err=errors, falls=falls)

    checks = evaluate.verdict([
        go((0.0, 0.4, 0.0), (0.0, 0.1, 0.3)),  # vy within its 0.15: the wz error is not this start's axis
        go((0.0, 0.4, 0.0), (0.0, 0.1, 0.0), falls=1),
        go((0.0, 0.0, 0.8), (0.0, 0.0, 0.3)),  # wz over its 0.25
        go((-0.5, 0.0, 0.0), (0.1, 0.0, 0.0)),
    ])  # fmt: skip
    assert [ok for _, ok, _ in checks] == [True, False, False, True]
    assert "|vy error| <= 0.15" in checks[0][0] and checks[1][2] == "0.100 (1 fall)"
    assert evaluate.error_checks(checks[:2])["go: |vy error| <= 0.15, no fall"] == ("lin", 0.1)
    wheel = evaluate.verdict([go((0.0, 0.0, 0.8), (0.0, 0.0, 0.22))], "go2_wheel_flat")
    assert not wheel[0][1]  # the wheel task's own wz bar (0.2)


def test_a_selected_checkpoint_is_what_a_run_loads_by_default(tmp_path):
    from legged_casters.tools import evaluate

    for it in (50, 100, 150):
        (tmp_path / f"model_{it}.pt").write_bytes(b"x")
    assert common.find_checkpoint(tmp_path, None).name == "model_150.pt"
    with pytest.raises(common.UsageError, match="selected.yaml"):
        common.find_checkpoint(tmp_path, "selected")
    rows = [{"file": f"model_{it}.pt", "iteration": it, "passed": p, "checks": 20, "falls": f, "failed": []}
            for it, p, f in ((50, 12, 0), (100, 15, 1), (150, 11, 0))]  # fmt: skip
    top = min(rows, key=evaluate._rank_key)
    assert top["iteration"] == 50  # no fall first, then the most checks
    evaluate.write_selection(tmp_path, top, rows, "full", "training conditions")
    record = yaml.safe_load((tmp_path / common.SELECTED_FILE).read_text())
    assert record["file"] == "model_50.pt" and [r["iteration"] for r in record["ranked"]] == [50, 150, 100]
    assert common.find_checkpoint(tmp_path, None).name == "model_50.pt"
    assert common.find_checkpoint(tmp_path, "selected").name == "model_50.pt"
    assert common.find_checkpoint(tmp_path, "latest").name == "model_150.pt"
    assert common.find_checkpoint(tmp_path, None, newest=True).name == "model_150.pt"  # what a resume continues
    (tmp_path / "model_50.pt").unlink()
    with pytest.raises(common.UsageError, match="names no checkpoint"):
        common.find_checkpoint(tmp_path, None)
