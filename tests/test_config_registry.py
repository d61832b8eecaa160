from dataclasses import dataclass, field
from typing import Literal

import pytest

import legged_casters.envs  # noqa: F401  (built-in tasks registered before the registry is swapped)
from legged_casters import registry
from legged_casters.config import ConfigError, apply_overrides, dump_yaml, load_yaml, parse_overrides, to_dict


@dataclass
class Ranges:
    lin_vel_x: tuple[float, float] = (-1.0, 1.0)
    heading: bool = False


@dataclass
class Commands:
    resampling_time: float = field(default=10.0, metadata={"min": 0.1})
    ranges: Ranges = field(default_factory=Ranges)


@dataclass
class EnvCfg:
    num_envs: int = field(default=4096, metadata={"min": 1})
    sim_backend: Literal["auto", "cpu", "warp"] = "auto"
    commands: Commands = field(default_factory=Commands)
    reward_scales: dict[str, float] = field(default_factory=lambda: {"tracking": 1.0})
    seed: int | None = None


def test_yaml_round_trip(tmp_path):
    cfg = apply_overrides(EnvCfg(), ["num_envs=8", "commands.ranges.lin_vel_x=[-2, 3]", "seed=3"])
    path = dump_yaml(cfg, tmp_path / "env.yaml")
    back = load_yaml(EnvCfg, path)
    assert back == cfg
    assert back.commands.ranges.lin_vel_x == (-2.0, 3.0)
    assert isinstance(back.commands.ranges.lin_vel_x[0], float)
    assert to_dict(back)["commands"]["ranges"]["lin_vel_x"] == [-2.0, 3.0]


def test_overrides_reach_nested_fields_and_keep_the_original():
    base = EnvCfg()
    cfg = apply_overrides(base, {"commands.resampling_time": 5, "reward_scales.tracking": 2.5, "sim_backend": "cpu"})
    assert cfg.commands.resampling_time == 5.0 and cfg.reward_scales["tracking"] == 2.5 and cfg.sim_backend == "cpu"
    assert base.commands.resampling_time == 10.0 and base.sim_backend == "auto"


@pytest.mark.parametrize(
    "override, message",
    [
        ("num_envs=0", "below the minimum 1"),
        ("num_envs=abc", "expected an integer"),
        ("sim_backend=gpu", "expected one of 'auto', 'cpu', 'warp'"),
        ("commands.nope=1", "commands has no 'nope'; allowed: ['resampling_time', 'ranges']"),
        ("num_envs.x=1", "num_envs is a value, not a group"),
        ("reward_scales.tracking=abc", "expected a number"),
        ("commands.ranges.lin_vel_x=[1]", "expected 2 values"),
        ("commands.ranges.heading=3", "expected true or false"),
        ("num_envs", "must look like name.path=value"),
    ],
)
def test_invalid_values_say_what_is_allowed(override, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]").replace("(", r"\(")):
        apply_overrides(EnvCfg(), [override])


def test_load_rejects_unknown_keys_and_missing_files(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("num_envs: 4\nnum_env: 5\n")
    with pytest.raises(ConfigError, match="unknown key"):
        load_yaml(EnvCfg, path)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_yaml(EnvCfg, tmp_path / "missing.yaml")


def test_parse_overrides_parses_yaml_values():
    assert parse_overrides(["a.b=true", "c=[1, 2]", "d=0.5", "e=x=y"]) == {
        "a.b": True,
        "c": [1, 2],
        "d": 0.5,
        "e": "x=y",
    }


class _Env:
    def __init__(self, cfg):
        self.cfg = cfg


def test_registry_make_env_and_errors(monkeypatch):
    monkeypatch.setattr(registry, "_TASKS", {})
    registry.register("toy", _Env, EnvCfg(), {"algorithm": "ppo"})
    assert registry.list_tasks() == ["toy"]
    env = registry.make_env("toy", ["commands.resampling_time=2"], num_envs=16)
    assert env.cfg.num_envs == 16 and env.cfg.commands.resampling_time == 2.0
    assert registry.get_task("toy").env_cfg.num_envs == 4096  # the registered config is untouched
    with pytest.raises(ValueError, match="already registered"):
        registry.register("toy", _Env, EnvCfg(), {})
    with pytest.raises(registry.UnknownTaskError, match="unknown task 'toi'; known tasks: toy"):
        registry.make_env("toi")
    with pytest.raises(ConfigError):
        registry.make_env("toy", num_envs=-1)


def test_mapping_fields_accept_new_keys():
    cfg = apply_overrides(EnvCfg(), ["reward_scales.stand_still=-0.5"])
    assert cfg.reward_scales == {"tracking": 1.0, "stand_still": -0.5}
