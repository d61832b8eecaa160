"""The training loop's hooks around rsl_rl's runner: the one-line progress report, the
periodic deterministic evaluation (TensorBoard Eval/...), `model_best.pt` (the checkpoint
that evaluation liked best), numbered checkpoints every `save_interval` iterations, and the
wall-time budget (`--max_minutes`). train.py installs them with `install_progress_hook`."""

from __future__ import annotations

import contextlib
import datetime
import io
import math
import os
import re
import statistics
import time

import torch

from legged_casters.learning.runner import CheckpointingRunner


class BudgetReached(Exception):
    """--max_minutes ran out: raised after the iteration's report and checkpoint."""


BEST_CHECKPOINT = "model_best.pt"
"""The checkpoint with the lowest evaluation score so far (`--checkpoint best`)."""
ITERATION_RE = re.compile(r"Learning iteration (\d+)/(\d+)")
"""rsl_rl's per-iteration report heading, renumbered from 1 in the console."""


def eval_score(summary: dict[str, float]) -> float:
    """One number for the deterministic evaluation, lower is better: the mean |error| of
    vx and vy (m/s) and wz (rad/s) added up, plus one per fall."""
    return sum(summary.get(k, 0.0) for k in ("vx_error", "vy_error", "wz_error")) + summary.get("falls", 0.0)


def budget_reached(runner: CheckpointingRunner, started: float, max_seconds: float | None) -> bool:
    """Whether the wall-time budget is spent; in a distributed run rank 0 decides for all."""
    if max_seconds is None:
        return False
    stop = time.time() - started >= max_seconds
    if runner.is_distributed:
        flag = torch.tensor([1.0 if stop else 0.0], device=runner.device)
        torch.distributed.broadcast(flag, src=0)
        stop = bool(flag.item())
    return stop


def install_progress_hook(
    runner: CheckpointingRunner,
    console: str,
    task: str,
    evaluator=None,
    eval_every: int = 0,
    max_seconds: float | None = None,
    run_total: int | None = None,
) -> None:
    """Wrap the rsl_rl logger's per-iteration report with a one-line progress summary and,
    every `eval_every` iterations, the deterministic evaluation (TensorBoard Eval/...).
    With `max_seconds`, the iteration that ends past that much wall time is the last:
    BudgetReached is raised after its report (and on rank 0 its final checkpoint).
    `run_total`: the iteration the whole run ends at, when this learn() is one stage of it
    (TrainCfg.stages): the progress line and its ETA count to it."""
    started = time.time()
    logger = runner.logger
    original = logger.log
    steps_per_it = runner.cfg["num_steps_per_env"] * runner.env.num_envs * logger.gpu_world_size
    last_eval: dict[str, float] = {}
    eval_time = [0.0]
    best = [math.inf]
    previous = os.path.join(logger.log_dir or "", BEST_CHECKPOINT)
    if logger.log_dir and os.path.isfile(previous):  # a resume competes with the run's best so far
        with contextlib.suppress(RuntimeError, KeyError, TypeError, ValueError, OSError):
            best[0] = float(torch.load(previous, weights_only=True)["infos"]["eval_score"])

    def log(**kw):
        it, start_it, total_it = kw["it"], kw["start_it"], kw["total_it"]
        report = io.StringIO()
        with contextlib.redirect_stdout(report):
            original(**kw)
        if console == "block":  # rsl_rl counts from 0; say the iteration's number as ours does
            text = report.getvalue()
            print(ITERATION_RE.sub(lambda m: f"Learning iteration {it + 1}/{run_total or m.group(2)}", text), end="")
        stop = it + 1 < total_it and budget_reached(runner, started, max_seconds)
        if logger.writer is None:
            if stop:
                raise BudgetReached(it + 1)
            return
        runner.last_iteration_logged = it + 1 == total_it or stop
        if (it + 1) % runner.cfg["save_interval"] == 0 and not runner.last_iteration_logged:
            runner.write_checkpoint(os.path.join(logger.log_dir, f"model_{it + 1}.pt"))
        it_time = kw["collect_time"] + kw["learn_time"]
        done = it + 1 - start_it
        shown_total = run_total or total_it
        eta = logger.tot_time / max(done, 1) * (shown_total - it - 1)
        reward = statistics.mean(logger.rewbuffer) if logger.rewbuffer else math.nan
        length = statistics.mean(logger.lenbuffer) if logger.lenbuffer else math.nan
        std = kw.get("action_std")
        if std is not None:
            joints = runner.env.layout.joints
            per_joint = std.reshape(-1, len(joints))[0].tolist()
            for name, value in zip(joints, per_joint, strict=True):
                logger.writer.add_scalar(f"Noise/std_{name}", value, it)
        last = it + 1 == total_it or stop
        if evaluator is not None and eval_every and ((it + 1) % eval_every == 0 or last or done == 1):
            t0 = time.time()
            last_eval.clear()
            last_eval.update(evaluator(runner.alg.get_policy()))
            eval_time[0] += time.time() - t0
            for key, value in last_eval.items():
                logger.writer.add_scalar(f"Eval/{key}", value, it)
            score = eval_score(last_eval)
            if score < best[0]:  # keep the policy the evaluation liked best: model_best.pt
                best[0] = score
                runner.write_checkpoint(
                    os.path.join(logger.log_dir, BEST_CHECKPOINT), {"eval": dict(last_eval), "eval_score": score}
                )
            logger.writer.add_scalar("Eval/score", score, it)
            logger.writer.add_scalar("Eval/time_share", eval_time[0] / max(logger.tot_time + eval_time[0], 1e-9), it)
        ev = ""
        if last_eval:
            ev = " | eval |err| " + " ".join(
                f"{k[:2]} {last_eval[k]:.2f}" for k in ("vx_error", "vy_error", "wz_error") if k in last_eval
            )
            ev += f" falls {last_eval.get('falls', 0):.0f}"
        print(
            f"[{task}] it {it + 1}/{shown_total} | {steps_per_it / it_time:,.0f} steps/s | {it_time:.2f} s/it "
            f"(collect {kw['collect_time']:.2f}) | mean reward {reward:.3f} | ep len {length:.0f}{ev} | "
            f"ETA {datetime.timedelta(seconds=int(eta))}",
            flush=True,
        )
        if stop:
            runner.write_checkpoint(os.path.join(logger.log_dir, f"model_{it + 1}.pt"))
            logger.stop_logging_writer()
            raise BudgetReached(it + 1)

    logger.log = log
