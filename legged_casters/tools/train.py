"""train.py: PPO (rsl_rl OnPolicyRunner) on a registered task, with runs, resume and safe checkpoints.

    python train.py --task go2_flat --max_iterations 300 --set commands.ranges.lin_vel_x=[-2,2]

Each run lives in logs/<experiment>/<YYYY-mm-dd_HH-MM-SS>_<run_name>/: model_<n>.pt
checkpoints (the policy after n iterations), TensorBoard events, env.yaml and train.yaml, run.yaml (task, experiment),
git.yaml + git.diff (code state), command.txt (every invocation, resumes appended).
"""

from __future__ import annotations

import argparse
import datetime
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import torch
import yaml

from legged_casters.config import dump_yaml
from legged_casters.envs.base import CPU_DEFAULT_NUM_ENVS, resolve_backend
from legged_casters.learning.progress import BudgetReached, install_progress_hook
from legged_casters.learning.runner import CheckpointingRunner
from legged_casters.sim.base import BACKEND_KINDS, usable_cpus
from legged_casters.tools import common
from legged_casters.tools.common import UsageError

PROG = "train.py"
LAUNCHER_ENV = "LEGGED_CASTERS_LAUNCHER_CMD"
"""Set by --procs for its workers: the command line command.txt records."""


def _procs_arg(text: str) -> int | str:
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of processes or auto, got {text!r}") from None


def resolve_procs(args: argparse.Namespace) -> int:
    """--procs auto: 2 processes where training runs on the CPU (device and backend) and this
    process may use 2 or more cores (docs/training.md: 2 on 2 cores measured faster than 1), else 1."""
    if args.procs != "auto":
        return args.procs
    backend = resolve_backend(args.sim_backend)
    on_cpu = backend == "cpu" and common.resolve_device(args.device, backend) == "cpu"
    return 2 if on_cpu and usable_cpus() >= 2 else 1


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Train a policy with PPO (rsl_rl) on a registered task.",
        formatter_class=common.HelpFormatter,
    )
    p.add_argument("--task", help="registered task (default: caster_omni when registered, else the first)")
    p.add_argument("--num_envs", type=int, help="parallel envs (default: the env's: 512 on CPU, 4096 on Warp/CUDA)")
    p.add_argument("--max_iterations", type=int, help="PPO iterations to run now (on --resume: more iterations)")
    p.add_argument(
        "--max_minutes",
        type=float,
        help="wall-time budget, counted from the first iteration (after the env is built: on Warp with an "
        "empty kernel cache, 79-88 s on an H200): stop after the iteration that reaches it (its checkpoint is "
        "the run's last)",
    )
    p.add_argument("--seed", type=int, help="seed of env and networks (default: the train config's)")
    p.add_argument("--device", default="auto", help="torch device of the learner and env tensors: auto, cpu, cuda:N")
    p.add_argument("--sim_backend", default="auto", choices=BACKEND_KINDS, help="auto: warp on CUDA, else cpu")
    p.add_argument("--headless", action="store_true", help="accepted for legged_gym habits; training never renders")
    p.add_argument("--resume", action="store_true", help="continue a run: same folder, iteration, optimizer, ...")
    p.add_argument("--load_run", help="run to resume: folder name under logs/<experiment>, or a path (default newest)")
    p.add_argument("--checkpoint", help="checkpoint to resume from: iteration, model_<it>.pt or path (default newest)")
    p.add_argument("--experiment_name", help="folder under the log root (default: the task's train config)")
    p.add_argument("--run_name", help="suffix of the run folder name")
    p.add_argument("--log_root", help=f"root of the run folders (default: ${common.LOG_ROOT_ENV} or <repo>/logs)")
    common.add_verbose_flag(p)
    common.add_env_set_flag(p)
    p.add_argument(
        "--train-set",
        "--train_set",
        dest="train_set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a train config field, e.g. --train-set algorithm.learning_rate=5e-4 (repeatable)",
    )
    p.add_argument(
        "--set-per-process",
        "--set_per_process",
        dest="env_set_per_process",
        action="append",
        default=[],
        metavar="KEY=[V0,V1,...]",
        help="an env config field that differs between the processes of a --procs run, one value per process in "
        "rank order, e.g. --procs 2 --set-per-process 'sim.timestep=[0.005,0.002]' --set-per-process "
        "'sim.decimation=[4,10]' (half the batch at 5 ms physics, half at 2 ms; repeatable); all processes keep one "
        "control period. env.yaml holds process 0's config, run.yaml the lists; --resume applies them again for "
        "every key not given anew, per process or alike for all by --set",
    )
    p.add_argument(
        "--torch_threads",
        type=int,
        help="torch intra-op threads (default: torch's, one per core; the env step always runs on one, "
        "next to the simulator's thread pool)",
    )
    p.add_argument(
        "--procs",
        type=_procs_arg,
        default=1,
        help="train on the CPU in N processes, one per core (torchrun, gloo: gradients averaged, "
        "rank 0 writes the run); --num_envs is then the total, split evenly (default: the task's, "
        "or on --resume the run's, so an iteration's batch stays the same); auto: 2 on the CPU "
        "backend with 2 or more usable cores, else 1 (what ./setup.sh train passes)",
    )
    p.add_argument(
        "--eval_every",
        type=int,
        default=25,
        help="evaluate the deterministic actor every N iterations (Eval/ in TensorBoard; 0: never)",
    )
    p.add_argument(
        "--console",
        choices=("block", "line"),
        default="block",
        help="block: rsl_rl's per-iteration report (with ETA) plus a progress line; line: only the progress line",
    )
    return p


PER_PROCESS_KEY = "env_set_per_process"
"""run.yaml's record of --set-per-process: {env config key: [value of process 0, 1, ...]}."""


def parse_per_process(items: list[str], world: int) -> dict[str, list]:
    """--set-per-process KEY=[V0,V1,...] items -> {KEY: [values]}, one value per process."""
    out: dict[str, list] = {}
    for item in items:
        key, sep, text = item.partition("=")
        try:
            values = yaml.safe_load(text) if sep else None
        except yaml.YAMLError:
            values = None
        if not key or not isinstance(values, list):
            raise UsageError(
                f"--set-per-process {item!r}: expected KEY=[V0,V1,...] with one value per process, "
                "e.g. 'sim.timestep=[0.005,0.002]'"
            )
        if len(values) != world:
            raise UsageError(
                f"--set-per-process {key}: {len(values)} values for {world} process(es); give one per process "
                f"(--procs {len(values)}) or leave it out"
            )
        out[key.strip()] = values
    return out


def process_env_cfg(env_cfg, per_process: dict[str, list], rank: int, world: int):
    """The env config of process `rank`: each --set-per-process list's entry `rank`. Every
    process's is built (and so checked) first, so a bad value fails in every process alike,
    and all must share one control period (physics step x decimation): PPO's batch is one."""
    configs = [
        common.with_overrides(env_cfg, {k: v[r] for k, v in per_process.items()}, f"--set-per-process (process {r})")
        for r in range(world)
    ]
    if all(c.sim.timestep for c in configs):
        periods = [c.sim.timestep * c.sim.decimation for c in configs]
        if max(periods) - min(periods) > 1e-9:
            keep = [max(1, round(periods[0] / c.sim.timestep)) for c in configs]
            raise UsageError(
                "--set-per-process: the control period (sim.timestep x sim.decimation) differs between the processes "
                f"({', '.join(f'{t * 1e3:g} ms' for t in periods)}); keep it equal, e.g. "
                f"--set-per-process 'sim.decimation=[{','.join(map(str, keep))}]'"
            )
    return configs[rank]


def _flags(per_process: dict[str, list]) -> str:
    """{key: [values]} as the --set-per-process flags that give it, ready to paste."""
    return " ".join(f"--set-per-process '{k}=[{','.join(map(str, v))}]'" for k, v in per_process.items())


def per_process_for(
    args: argparse.Namespace, run_dir: Path | None, world: int, task_default: dict[str, list] | None = None
) -> dict[str, list]:
    """The per-process lists of this invocation: --set-per-process as given; on --resume also
    the run's own (run.yaml), and on a new run of 2+ processes the task's
    (`TrainCfg.env_per_process`, entry r % its length for process r), for every key not given
    anew, neither per process nor by --set (which makes every process alike)."""
    given = parse_per_process(args.env_set_per_process, world)
    set_keys = {item.partition("=")[0].strip() for item in args.env_set}
    if run_dir is None:
        if world < 2:
            return given
        default = {
            k: [v[r % len(v)] for r in range(world)]
            for k, v in (task_default or {}).items()
            if v and k not in given and k not in set_keys
        }
        return {**default, **given}
    saved = common.read_run_info(run_dir).get(PER_PROCESS_KEY) or {}
    kept = {k: list(v) for k, v in saved.items() if k not in given and k not in set_keys}
    if kept and any(len(v) != world for v in kept.values()):
        n = len(next(iter(kept.values())))
        raise UsageError(
            f"run {run_dir} was trained in {n} processes with {_flags(kept)}: resume it with --procs {n}, or give "
            f"each key anew, per process ({world} value(s) each) or alike for all (--set KEY=VALUE)"
        )
    return {**kept, **given}


def configs_for(args: argparse.Namespace, spec, run_dir: Path | None, world: int) -> tuple[Any, Any, dict[str, list]]:
    """The env and train configs of this invocation (the run's on --resume, else the task's,
    with --set / --train-set on top) and its per-process lists; what a worker trains with and
    what the --procs launcher checks once."""
    env_cfg, train_cfg = common.run_configs(spec, run_dir)
    env_cfg = common.with_overrides(env_cfg, args.env_set, "--set")
    train_cfg = common.with_overrides(train_cfg, args.train_set, "--train-set")
    return env_cfg, train_cfg, per_process_for(args, run_dir, world, train_cfg.env_per_process)


def _stop_on_signals(once: bool = False) -> None:
    """Ctrl-C, `kill -INT` and `kill` (SIGTERM) all stop training the same way: the
    newest checkpoint is named with the command that continues from it. (A process a
    script starts in the background ignores SIGINT unless it says otherwise.) With `once`
    (a worker of a distributed run) the first signal also ignores every later one:
    torchrun's agent sends its workers the stop that a terminal's Ctrl-C already sent each
    of them, and a second KeyboardInterrupt would cut the first one's report short."""

    def interrupt(signum, frame):
        if once:  # a handler that does nothing: SIG_IGN would turn a signal already pending into an OSError
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, lambda *_: None)
        raise KeyboardInterrupt

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, interrupt if once else signal.default_int_handler)
        signal.signal(signal.SIGTERM, interrupt)


def _write_run_files(
    run_dir: Path, task: str, experiment: str, env_cfg, train_cfg, argv, resumed_from, per_process: dict
) -> None:
    dump_yaml(env_cfg, run_dir / "env.yaml")
    dump_yaml(train_cfg, run_dir / "train.yaml")
    info = common.read_run_info(run_dir)
    info.setdefault("task", task)
    info.setdefault("experiment", experiment)
    info.setdefault("created", datetime.datetime.now().isoformat(timespec="seconds"))
    info["processes"] = int(os.environ.get("WORLD_SIZE", "1"))  # env.yaml's num_envs is per process
    if per_process:
        info[PER_PROCESS_KEY] = per_process  # env.yaml is process 0's; process r used each list's entry r
    else:
        info.pop(PER_PROCESS_KEY, None)
    if resumed_from:
        info.setdefault("resumed", []).append(
            {"from": str(resumed_from), "at": datetime.datetime.now().isoformat(timespec="seconds")}
        )
    common.write_text_atomic(run_dir / common.RUN_FILE, yaml.safe_dump(info, sort_keys=False))
    repo = Path(__file__).resolve().parents[2]
    git, diff = common.git_state(repo)
    # The first invocation's code state is git.yaml/git.diff; each resume adds its own.
    tag = "" if not resumed_from else "_resume_" + datetime.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    common.write_text_atomic(run_dir / f"git{tag}.yaml", yaml.safe_dump(git, sort_keys=False))
    common.write_text_atomic(run_dir / f"git{tag}.diff", diff)
    with open(run_dir / "command.txt", "a") as f:
        f.write(f"# {datetime.datetime.now().isoformat(timespec='seconds')} cwd={os.getcwd()}\n")
        f.write(os.environ.get(LAUNCHER_ENV, common.command_line(argv)) + "\n")


def train(args: argparse.Namespace, argv: list[str] | None, default_log_root: Path | None) -> int:
    # --- everything is checked before the simulation starts ---------------------------
    task = args.task or common.default_task()
    spec = common.check_task(task)
    if args.num_envs is not None and args.num_envs < 1:
        raise UsageError(f"--num_envs must be at least 1, got {args.num_envs}")
    if args.max_iterations is not None and args.max_iterations < 1:
        raise UsageError(f"--max_iterations must be at least 1, got {args.max_iterations}")
    if (args.load_run or args.checkpoint) and not args.resume:
        raise UsageError("--load_run/--checkpoint choose what to resume from: add --resume")
    backend = resolve_backend(args.sim_backend)
    device = common.resolve_device(args.device, backend)
    rank = int(os.environ.get("RANK", "0"))
    world = int(os.environ.get("WORLD_SIZE", "1"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if world > 1 and device not in (f"cuda:{local}", "cpu"):
        raise UsageError(
            f"distributed training (WORLD_SIZE={world}) runs one process per GPU (--device auto or "
            f"cuda:LOCAL_RANK) or on the CPU (--device cpu, gloo), not on {device}"
        )
    if args.max_minutes is not None and args.max_minutes <= 0:
        raise UsageError(f"--max_minutes must be positive, got {args.max_minutes}")
    if args.eval_every < 0:
        raise UsageError(f"--eval_every must be 0 (off) or positive, got {args.eval_every}")
    if args.torch_threads is not None and args.torch_threads < 1:
        raise UsageError(f"--torch_threads must be at least 1, got {args.torch_threads}")
    root = common.log_root(args.log_root, default_log_root)

    ckpt, ckpt_path, run_dir = None, None, None
    experiment = args.experiment_name or spec.train_cfg.experiment_name
    if args.resume:
        run_dir = common.find_run(root, experiment, args.load_run)
        ckpt_path = common.find_checkpoint(run_dir, args.checkpoint, newest=True)  # resume: where it stopped
        ckpt = common.load_checkpoint(ckpt_path, map_location=device)
    env_cfg, train_cfg, per_process = configs_for(args, spec, run_dir, world)
    if per_process and rank == 0:
        print(f"[{PROG}] per process: {_flags(per_process)}")
    elif run_dir is None and world == 1 and train_cfg.env_per_process:
        print(
            f"[{PROG}] note: task {task} varies {', '.join(train_cfg.env_per_process)} between the processes of a "
            f"--procs run ({_flags(train_cfg.env_per_process)}); this run has one process and keeps process 0's "
            "config (train on the CPU with --procs 2 or auto for the mix)"
        )
    train_fields = {}
    for flag in ("max_iterations", "seed", "experiment_name", "run_name"):
        if getattr(args, flag) is not None:
            train_fields[flag] = getattr(args, flag)
    train_cfg = common.with_overrides(train_cfg, train_fields, "train flags")
    train_cfg.check_stages()
    env_fields = {"sim.backend": args.sim_backend, "sim.device": device, "seed": train_cfg.seed + rank}
    if args.num_envs is not None:
        env_fields["num_envs"] = args.num_envs  # each process of a distributed run its own env draws (seed)

    def configs_at(iteration: int) -> tuple[Any, Any]:
        """This process's env config and the train config for iteration `iteration` (from 1):
        the task's or run's, its stages (TrainCfg.stages) up to then, --set again on top (what
        the command line says wins), the process's own values and the flags."""
        stage_env, stage_train = train_cfg.stage_overrides(iteration)
        cfg = common.with_overrides(env_cfg, stage_env, f"stages (iteration {iteration})")
        cfg = common.with_overrides(cfg, args.env_set, "--set")
        cfg = common.with_overrides(process_env_cfg(cfg, per_process, rank, world), env_fields, "env flags")
        return cfg, common.with_overrides(train_cfg, stage_train, f"stages (iteration {iteration})")

    first_env_cfg, _ = configs_at(1)  # what env.yaml records: the run's first iteration
    for it in sorted(train_cfg.stages):  # every stage's settings checked before the simulation starts
        configs_at(it + 1)
    experiment = train_cfg.experiment_name
    if run_dir is None:
        run_dir = common.new_run_dir(root, experiment, train_cfg.run_name)

    # --- simulation -------------------------------------------------------------------------
    pin_to_core(device)  # a CPU rank of a distributed run only
    common.limit_cpu_threads(device, args.torch_threads)
    torch.manual_seed(train_cfg.seed + rank)
    done = common.checkpoint_iteration(ckpt) if ckpt is not None else 0
    end = done + train_cfg.max_iterations
    cuts = [done] + [s for s in sorted(train_cfg.stages) if done < s < end] + [end]
    started = time.time()
    try:
        for first, last in zip(cuts, cuts[1:], strict=False):
            seg_env_cfg, seg_train_cfg = configs_at(first + 1)
            if first > done and rank == 0:
                stage = train_cfg.stages[first]
                print(f"[{PROG}] stage after iteration {first}: {', '.join(f'{k}={v}' for k, v in stage.items())}")
            budget = None
            if args.max_minutes is not None:
                budget = args.max_minutes * 60.0 - (time.time() - started)
            outcome = _train_segment(
                args, task, spec, seg_env_cfg, seg_train_cfg, run_dir, device, rank, world, ckpt, ckpt_path,
                last - first, end, budget,
                run_files=(experiment, first_env_cfg, train_cfg, argv, per_process) if first == done else None,
            )  # fmt: skip
            if isinstance(outcome, int):
                return outcome
            if outcome is None:
                break
            ckpt, ckpt_path = outcome, run_dir / f"model_{last}.pt"
    finally:
        if world > 1 and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
    if rank == 0:
        last = common.checkpoints(run_dir)[-1][1]
        print(f"[{PROG}] done: {last}")
        logdir = root if root in run_dir.parents else run_dir  # a resumed run given by its own path
        print(
            f"[{PROG}] watch: tensorboard --logdir {logdir}    play: python play.py --task {task} --load_run {run_dir}"
        )
        if train_cfg.select_last:
            return select_after_training(task, run_dir, train_cfg)
    return common.EXIT_OK


def _train_segment(
    args, task, spec, env_cfg, train_cfg, run_dir, device, rank, world, ckpt, ckpt_path, iterations, run_end,
    budget, run_files,
) -> dict | int | None:  # fmt: skip
    """`iterations` PPO iterations on a new env and runner of these configs, from `ckpt` if
    given: the state reached as a checkpoint dict (for the next stage); None when the
    --max_minutes budget ended the run; 130 when it was interrupted. `run_files`: on the
    first segment, what the run folder records."""
    t0 = time.time()
    env = spec.env_class(env_cfg)
    print(
        f"[{PROG}] task {task}: {env.num_envs} envs on the {env.backend_kind} backend, device {device}, "
        f"obs {env.observation_dims()}, control dt {env.dt:.3f} s = {env.sim.decimation} x "
        f"{env.sim.physics_dt * 1e3:g} ms physics (env built in {time.time() - t0:.1f} s)"
    )
    rsl_cfg = train_cfg.for_env(env)
    rsl_cfg["run_name"] = train_cfg.run_name
    log_dir = str(run_dir) if rank == 0 else None
    evaluator = None
    try:
        runner = CheckpointingRunner(env, rsl_cfg, log_dir=log_dir, device=device, task=task)
        # The code state is ours to record (git.yaml, git.diff); rsl_rl's own would add an empty git/ folder.
        runner.logger.git_status_repos = []
        runner.logger._store_code_state = list
        if ckpt is not None:
            runner.load_checkpoint(ckpt, ckpt_path)
            if run_files is not None:
                print(f"[{PROG}] resumed {ckpt_path} after {runner.current_learning_iteration} iterations")
        if rank == 0 and run_files is not None:
            experiment, first_env_cfg, full_train_cfg, argv, per_process = run_files
            _write_run_files(run_dir, task, experiment, first_env_cfg, full_train_cfg, argv, ckpt_path, per_process)
            print(f"[{PROG}] run folder {run_dir}")
        if args.eval_every and rank == 0:
            from legged_casters.tools.evaluate import DeterministicEval

            evaluator = DeterministicEval(spec, env_cfg)
        install_progress_hook(runner, args.console, task, evaluator, args.eval_every, budget, run_end)
        _stop_on_signals(once=world > 1)
        try:
            runner.learn(num_learning_iterations=iterations, init_at_random_ep_len=True)
        except BudgetReached as stop:
            if rank == 0:
                print(f"[{PROG}] --max_minutes {args.max_minutes:g}: stopped after iteration {stop.args[0]}")
            return None
        except KeyboardInterrupt:
            if rank == 0:  # the run folder is rank 0's (the others never write theirs)
                latest = common.checkpoints(run_dir)
                if latest:
                    procs = f" --procs {world}" if world > 1 and LAUNCHER_ENV in os.environ else ""
                    print(f"\n[{PROG}] interrupted; newest checkpoint {latest[-1][1]}", file=sys.stderr)
                    print(f"[{PROG}] continue with: python train.py --task {task}{procs} --resume --load_run {run_dir}")
                else:
                    every = train_cfg.save_interval
                    print(f"\n[{PROG}] interrupted before the first checkpoint (saved every {every} iterations): "
                          f"no model_<iteration>.pt to continue from in {run_dir}", file=sys.stderr)  # fmt: skip
            return 130
        return runner.checkpoint()
    finally:
        env.close()
        if evaluator is not None:
            evaluator.close()


def select_after_training(task: str, run_dir: Path, train_cfg) -> int:
    """Rank the newest `select_last` saved checkpoints by evaluate.py's full fixed evaluation
    and record the first in the run's selected.yaml (evaluate.py --select)."""
    from legged_casters.tools import evaluate

    saved = [it for it, _ in common.checkpoints(run_dir)]
    if train_cfg.stages:  # only checkpoints trained with every stage's settings are the recipe's
        after = max(train_cfg.stages)
        saved = [it for it in saved if it > after]
        if not saved:
            print(
                f"[{PROG}] no checkpoint after the last stage (iteration {after}) to select from: play, evaluate and "
                "export load the newest"
            )
            return common.EXIT_OK
    saved = saved[-train_cfg.select_last :]
    print(f"[{PROG}] selecting the checkpoint by the full evaluation: iterations {', '.join(map(str, saved))}")
    from legged_casters.sim.base import usable_cpus

    argv = ["--task", task, "--load_run", str(run_dir), "--checkpoints", ",".join(map(str, saved)), "--select"]
    argv += ["--jobs", str(max(1, min(len(saved), usable_cpus())))]  # one checkpoint per core
    return evaluate.main(argv)


def _strip_flag(argv: list[str], flag: str) -> list[str]:
    """argv without `flag VALUE` / `flag=VALUE`."""
    out, skip = [], False
    for item in argv:
        if skip:
            skip = False
        elif item == flag:
            skip = True
        elif not item.startswith(flag + "="):
            out.append(item)
    return out


def _resume_dir(args: argparse.Namespace, spec, default_log_root: Path | None) -> Path:
    """The run folder --resume (with --load_run, --experiment_name, --log_root) continues."""
    root = common.log_root(args.log_root, default_log_root)
    return common.find_run(root, args.experiment_name or spec.train_cfg.experiment_name, args.load_run)


def total_envs(args: argparse.Namespace, spec, default_log_root: Path | None) -> int:
    """The envs of all processes together: --num_envs, else on --resume the run's (env.yaml's
    envs per process x run.yaml's processes), else the task's."""
    if args.num_envs is not None:
        return args.num_envs
    if args.resume:
        run_dir = _resume_dir(args, spec, default_log_root)
        saved_env, _ = common.run_configs(spec, run_dir)
        processes = int(common.read_run_info(run_dir).get("processes", 1))
        return (saved_env.num_envs or CPU_DEFAULT_NUM_ENVS) * processes
    return spec.env_cfg.num_envs or CPU_DEFAULT_NUM_ENVS


def check_process_configs(args: argparse.Namespace, spec, default_log_root: Path | None) -> None:
    """What every worker of --procs will check of its config, checked once in the launcher."""
    run_dir = _resume_dir(args, spec, default_log_root) if args.resume else None
    env_cfg, _, per_process = configs_for(args, spec, run_dir, args.procs)
    process_env_cfg(env_cfg, per_process, 0, args.procs)


def launch_procs(args: argparse.Namespace, argv: list[str], default_log_root: Path | None) -> int:
    """--procs N: this process starts torchrun with N copies of train.py on this machine's
    CPU (each pins itself to one core, `pin_to_core`) and waits for them; Ctrl-C and
    SIGTERM are passed on, so the workers stop as a single run does."""
    if args.procs < 1:
        raise UsageError(f"--procs must be at least 1, got {args.procs}")
    backend = resolve_backend(args.sim_backend)
    device = common.resolve_device(args.device, backend)
    if device != "cpu" or backend != "cpu":
        raise UsageError(
            f"--procs {args.procs} runs CPU processes (device cpu, backend cpu), not device {device} with the "
            f"{backend} backend: use --procs 1 or auto; for several GPUs start torchrun yourself "
            "(docs/training.md, 'On a GPU')"
        )
    cores = usable_cpus()
    if args.procs > cores:
        raise UsageError(f"--procs {args.procs}: this process may use {cores} CPU core(s); one process per core")
    task = args.task or common.default_task()
    spec = common.check_task(task)
    check_process_configs(args, spec, default_log_root)  # a bad --set-per-process fails here, not in every worker
    child = _strip_flag(_strip_flag(argv, "--procs"), "--num_envs")
    total = total_envs(args, spec, default_log_root)
    if total % args.procs:
        raise UsageError(f"--num_envs {total} does not split evenly into {args.procs} processes")
    child += ["--num_envs", str(total // args.procs)]
    if args.log_root is None:
        child += ["--log_root", str(common.log_root(None, default_log_root))]
    cmd = [sys.executable, "-m", "legged_casters.tools.launcher", "--standalone", "--nnodes=1"]
    cmd += [f"--nproc_per_node={args.procs}", "-m", "legged_casters.tools.train", *child]
    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    env[LAUNCHER_ENV] = common.command_line(argv)
    print(f"[{PROG}] {args.procs} processes on {cores} cores, {total // args.procs} envs each")
    proc = subprocess.Popen(cmd, env=env)

    def forward(signum, frame):
        proc.send_signal(signum)

    previous = {sig: signal.signal(sig, forward) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return proc.wait()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def pin_to_core(device: str) -> None:
    """A CPU process of a distributed run takes one core of those it may use (by its local
    rank) and one torch thread, so that the processes do not fight over cores: two such
    processes on 2 cores simulate and learn faster than one process on both
    (docs/training.md)."""
    local = int(os.environ.get("LOCAL_RANK", "0"))
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", os.environ.get("WORLD_SIZE", "1")))
    if device != "cpu" or local_world <= 1 or not hasattr(os, "sched_setaffinity"):
        return
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) < local_world:
        return  # fewer cores than processes: leave the scheduler to share them
    core = cores[local % len(cores)]
    os.sched_setaffinity(0, {core})
    torch.set_num_threads(1)
    print(f"[{PROG}] rank {os.environ.get('RANK', '0')}: CPU core {core}, 1 torch thread")


def _run(args: argparse.Namespace, argv: list[str] | None, root: Path | None) -> int:
    if "WORLD_SIZE" in os.environ:  # a worker of --procs, or of a torchrun of yours
        if args.procs not in (1, "auto"):
            raise UsageError("--procs starts torchrun itself; do not run it under torchrun")
        return train(args, argv, root)
    args.procs = resolve_procs(args)
    if args.procs != 1:
        return launch_procs(args, sys.argv[1:] if argv is None else list(argv), root)
    return train(args, argv, root)


def main(argv: list[str] | None = None, default_log_root: Path | str | None = None) -> int:
    args = build_parser().parse_args(argv)
    root = Path(default_log_root) if default_log_root else None
    return common.run_cli(lambda: _run(args, argv, root), PROG, args.verbose)


if __name__ == "__main__":  # torchrun's workers of --procs
    sys.exit(main())
