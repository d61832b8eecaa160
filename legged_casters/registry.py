"""Task registry: a task name maps to (env class, env config, train config)."""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

from legged_casters.config import apply_overrides, parse_overrides


@dataclass(frozen=True)
class TaskSpec:
    name: str
    env_class: type
    env_cfg: Any
    train_cfg: Any


_TASKS: dict[str, TaskSpec] = {}


class UnknownTaskError(KeyError):
    def __str__(self) -> str:  # KeyError quotes its message; show it plainly
        return self.args[0]


def register(name: str, env_class: type, env_cfg: Any, train_cfg: Any) -> None:
    if name in _TASKS:
        raise ValueError(f"task {name!r} is already registered")
    _TASKS[name] = TaskSpec(name, env_class, env_cfg, train_cfg)


def _load_builtin_tasks() -> None:
    import legged_casters.envs  # noqa: F401  (registers the built-in tasks)


def list_tasks() -> list[str]:
    _load_builtin_tasks()
    return sorted(_TASKS)


def get_task(name: str) -> TaskSpec:
    _load_builtin_tasks()
    try:
        return _TASKS[name]
    except KeyError:
        known = ", ".join(list_tasks()) or "(none registered)"
        raise UnknownTaskError(f"unknown task {name!r}; known tasks: {known}") from None


def task_configs(name: str, env_overrides=None, train_overrides=None) -> tuple[Any, Any]:
    """Fresh copies of a task's configs with dotted overrides applied."""
    spec = get_task(name)
    env_cfg, train_cfg = copy.deepcopy(spec.env_cfg), copy.deepcopy(spec.train_cfg)
    if env_overrides:
        env_cfg = apply_overrides(env_cfg, env_overrides)
    if train_overrides:
        train_cfg = apply_overrides(train_cfg, train_overrides)
    return env_cfg, train_cfg


def make_env(name: str, overrides: list[str] | dict[str, Any] | None = None, **fields: Any):
    """Instantiate a registered task's env from a fresh copy of its config.

    `overrides` are dotted names ("commands.ranges.lin_vel_x=[-1, 1]") and `fields`
    top-level env config fields (`num_envs=64`); both are validated.
    """
    spec = get_task(name)
    env_cfg, _ = task_configs(name, {**parse_overrides(overrides), **fields})
    return spec.env_class(env_cfg)
