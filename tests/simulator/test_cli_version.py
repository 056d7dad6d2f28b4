"""`image2sim --version` names every installed image2sim package and torch, then exits 0."""

from __future__ import annotations

from importlib.metadata import version

from image2sim.simulator.cli import build_app
from typer.testing import CliRunner


def test_version_lists_the_packages_and_exits():
    res = CliRunner().invoke(build_app(), ["--version"])
    assert res.exit_code == 0, res.output
    lines = res.output.strip().splitlines()
    assert lines[0] == f"image2sim-simulator {version('image2sim-simulator')}"
    assert any(line.startswith("image2sim-navpolicy ") for line in lines)
    assert lines[-1] == f"torch {version('torch')}"
    # Sub-commands still work with the root callback in place.
    assert CliRunner().invoke(build_app(), ["sim", "--help"]).exit_code == 0
