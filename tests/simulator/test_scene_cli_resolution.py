"""``sim build-scene`` states (and records) the resolution it encodes at; ``sim render`` renders at
the source capture's camera by default and says so. Tiny synthetic captures (the analytic box room
written in the ``hm3d_360`` format), no data engine."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from image2sim.simulator.cli import sim_app
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.io.images import read_rgb, read_uint16
from typer.testing import CliRunner

from .test_io_room import write_hm3d_fixture

runner = CliRunner()


def _invoke(*args) -> tuple[int, str]:
    res = runner.invoke(sim_app, [str(a) for a in args])
    return res.exit_code, res.output


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, Path, str]:
    """A 64x32 capture and a scene built from it with the default config (tiny: 256x128)."""
    root = tmp_path_factory.mktemp("res")
    capture = write_hm3d_fixture(root / "capture", n=2, height=32, width=64)
    scene = root / "scene"
    code, out = _invoke("build-scene", capture, "--out", scene, "--no-ply")
    assert code == 0, out
    return capture, scene, out


def test_build_scene_states_and_records_the_encoding_resolution(built) -> None:
    _, scene, out = built
    assert "encoded at 256x128 (W x H = encoder.width x encoder.height of --config tiny)" in out
    assert "the capture's frames are 64x32, area-resized" in out
    manifest = json.loads((scene / "manifest.json").read_text())
    assert manifest["encoding"] == {
        "height": 128,
        "width": 256,
        "from": "encoder.height, encoder.width of config 'tiny'",
    }
    assert manifest["camera"] == EquirectCamera(128, 256).to_dict()  # what the frames were encoded at
    assert manifest["source"]["camera"] == EquirectCamera(32, 64).to_dict()  # the capture's own


def test_build_scene_resolution_from_a_config_file(built, tmp_path: Path) -> None:
    capture, _, _ = built
    cfg = tmp_path / "small.yaml"
    cfg.write_text("encoder:\n  height: 16\n  width: 32\n")
    code, out = _invoke("build-scene", capture, "--out", tmp_path / "s", "--config", cfg, "--no-ply")
    assert code == 0, out
    assert f"encoded at 32x16 (W x H = encoder.width x encoder.height of --config {cfg})" in out
    assert json.loads((tmp_path / "s" / "manifest.json").read_text())["encoding"]["width"] == 32


def test_render_defaults_to_the_capture_camera_and_says_so(built, tmp_path: Path) -> None:
    _, scene, _ = built
    code, out = _invoke("render", scene, "--frame", 0, "--out", tmp_path / "a.png", "--backend", "torch")
    assert code == 0, out
    assert "rendering at 64x32 (W x H, the source capture's camera, manifest source.camera)" in out
    assert read_rgb(tmp_path / "a.png").shape == (32, 64, 3)  # not the 256x128 encoding size
    assert read_uint16(tmp_path / "a_depth.png").shape == (32, 64)
    # Overrides: both sizes as given; one alone keeps the camera's aspect.
    code, out = _invoke(
        "render", scene, "--frame", 1, "--out", tmp_path / "b.png", "--height", 16, "--width", 48
    )
    assert code == 0, out
    assert "rendering at 48x16 (W x H, --height/--width)" in out
    assert read_rgb(tmp_path / "b.png").shape == (16, 48, 3)
    code, out = _invoke("render", scene, "--frame", 1, "--out", tmp_path / "c.png", "--height", 16)
    assert code == 0, out
    assert read_rgb(tmp_path / "c.png").shape == (16, 32, 3)
    code, out = _invoke("render", scene, "--frame", 1, "--out", tmp_path / "d.png", "--width", 128)
    assert code == 0, out
    assert read_rgb(tmp_path / "d.png").shape == (64, 128, 3)
    code, out = _invoke("render", scene, "--frame", 1, "--out", tmp_path / "e.png", "--height", -4)
    assert code == 2 and "must be positive" in out


def test_render_default_for_scenes_without_a_recorded_source_camera(built, tmp_path: Path) -> None:
    """Scenes built before ``source.camera`` was recorded: the source capture's camera read from disk,
    else the scene's input camera; the command names which."""
    capture, scene, _ = built
    old = tmp_path / "old_scene"
    shutil.copytree(scene, old)
    manifest = json.loads((old / "manifest.json").read_text())
    del manifest["source"]["camera"], manifest["encoding"]
    manifest["source"]["capture"] = str(capture.resolve())  # such scenes stored absolute paths
    (old / "manifest.json").write_text(json.dumps(manifest))
    code, out = _invoke("render", old, "--frame", 0, "--out", tmp_path / "a.png")
    assert code == 0, out
    assert f"rendering at 64x32 (W x H, the source capture's camera, read from {capture.resolve()})" in out
    assert read_rgb(tmp_path / "a.png").shape == (32, 64, 3)

    manifest["source"]["capture"] = str(tmp_path / "gone")
    (old / "manifest.json").write_text(json.dumps(manifest))
    code, out = _invoke("render", old, "--pose", "0.5 0.5 1.2 1 0 0 0", "--out", tmp_path / "b.png")
    assert code == 0, out
    assert "rendering at 256x128 (W x H, the scene's input camera" in out
    assert read_rgb(tmp_path / "b.png").shape == (128, 256, 3)


def test_build_scene_with_no_surviving_gaussian_is_an_error(built, tmp_path: Path) -> None:
    """Every depth beyond fusion.max_range: nothing to fuse is an error, and nothing is written."""
    capture, _, _ = built
    cfg = tmp_path / "near.yaml"
    cfg.write_text("fusion:\n  max_range: 0.2\n")
    code, out = _invoke("build-scene", capture, "--out", tmp_path / "s", "--config", cfg, "--no-ply")
    assert code == 2, out
    assert "no Gaussian survived fusion" in out and "nothing written" in out
    assert not (tmp_path / "s").exists()
