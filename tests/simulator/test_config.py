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
    read_mapping,
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


@dataclass(frozen=True)
class Fixed:
    mean: tuple[float, float, float] = (0.5, 0.5, 0.5)
    """A fixed-length tuple of mixed int/float input."""
    counts: tuple[int, str] = (1, "a")
    """A fixed-length tuple of different types."""
    inner: Inner = field(default_factory=Inner)
    """Nested."""


def test_fixed_length_tuples_coerce_each_item_with_its_own_type():
    cfg = config_from_dict(Fixed, {"mean": [1, 2.5, 3], "counts": [7, "b"]})
    assert cfg.mean == (1.0, 2.5, 3.0) and all(isinstance(v, float) for v in cfg.mean)
    assert cfg.counts == (7, "b")
    with pytest.raises(ConfigError, match=r"counts\[1\]: expected str"):
        config_from_dict(Fixed, {"counts": [7, 8]})
    with pytest.raises(ConfigError, match=r"mean: expected 3 values, got 2"):
        config_from_dict(Fixed, {"mean": [1.0, 2.0]})


def test_an_already_built_section_is_kept_and_messages_use_plain_words():
    section = Inner(size=9, scale=3.0)
    assert config_from_dict(Fixed, {"inner": section}).inner is section
    plain_words = r"inner\.size: expected int, got str \('9'\); an integer is required"
    with pytest.raises(ConfigError, match=plain_words):
        config_from_dict(Fixed, {"inner": {"size": "9"}})
    unknown = r"unknown config key\(s\) \['inner\.sise'\] \(an unknown key is an error"
    with pytest.raises(ConfigError, match=unknown):
        config_from_dict(Fixed, {"inner": {"sise": 9}})


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        ("a.yaml", "x: [1, 2", "a.yaml: cannot parse"),
        ("a.json", "{x: 1}", "a.json: cannot parse"),
        ("a.yaml", "- 1\n- 2\n", "a.yaml: expected a mapping at the top level, got list"),
        ("a.json", "[1]", "a.json: expected a mapping at the top level, got list"),
    ],
)
def test_read_mapping_names_the_file_and_the_problem(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        read_mapping(path)


def test_read_mapping_reads_yaml_and_json_and_empty_files(tmp_path):
    (tmp_path / "a.yaml").write_text("x: 1\ny: {z: two}\n")
    (tmp_path / "b.json").write_text('{"x": 1}')
    (tmp_path / "c.yml").write_text("")
    assert read_mapping(tmp_path / "a.yaml") == {"x": 1, "y": {"z": "two"}}
    assert read_mapping(tmp_path / "b.json") == {"x": 1}
    assert read_mapping(tmp_path / "c.yml") == {}
    with pytest.raises(ConfigError, match="missing.yaml: config file not found"):
        read_mapping(tmp_path / "missing.yaml")


def test_parse_overrides_nests_dotted_keys_and_parses_yaml_values():
    from image2sim.simulator.config import parse_overrides

    got = parse_overrides(
        ["train.seed=1", "data.shuffle_instructions=true", "train.lr=2e-3", "name=", "a.b.c=[1, 2]"]
    )
    assert got == {
        "train": {"seed": 1, "lr": 2e-3},
        "data": {"shuffle_instructions": True},
        "name": "",
        "a": {"b": {"c": [1, 2]}},
    }
    for bad in ("seed", "=1", "train..seed=1", "train=1", "train.seed=[1"):
        items = ["train.seed=1", bad] if bad == "train=1" else [bad]
        with pytest.raises(ConfigError, match="--set"):
            parse_overrides(items)


def test_field_checks_name_the_dotted_field_and_the_value():
    import math
    from dataclasses import dataclass, field

    from image2sim.simulator.config import require_at_least, require_in_range, require_one_of

    @dataclass
    class Inner:
        p: float = 0.5
        mode: str = "a"

    @dataclass
    class Outer:
        steps: int = 3
        inner: Inner = field(default_factory=Inner)

    cfg = Outer()
    require_at_least(cfg, ("steps", "inner.p"), 0)
    require_in_range(cfg, "inner.p", 0.0, 1.0)
    require_one_of(cfg, "inner.mode", ("a", "b"))
    with pytest.raises(ConfigError, match=r"x: steps must be >= 4, got 3"):
        require_at_least(cfg, "steps", 4, where="x: ")
    cfg.inner.p = math.nan  # nan passes no bound
    with pytest.raises(ConfigError, match=r"inner.p must be >= 0, got nan"):
        require_at_least(cfg, "inner.p", 0)
    for value, kwargs in ((1.0, {"high_open": True}), (0.0, {"low_open": True}), (1.5, {})):
        cfg.inner.p = value
        with pytest.raises(ConfigError, match=r"inner.p must lie in [\[(]0.0, 1.0[\])]"):
            require_in_range(cfg, "inner.p", 0.0, 1.0, **kwargs)
    cfg.inner.mode = "c"
    with pytest.raises(ValueError, match="inner.mode must be one of a, b; got 'c'"):  # ConfigError is one
        require_one_of(cfg, "inner.mode", ("a", "b"))
