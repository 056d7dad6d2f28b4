"""Typed configs for every component: dataclasses with a docstring per field, loaded from YAML.

One mechanism for the whole repository (nerfstudio style): a component defines frozen dataclasses
and named presets (``tiny``, ``paper``, ...); :func:`merge_config` overlays plain data (YAML/JSON/CLI)
on a preset, rejecting unknown keys and wrong types with the dotted path of the offending field;
:func:`save_config` writes the resolved config beside a run's outputs.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")

__all__ = [
    "ConfigError",
    "merge_config",
    "parse_overrides",
    "require_at_least",
    "require_in_range",
    "require_one_of",
    "config_from_dict",
    "config_to_dict",
    "load_config",
    "read_mapping",
    "save_config",
]


class ConfigError(ValueError):
    """A config has an unknown key, a wrong type or an impossible value; the message names the field."""


_KIND = {int: "an integer", float: "a number", bool: "true/false", str: "a string"}
"""Plain-words name of each scalar type, for error messages read by people who write YAML."""


def _strip_optional(annotation: Any) -> tuple[Any, bool]:
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        optional = len(args) < len(typing.get_args(annotation))
        if len(args) == 1:
            return args[0], optional
    return annotation, False


def _coerce(value: Any, annotation: Any, where: str) -> Any:
    annotation, optional = _strip_optional(annotation)
    if value is None:
        if optional or annotation is Any:
            return None
        raise ConfigError(f"{where}: may not be null")
    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        if value not in typing.get_args(annotation):
            raise ConfigError(f"{where}: {value!r} is not one of {list(typing.get_args(annotation))}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {type(value).__name__} ({value!r})")
        args = typing.get_args(annotation)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
            items = [_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))]
        else:
            item_type = args[0] if args else Any
            items = [_coerce(v, item_type, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if dataclasses.is_dataclass(annotation) and isinstance(annotation, type):
        if isinstance(value, annotation):  # an already-built section is taken as is
            return value
        return merge_config(annotation(), value, where)
    if annotation is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if annotation in (int, float) and isinstance(value, bool):
        raise ConfigError(f"{where}: expected {annotation.__name__}, got a boolean")
    if annotation in (int, float, bool, str) and not isinstance(value, annotation):
        raise ConfigError(
            f"{where}: expected {annotation.__name__}, got {type(value).__name__} ({value!r}); "
            f"{_KIND[annotation]} is required"
        )
    return value


def merge_config(base: T, data: Mapping[str, Any] | None, where: str = "") -> T:
    """Return a copy of dataclass instance ``base`` with ``data`` applied (recursively).

    Unknown keys and wrong types raise :class:`ConfigError` naming the dotted field path; errors
    raised by the dataclass's own ``__post_init__`` validation are re-raised with the path.
    """
    if data is None:
        return base
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where or type(base).__name__}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(type(base))
    names = [f.name for f in dataclasses.fields(base)]
    unknown = sorted(set(data) - set(names))
    if unknown:
        prefix = f"{where}." if where else ""
        raise ConfigError(
            f"unknown config key(s) {[prefix + k for k in unknown]} (an unknown key is an error, never "
            f"ignored); known: {sorted(names)}"
        )
    updates = {}
    for key, value in data.items():
        sub = f"{where}.{key}" if where else key
        current = getattr(base, key)
        if dataclasses.is_dataclass(current) and isinstance(value, Mapping):
            updates[key] = merge_config(current, value, sub)
        else:
            updates[key] = _coerce(value, hints[key], sub)
    try:
        return dataclasses.replace(base, **updates)
    except ConfigError:
        raise
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{where or type(base).__name__}: {err}") from err


# ------------------------------------------------------------------- field checks for validate()
# The shapes every config's validate() repeats: a lower bound, an interval, a choice. Each names the
# dotted field and the value it got; ``where`` prefixes the message (e.g. "pretrain-vision: ").


def _field(config: Any, name: str) -> Any:
    value = config
    for part in name.split("."):
        value = getattr(value, part)
    return value


def require_at_least(config: Any, names: str | Sequence[str], low: float, where: str = "") -> None:
    """Every field in ``names`` (dotted paths on ``config``) is a finite number >= ``low``."""
    for name in [names] if isinstance(names, str) else names:
        v = _field(config, name)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= low):
            raise ConfigError(f"{where}{name} must be >= {low}, got {v!r}")


def require_in_range(
    config: Any,
    names: str | Sequence[str],
    low: float,
    high: float,
    *,
    low_open: bool = False,
    high_open: bool = False,
    where: str = "",
) -> None:
    """Every field in ``names`` lies in the interval from ``low`` to ``high`` (closed unless stated)."""
    for name in [names] if isinstance(names, str) else names:
        v = _field(config, name)
        ok = isinstance(v, (int, float)) and math.isfinite(v)
        ok = ok and (v > low if low_open else v >= low) and (v < high if high_open else v <= high)
        if not ok:
            interval = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
            raise ConfigError(f"{where}{name} must lie in {interval}, got {v!r}")


def require_one_of(config: Any, name: str, choices: Sequence[Any], where: str = "") -> None:
    """Field ``name`` is one of ``choices``."""
    v = _field(config, name)
    if v not in choices:
        raise ConfigError(f"{where}{name} must be one of {', '.join(map(str, choices))}; got {v!r}")


_RENDER_DEVICE = re.compile(r"cpu|cuda(:\d+)?")


def require_render_device(config: Any, name: str, where: str = "") -> None:
    """Field ``name`` names a device scenes can render on: ``cpu``, ``cuda`` or ``cuda:N`` (whether
    this machine has it is checked where the render function is built)."""
    v = _field(config, name)
    if not (isinstance(v, str) and _RENDER_DEVICE.fullmatch(v)):
        raise ConfigError(f"{where}{name} must be cpu or cuda[:N], got {v!r}")


_NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)")


def parse_overrides(items: Sequence[str], where: str = "--set") -> dict[str, Any]:
    """Nested overrides from ``KEY=VALUE`` strings (dotted keys, YAML values): ``["train.seed=1",
    "data.shuffle_instructions=true"]`` -> ``{"train": {"seed": 1}, "data": {"shuffle_instructions":
    True}}``. Keys and types are checked later, by :func:`merge_config`, against the config itself."""
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        parts = key.strip().split(".")
        if not sep or not all(parts):
            raise ConfigError(f"{where} {item!r}: expected KEY=VALUE with a dotted KEY, e.g. train.seed=1")
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError as err:
            raise ConfigError(f"{where} {item!r}: the value is not YAML ({err})") from None
        if isinstance(value, str) and _NUMBER.fullmatch(value.strip()):
            value = float(value)  # YAML 1.1 reads 2e-3 (no dot) as a string
        node = out
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{where} {item!r}: {part} is set to a value and used as a section")
        if isinstance(node.get(parts[-1]), dict):
            raise ConfigError(f"{where} {item!r}: {key} is a section, set its fields instead")
        node[parts[-1]] = value
    return out


def config_from_dict(cls: type[T], data: Mapping[str, Any] | None, where: str = "") -> T:
    """Build dataclass ``cls`` from its defaults overlaid with ``data``."""
    return merge_config(cls(), data, where)


def config_to_dict(config: Any) -> dict[str, Any]:
    """Plain-data (YAML/JSON-safe) view of a config dataclass; tuples become lists."""

    def plain(value: Any) -> Any:
        if dataclasses.is_dataclass(value):
            return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, Path):
            return str(value)
        return value

    return plain(config)


def load_config(
    presets: Mapping[str, Callable[[], T]],
    name_or_path: str | os.PathLike,
    overrides: Mapping[str, Any] | None = None,
) -> T:
    """A preset name, or a YAML file of overrides (optionally naming its ``base`` preset), plus
    ``overrides``. The first preset in ``presets`` is the default base of a YAML file."""
    key = str(name_or_path)
    if key in presets:
        config = presets[key]()
    else:
        path = Path(key)
        if not path.is_file():
            raise ConfigError(f"config {key!r} is neither a preset {sorted(presets)} nor an existing file")
        data = read_mapping(path)
        base = data.pop("base", next(iter(presets)))
        if base not in presets:
            raise ConfigError(f"{path}: base {base!r} is not a preset {sorted(presets)}")
        try:
            config = merge_config(presets[base](), data)
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from err
    return merge_config(config, overrides)


def read_mapping(path: str | os.PathLike) -> dict[str, Any]:
    """The top-level mapping of a YAML (``.yaml``/``.yml``) or JSON file; an empty file is ``{}``.

    Every config file in the repository is read through this, so a missing file, a parse error or a
    non-mapping top level always gives the same :class:`ConfigError` naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    text = path.read_text(encoding="utf-8")
    try:
        if path.suffix.lower() == ".json":
            import json

            data = json.loads(text) if text.strip() else {}
        else:
            import yaml

            data = yaml.safe_load(text) or {}
    except Exception as err:  # yaml.YAMLError / json.JSONDecodeError: both are parse errors here
        raise ConfigError(f"{path}: cannot parse ({err})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def save_config(config: Any, path: str | os.PathLike) -> Path:
    """Write the resolved config as YAML atomically (temp file + rename); returns the path."""
    import yaml
    from image2sim.simulator.io.atomic import write_text_atomic

    return write_text_atomic(path, yaml.safe_dump(config_to_dict(config), sort_keys=False))
