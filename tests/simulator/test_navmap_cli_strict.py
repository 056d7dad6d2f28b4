"""`sim navmap` reads captures strictly: a bad frame is one clear error, `--skip-bad` lists what it skips."""

from __future__ import annotations

import pytest
from image2sim.simulator.cli import build_app
from typer.testing import CliRunner


@pytest.fixture()
def capture(tmp_path):
    from image2sim.dataengine.procedural import preset, synthesize

    return synthesize(preset("tiny"), tmp_path / "caps", scenes=1, seed=0, progress=False)[0]


def test_a_missing_depth_file_is_an_error_naming_it(capture, tmp_path):
    victim = sorted(capture.glob("**/*depth*.png"))[1]
    victim.unlink()
    out = tmp_path / "nm" / "navmap.npz"
    out.parent.mkdir()
    res = CliRunner().invoke(build_app(), ["sim", "navmap", str(capture), "--out", str(out), "--no-graph"])
    assert res.exit_code == 2, res.output
    assert victim.name in res.output and "--skip-bad" in res.output
    assert "Traceback" not in res.output and not out.exists()
    res = CliRunner().invoke(
        build_app(), ["sim", "navmap", str(capture), "--out", str(out), "--no-graph", "--skip-bad"]
    )
    assert res.exit_code == 0, res.output
    assert "skipped frame" in res.output and victim.name in res.output and out.exists()
