"""The shared typed-config mechanism: overlay, unknown keys, types, presets, YAML round trip."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import pytest

from image2sim.simulator.config import (
    ConfigError,
    config_from_dict,
    config_to_dict,
    load_config,
    merge_config,
    save_config,
)


@dataclass(frozen=True)
class Inner:
    size: int = 4
    """An integer."""
    scale: float = 1.0
    """A float."""

    def __post_init__(self) -> None:
        if self.size <= 0:
            raise ValueError(f"size must be positive, got {self.size}")


@dataclass(frozen=True)
class Outer:
    name: str = "tiny"
    """A name."""
    mode: Literal["a", "b"] = "a"
    """A choice."""
    widths: tuple[int, ...] = (8, 16)
    """A tuple."""
    path: str | None = None
    """Optional."""
    inner: Inner = field(default_factory=Inner)
    """Nested."""


PRESETS = {"tiny": Outer, "big": lambda: Outer(name="big", inner=Inner(size=64))}


def test_overlay_nested_and_coercion():
    cfg = merge_config(Outer(), {"inner": {"scale": 2}, "widths": [1, 2, 3], "mode": "b"})
    assert cfg.inner == Inner(size=4, scale=2.0) and isinstance(cfg.inner.scale, float)
    assert cfg.widths == (1, 2, 3) and cfg.mode == "b"


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"nope": 1}, r"unknown config key\(s\) \['nope'\]"),
        ({"inner": {"sise": 1}}, r"inner\.sise"),
        ({"inner": {"size": "4"}}, r"inner\.size: expected int"),
        ({"inner": {"size": True}}, r"inner\.size: expected int, got a boolean"),
        ({"mode": "c"}, r"mode: 'c' is not one of"),
        ({"widths": [1, "x"]}, r"widths\[1\]"),
        ({"name": None}, r"name: may not be null"),
        ({"inner": {"size": -1}}, r"inner: size must be positive"),
    ],
)
def test_errors_name_the_field(data, message):
    with pytest.raises(ConfigError, match=message):
        config_from_dict(Outer, data)


def test_presets_yaml_and_round_trip(tmp_path):
    assert load_config(PRESETS, "big").inner.size == 64
    yaml_file = tmp_path / "over.yaml"
    yaml_file.write_text("base: big\ninner:\n  scale: 0.5\n")
    cfg = load_config(PRESETS, yaml_file, overrides={"path": "x"})
    assert (cfg.name, cfg.inner.size, cfg.inner.scale, cfg.path) == ("big", 64, 0.5, "x")
    saved = save_config(cfg, tmp_path / "run" / "config.yaml")
    assert load_config(PRESETS, saved) == cfg
    assert config_to_dict(cfg)["widths"] == [8, 16]
    with pytest.raises(ConfigError, match="neither a preset"):
        load_config(PRESETS, tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("base: huge\n")
    with pytest.raises(ConfigError, match="base 'huge'"):
        load_config(PRESETS, tmp_path / "bad.yaml")
