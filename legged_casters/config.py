"""Typed configuration: dataclasses with defaults, YAML round trip, dotted overrides.

Every config is a tree of dataclasses. Fields may carry limits in their metadata,
``field(default=..., metadata={"min": 0})``, and ``Literal[...]`` types name the
allowed values; ``validate`` checks both and says what is allowed.

    cfg = apply_overrides(cfg, ["env.num_envs=64", "rewards.tracking_lin_vel=2.5"])
    dump_yaml(cfg, "run/env.yaml"); same = load_yaml(type(cfg), "run/env.yaml")
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

import yaml

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value or key that is not allowed; the message says what is."""


def _hints(cls: type) -> dict[str, Any]:
    return get_type_hints(cls)


def _describe(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(tp))
    if dataclasses.is_dataclass(tp):
        return f"a {tp.__name__} mapping"
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Convert `value` (from YAML or a CLI string) to type `tp`, or raise ConfigError."""
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin is Literal:
        if value not in get_args(tp):
            raise ConfigError(f"{where}: {value!r} is not allowed; expected {_describe(tp)}")
        return value
    if origin in (typing.Union, types.UnionType):
        options = get_args(tp)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _coerce(value, option, where)
            except ConfigError as err:
                errors.append(str(err))
        raise ConfigError(f"{where}: {value!r} matches none of {[_describe(o) for o in options]}")
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected {_describe(tp)}, got {value!r}")
        return from_dict(tp, value, prefix=where)
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        args = get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
            items = [_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))]
        else:
            item_tp = args[0] if args else Any
            items = [_coerce(v, item_tp, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        key_tp, val_tp = get_args(tp) or (Any, Any)
        return {_coerce(k, key_tp, where): _coerce(v, val_tp, f"{where}.{k}") for k, v in value.items()}
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true or false, got {value!r}")
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def from_dict(cls: type[T], data: dict, prefix: str = "") -> T:
    """Build dataclass `cls` from a mapping; unknown keys and bad types raise ConfigError."""
    hints = _hints(cls)
    names = [f.name for f in dataclasses.fields(cls) if f.init]
    unknown = set(data) - set(names)
    if unknown:
        where = prefix or cls.__name__
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {names}")
    kwargs = {k: _coerce(v, hints[k], f"{prefix}.{k}" if prefix else k) for k, v in data.items()}
    cfg = cls(**kwargs)
    validate(cfg, prefix)
    return cfg


def to_dict(cfg: Any) -> Any:
    """Plain data (dicts, lists, scalars) for a dataclass tree."""
    if dataclasses.is_dataclass(cfg):
        return {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, (list, tuple)):
        return [to_dict(v) for v in cfg]
    if isinstance(cfg, dict):
        return {k: to_dict(v) for k, v in cfg.items()}
    return cfg


def validate(cfg: Any, prefix: str = "") -> None:
    """Check `min`/`max`/`choices` metadata of every field in the tree."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        where = f"{prefix}.{f.name}" if prefix else f.name
        if dataclasses.is_dataclass(value):
            validate(value, where)
            continue
        meta = f.metadata
        for item in value if isinstance(value, (list, tuple)) else [value]:
            if not isinstance(item, (int, float)) or isinstance(item, bool):
                continue
            if "min" in meta and item < meta["min"]:
                raise ConfigError(f"{where}: {value!r} is below the minimum {meta['min']}")
            if "max" in meta and item > meta["max"]:
                raise ConfigError(f"{where}: {value!r} is above the maximum {meta['max']}")
        if "choices" in meta and value not in meta["choices"]:
            raise ConfigError(f"{where}: {value!r} is not allowed; expected one of {list(meta['choices'])}")


def dump_yaml(cfg: Any, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))
    return path


def load_yaml(cls: type[T], path: str | Path) -> T:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file {path} does not exist")
    data = yaml.safe_load(path.read_text()) or {}
    return from_dict(cls, data)


def parse_overrides(overrides: list[str] | dict[str, Any] | None) -> dict[str, Any]:
    """{"a.b": value} from ["a.b=value", ...] (values parsed as YAML) or a mapping."""
    if not overrides:
        return {}
    if isinstance(overrides, dict):
        return dict(overrides)
    out = {}
    for text in overrides:
        key, sep, raw = text.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"override {text!r} must look like name.path=value")
        out[key.strip()] = yaml.safe_load(raw)
    return out


def apply_overrides(cfg: T, overrides: list[str] | dict[str, Any]) -> T:
    """Return a copy of `cfg` with dotted-name overrides applied.

    `overrides` is a list of "a.b.c=value" strings (values parsed as YAML, so
    `true`, `3`, `[0.1, 0.2]` work) or a mapping {"a.b.c": value}.
    """
    data = to_dict(cfg)
    for key, value in parse_overrides(overrides).items():
        node, obj, parts = data, cfg, key.split(".")
        for depth, part in enumerate(parts):
            last = depth == len(parts) - 1
            scope = ".".join(parts[:depth]) or type(cfg).__name__
            if dataclasses.is_dataclass(obj):
                names = [f.name for f in dataclasses.fields(obj)]
                if part not in names:
                    raise ConfigError(f"unknown config field {key!r}: {scope} has no {part!r}; allowed: {names}")
                obj = getattr(obj, part)
            elif isinstance(obj, dict):
                # A mapping field (e.g. reward scales) is open: new keys may be added.
                if part not in node and not last:
                    raise ConfigError(f"unknown config field {key!r}: {scope} has no {part!r}; has: {sorted(node)}")
                obj = obj.get(part)
            else:
                raise ConfigError(f"unknown config field {key!r}: {scope} is a value, not a group")
            if last:
                node[part] = value
            else:
                node = node[part]
    return from_dict(type(cfg), data)
