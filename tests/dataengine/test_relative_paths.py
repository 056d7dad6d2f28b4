"""Paths stored in outputs are relative to the file holding them, so output folders can move (issue 22)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from image2sim.dataengine.distributed import read_shard_list
from image2sim.dataengine.scene_assets import resolve_scene
from image2sim.simulator.io.paths import relative_to_file, resolve_from_file


def test_relative_to_file_round_trips_inside_and_outside_the_folder(tmp_path, monkeypatch):
    holder = tmp_path / "out" / "shards.json"
    assert relative_to_file(tmp_path / "out" / "scenes" / "a", holder) == "scenes/a"
    assert relative_to_file(tmp_path / "data" / "cap", holder) == "../data/cap"
    monkeypatch.chdir(tmp_path)  # relative inputs are taken from the working directory
    assert relative_to_file("data/cap", "out/scene/manifest.json") == "../../data/cap"
    assert resolve_from_file("../data/cap", holder) == tmp_path / "out" / "../data/cap"
    assert resolve_from_file("/abs/cap", holder) == Path("/abs/cap")  # older files: absolute, as is


def _engine_output(root: Path, absolute: bool = False) -> Path:
    """An output folder with two shards and its shards.json (absolute entries: the old layout)."""
    out = root / "engine"
    for name in ("scene_000", "scene_001"):
        (out / "scenes" / name / "shard").mkdir(parents=True)
        (out / "scenes" / name / "shard" / "manifest.json").write_text("{}")
    listed = [
        str((out / "scenes" / n / "shard").resolve()) if absolute else f"scenes/{n}/shard"
        for n in ("scene_000", "scene_001")
    ]
    (out / "shards.json").write_text(json.dumps({"shards": listed}))
    return out


def test_shard_list_resolves_after_the_folder_moves(tmp_path):
    out = _engine_output(tmp_path / "a")
    moved = tmp_path / "b" / "engine"
    shutil.move(str(out), str(moved))
    shards = read_shard_list(moved)
    assert shards == [moved / "scenes" / "scene_000" / "shard", moved / "scenes" / "scene_001" / "shard"]
    assert all((s / "manifest.json").is_file() for s in shards)


def test_shard_list_accepts_old_absolute_entries_and_names_bad_files(tmp_path):
    out = _engine_output(tmp_path, absolute=True)
    assert read_shard_list(out / "shards.json")[0] == (out / "scenes" / "scene_000" / "shard").resolve()
    with pytest.raises(FileNotFoundError, match="nowhere: no such shard list"):
        read_shard_list(tmp_path / "nowhere")
    (tmp_path / "bad.json").write_text('{"shards": 3}')
    with pytest.raises(ValueError, match="bad.json: expected"):
        read_shard_list(tmp_path / "bad.json")


def _scene(root: Path, capture_field: str) -> Path:
    """A built scene folder whose manifest's ``source.capture`` is ``capture_field``."""
    scene = root / "scenes" / "s0"
    scene.mkdir(parents=True)
    (scene / "gaussians.safetensors").write_bytes(b"")
    (scene / "manifest.json").write_text(json.dumps({"source": {"capture": capture_field}}))
    return scene


def test_scene_manifest_source_capture_relative_or_absolute(tmp_path):
    capture = tmp_path / "data" / "cap"
    capture.mkdir(parents=True)
    (capture / "manifest.json").write_text(json.dumps({"scene_id": "cap", "metadata": {}}))
    rel = resolve_scene(
        _scene(tmp_path / "rel", relative_to_file(capture, tmp_path / "rel/scenes/s0/m.json"))
    )
    assert rel.capture_dir.resolve() == capture.resolve()
    absolute = resolve_scene(_scene(tmp_path / "abs", str(capture)))
    assert absolute.capture_dir == capture
    with pytest.raises(FileNotFoundError, match="source.capture"):
        resolve_scene(_scene(tmp_path / "gone", "../../missing"))
