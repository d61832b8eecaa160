"""The training runner: rsl_rl's OnPolicyRunner with safe checkpoints that carry the env's
state, iterations numbered from 1, and distributed training on CPUs (gloo)."""

from __future__ import annotations

import datetime
import math
import os
from pathlib import Path

import numpy as np
import torch
from rsl_rl.runners import OnPolicyRunner

from legged_casters.tools import common
from legged_casters.tools.common import CheckpointError


class CheckpointingRunner(OnPolicyRunner):
    """OnPolicyRunner whose checkpoints are written atomically and carry the env's state
    (curriculum) and the task name, so that a resume restores them.

    Iterations are counted as they are done, from 1: model_<n>.pt is the policy after n
    iterations, written every `save_interval` iterations and after the last one; the
    progress line says "it n/total". (rsl_rl's own numbering starts at 0 and would save
    model_0.pt, model_50.pt, ... and model_<total - 1>.pt.)"""

    def __init__(self, env, train_cfg: dict, log_dir: str | None, device: str, task: str):
        self.task = task
        self.last_iteration_logged = False
        self.noise_std_schedule = [tuple(point) for point in train_cfg.get("noise_std_schedule") or ()]
        self.noise_std_dims = train_cfg.get("noise_std_schedule_dims")  # None: every action dimension
        super().__init__(env, train_cfg, log_dir=log_dir, device=device)
        if getattr(self.alg, "estimator_mirror", False):  # symmetry.estimator: the maps come from the env
            self.alg.mirror_env = env
        if self.noise_std_schedule:  # after each iteration's report, the std of the next one
            report = self.logger.log

            def log(**kw):
                report(**kw)
                self.set_noise_std(kw["it"] + 1)

            self.logger.log = log

    def noise_std_at(self, done: int) -> float | None:
        """The scheduled exploration std for an iteration that starts after `done` iterations."""
        if not self.noise_std_schedule:
            return None
        its, stds = zip(*self.noise_std_schedule, strict=True)
        return float(np.interp(done, its, stds))

    def set_noise_std(self, done: int) -> None:
        """policy.noise_std_schedule: the std of every action dimension (or of those that
        policy.noise_std_schedule_joints names: TrainCfg.for_env) set to the schedule's value."""
        std = self.noise_std_at(done)
        if std is None:
            return
        dist = self.alg.get_policy().distribution
        param, value = (dist.std_param, std) if hasattr(dist, "std_param") else (dist.log_std_param, math.log(std))
        with torch.no_grad():
            if self.noise_std_dims is None:
                param.fill_(value)
            else:
                param[self.noise_std_dims] = value

    def learn(self, num_learning_iterations: int, init_at_random_ep_len: bool = False):
        self.set_noise_std(self.current_learning_iteration)
        return super().learn(num_learning_iterations, init_at_random_ep_len=init_at_random_ep_len)

    def completed_iterations(self) -> int:
        return self.current_learning_iteration + 1

    def _configure_multi_gpu(self) -> None:
        """rsl_rl's set-up of a torchrun launch, which hard-codes nccl and cuda:LOCAL_RANK;
        on a CPU device the processes reduce their gradients through gloo instead."""
        world = int(os.getenv("WORLD_SIZE", "1"))
        if world <= 1 or str(self.device).startswith("cuda"):
            super()._configure_multi_gpu()
            return
        if str(self.device) != "cpu":
            raise ValueError(f"distributed training runs on cuda:LOCAL_RANK or cpu, not {self.device}")
        self.gpu_world_size, self.is_distributed = world, True
        self.gpu_local_rank = int(os.getenv("LOCAL_RANK", "0"))
        self.gpu_global_rank = int(os.getenv("RANK", "0"))
        if not 0 <= self.gpu_global_rank < world:
            raise ValueError(f"RANK {self.gpu_global_rank} is outside WORLD_SIZE {world}")
        self.cfg["multi_gpu"] = {
            "global_rank": self.gpu_global_rank,
            "local_rank": self.gpu_local_rank,
            "world_size": world,
        }
        if not torch.distributed.is_initialized():
            torch.distributed.init_process_group(backend="gloo", rank=self.gpu_global_rank, world_size=world)

    def save(self, path: str, infos: dict | None = None) -> None:
        """rsl_rl's own calls (its 0-based model_<index>.pt) are replaced by model_<n>.pt
        from the progress hook; only its final save, after the last iteration, is kept."""
        if common.CHECKPOINT_RE.match(os.path.basename(path)):
            if not self.last_iteration_logged:
                return
            path = os.path.join(os.path.dirname(path), f"model_{self.completed_iterations()}.pt")
        self.write_checkpoint(path, infos)

    def checkpoint(self, infos: dict | None = None) -> dict:
        """What a model_<n>.pt holds: policy, critic, normaliser, optimizer, the last iteration
        done and the env's state."""
        saved = self.alg.save()
        saved["iter"] = self.current_learning_iteration
        saved["infos"] = {
            **(infos or {}),
            "task": self.task,
            "env_state": self.env.get_state(),
            "saved_at": datetime.datetime.now().isoformat(timespec="seconds"),
        }
        return saved

    def write_checkpoint(self, path: str, infos: dict | None = None) -> None:
        saved = self.checkpoint(infos)
        common.save_checkpoint_atomic(saved, path)
        self.logger.save_model(path, self.current_learning_iteration)

    def load_checkpoint(self, ckpt: dict, path: Path) -> None:
        """Policy, critic, normaliser, optimizer and iteration from a weights-only loaded checkpoint."""
        infos = ckpt.get("infos") or {}
        saved_task = infos.get("task")
        if saved_task and saved_task != self.task:
            raise CheckpointError(f"checkpoint {path} was trained on task {saved_task!r}, not {self.task!r}")
        try:
            self.alg.load(ckpt, None, True)
        except (RuntimeError, KeyError, ValueError) as err:
            first = str(err).strip().splitlines()[0][:300]
            raise CheckpointError(f"checkpoint {path} does not fit this task's networks: {first}") from None
        # rsl_rl stores the last finished iteration; continue with the next one.
        self.current_learning_iteration = int(ckpt["iter"]) + 1
        state = infos.get("env_state")
        if state:
            try:
                self.env.set_state(state)
            except (KeyError, ValueError, TypeError) as err:
                raise CheckpointError(f"checkpoint {path}: saved env state does not fit the env: {err}") from None
