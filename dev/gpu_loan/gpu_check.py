"""The GPU check (dev/gpu_loan/gpu.py run): everything the GPU path promises, measured in one run.

Stages, in order, each with its own time limit (a stage past it is killed and the run
goes on with the next; one that raises is recorded with its error):

  machine     versions, GPU, driver, Warp's CUDA toolkit and graph support
  compile     Warp kernel compile time: env build + first steps with the kernel cache
              as found (empty on a fresh machine) against the same again, modules loaded
  throughput  env steps/s of each task on the Warp backend at each size, CUDA graphs on
              and off, and device memory per env
  parity      Warp against MuJoCo C on the same starts and targets (legged_casters.sim.parity)
  overflow    contact and constraint buffers after a random-action rollout (mujoco_warp
              drops contacts past its buffers and only flags it)
  train       train.py on caster_omni, the learner on the same device, for a wall budget
  evaluate    scripts/evaluate.py --scenarios quick on that run
  export      export.py on that run
  multi_gpu   train.py under torchrun, one process per GPU (only with more than one GPU)

The orchestrator (`run_check`) uses only the standard library: it starts a worker
process (`python dev/gpu_loan/gpu_check.py worker ...`) that runs the stages
one after the other and writes each one's result as it ends; it watches the worker's
progress file, kills it when a stage outlives its limit, and starts a new worker for
the stages left. Results go to <out>/gpu_check.json and a table to <out>/gpu_check.txt
after every stage, so a run cut short still returns what it measured.

`--cpu` runs the same code with Warp on the CPU device at tiny sizes (a CI test).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
import traceback
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
STAGES = ("machine", "compile", "throughput", "parity", "overflow", "train", "evaluate", "export", "multi_gpu")
PROGRESS_RE = re.compile(
    r"\[(?P<task>[\w-]+)\] it (?P<it>\d+)/(?P<total>\d+) \| (?P<rate>[\d,]+) steps/s \| (?P<it_s>[\d.]+) s/it "
    r"\(collect (?P<collect>[\d.]+)\)"
)
"""train.py's progress line (legged_casters/learning/progress.py)."""
MODULE_RE = re.compile(r"Module \S+ \S+ load on device '[^']+' took ([\d.]+) ms\s+\((compiled|cached)\)")
"""Warp's line for each kernel module it loads (printed unless wp.config.quiet)."""
CHECK_RE = re.compile(r"^(PASS|FAIL)  (.+?)  \(measured (.*)\)$", re.M)
VERDICT_RE = re.compile(r"verdict: (\d+)/(\d+) checks passed")
LOG_TAIL = 3000


@dataclasses.dataclass
class Settings:
    """What a run measures; `for_mode` gives the GPU and the CPU (CI) choice."""

    cpu: bool
    device: str
    tasks: list[str]
    sizes: list[int]
    graphs: list[bool]
    warmup: int
    min_steps: int
    min_time: float
    compile_envs: int
    parity_envs: list[int]
    parity_steps: int
    overflow_task: str
    overflow_envs: int
    overflow_steps: int
    overflow_action_std: float
    train_args: list[str]
    train_reserve_s: float
    """Seconds of the train stage's limit kept for building the env and the last iteration."""
    limits: dict[str, float]
    floors: dict[str, float]
    """A stage starts only with this many seconds for it left; what later stages' floors need is kept."""
    kill_grace_s: float
    """A stage is killed this long after its limit (the worker does not watch the clock itself)."""

    @classmethod
    def for_mode(cls, cpu: bool) -> Settings:
        if cpu:
            limits = dict.fromkeys(STAGES, 120.0)
            return cls(
                cpu=True,
                device="cpu",
                tasks=["caster_omni"],
                sizes=[4, 8],
                graphs=[False],
                warmup=1,
                min_steps=2,
                min_time=0.0,
                compile_envs=4,
                parity_envs=[4],
                parity_steps=25,
                overflow_task="caster_omni",
                overflow_envs=8,
                overflow_steps=4,
                overflow_action_std=1.0,
                train_args=[
                    "--num_envs",
                    "4",
                    "--max_iterations",
                    "2",
                    "--train-set",
                    "num_steps_per_env=4",
                    "--train-set",
                    "policy.actor_hidden_dims=[32,32]",
                    "--train-set",
                    "policy.critic_hidden_dims=[32,32]",
                ],
                train_reserve_s=0.0,
                limits=limits,
                floors=dict.fromkeys(STAGES, 1.0),
                kill_grace_s=5.0,
            )
        return cls(
            cpu=False,
            device="cuda:0",
            tasks=["caster_omni", "go2_flat"],
            sizes=[1024, 4096, 8192, 16384],
            graphs=[True, False],
            warmup=3,
            min_steps=20,
            min_time=1.5,
            compile_envs=256,
            parity_envs=[4, 64],
            parity_steps=25,
            overflow_task="caster_omni",
            overflow_envs=8192,
            overflow_steps=150,
            overflow_action_std=1.0,
            train_args=[],
            train_reserve_s=30.0,
            limits={
                "machine": 40,
                "compile": 150,
                "throughput": 110,
                "parity": 45,
                "overflow": 45,
                "train": 150,
                "evaluate": 60,
                "export": 45,
                "multi_gpu": 90,
            },
            floors={
                "machine": 5,
                "compile": 30,
                "throughput": 20,
                "parity": 10,
                "overflow": 10,
                "train": 60,
                "evaluate": 20,
                "export": 15,
                "multi_gpu": 0,
            },
            kill_grace_s=15.0,
        )


def warp_modules(log_text: str) -> dict:
    """How many Warp modules a log shows compiled and loaded from the cache, and the milliseconds each took."""
    found = MODULE_RE.findall(log_text)
    compiled = [float(ms) for ms, kind in found if kind == "compiled"]
    cached = [float(ms) for ms, kind in found if kind == "cached"]
    return {
        "compiled": len(compiled),
        "compiled_s": round(sum(compiled) / 1000, 2),
        "cached": len(cached),
        "cached_s": round(sum(cached) / 1000, 2),
    }


def stage_timeout(settings: Settings, stage: str, later: list[str], now: float, deadline: float) -> float:
    """Seconds a stage may run: its limit, less what the later stages' floors keep back."""
    keep = sum(settings.floors.get(s, 0.0) for s in later)
    return max(0.0, min(settings.limits[stage], deadline - now - keep))


# --- helpers used inside the worker ----------------------------------------------------------------
def _sync(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _short(err: BaseException) -> str:
    return f"{type(err).__name__}: {str(err).strip()[:800]}"


def _make_env(task: str, settings: Settings, num_envs: int, extra: list[str] | None = None):
    from legged_casters import registry

    overrides = ["sim.backend=warp", f"sim.device={settings.device}", *(extra or [])]
    return registry.make_env(task, overrides, num_envs=num_envs)


def _random_actions(env, gen, std: float = 0.5):
    import torch

    return torch.randn(env.num_envs, env.num_actions, generator=gen, device=env.device) * std


def _cache_state(path: str | None) -> dict:
    if not path or not os.path.isdir(path):
        return {"dir": path, "modules": 0, "mb": 0.0}
    entries = [e for e in os.listdir(path) if not e.startswith(".")]
    size = 0
    for root, _, files in os.walk(path):
        size += sum(os.path.getsize(os.path.join(root, f)) for f in files)
    return {"dir": path, "modules": len(entries), "mb": round(size / 2**20, 1)}


class _Memory:
    """Device memory held by one env: Warp's memory pool and torch's allocator, from a
    baseline taken before the env was built (CUDA only)."""

    def __init__(self, device: str):
        self.cuda = device.startswith("cuda")
        if not self.cuda:
            return
        import gc

        import torch
        import warp as wp

        gc.collect()
        torch.cuda.synchronize()
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
        self.device = device
        self.torch0 = torch.cuda.memory_allocated()
        self.warp_pool = wp.get_device(device).is_mempool_supported
        self.warp0 = wp.get_mempool_used_mem_current(device) if self.warp_pool else 0
        self.free0 = torch.cuda.mem_get_info()[0]

    def read(self, num_envs: int) -> dict:
        if not self.cuda:
            return {}
        import torch
        import warp as wp

        torch.cuda.synchronize()
        warp_bytes = (wp.get_mempool_used_mem_current(self.device) - self.warp0) if self.warp_pool else None
        torch_peak = torch.cuda.max_memory_allocated() - self.torch0
        device_used = self.free0 - torch.cuda.mem_get_info()[0]
        held = (warp_bytes or 0) + torch_peak
        return {
            "warp_pool_mb": None if warp_bytes is None else round(warp_bytes / 2**20, 1),
            "torch_peak_mb": round(torch_peak / 2**20, 1),
            "device_used_mb": round(device_used / 2**20, 1),
            "kb_per_env": round(held / num_envs / 1024, 1),
        }


def _time_steps(env, gen, settings: Settings) -> dict:
    import torch

    for _ in range(settings.warmup):
        env.step(_random_actions(env, gen))
    _sync(settings.device)
    dones = torch.zeros((), device=env.device)
    n, t0 = 0, time.perf_counter()
    while n < settings.min_steps or time.perf_counter() - t0 < settings.min_time:
        _, _, done, _ = env.step(_random_actions(env, gen))
        dones += done.sum()
        n += 1
    _sync(settings.device)
    elapsed = time.perf_counter() - t0
    return {"steps": n, "seconds": round(elapsed, 3), "rate": env.num_envs * n / elapsed, "resets": int(dones)}


# --- the stages (run inside the worker) ---------------------------------------------------------------
def stage_machine(settings: Settings, work: Path, report) -> dict:
    t0 = time.time()
    import torch

    t_torch = time.time() - t0
    import mujoco
    import warp as wp

    t1 = time.time()
    import mujoco_warp

    t_mjw = time.time() - t1
    wp.init()
    info = {
        "python": sys.version.split()[0],
        "executable": sys.executable,
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "cuda_available": torch.cuda.is_available(),
        "mujoco": mujoco.__version__,
        "mujoco_warp": getattr(mujoco_warp, "__version__", None) or _dist_version("mujoco-warp"),
        "warp": wp.__version__,
        "rsl_rl": _dist_version("rsl-rl-lib"),
        "import_s": {"torch": round(t_torch, 2), "mujoco_warp": round(t_mjw, 2)},
        "loaded_from": {m.__name__: os.path.dirname(m.__file__) for m in (torch, mujoco, wp, mujoco_warp)},
        "warp_kernel_cache": wp.config.kernel_cache_dir,
    }
    if torch.cuda.is_available():
        props = torch.cuda.get_device_properties(0)
        info.update(
            gpu=props.name,
            gpu_count=torch.cuda.device_count(),
            gpu_memory_gb=round(props.total_memory / 1e9, 1),
            multiprocessors=props.multi_processor_count,
            torch_cuda=torch.version.cuda,
        )
        rt = wp._src.context.runtime
        info.update(
            warp_toolkit=".".join(map(str, rt.toolkit_version)) if rt.toolkit_version else None,
            warp_driver=".".join(map(str, rt.driver_version)) if rt.driver_version else None,
            conditional_graphs=bool(wp.is_conditional_graph_supported()),
        )
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            smi = subprocess.run(
                ["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                capture_output=True,
                text=True,
                timeout=20,
            )
            info["nvidia_smi"] = smi.stdout.strip()
    return info


def _dist_version(name: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def stage_compile(settings: Settings, work: Path, report) -> dict:
    """Build each task's env and step it twice, two times over: the first pays for
    compiling (or loading) the Warp kernels, the second finds them loaded."""
    import torch
    import warp as wp

    wp.init()
    before = _cache_state(wp.config.kernel_cache_dir)
    out = {"cache_before": before, "cache_was_empty": before["modules"] == 0, "tasks": {}}
    for task in settings.tasks:
        rows = []
        for attempt in ("first", "again"):
            t0 = time.perf_counter()
            env = _make_env(task, settings, settings.compile_envs)
            t1 = time.perf_counter()
            gen = torch.Generator(device=env.device).manual_seed(0)
            env.step(_random_actions(env, gen))
            _sync(settings.device)
            t2 = time.perf_counter()
            env.step(_random_actions(env, gen))
            _sync(settings.device)
            t3 = time.perf_counter()
            env.close()
            rows.append({"attempt": attempt, "build_s": t1 - t0, "first_step_s": t2 - t1, "second_step_s": t3 - t2})
        first, again = rows
        cost = lambda r: r["build_s"] + r["first_step_s"]  # noqa: E731
        out["tasks"][task] = {
            "rows": [{k: round(v, 2) if isinstance(v, float) else v for k, v in r.items()} for r in rows],
            "compile_s": round(cost(first) - cost(again), 2),
        }
        report(out)
    out["compile_s"] = round(sum(t["compile_s"] for t in out["tasks"].values()), 2)
    out["cache_after"] = _cache_state(wp.config.kernel_cache_dir)
    return out


def stage_throughput(settings: Settings, work: Path, report) -> dict:
    import gc

    import torch

    rows = []
    for task in settings.tasks:
        for n in settings.sizes:
            row = {"task": task, "num_envs": n}
            rows.append(row)
            mem = _Memory(settings.device)
            env = None
            try:
                t0 = time.perf_counter()
                env = _make_env(task, settings, n)
                row["build_s"] = round(time.perf_counter() - t0, 2)
                row["decimation"] = env.cfg.sim.decimation
                gen = torch.Generator(device=env.device).manual_seed(0)
                for graph in settings.graphs:
                    key = "graph_on" if graph else "graph_off"
                    if graph != env.sim.use_graph:
                        env.sim.use_graph = graph
                    timed = _time_steps(env, gen, settings)
                    row[key] = {k: round(v, 3) if isinstance(v, float) else v for k, v in timed.items()}
                    if graph or len(settings.graphs) == 1:
                        row["memory"] = mem.read(n)
                    report({"rows": rows})
            except Exception as err:  # one size failing (e.g. out of memory) leaves the others
                row["error"] = _short(err)
                if "out of memory" in str(err).lower():
                    break
            finally:
                if env is not None:
                    env.close()
                del env
                gc.collect()
            report({"rows": rows})
    return {"rows": rows}


def stage_parity(settings: Settings, work: Path, report) -> dict:
    from legged_casters.robot.build import MODEL_FILES
    from legged_casters.sim.base import physics_model
    from legged_casters.sim.parity import BOUNDS, parity_errors

    model = physics_model(MODEL_FILES["caster"])
    out = {"bounds": BOUNDS, "steps": settings.parity_steps, "runs": []}
    for n in settings.parity_envs:
        err = parity_errors(model, n=n, steps=settings.parity_steps, warp_device=settings.device)
        err["num_envs"] = n
        err["within_bounds"] = err["worlds_outside"] == 0 and err["finite"] and not err["contact_overflow"]
        out["runs"].append(err)
        report(out)
    out["passed"] = all(r["within_bounds"] for r in out["runs"])
    return out


def stage_overflow(settings: Settings, work: Path, report) -> dict:
    """Random actions until robots fall (more contacts); after each step the contact
    count of all worlds and the largest of one world, the constraint rows of the fullest
    world, and at the end mujoco_warp's per-world overflow flags (sticky since the
    Data was made: resets write qpos, they do not clear them)."""
    import mujoco_warp as mjw
    import torch
    import warp as wp

    env = _make_env(settings.overflow_task, settings, settings.overflow_envs)
    try:
        sim = env.sim
        wd = sim.wd
        nworld = sim.num_envs
        naconmax, njmax = int(wd.naconmax), int(wd.njmax)
        nacon = wp.to_torch(wd.nacon)
        nefc = wp.to_torch(wd.nefc)
        worldid = wp.to_torch(wd.contact.worldid)
        slots = torch.arange(worldid.shape[0], device=env.device)
        gen = torch.Generator(device=env.device).manual_seed(0)
        max_total = torch.zeros((), dtype=torch.long, device=env.device)
        max_world = torch.zeros((), dtype=torch.long, device=env.device)
        max_rows = torch.zeros((), dtype=torch.long, device=env.device)
        resets = torch.zeros((), device=env.device)
        for _ in range(settings.overflow_steps):
            _, _, done, _ = env.step(_random_actions(env, gen, settings.overflow_action_std))
            resets += done.sum()
            total = nacon[0].long()
            valid = (slots < total).long()
            per_world = torch.zeros(nworld, dtype=torch.long, device=env.device)
            per_world.index_add_(0, worldid.long().clamp(0, nworld - 1), valid)
            max_total = torch.maximum(max_total, total)
            max_world = torch.maximum(max_world, per_world.max())
            max_rows = torch.maximum(max_rows, nefc.long().max())
        flags = wp.to_torch(wd.overflow).long().cpu()
        counts = {
            f.name: int(((flags & int(f.value)) != 0).sum()) for f in mjw.OverflowType if f.value and f.name != "ALL"
        }
        buffer_flags = ("NEFC", "NJMAX_NNZ", "BROADPHASE", "NARROWPHASE")
        overflowed = int(max_total) > naconmax or int(max_rows) > njmax or any(counts.get(f) for f in buffer_flags)
        return {
            "task": settings.overflow_task,
            "num_envs": nworld,
            "steps": settings.overflow_steps,
            "action_std": settings.overflow_action_std,
            "resets": int(resets),
            "nconmax_per_world": sim.nconmax,
            "naconmax_total": naconmax,
            "njmax_per_world": njmax,
            "buffers": "contacts: one pool of naconmax = nconmax x worlds shared by all worlds (one world may "
            "hold more than nconmax); constraint rows: njmax per world, rows past it dropped",
            "max_contacts_all_worlds": int(max_total),
            "max_contacts_one_world": int(max_world),
            "max_constraint_rows_one_world": int(max_rows),
            "worlds_flagged": counts,
            "backend_contact_overflow": bool(sim.contact_overflow()),
            "overflowed": overflowed,
        }
    finally:
        env.close()


def _train_argv(settings: Settings, work: Path, minutes: float | None) -> list[str]:
    argv = ["--task", "caster_omni", "--sim_backend", "warp", "--device", settings.device]
    argv += ["--log_root", str(work / "runs"), "--run_name", "gpu_check", "--eval_every", "0", "--console", "line"]
    argv += ["--train-set", "select_last=0"]  # a throughput check: no checkpoint selection at the end
    if minutes is not None:
        argv += ["--max_minutes", f"{minutes:.2f}"]
    return argv + settings.train_args


def stage_train(settings: Settings, work: Path, report, timeout: float) -> dict:
    from legged_casters.tools import train

    minutes = None if settings.cpu else max(0.5, (timeout - settings.train_reserve_s) / 60.0)
    argv = _train_argv(settings, work, minutes)
    log = work / "logs" / "train.log"
    t0 = time.time()
    rc = train.main(argv)
    sys.stdout.flush()
    wall = time.time() - t0
    text = log.read_text(errors="replace") if log.is_file() else ""
    its = [m.groupdict() for m in PROGRESS_RE.finditer(text)]
    rates = [float(i["rate"].replace(",", "")) for i in its]
    steady = rates[1:] or rates
    run_dir = re.search(r"\[train\.py\] run folder (\S+)", text)
    envs = re.search(r"task caster_omni: (\d+) envs", text)
    return {
        "argv": argv,
        "rc": rc,
        "wall_s": round(wall, 1),
        "budget_minutes": minutes,
        "num_envs": int(envs.group(1)) if envs else None,
        "iterations": len(its),
        "first_iteration_s": float(its[0]["it_s"]) if its else None,
        "steps_per_s_mean": round(sum(steady) / len(steady)) if steady else None,
        "steps_per_s_last": round(rates[-1]) if rates else None,
        "collect_share": round(sum(float(i["collect"]) for i in its) / max(sum(float(i["it_s"]) for i in its), 1e-9), 3)
        if its
        else None,
        "run_dir": run_dir.group(1) if run_dir else None,
    }


def _trained_run(work: Path) -> str:
    path = work / "stages" / "train.json"
    run_dir = json.loads(path.read_text()).get("result", {}).get("run_dir") if path.is_file() else None
    if not run_dir:
        found = sorted((work / "runs" / "caster_omni").glob("*")) if (work / "runs" / "caster_omni").is_dir() else []
        run_dir = str(found[-1]) if found else None
    if not run_dir or not list(Path(run_dir).glob("model_*.pt")):
        raise RuntimeError("no trained run with a checkpoint (the train stage did not get that far)")
    return run_dir


def stage_evaluate(settings: Settings, work: Path, report) -> dict:
    from legged_casters.tools import evaluate

    run_dir = _trained_run(work)
    rc = evaluate.main(["--load_run", run_dir, "--scenarios", "quick"])
    sys.stdout.flush()
    text = (work / "logs" / "evaluate.log").read_text(errors="replace")
    checks = [{"check": name, "passed": ok == "PASS", "measured": value} for ok, name, value in CHECK_RE.findall(text)]
    verdict = VERDICT_RE.search(text)
    table = [line for line in text.splitlines() if line.startswith("|")]
    return {
        "rc": rc,
        "run_dir": run_dir,
        "checks": checks,
        "passed": int(verdict.group(1)) if verdict else None,
        "of": int(verdict.group(2)) if verdict else None,
        "table": table,
    }


def stage_export(settings: Settings, work: Path, report) -> dict:
    from legged_casters.tools import export

    run_dir = _trained_run(work)
    out = work / "export"
    rc = export.main(["--load_run", run_dir, "--out", str(out)])
    sys.stdout.flush()
    text = (work / "logs" / "export.log").read_text(errors="replace")
    parity = re.search(r"parity vs training actor .*", text)
    files = {p.name: p.stat().st_size for p in sorted(out.glob("*"))} if out.is_dir() else {}
    return {"rc": rc, "out": str(out), "files": files, "parity": parity.group(0) if parity else None}


def stage_multi_gpu(settings: Settings, work: Path, report, timeout: float) -> dict:
    import torch

    count = torch.cuda.device_count() if not settings.cpu else 0
    if count < 2:
        return {"skipped": f"{count} GPU(s): one process per GPU needs at least 2"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nnodes=1", f"--nproc_per_node={count}"]
    cmd += [str(REPO / "train.py"), "--task", "caster_omni", "--sim_backend", "warp", "--max_iterations", "5"]
    cmd += ["--log_root", str(work / "runs_multi"), "--eval_every", "0", "--console", "line"]
    cmd += ["--train-set", "select_last=0"]
    t0 = time.time()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=max(10.0, timeout - 5))
    text = proc.stdout + proc.stderr
    rates = [float(m.group("rate").replace(",", "")) for m in PROGRESS_RE.finditer(text)]
    return {
        "gpus": count,
        "rc": proc.returncode,
        "wall_s": round(time.time() - t0, 1),
        "iterations": len(rates),
        "steps_per_s_last": rates[-1] if rates else None,
        "tail": text[-LOG_TAIL:],
    }


STAGE_FUNCS = {
    "machine": stage_machine,
    "compile": stage_compile,
    "throughput": stage_throughput,
    "parity": stage_parity,
    "overflow": stage_overflow,
    "train": stage_train,
    "evaluate": stage_evaluate,
    "export": stage_export,
    "multi_gpu": stage_multi_gpu,
}
NEEDS_TIMEOUT = {"train", "multi_gpu"}


def _write_json(path: Path, data) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, default=str) + "\n")
    os.replace(tmp, path)


@contextlib.contextmanager
def _output_to(path: Path):
    """Send this process's stdout and stderr (the C level too: Warp and MuJoCo print there) to `path`."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(path, "ab") as f:
        os.dup2(f.fileno(), 1)
        os.dup2(f.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def worker(work: Path, stages: list[str], settings: Settings, deadline: float) -> int:
    """Run `stages` in order; each one's result to work/stages/<stage>.json."""
    (work / "stages").mkdir(parents=True, exist_ok=True)
    (work / "logs").mkdir(parents=True, exist_ok=True)
    for i, stage in enumerate(stages):
        now = time.time()
        timeout = stage_timeout(settings, stage, stages[i + 1 :], now, deadline)
        record: dict = {"stage": stage, "started": now, "timeout_s": round(timeout, 1)}
        if timeout < settings.floors.get(stage, 0.0) or timeout <= 0:
            record.update(status="skipped", reason=f"out of budget ({timeout:.0f} s left for it)", seconds=0.0)
            _write_json(work / "stages" / f"{stage}.json", record)
            continue
        _write_json(work / "progress.json", record)
        partial = work / "stages" / f"{stage}.partial.json"

        def report(data, partial=partial):
            _write_json(partial, data)

        t0 = time.time()
        with _output_to(work / "logs" / f"{stage}.log"):
            try:
                fn = STAGE_FUNCS[stage]
                args = (settings, work, report, timeout) if stage in NEEDS_TIMEOUT else (settings, work, report)
                result = fn(*args)
                status = "skipped" if "skipped" in result else "ok"
                if result.get("rc") not in (None, 0):  # a tool that ran to its end with an error code
                    status = "failed"
                    record["error"] = f"exit code {result['rc']} (see its log)"
                record.update(status=status, result=result)
            except Exception as err:
                traceback.print_exc()
                record.update(status="error", error=_short(err), traceback=traceback.format_exc()[-LOG_TAIL:])
                if partial.is_file():
                    record["partial"] = json.loads(partial.read_text())
        record["seconds"] = round(time.time() - t0, 1)
        _write_json(work / "stages" / f"{stage}.json", record)
    return 0


# --- the orchestrator (standard library only) ----------------------------------------------------
def _tail(path: Path, n: int = LOG_TAIL) -> str:
    if not path.is_file():
        return ""
    with open(path, "rb") as f:
        f.seek(max(0, path.stat().st_size - n))
        return f.read().decode(errors="replace")


def _add_log(record: dict, path: Path) -> None:
    text = path.read_text(errors="replace") if path.is_file() else ""
    record["log_tail"] = text[-LOG_TAIL:]
    modules = warp_modules(text)
    if modules["compiled"] or modules["cached"]:
        record["warp_modules"] = modules


def _kill(proc: subprocess.Popen) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def child_env(site: Path | None) -> dict[str, str]:
    """The environment of a child Python (a stage, or `gpu.py train`'s train.py): unbuffered,
    with the installed wheels (`site`) and then this repo first on its path."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    paths = [str(site)] if site else []
    env["PYTHONPATH"] = os.pathsep.join([*paths, str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])
    return env


def run_check(
    out: Path,
    *,
    cpu: bool,
    budget_s: float,
    work: Path,
    install_result: dict | None = None,
    site: Path | None = None,
    stages: list[str] | None = None,
    limits: dict[str, float] | None = None,
    python: str | None = None,
    log=print,
) -> dict:
    """Run the stages in worker processes under the time limits (`limits` replaces some of
    the mode's); write the results."""
    t_start = time.time()
    deadline = t_start + budget_s
    settings = Settings.for_mode(cpu)
    for stage, seconds in (limits or {}).items():
        if stage not in settings.limits:
            raise ValueError(f"no stage {stage!r}; stages: {', '.join(STAGES)}")
        settings.limits[stage] = float(seconds)
    out.mkdir(parents=True, exist_ok=True)
    work.mkdir(parents=True, exist_ok=True)
    (work / "stages").mkdir(exist_ok=True)
    for old in (work / "stages").glob("*.json"):
        old.unlink()
    (work / "logs").mkdir(exist_ok=True)
    for old in (work / "logs").glob("*.log"):
        old.unlink()
    settings_file = work / "settings.json"
    _write_json(settings_file, dataclasses.asdict(settings))
    env = child_env(site)
    if not cpu:  # the check's own kernel cache: empty on a fresh machine, kept for a second run
        env.setdefault("WARP_CACHE_PATH", str(work / "warp_cache"))
    results = {
        "started": datetime.datetime.now().isoformat(timespec="seconds"),
        "mode": "cpu" if cpu else "gpu",
        "budget_s": budget_s,
        "host": os.uname().nodename,
        "git": _git_head() or f"{((install_result or {}).get('prepared') or {}).get('git')} (at prepare)",
        "settings": dataclasses.asdict(settings),
        "stages": {},
    }
    if install_result is not None:
        results["stages"]["install"] = install_result
    pending = [s for s in (stages or STAGES) if s in STAGE_FUNCS]

    def save() -> None:
        results["wall_s"] = round(time.time() - t_start, 1)
        _write_json(out / "gpu_check.json", results)
        (out / "gpu_check.txt").write_text(summary_table(results) + "\n")

    def collect() -> None:
        for stage in list(pending):
            path = work / "stages" / f"{stage}.json"
            if path.is_file():
                record = json.loads(path.read_text())
                _add_log(record, work / "logs" / f"{stage}.log")
                results["stages"][stage] = record
                pending.remove(stage)
                log(f"[gpu_check] {stage}: {record['status']} ({record.get('seconds', 0):.0f} s)")
                save()

    save()
    launches = 0
    while pending and launches <= len(STAGES) + 1:
        launches += 1
        progress = work / "progress.json"
        progress.unlink(missing_ok=True)
        cmd = [python or sys.executable, str(Path(__file__).resolve()), "worker", "--work", str(work)]
        cmd += ["--stages", ",".join(pending), "--settings", str(settings_file), "--deadline", repr(deadline)]
        with open(work / "logs" / "worker.log", "ab") as wlog:
            proc = subprocess.Popen(
                cmd, cwd=REPO, env=env, stdout=wlog, stderr=subprocess.STDOUT, start_new_session=True
            )
        killed = None
        while proc.poll() is None:
            time.sleep(0.5)
            collect()
            with contextlib.suppress(OSError, ValueError):
                current = json.loads(progress.read_text()) if progress.is_file() else None
                if current and current["stage"] in pending:
                    limit = current["timeout_s"] + settings.kill_grace_s
                    if time.time() - current["started"] > limit:
                        killed = current
                        _kill(proc)
        collect()
        if not pending:
            break
        current = killed
        if current is None and progress.is_file():
            with contextlib.suppress(OSError, ValueError):
                current = json.loads(progress.read_text())
        stage = current["stage"] if current and current["stage"] in pending else pending[0]
        record = {"stage": stage, "status": "timeout" if killed else "crashed", "returncode": proc.returncode}
        if killed:
            record["error"] = f"killed after its limit of {killed['timeout_s']:.0f} s"
        else:
            record["error"] = f"the worker process ended with code {proc.returncode} during this stage"
        record["seconds"] = round(time.time() - current["started"], 1) if current else None
        partial = work / "stages" / f"{stage}.partial.json"
        if partial.is_file():
            with contextlib.suppress(OSError, ValueError):
                record["partial"] = json.loads(partial.read_text())
        _add_log(record, work / "logs" / f"{stage}.log")
        record["log_tail"] = record["log_tail"] or _tail(work / "logs" / "worker.log")
        results["stages"][stage] = record
        pending.remove(stage)
        log(f"[gpu_check] {stage}: {record['status']} ({record['error']})")
        save()
    for stage in pending:
        results["stages"][stage] = {"stage": stage, "status": "skipped", "reason": "the worker kept failing"}
    save()
    _concat_logs(work, out / "gpu_check.log")
    return results


def _git_head() -> str | None:
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        proc = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        return proc.stdout.strip() or None
    return None


def _concat_logs(work: Path, dest: Path, limit: int = 4 << 20) -> None:
    """All stage logs in one file, each cut to its tail so the whole stays under `limit`."""
    logs = sorted((work / "logs").glob("*.log"), key=lambda p: p.stat().st_mtime)
    share = limit // max(1, len(logs))
    with open(dest, "w") as f:
        for p in logs:
            f.write(f"===== {p.name} =====\n{_tail(p, share)}\n")


# --- the table -----------------------------------------------------------------------------------
def _fmt(v, spec: str = ",.0f") -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return format(v, spec)


def summary_table(results: dict) -> str:
    stages = results.get("stages", {})
    lines = [
        f"GPU check ({results.get('mode')}), started {results.get('started')} on {results.get('host')}, "
        f"git {str(results.get('git'))[:12]}{' (at prepare)' if 'prepare' in str(results.get('git')) else ''}, "
        f"{results.get('wall_s', 0):.0f} s of a "
        f"{results.get('budget_s'):.0f} s budget"
    ]
    m = stages.get("machine", {}).get("result") or {}
    if m:
        lines.append(
            f"machine: {m.get('gpu', 'no GPU')} (driver {m.get('warp_driver', '-')}, Warp CUDA toolkit "
            f"{m.get('warp_toolkit', '-')}, conditional graphs {m.get('conditional_graphs', '-')}), "
            f"{m.get('cpu_count')} CPUs; python {m.get('python')}, torch {m.get('torch')}, warp {m.get('warp')}, "
            f"mujoco {m.get('mujoco')}, mujoco_warp {m.get('mujoco_warp')}"
        )
    lines.append("")
    lines.append("| stage | status | seconds | Warp modules compiled (s) / cached | note |")
    lines.append("|---|---|---:|---|---|")
    for name, rec in stages.items():
        note = rec.get("error") or rec.get("reason") or (rec.get("result") or {}).get("skipped") or ""
        if name == "install":
            problems = len(rec.get("problems", [])) + len(rec.get("requirements", []))
            note = note or f"{len(rec.get('wheels', []))} wheels; {problems} problems"
        wm = rec.get("warp_modules")
        mods = f"{wm['compiled']} ({wm['compiled_s']:.1f}) / {wm['cached']}" if wm else ""
        lines.append(
            f"| {name} | {rec.get('status')} | {_fmt(rec.get('seconds'), '.0f')} | {mods} | {str(note)[:100]} |"
        )

    comp = stages.get("compile", {}).get("result") or {}
    if comp:
        lines.append("")
        fresh = "an empty" if comp.get("cache_was_empty") else "an existing"
        per_task = ", ".join(f"{t} {v['compile_s']:.1f} s" for t, v in comp.get("tasks", {}).items())
        lines.append(f"kernel compile with {fresh} cache: {per_task} (total {comp.get('compile_s', 0):.1f} s)")

    thr = (stages.get("throughput", {}).get("result") or stages.get("throughput", {}).get("partial") or {}).get("rows")
    if thr:
        lines.append("")
        lines.append("| task | envs | env steps/s, graphs on | graphs off | physics steps/s (on) | KB/env | note |")
        lines.append("|---|---:|---:|---:|---:|---:|---|")
        for r in thr:
            on, off = (r.get("graph_on") or {}).get("rate"), (r.get("graph_off") or {}).get("rate")
            dec = r.get("decimation")
            phys = (on or off) * dec if dec and (on or off) else None
            lines.append(
                f"| {r['task']} | {r['num_envs']} | {_fmt(on)} | {_fmt(off)} | {_fmt(phys)} | "
                f"{_fmt((r.get('memory') or {}).get('kb_per_env'), ',.1f')} | {r.get('error', '')[:60]} |"
            )

    par = stages.get("parity", {}).get("result") or {}
    if par:
        lines.append("")
        for run in par.get("runs", []):
            errs = ", ".join(f"{k} {run[k]:.1e}" for k in par.get("bounds", {}))
            ok = "within" if run["within_bounds"] else "OUTSIDE"
            n, where = run["num_envs"], ""
            if "worlds_outside" in run and not run["within_bounds"]:
                where = f" ({run['worlds_outside']} of {n} robots; largest qvel difference: {run['worst_dof']})"
            lines.append(f"parity ({n} envs, {par['steps']} steps): {errs}: {ok} the test's bounds{where}")

    ov = stages.get("overflow", {}).get("result") or {}
    if ov:
        lines.append("")
        flagged = {k: v for k, v in ov.get("worlds_flagged", {}).items() if v}
        lines.append(
            f"overflow ({ov['task']}, {ov['num_envs']} envs, {ov['steps']} random-action steps, "
            f"{ov['resets']} resets): "
            f"contacts max {ov['max_contacts_all_worlds']} of {ov['naconmax_total']} pooled "
            f"(one world max {ov['max_contacts_one_world']}, nconmax {ov['nconmax_per_world']}/world), "
            f"constraint rows max {ov['max_constraint_rows_one_world']} of njmax {ov['njmax_per_world']}/world; "
            f"worlds flagged: {flagged or 'none'}"
        )

    tr = stages.get("train", {}).get("result") or {}
    if tr:
        lines.append("")
        lines.append(
            f"train caster_omni: {tr.get('iterations')} iterations in {tr.get('wall_s')} s "
            f"on {tr.get('num_envs')} envs, "
            f"{_fmt(tr.get('steps_per_s_mean'))} env steps/s with the PPO update (first iteration "
            f"{_fmt(tr.get('first_iteration_s'), '.1f')} s, collect share {_fmt(tr.get('collect_share'), '.2f')})"
        )
    ev = stages.get("evaluate", {}).get("result") or {}
    if ev:
        lines.append(f"evaluate --scenarios quick: {ev.get('passed')}/{ev.get('of')} checks passed")
    ex = stages.get("export", {}).get("result") or {}
    if ex:
        lines.append(f"export: rc {ex.get('rc')}, {', '.join(ex.get('files', {}))}; {ex.get('parity') or ''}")
    return "\n".join(lines)


# --- worker entry point ----------------------------------------------------------------------------
def _worker_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="gpu_check worker")
    p.add_argument("worker")
    p.add_argument("--work", required=True)
    p.add_argument("--stages", required=True)
    p.add_argument("--settings", required=True)
    p.add_argument("--deadline", type=float, required=True)
    args = p.parse_args(argv)
    settings = Settings(**json.loads(Path(args.settings).read_text()))
    return worker(Path(args.work), args.stages.split(","), settings, args.deadline)


if __name__ == "__main__":
    sys.exit(_worker_main(sys.argv[1:]))
