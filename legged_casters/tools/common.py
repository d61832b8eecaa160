"""What the three commands share: errors and exit codes, log folders, run selection,
checkpoint files (atomic writes, weights-only loads), git state, config loading."""

from __future__ import annotations

import argparse
import datetime
import os
import re
import shlex
import subprocess
import sys
import tempfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import yaml

from legged_casters import registry
from legged_casters.config import ConfigError, apply_overrides, load_yaml

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
"""Bad flags or values: the same code argparse uses."""

LOG_ROOT_ENV = "LEGGED_CASTERS_LOG_ROOT"
PREFERRED_TASK = "caster_omni"
RUN_FILE = "run.yaml"
SELECTED_FILE = "selected.yaml"
"""The checkpoint a run's full fixed evaluation chose (evaluate.py --select, train.py's
`select_last`): what play, evaluate and export load when no --checkpoint is given."""
CHECKPOINT_RE = re.compile(r"^model_(\d+)\.pt$")
RUN_DIR_RE = re.compile(r"^\d{4}-\d{2}-\d{2}_\d{2}-\d{2}-\d{2}(_.*)?$")


class UsageError(Exception):
    """A flag or value that is not allowed; the message says what is. Exit code 2."""


class CheckpointError(Exception):
    """A checkpoint that cannot be read or does not fit the task. Exit code 1.
    `detail`: the underlying library's full message, shown with --verbose."""

    def __init__(self, message: str, detail: str | None = None):
        super().__init__(message)
        self.detail = detail


def run_cli(fn: Callable[[], int], prog: str, verbose: bool = False) -> int:
    """Run a command body and turn the errors a user can fix into a message and an exit code."""
    try:
        return fn()
    except (UsageError, ConfigError, registry.UnknownTaskError) as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except CheckpointError as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        if err.detail:
            if verbose:
                print(f"{prog}: the loader said:\n{err.detail}", file=sys.stderr)
            else:
                print(f"{prog}: (--verbose shows the loader's own message)", file=sys.stderr)
        return EXIT_FAILURE


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """argparse's defaults formatter, without "(default: None)" and without a second
    default where the help text already states its own."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if "(default" in text or default is None or default is argparse.SUPPRESS or default is False or default == []:
            return text
        return super()._get_help_string(action)


def add_verbose_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--verbose", action="store_true", help="on errors, also print the libraries' own messages")


# --- tasks and devices -----------------------------------------------------------------
def default_task() -> str:
    """caster_omni where it is registered, else the first registered task."""
    tasks = registry.list_tasks()
    if not tasks:
        raise UsageError("no tasks are registered")
    return PREFERRED_TASK if PREFERRED_TASK in tasks else tasks[0]


def check_task(name: str) -> registry.TaskSpec:
    return registry.get_task(name)  # UnknownTaskError lists the known tasks


def resolve_device(device: str | None, backend: str) -> str:
    """'auto' or None: cuda:<LOCAL_RANK> for the Warp backend on a CUDA machine, else cpu."""
    if device in (None, "auto"):
        if backend == "warp" and torch.cuda.is_available():
            return f"cuda:{int(os.environ.get('LOCAL_RANK', '0'))}"
        return "cpu"
    try:
        parsed = torch.device(device)
    except (RuntimeError, ValueError):
        raise UsageError(f"--device {device!r} is not a torch device; use auto, cpu, cuda or cuda:N") from None
    if parsed.type == "cuda":
        if not torch.cuda.is_available():
            raise UsageError(f"--device {device}: CUDA is not available on this machine; use --device cpu")
        if parsed.index is not None and parsed.index >= torch.cuda.device_count():
            raise UsageError(f"--device {device}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif parsed.type != "cpu":
        raise UsageError(f"--device {device}: only cpu and cuda devices are supported")
    return str(parsed)


def limit_cpu_threads(device: str, threads: int | None = None) -> None:
    """`threads` torch intra-op threads, else torch's default (one per core). The env step
    runs on one torch thread whatever this says (LeggedEnv.step: the simulator's thread pool
    owns the cores then); the PPO update gets them all (2 threads: 1.2 s instead of 2.3 s
    per update on 2 cores, scripts/bench_train.py)."""
    if threads:
        torch.set_num_threads(threads)


# --- log folders and runs ------------------------------------------------------------------
def log_root(flag: str | None, default: Path | str | None = None) -> Path:
    """--log_root, else $LEGGED_CASTERS_LOG_ROOT, else `default` (the repo's logs/), else ./logs."""
    if flag:
        return Path(flag).expanduser().resolve()
    if os.environ.get(LOG_ROOT_ENV):
        return Path(os.environ[LOG_ROOT_ENV]).expanduser().resolve()
    return Path(default).resolve() if default else (Path.cwd() / "logs").resolve()


def new_run_dir(root: Path, experiment: str, run_name: str) -> Path:
    stamp = datetime.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    name = f"{stamp}_{run_name}" if run_name else stamp
    path = root / experiment / name
    suffix = 1
    while path.exists():  # two runs started within one second
        suffix += 1
        path = root / experiment / f"{name}-{suffix}"
    return path


def checkpoints(run_dir: Path) -> list[tuple[int, Path]]:
    """(iteration, path) of the run's model_<it>.pt files, oldest first."""
    found = []
    if run_dir.is_dir():
        for p in run_dir.iterdir():
            m = CHECKPOINT_RE.match(p.name)
            if m and p.is_file():
                found.append((int(m.group(1)), p))
    return sorted(found)


def _run_time(run_dir: Path) -> tuple[float, str]:
    """When a run started: run.yaml's `created`, else the time in a <date>_<time> folder
    name, else the folder's modification time (a renamed or copied run)."""
    created = read_run_info(run_dir).get("created")
    stamp = None
    try:
        if created:
            stamp = datetime.datetime.fromisoformat(str(created)).timestamp()
        elif RUN_DIR_RE.match(run_dir.name):
            stamp = datetime.datetime.strptime(run_dir.name[:19], "%Y-%m-%d_%H-%M-%S").timestamp()
    except ValueError:
        stamp = None
    return (stamp if stamp is not None else run_dir.stat().st_mtime, run_dir.name)


def list_runs(root: Path, experiment: str) -> list[Path]:
    """Run folders of an experiment, oldest first. A run is found by its contents (run.yaml
    or a checkpoint), not its name, so a renamed run folder is still one."""
    exp = root / experiment
    if not exp.is_dir():
        return []
    runs = [p for p in exp.iterdir() if p.is_dir() and ((p / RUN_FILE).is_file() or checkpoints(p))]
    return sorted(runs, key=_run_time)


def find_run(root: Path, experiment: str, load_run: str | None) -> Path:
    """The run folder named by --load_run (a name under the experiment, or a path), else
    the newest run of the experiment that has a checkpoint."""
    runs = list_runs(root, experiment)
    if load_run:
        for candidate in (Path(load_run).expanduser(), root / experiment / load_run):
            if candidate.is_dir():
                return candidate.resolve()
        names = ", ".join(p.name for p in runs[-10:]) or "(none)"
        raise UsageError(f"--load_run {load_run!r}: no such run under {root / experiment}; runs there: {names}")
    with_ckpt = [r for r in runs if checkpoints(r)]
    if not with_ckpt:
        where = root / experiment
        raise UsageError(
            f"no run with a checkpoint under {where}; train one first (python train.py --experiment_name "
            f"{experiment} ...), or pass --load_run NAME/PATH, or --log_root DIR"
        )
    return with_ckpt[-1]


def selected_checkpoint(run_dir: Path) -> Path | None:
    """The checkpoint recorded in the run's selected.yaml, None where there is none."""
    path = run_dir / SELECTED_FILE
    if not path.is_file():
        return None
    try:
        name = (yaml.safe_load(path.read_text()) or {}).get("file")
    except yaml.YAMLError:
        name = None
    if not name or not (run_dir / name).is_file():
        raise UsageError(
            f"{path} names no checkpoint of this run ({name!r}): delete it or run evaluate.py --select again"
        )
    return (run_dir / name).resolve()


def find_checkpoint(run_dir: Path, checkpoint: str | None, newest: bool = False) -> Path:
    """--checkpoint: an iteration (5), "best" (model_best.pt: the best deterministic
    evaluation during training), "selected" (the run's selected.yaml: the checkpoint its
    full evaluation chose), "latest", a file name (model_5.pt) or a path; default the
    selected one where the run has one, else (or with `newest`) the newest."""
    found = checkpoints(run_dir)
    available = ", ".join(p.name for _, p in found[-10:]) or "(none)"
    if checkpoint in (None, "", "selected") and not newest:
        chosen = selected_checkpoint(run_dir)
        if chosen is not None:
            return chosen
        if checkpoint == "selected":
            raise UsageError(f"--checkpoint selected: run {run_dir} has no {SELECTED_FILE} (evaluate.py --select)")
    if checkpoint in (None, "", "-1", "latest"):
        if not found:
            raise UsageError(f"run {run_dir} has no checkpoint (model_<iteration>.pt)")
        return found[-1][1]
    candidates = [run_dir / f"model_{checkpoint}.pt"] if checkpoint.isdigit() or checkpoint == "best" else []
    candidates += [run_dir / checkpoint, Path(checkpoint).expanduser()]
    for c in candidates:
        if c.is_file():
            return c.resolve()
    raise UsageError(f"--checkpoint {checkpoint!r}: not found in {run_dir}; checkpoints there: {available}")


def read_run_info(run_dir: Path) -> dict:
    path = run_dir / RUN_FILE
    if not path.is_file():
        return {}
    try:
        return yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError:
        return {}


def _umask_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def write_text_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.chmod(tmp, _umask_mode())  # mkstemp creates 0600 files
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# --- checkpoints -----------------------------------------------------------------------------
def save_checkpoint_atomic(obj: dict, path: str | Path) -> Path:
    """torch.save into a temporary file beside `path`, flushed to disk, then renamed over it:
    a run killed mid-write leaves the previous file (or none), never a truncated one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, _umask_mode())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


REQUIRED_CHECKPOINT_KEYS = ("actor_state_dict", "critic_state_dict", "optimizer_state_dict", "iter")


def _is_torchscript_archive(path: Path) -> bool:
    """A TorchScript archive (torch.jit.save) holds compiled code and constants.pkl, which a
    torch.save zip never does; read from the zip's directory, nothing loaded."""
    try:
        with zipfile.ZipFile(path) as archive:
            return any(n.endswith("/constants.pkl") or "/code/" in n for n in archive.namelist())
    except (OSError, zipfile.BadZipFile):
        return False


def load_checkpoint(path: str | Path, map_location: str = "cpu") -> dict:
    """A training checkpoint, loaded with weights_only=True (no code from the file is run)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    if _is_torchscript_archive(path):  # torch.load would load it as TorchScript, with a warning
        raise CheckpointError(
            f"{path} is an exported TorchScript policy, not a training checkpoint: play.py and evaluate.py take it "
            "(or its folder) with --policy"
        )
    try:
        data = torch.load(path, weights_only=True, map_location=map_location)
    except Exception as err:  # truncated zip, not a torch file, disallowed pickle content...
        raise CheckpointError(
            f"checkpoint {path} cannot be read: the file is corrupt (a copy or save that did not finish?) "
            "or not a training checkpoint of this project; pick another with --checkpoint",
            f"{type(err).__name__}: {err}",
        ) from None
    if not isinstance(data, dict) or any(k not in data for k in REQUIRED_CHECKPOINT_KEYS):
        keys = sorted(data) if isinstance(data, dict) else type(data).__name__
        raise CheckpointError(f"checkpoint {path} is not an rsl_rl training checkpoint (has {keys})")
    return data


def is_training_checkpoint(path: Path) -> bool:
    """Is `path` a training checkpoint (model_<n>.pt: networks, optimizer, iteration) rather
    than an exported TorchScript policy or another file? load_checkpoint decides."""
    try:
        load_checkpoint(path)
    except CheckpointError:
        return False
    return True


# --- configs of a run ------------------------------------------------------------------------
SHIPPED_POLICIES = Path(__file__).resolve().parents[2] / "resources" / "policies"


def shipped_policy_dir(task: str) -> Path | None:
    """resources/policies/<task>/ when the project ships a trained policy for the task."""
    d = SHIPPED_POLICIES / task
    return d if (d / "policy.pt").is_file() else None


@dataclass
class Export:
    """An exported policy file with what it was exported for."""

    path: Path
    meta: dict
    task: str
    spec: registry.TaskSpec
    env_cfg: Any
    train_cfg: Any

    @property
    def obs_dim(self) -> int | None:
        return (self.meta.get("observation") or {}).get("dim")


def read_export(path: Path, task_arg: str | None) -> Export:
    """policy.pt / policy.onnx -> its policy.yaml, task and configs: the ones next to it
    (a shipped policy) or its run's (<run>/exported/), else the task's defaults."""
    meta_path = path.with_suffix(".yaml")
    try:
        meta = (yaml.safe_load(meta_path.read_text()) or {}) if meta_path.is_file() else {}
    except yaml.YAMLError as err:
        raise UsageError(f"{meta_path} is not valid YAML: {str(err).splitlines()[0]}") from None
    if not isinstance(meta, dict):
        raise UsageError(f"{meta_path}: not a policy description (a YAML mapping)")
    task = task_arg or meta.get("task") or default_task()
    if meta.get("task") and meta["task"] != task:
        raise UsageError(f"{path} was exported for task {meta['task']!r}, not {task!r}")
    spec = check_task(task)
    cfg_dir = next((d for d in (path.parent, path.parent.parent) if (d / "env.yaml").is_file()), None)
    env_cfg, train_cfg = run_configs(spec, cfg_dir)
    return Export(path, meta, task, spec, env_cfg, train_cfg)


def run_configs(spec: registry.TaskSpec, run_dir: Path | None) -> tuple[Any, Any]:
    """The env and train configs a run was trained with (its env.yaml / train.yaml), or the
    task's defaults where the run has none."""
    import copy

    env_cfg, train_cfg = copy.deepcopy(spec.env_cfg), copy.deepcopy(spec.train_cfg)
    if run_dir is not None:
        for name, cls, attr in (("env.yaml", type(spec.env_cfg), "env"), ("train.yaml", type(spec.train_cfg), "train")):
            path = run_dir / name
            if not path.is_file():
                print(f"[{attr} config] {path} missing: using the task's defaults", file=sys.stderr)
                continue
            try:
                loaded = load_yaml(cls, path)
            except ConfigError as err:
                raise UsageError(f"{path} does not fit task {spec.name!r}'s config: {err}") from None
            if attr == "env":
                env_cfg = loaded
            else:
                train_cfg = loaded
    return env_cfg, train_cfg


def with_overrides(cfg: Any, overrides: list[str] | dict, what: str) -> Any:
    if not overrides:
        return cfg
    try:
        return apply_overrides(cfg, overrides)
    except ConfigError as err:
        raise ConfigError(f"{what}: {err}") from None


# --- git state and command line --------------------------------------------------------------
def _git(repo: Path, *args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout if out.returncode == 0 else None


def git_state(repo: Path) -> tuple[dict, str]:
    """({commit, branch, dirty, repo}, diff text against HEAD incl. untracked file names)."""
    commit = _git(repo, "rev-parse", "HEAD")
    if commit is None:
        return {"repo": str(repo), "commit": None, "note": "not a git repository (or git missing)"}, ""
    status = _git(repo, "status", "--porcelain") or ""
    diff = _git(repo, "diff", "HEAD") or ""
    untracked = [line[3:] for line in status.splitlines() if line.startswith("??")]
    if untracked:
        diff += "\n# untracked files:\n" + "\n".join(f"#   {u}" for u in untracked) + "\n"
    info = {
        "repo": str(repo),
        "commit": commit.strip(),
        "branch": (_git(repo, "rev-parse", "--abbrev-ref", "HEAD") or "").strip(),
        "dirty": bool(status.strip()),
    }
    return info, diff


def command_line(argv: list[str] | None) -> str:
    args = sys.argv[1:] if argv is None else argv
    script = sys.argv[0] if argv is None else "train.py"
    return shlex.join([sys.executable, script, *args])


# --- shared flags ---------------------------------------------------------------------------
def add_env_set_flag(parser: argparse.ArgumentParser) -> None:
    """--set KEY=VALUE (repeatable): an env config field by dotted name, value in YAML."""
    parser.add_argument(
        "--set",
        dest="env_set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an env config field by dotted name, value in YAML (repeatable), e.g. "
        "--set commands.ranges.lin_vel_x=[-2,2]",
    )


def add_run_selection_flags(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("which checkpoint")
    g.add_argument("--task", help="registered task (default: caster_omni when registered, else the first)")
    g.add_argument("--experiment_name", help="folder under the log root (default: the task's train config)")
    g.add_argument("--load_run", help="run folder name under logs/<experiment>, or a path (default: newest)")
    g.add_argument(
        "--checkpoint",
        help="iteration number, 'best', 'selected', 'latest', model_<it>.pt or a path (default: the checkpoint the "
        "run's full evaluation selected, else the newest)",
    )
    g.add_argument("--log_root", help=f"root of the run folders (default: ${LOG_ROOT_ENV} or <repo>/logs)")
    add_verbose_flag(parser)


# --- a checkpoint to evaluate (play, export) ---------------------------------------------------
@dataclass
class Selection:
    task: str
    spec: registry.TaskSpec
    run_dir: Path
    ckpt_path: Path
    ckpt: dict
    env_cfg: Any
    """The env config of this checkpoint's training: the run's, with the stages it was trained under."""
    train_cfg: Any
    run_env_cfg: Any = None
    """The run's env.yaml as it is (the settings of its first iteration)."""

    def env_cfg_for(self, ckpt: dict) -> Any:
        """The env config another checkpoint of the same run was trained under."""
        return stage_env_cfg(self.run_env_cfg or self.env_cfg, self.train_cfg, checkpoint_iteration(ckpt))


def checkpoint_iteration(ckpt: dict) -> int:
    """The iterations done when a checkpoint was saved (model_<n>.pt: n)."""
    return int(ckpt.get("iter", -1)) + 1


def stage_env_cfg(env_cfg: Any, train_cfg: Any, iteration: int) -> Any:
    """`env_cfg` (a run's env.yaml) as it was at iteration `iteration` of a run with stages
    (TrainCfg.stages); unchanged for a run without."""
    if not getattr(train_cfg, "stages", None):
        return env_cfg
    overrides, _ = train_cfg.stage_overrides(iteration)
    return with_overrides(env_cfg, overrides, f"stages (iteration {iteration})")


def select_task(args: argparse.Namespace) -> str:
    """--task, else the task recorded in --load_run's run.yaml, else the default task."""
    if args.task:
        return args.task
    if getattr(args, "load_run", None) and Path(args.load_run).expanduser().is_dir():
        recorded = read_run_info(Path(args.load_run).expanduser()).get("task")
        if recorded:
            return recorded
    return default_task()


def select_checkpoint(args: argparse.Namespace, default_log_root: Path | None) -> Selection:
    """Resolve --task/--experiment_name/--load_run/--checkpoint/--log_root to a loaded checkpoint
    and the configs its run was trained with. Raises UsageError / CheckpointError."""
    task = select_task(args)
    spec = check_task(task)
    root = log_root(args.log_root, default_log_root)
    experiment = args.experiment_name or spec.train_cfg.experiment_name
    run_dir = find_run(root, experiment, args.load_run)
    ckpt_path = find_checkpoint(run_dir, args.checkpoint)
    ckpt = load_checkpoint(ckpt_path)
    saved_task = (ckpt.get("infos") or {}).get("task")
    if saved_task and saved_task != task:
        raise UsageError(f"checkpoint {ckpt_path} belongs to task {saved_task!r}; pass --task {saved_task}")
    env_cfg, train_cfg = run_configs(spec, run_dir)
    staged = stage_env_cfg(env_cfg, train_cfg, checkpoint_iteration(ckpt))
    return Selection(task, spec, run_dir, ckpt_path, ckpt, staged, train_cfg, env_cfg)


EVAL_OVERRIDES = {
    "noise.enabled": False,
    "domain_rand.push_robots": False,
    "terrain.spawn_on_course": False,
    "terrain.slope_deg": 0.0,
}
"""Evaluation and play envs: no observation noise, no random pushes, robots start at the
origin (a policy trained on a terrain course keeps its course, not its random starts)."""


def eval_env_cfg(env_cfg: Any, num_envs: int, overrides: list[str] | None, backend: str = "cpu") -> Any:
    cfg = with_overrides(env_cfg, {**EVAL_OVERRIDES, "num_envs": num_envs, "sim.backend": backend}, "eval env")
    cfg = with_overrides(cfg, overrides or [], "--set")
    return with_overrides(cfg, {"sim.device": "cpu" if backend == "cpu" else cfg.sim.device}, "eval env")


def make_eval_env(sel: Selection, num_envs: int, overrides: list[str] | None, backend: str = "cpu"):
    return sel.spec.env_class(eval_env_cfg(sel.env_cfg, num_envs, overrides, backend))
