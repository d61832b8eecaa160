"""dev/gpu_loan/gpu.py: the GPU check in its CPU mode (every stage, Warp on the CPU device),
the orchestrator's time limits, and the wheel planning (which packages, how they are
cut into device calls and joined back), all without a GPU or a network."""

from __future__ import annotations

import hashlib
import json
import os
import random
import subprocess
import sys
import textwrap
from importlib import metadata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
GPU_LOAN = REPO / "dev" / "gpu_loan"
"""The lent-GPU tooling: kept beside the package, not in it."""
GPU_PY = GPU_LOAN / "gpu.py"
sys.path.insert(0, str(GPU_LOAN))

import gpu_check  # noqa: E402
import gpu_wheels  # noqa: E402
from gpu_wheels import MIB, canonical  # noqa: E402


# --- the CPU mode of `run` ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def cpu_run(tmp_path_factory):
    out, work = tmp_path_factory.mktemp("out"), tmp_path_factory.mktemp("work")
    cmd = [sys.executable, str(GPU_PY), "run", "--cpu", "--out", str(out), "--work", str(work)]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=280)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads((out / "gpu_check.json").read_text()), out, proc.stdout


def test_cpu_run_has_every_stage(cpu_run):
    results, out, stdout = cpu_run
    assert list(results["stages"]) == list(gpu_check.STAGES)
    for name, stage in results["stages"].items():
        expected = "skipped" if name == "multi_gpu" else "ok"
        assert stage["status"] == expected, (name, stage.get("error"), stage.get("log_tail", "")[-1500:])
        assert stage["seconds"] is not None
    assert (out / "gpu_check.txt").read_text() in stdout
    report = [sys.executable, str(GPU_PY), "report", str(out / "gpu_check.json")]
    assert (
        subprocess.run(report, capture_output=True, text=True, check=True).stdout == (out / "gpu_check.txt").read_text()
    )
    assert (out / "gpu_check.log").stat().st_size > 0


def test_cpu_run_measures(cpu_run):
    s = cpu_run[0]["stages"]
    assert s["machine"]["result"]["warp"] and not s["machine"]["result"]["cuda_available"]
    rows = s["throughput"]["result"]["rows"]
    assert [(r["task"], r["num_envs"]) for r in rows] == [("caster_omni", 4), ("caster_omni", 8)]
    assert all(r["graph_off"]["rate"] > 0 and r["graph_off"]["steps"] >= 2 for r in rows)
    assert s["compile"]["result"]["tasks"]["caster_omni"]["rows"][0]["build_s"] > 0
    parity = s["parity"]["result"]
    assert parity["passed"] and parity["runs"][0]["moved"] > 0.02
    ov = s["overflow"]["result"]
    assert ov["naconmax_total"] == ov["nconmax_per_world"] * ov["num_envs"]
    assert 0 < ov["max_contacts_one_world"] <= ov["max_contacts_all_worlds"] <= ov["naconmax_total"]
    assert not ov["overflowed"] and set(ov["worlds_flagged"]) >= {"NEFC", "NARROWPHASE"}
    train = s["train"]["result"]
    assert train["rc"] == 0 and train["iterations"] == 2 and train["steps_per_s_mean"] > 0
    assert Path(train["run_dir"], "model_2.pt").is_file()
    ev = s["evaluate"]["result"]
    # the quick scenarios: 7 tracking checks, and the velocity estimator's error (caster_omni's actor has one)
    assert ev["rc"] == 0 and len(ev["checks"]) == ev["of"] == 8 and len(ev["table"]) > 2
    ex = s["export"]["result"]
    assert ex["rc"] == 0 and {"policy.pt", "policy.onnx", "policy.yaml"} <= set(ex["files"]) and ex["parity"]


FAKE_WORKER = """\
#!{python}
# Stands in for the worker: "slow" stages hang, "crash" stages exit, the others succeed.
import json, sys, time, os
args = sys.argv
work = args[args.index("--work") + 1]
for stage in args[args.index("--stages") + 1].split(","):
    now = time.time()
    with open(os.path.join(work, "progress.json"), "w") as f:
        json.dump({{"stage": stage, "started": now, "timeout_s": 0.2}}, f)
    if stage == "{slow}":
        time.sleep(60)
    if stage == "{crash}":
        sys.exit(3)
    with open(os.path.join(work, "stages", stage + ".json"), "w") as f:
        json.dump({{"stage": stage, "status": "ok", "seconds": 0.0, "result": {{"fake": True}}}}, f)
"""


def test_orchestrator_kills_a_stage_past_its_limit_and_goes_on(tmp_path, monkeypatch):
    fake = tmp_path / "python"
    fake.write_text(FAKE_WORKER.format(python=sys.executable, slow="compile", crash="overflow"))
    fake.chmod(0o755)
    settings = gpu_check.Settings.for_mode(True)
    settings.kill_grace_s = 0.5
    monkeypatch.setattr(gpu_check.Settings, "for_mode", classmethod(lambda cls, cpu: settings))
    stages = ["machine", "compile", "parity", "overflow", "train"]
    results = gpu_check.run_check(
        tmp_path / "out",
        cpu=True,
        budget_s=60,
        work=tmp_path / "work",
        stages=stages,
        python=str(fake),
        log=lambda *a: None,
    )
    status = {k: v["status"] for k, v in results["stages"].items()}
    assert status == {"machine": "ok", "compile": "timeout", "parity": "ok", "overflow": "crashed", "train": "ok"}
    assert "killed after its limit" in results["stages"]["compile"]["error"]
    assert results["stages"]["compile"]["seconds"] < 20
    assert json.loads((tmp_path / "out" / "gpu_check.json").read_text())["stages"]["train"]["status"] == "ok"


def test_stage_timeouts_keep_room_for_later_stages():
    s = gpu_check.Settings.for_mode(False)
    now = 1000.0
    # plenty of time: the stage's own limit
    assert gpu_check.stage_timeout(s, "train", ["evaluate", "export"], now, now + 1000) == s.limits["train"]
    # little time: what the later stages' floors need is kept back
    left = gpu_check.stage_timeout(s, "train", ["evaluate", "export"], now, now + 100)
    assert left == 100 - s.floors["evaluate"] - s.floors["export"]
    assert gpu_check.stage_timeout(s, "train", [], now, now - 5) == 0


def test_log_parsers_match_the_tools():
    """The lines the check reads from train.py, evaluate.py and Warp, as those print them."""
    line = (
        "[caster_omni] it 3/10 | 12,345 steps/s | 0.80 s/it (collect 0.60) | mean reward 0.1 | ep len 20 | ETA 0:00:05"
    )
    m = gpu_check.PROGRESS_RE.search(line)
    assert m and m["rate"] == "12,345" and m["collect"] == "0.60"
    log = "Module mujoco_warp._src.smooth 439a86e load on device 'cuda:0' took 2100.50 ms  (compiled)\n"
    log += "Module _nxn_broadphase 8df3760 load on device 'cuda:0' took 0.68 ms  (cached)\n"
    assert gpu_check.warp_modules(log) == {"compiled": 1, "compiled_s": 2.1, "cached": 1, "cached_s": 0.0}
    src = (REPO / "legged_casters" / "learning" / "progress.py").read_text()  # train.py's progress line
    assert "steps/s | {it_time:.2f} s/it " in src and "(collect {kw['collect_time']:.2f})" in src
    assert "verdict: {passed}/{len(checks)} checks passed" in (REPO / "legged_casters/tools/evaluate.py").read_text()


def test_report_reprints_the_first_gpu_run():
    """`gpu.py report` on the JSON returned by the first H200 run (research/gpu_check/)
    prints exactly the table that run returned, so older results stay readable."""
    results = json.loads((REPO / "research/gpu_check/2026-12-04_h200.json").read_text())
    returned = (REPO / "research/gpu_check/2026-12-04_h200.txt").read_text()
    assert gpu_check.summary_table(results).strip() == returned.strip()
    # a parity run outside its bounds names how many robots and where, when the JSON says so
    par = results["stages"]["parity"]["result"]["runs"][1]
    assert not par["within_bounds"]
    par.update(worlds_outside=17, worst_dof="FL_caster_wheel_joint (robot 8)")
    line = next(x for x in gpu_check.summary_table(results).splitlines() if x.startswith("parity (64 envs"))
    where = "(17 of 64 robots; largest qvel difference: FL_caster_wheel_joint (robot 8))"
    assert line.endswith(f"OUTSIDE the test's bounds {where}")


# --- which packages travel ------------------------------------------------------------------------
def test_closure_follows_extras_and_markers():
    requires = {
        "a": ["b[x]", "c; python_version < '3.11'", "d; extra == 'never'", "numpy"],
        "b": ["e; extra == 'x'", "f", "a"],  # a cycle back to a
        "e": ["g>=1; sys_platform == 'linux'", "h; sys_platform == 'win32'"],
        "f": [],
        "g": [],
    }
    needed = gpu_wheels.closure(["a"], lambda n: requires[n], have={"numpy", "F"})
    assert set(needed) == {"a", "b", "e", "g"}
    assert needed["b"] == {"x"}


def test_every_project_dependency_is_accounted_for():
    """A dependency added to pyproject.toml must be carried (a root), be on the GPU machine,
    or be named as not needed there."""
    from packaging.requirements import Requirement

    deps = [Requirement(r) for r in metadata.distribution("legged_casters").requires or []]
    runtime = {canonical(r.name) for r in deps if r.marker is None}
    known = set(gpu_wheels.ROOTS) | gpu_wheels.GPU_MACHINE_HAS | set(gpu_wheels.NOT_CARRIED)
    assert runtime - known == set()


def test_dry_run_plans_from_this_environment_without_network(capsys):
    plan = gpu_wheels.prepare(REPO, dry_run=True, log=print)["packages"]
    assert {"mujoco", "mujoco-core", "mujoco-warp", "warp-lang", "rsl-rl-lib", "tensordict"} <= set(plan)
    assert not set(plan) & gpu_wheels.GPU_MACHINE_HAS  # nothing the machine already has
    for name, version in plan.items():
        assert metadata.version(name) == version  # the versions this environment runs
    assert "imageio-ffmpeg" not in plan


# --- cutting into calls, joining back -------------------------------------------------------------
def test_plan_packs_into_the_fewest_calls():
    sizes = {
        "big.whl": 142 * MIB,
        "core.whl": 9 * MIB,
        "small.whl": MIB // 3,
        "opt1.whl": 10 * MIB,
        "opt2.whl": 12 * MIB,
    }
    plan = gpu_wheels.plan_transfers(sizes, {"opt1.whl", "opt2.whl"}, capacity=57 * MIB)
    assert plan.calls == 3  # ceil((142 + 9 + 1/3) / 57)
    per_call = {}
    for p in plan.pieces:
        per_call[p.call] = per_call.get(p.call, 0) + p.size
    assert max(per_call.values()) <= 57 * MIB
    for name, size in sizes.items():
        pieces = sorted((p for p in plan.pieces if p.wheel == name), key=lambda p: p.offset)
        if name in plan.left_behind:
            assert not pieces
            continue
        assert pieces[0].offset == 0 and sum(p.size for p in pieces) == size
        assert all(a.offset + a.size == b.offset for a, b in zip(pieces, pieces[1:], strict=False))
    assert [p.file for p in plan.pieces if p.wheel == "core.whl"] == ["core.whl"]  # small files travel whole
    assert len([p for p in plan.pieces if p.wheel == "big.whl"]) == 3
    assert set(plan.left_behind) == {"opt2.whl"}  # only one optional wheel fits the room left


def test_pieces_join_back_byte_identical(tmp_path):
    rng = random.Random(0)
    src = tmp_path / "wheels"
    src.mkdir()
    blobs = {"a.whl": rng.randbytes(3 * MIB + 17), "b.whl": rng.randbytes(1000), "c.whl": rng.randbytes(MIB)}
    for name, data in blobs.items():
        (src / name).write_bytes(data)
    plan = gpu_wheels.plan_transfers({n: len(d) for n, d in blobs.items()}, set(), capacity=MIB + MIB // 2)
    repo = tmp_path / "repo"
    gpu_wheels.write_pieces(src, repo / gpu_wheels.WHEEL_DIR, plan.pieces)
    manifest = {
        "created": "2026-01-01T00:00:00",
        "calls": plan.calls,
        "wheels": [
            {
                "file": n,
                "size": len(d),
                "sha256": hashlib.sha256(d).hexdigest(),
                "optional": False,
                "pieces": [vars(p) for p in plan.pieces if p.wheel == n],
            }
            for n, d in blobs.items()
        ],
    }
    for c in range(1, plan.calls + 1):
        (repo / gpu_wheels.WHEEL_DIR / f"call{c}" / gpu_wheels.MANIFEST).write_text(json.dumps(manifest))
    # the calls arrive one by one: call 1's folder alone leaves the others missing
    stash = tmp_path / "stash"
    later = tmp_path / "later"
    later.mkdir()
    for c in range(2, plan.calls + 1):
        os.rename(repo / gpu_wheels.WHEEL_DIR / f"call{c}", later / f"call{c}")
    first = gpu_wheels.stash(repo, stash, log=lambda *a: None)
    assert set(first["missing"]) == set(range(2, plan.calls + 1))
    for c in range(2, plan.calls + 1):
        os.rename(later / f"call{c}", repo / gpu_wheels.WHEEL_DIR / f"call{c}")
    assert not gpu_wheels.stash(repo, stash, log=lambda *a: None)["missing"]
    for entry in manifest["wheels"]:
        out = gpu_wheels.join_wheel(entry, stash, tmp_path / "joined")
        assert out.read_bytes() == blobs[entry["file"]]
    # a damaged piece is refused
    entry = manifest["wheels"][0]
    piece = stash / entry["pieces"][-1]["file"]
    piece.write_bytes(b"x" + piece.read_bytes()[1:])
    (tmp_path / "joined" / entry["file"]).unlink()
    with pytest.raises(ValueError, match="damaged"):
        gpu_wheels.join_wheel(entry, stash, tmp_path / "joined")


def test_device_calls_fit_the_tool():
    manifest = {"calls": 3}
    calls = gpu_wheels.device_calls(manifest)
    assert [c["carry"] for c in calls] == [[".whl/call1"], [".whl/call2"], [".whl/call3"]]
    assert all(len(c["command"]) <= 2000 and len(c["carry"]) <= 8 for c in calls)
    assert calls[-1]["command"].endswith("dev/gpu_loan/gpu.py run --out $OUT")


def test_read_have_takes_pip_list_and_freeze(tmp_path):
    f = tmp_path / "have.txt"
    f.write_text(
        textwrap.dedent("""\
        Package    Version
        ---------- -------
        Torch      2.11.0
        typing_extensions==4.12
        # comment
        onnx
        """)
    )
    assert gpu_wheels.read_have(f) == {"torch", "typing-extensions", "onnx"}


def test_train_stops_at_its_wall_budget(tmp_path, capsys):
    """--max_minutes (the GPU check's training budget): the iteration that ends past it is
    the last, and its checkpoint is written as the run's final one."""
    from legged_casters.tools import train

    argv = ["--task", "go2_flat", "--num_envs", "4", "--sim_backend", "cpu", "--device", "cpu"]
    argv += ["--log_root", str(tmp_path), "--console", "line", "--eval_every", "0", "--max_iterations", "50"]
    argv += ["--max_minutes", "0.0001", "--train-set", "num_steps_per_env=4"]
    argv += ["--train-set", "policy.actor_hidden_dims=[32,32]", "--train-set", "policy.critic_hidden_dims=[32,32]"]
    assert train.main(argv) == 0
    out = capsys.readouterr().out
    assert "--max_minutes 0.0001: stopped after iteration 1" in out
    (run_dir,) = (tmp_path / "go2_flat").iterdir()
    assert sorted(p.name for p in run_dir.glob("model_*.pt")) == ["model_1.pt"]
    assert train.main([*argv[:-8], "--max_minutes", "0"]) == 2  # a usage error


# --- `train`: one training with a deadline, its run folder packed to come back ---------------------------
def _unpack(parts: list[Path], dest: Path) -> None:
    import io
    import tarfile

    data = b"".join(p.read_bytes() for p in sorted(parts))
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        tar.extractall(dest, filter="data")


def test_pack_run_keeps_the_newest_checkpoints_within_the_parts(tmp_path):
    import gpu_train

    run = tmp_path / "logs" / "2026-01-01_00-00-00_x"
    run.mkdir(parents=True)
    rng = random.Random(0)
    for name in ("env.yaml", "train.yaml", "run.yaml", "events.out.tfevents.1"):
        (run / name).write_text(name * 50)
    for it in (50, 100, 150, 200, 250):
        (run / f"model_{it}.pt").write_bytes(rng.randbytes(30_000))
    (run / "model_best.pt").write_bytes(rng.randbytes(30_000))
    out = tmp_path / "out"
    # room for the small files, model_best and two numbered checkpoints, in 20 kB parts
    packed = gpu_train.pack_run(run, out, part_bytes=20_000, max_parts=6)
    assert packed["left_out"] == ["model_100.pt", "model_150.pt", "model_50.pt"]
    assert {"model_250.pt", "model_200.pt", "model_best.pt", "env.yaml"} <= set(packed["packed"])
    assert [p.name for p in packed["parts"]] == [f"{run.name}.tar.{i:02d}" for i in range(len(packed["parts"]))]
    assert all(p.stat().st_size <= 20_000 for p in packed["parts"]) and len(packed["parts"]) <= 6
    _unpack(packed["parts"], tmp_path / "back")
    back = tmp_path / "back" / run.name
    assert sorted(p.name for p in back.iterdir()) == packed["packed"]
    for name in packed["packed"]:
        assert (back / name).read_bytes() == (run / name).read_bytes()
    with pytest.raises(ValueError, match="without its numbered checkpoints"):
        gpu_train.pack_run(run, tmp_path / "out2", part_bytes=1_000, max_parts=1)


def test_pack_run_counts_the_tar_headers_and_names_parts_as_the_device_tool_returns_them(tmp_path):
    """Many small files cost a header each (and Python's tar adds one per fractional mtime):
    the parts still number at most max_parts; a run name outside [A-Za-z0-9._-] is made safe."""
    import gpu_train

    run = tmp_path / "2026-01-01_00-00-00_a b+c"
    run.mkdir()
    for i in range(20):
        (run / f"events.{i}").write_bytes(b"x" * 520)
    for it in range(1, 6):
        (run / f"model_{it}.pt").write_bytes(bytes(5_000))
    packed = gpu_train.pack_run(run, tmp_path / "out", part_bytes=20_000, max_parts=4)
    assert 1 <= len(packed["parts"]) <= 4 and packed["left_out"]
    assert all(p.name.startswith("2026-01-01_00-00-00_a_b_c.tar.") for p in packed["parts"])
    _unpack(packed["parts"], tmp_path / "back")
    assert sorted(p.name for p in (tmp_path / "back" / run.name).iterdir()) == packed["packed"]


TINY_TRAIN = ["--task", "go2_flat", "--num_envs", "4", "--sim_backend", "cpu", "--device", "cpu", "--console", "line"]
TINY_TRAIN += ["--eval_every", "0", "--train-set", "num_steps_per_env=4", "--train-set", "save_interval=5"]
TINY_TRAIN += ["--train-set", "policy.actor_hidden_dims=[32,32]", "--train-set", "policy.critic_hidden_dims=[32,32]"]


def _gpu_train(tmp_path: Path, *args: str, timeout: float = 200) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(GPU_PY), "train", "--no-install", "--out", str(tmp_path / "out")]
    return subprocess.run([*cmd, *args], cwd=REPO, capture_output=True, text=True, timeout=timeout)


def test_gpu_train_runs_train_py_and_packs_its_run_folder(tmp_path):
    logs = tmp_path / "logs"
    proc = _gpu_train(tmp_path, "--", *TINY_TRAIN, "--log_root", str(logs), "--max_iterations", "2")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    (run,) = (logs / "go2_flat").iterdir()
    parts = sorted((tmp_path / "out").glob(f"{run.name}.tar.*"))
    assert parts and "mkdir -p logs/go2_flat && cat <files_at>/" in proc.stdout
    _unpack(parts, tmp_path / "back")
    back = tmp_path / "back" / run.name
    assert (back / "model_2.pt").read_bytes() == (run / "model_2.pt").read_bytes()
    assert (back / "env.yaml").is_file() and (back / "run.yaml").is_file()
    assert "[train.py] done" in (tmp_path / "out" / "train.log").read_text()


def test_gpu_train_stops_train_py_at_the_deadline_and_still_packs(tmp_path):
    logs = tmp_path / "logs"
    # the shortest deadline, 60 s less the 20 s kept for packing: SIGTERM about 40 s after the
    # start, long before 100000 iterations and long after the env is built (checkpoints every 5)
    args = ["--deadline-s", "60", "--", *TINY_TRAIN, "--log_root", str(logs), "--max_iterations", "100000"]
    proc = _gpu_train(tmp_path, *args)
    out = proc.stdout + proc.stderr
    assert "[gpu_train] deadline:" in out and "stopping train.py (SIGTERM)" in out, out[-3000:]
    assert "stopped cleanly at the deadline" in out and proc.returncode == 0, out[-3000:]
    (run,) = (logs / "go2_flat").iterdir()
    assert "interrupted; newest checkpoint" in (tmp_path / "out" / "train.log").read_text()
    kept = sorted(p.name for p in run.glob("model_*.pt"))
    assert len(kept) >= 2  # model_best.pt and at least one numbered checkpoint
    _unpack(sorted((tmp_path / "out").glob(f"{run.name}.tar.*")), tmp_path / "back")
    assert sorted(p.name for p in (tmp_path / "back" / run.name).glob("model_*.pt")) == kept


def test_gpu_train_usage_errors(tmp_path):
    proc = _gpu_train(tmp_path)
    assert proc.returncode == 2 and "give train.py's arguments after --" in proc.stdout
    proc = _gpu_train(tmp_path, "--deadline-s", "30", "--", *TINY_TRAIN)
    assert proc.returncode == 2 and "--deadline-s 30 is too short: at least 60" in proc.stdout
    assert not (tmp_path / "out").exists()  # nothing ran
