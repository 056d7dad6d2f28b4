"""``image2sim data inspect | fuse | ingest`` end to end on fixtures the tests write themselves."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from image2sim.dataengine.cli import app
from image2sim.simulator.io import open_capture, read_ply
from typer.testing import CliRunner

from tests.simulator.test_io_room import (
    surface_distance,
    write_hm3d_fixture,
    write_pinhole_fixture,
    write_realsee_fixture,
)

runner = CliRunner()


def _run(*args: str):
    return runner.invoke(app, [str(a) for a in args], catch_exceptions=False)


@pytest.mark.parametrize(
    "writer, fmt",
    [
        (write_hm3d_fixture, "hm3d_360"),
        (write_realsee_fixture, "realsee"),
        (write_pinhole_fixture, "pinhole_dir"),
    ],
)
def test_ingest_round_trip(tmp_path: Path, writer, fmt: str) -> None:
    src = writer(tmp_path / "src")
    out = tmp_path / "canon"
    result = _run("ingest", src, "--out", out)
    assert result.exit_code == 0, result.output
    assert "ingested 3 frames" in result.output
    source, canon = open_capture(src), open_capture(out)
    assert canon.format == "image2sim" and canon.frame_ids == source.frame_ids
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["metadata"]["source_format"] == fmt and manifest["metadata"]["skipped"] == []
    for a, b in zip(source, canon, strict=False):
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_allclose(a.depth, b.depth, atol=0.5e-3 + 1e-6)
        np.testing.assert_array_equal(a.cam_to_world, b.cam_to_world)
        assert a.camera == b.camera and a.notes == b.notes


def test_ingest_bad_frame_fails_cleanly_then_skip_bad(tmp_path: Path) -> None:
    src = write_hm3d_fixture(tmp_path / "src", n=4)
    data = (src / "00002_depth.png").read_bytes()
    (src / "00002_depth.png").write_bytes(data[: len(data) // 2])
    (src / "00003_pose.txt").write_text("0 0 1 0 0 0 5")
    out = tmp_path / "canon"

    result = _run("ingest", src, "--out", out)
    assert result.exit_code == 2
    assert "00003_pose.txt: quaternion norm is 5" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # nothing written, no temp folder

    result = _run("ingest", src, "--out", out, "--skip-bad")
    assert result.exit_code == 0, result.output
    assert "ingested 2 frames" in result.output
    assert "skipped 00002" in result.output and "truncated" in result.output
    assert "skipped 00003" in result.output
    assert open_capture(out).frame_ids == ["00000", "00001"]
    skipped = json.loads((out / "manifest.json").read_text())["metadata"]["skipped"]
    assert [s["frame_id"] for s in skipped] == ["00003", "00002"] and "truncated" in skipped[1]["reason"]


def test_ingest_refuses_existing_output_and_all_bad(tmp_path: Path) -> None:
    src = write_hm3d_fixture(tmp_path / "src", n=2)
    out = tmp_path / "canon"
    out.mkdir()
    result = _run("ingest", src, "--out", out)
    assert result.exit_code == 2 and "already exists" in result.output
    assert _run("ingest", src, "--out", out, "--overwrite").exit_code == 0
    # The first frame's colour (used to size the camera) is broken: --skip-bad still ingests frame 1.
    (src / "00000_rgb.png").write_bytes(b"junk")
    result = _run("ingest", src, "--out", tmp_path / "c2", "--skip-bad")
    assert result.exit_code == 0 and "ingested 1 frames" in result.output and "skipped 00000" in result.output
    (src / "00001_rgb.png").write_bytes(b"junk")
    result = _run("ingest", src, "--out", tmp_path / "c3", "--skip-bad")
    assert result.exit_code == 2 and "no readable colour image among 2 frames" in result.output
    assert "00001_rgb.png: cannot decode" in result.output and not (tmp_path / "c3").exists()


def test_unknown_format_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "x").mkdir()
    for cmd in (["inspect", tmp_path / "x"], ["fuse", tmp_path / "x", "--out", tmp_path / "c.ply"]):
        result = _run(*cmd)
        assert result.exit_code == 2 and "unknown capture format" in result.output


def test_inspect_reports_truthful_numbers(tmp_path: Path) -> None:
    src = write_hm3d_fixture(tmp_path / "src", n=3)
    result = runner.invoke(app, ["inspect", str(src)], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    cap = open_capture(src)
    depths = np.concatenate([f.depth[f.depth > 0] for f in cap])
    pos = cap.poses[:, :3, 3]
    assert "hm3d_360" in result.output and "3 (3 read" in result.output
    assert f"{depths.min():.3f} - {depths.max():.3f} m" in result.output
    assert "x {:.3f}  y {:.3f}  z {:.3f}".format(*pos.min(axis=0)) in result.output
    assert "x {:.3f}  y {:.3f}  z {:.3f}".format(*pos.max(axis=0)) in result.output
    assert "00002" in result.output and "64x32" in result.output


def test_inspect_lists_skipped_and_exits_2(tmp_path: Path) -> None:
    """The report is printed in full, then the exit status says the capture is bad (it was 0)."""
    src = write_pinhole_fixture(tmp_path / "src", n=3)
    (src / "pose" / "1.txt").write_text("\n".join(["nan nan nan nan"] * 4))
    result = runner.invoke(app, ["inspect", str(src)], env={"COLUMNS": "200"})
    assert result.exit_code == 2, result.output
    assert "1 skipped" in result.output and "non-finite" in result.output
    assert "1 of 3 frames" in result.output and "unreadable" in result.output


def test_fuse_writes_a_cloud_on_the_walls(tmp_path: Path) -> None:
    src = write_hm3d_fixture(tmp_path / "src", n=4)
    out = tmp_path / "cloud.ply"
    result = _run("fuse", src, "--out", out, "--voxel", "0.1")
    assert result.exit_code == 0, result.output
    cloud = read_ply(out)
    assert "fused 4 frames" in result.output and f"-> {len(cloud['points'])} voxels" in result.output
    assert np.quantile(surface_distance(cloud["points"]), 0.9) < 0.01
    assert cloud["colors"].shape == cloud["points"].shape
    result = _run("fuse", src, "--out", out, "--stride", "2", "--max-frames", "1")
    assert "fused 1 frames" in result.output and f"{32 * 64} points" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cloud.ply", "src"]


def test_fused_ply_opens_in_an_independent_reader(tmp_path: Path) -> None:
    """trimesh (a dataengine dependency) parses the PLY with its own code: points and colours agree."""
    trimesh = pytest.importorskip("trimesh")
    src = write_hm3d_fixture(tmp_path / "src", n=2)
    out = tmp_path / "cloud.ply"
    assert _run("fuse", src, "--out", out, "--voxel", "0.2").exit_code == 0
    ours = read_ply(out)
    cloud = trimesh.load(out)
    np.testing.assert_allclose(np.asarray(cloud.vertices), ours["points"], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(cloud.colors)[:, :3], ours["colors"])


def test_half_pixel_flag_reaches_the_realsee_reader(tmp_path: Path) -> None:
    """`--half-pixel resample` reads data written at integer pixel indices; the default reads pixel
    centres; the flag on another format is an error naming the option, not a traceback."""
    src = write_realsee_fixture(tmp_path / "src", convention="index")
    out = tmp_path / "canon"
    result = _run("ingest", src, "--out", out, "--half-pixel", "resample")
    assert result.exit_code == 0, result.output
    notes = json.loads(next((out / "frames").glob("*_pose.json")).read_text())["notes"]
    assert any("resample" in n for n in notes), notes
    default = _run("inspect", write_realsee_fixture(tmp_path / "centred"))
    assert default.exit_code == 0, default.output
    bad = _run("inspect", write_hm3d_fixture(tmp_path / "hm3d"), "--half-pixel", "resample")
    assert bad.exit_code == 2 and "half_pixel" in bad.output
