"""The CLI's one error boundary: one line per error, the exit status by class, tracebacks on --debug."""

from __future__ import annotations

import subprocess
import sys

import pytest
import typer
from image2sim.simulator import cli


class _Declared(RuntimeError):
    cli_exit_code = 2


def _app(exc: BaseException) -> typer.Typer:
    app = typer.Typer()

    @app.command()
    def boom() -> None:
        raise exc

    @app.command()
    def fine() -> None:
        typer.echo("ok")

    return app


@pytest.mark.parametrize(
    "exc,code,kind",
    [
        (ValueError("bad.json: field 'x' must be positive"), 2, "bad input"),
        (FileNotFoundError("missing.npz"), 2, "bad input"),
        (_Declared("scene 'a' not found"), 2, "bad input"),
        (RuntimeError("the solver diverged"), 1, "failed"),
        (KeyboardInterrupt(), 130, None),
    ],
)
def test_errors_become_one_line_and_a_status(monkeypatch, capsys, exc, code, kind):
    monkeypatch.setattr(cli, "build_app", lambda: _app(exc))
    monkeypatch.delenv("IMAGE2SIM_DEBUG", raising=False)
    with pytest.raises(SystemExit) as info:
        cli.main(["boom"])
    assert info.value.code == code
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" not in err
    if kind:
        assert err.startswith(f"error ({kind}, {type(exc).__name__}): {exc}")
        assert len(err.strip().splitlines()) == 2  # the line and the --debug hint


def test_debug_lets_the_traceback_through(monkeypatch):
    monkeypatch.setattr(cli, "build_app", lambda: _app(RuntimeError("boom")))
    with pytest.raises(RuntimeError, match="boom"):
        cli.main(["--debug", "boom"])


def test_a_real_command_with_bad_input_prints_no_traceback(tmp_path):
    """`eval nav` on a scenes folder without the episodes' scene: one line, status 2."""
    import gzip

    eps = tmp_path / "eps.json.gz"
    eps.write_bytes(
        gzip.compress(
            b'{"episodes": [{"episode_id": "e", "scene_id": "scene_009", "start_position": [0, 0, 0], '
            b'"start_rotation": [0, 0, 0, 1], "goals": [{"position": [1, 0, 0], "radius": 3.0}], '
            b'"instruction": {"instruction_text": "go"}, "reference_path": [[0, 0, 0], [1, 0, 0]]}]}'
        )
    )
    (tmp_path / "scenes").mkdir()
    res = subprocess.run(
        [sys.executable, "-c", "from image2sim.simulator.cli import main; main()", "eval", "nav",
         "--backend", "neural", "--scenes", str(tmp_path / "scenes"), "--episodes", str(eps),
         "--agent", "random", "--out", str(tmp_path / "run"), "--metrics", str(tmp_path / "nav.json")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert res.returncode == 2, res.stderr
    assert "Traceback (most recent call last)" not in res.stderr, res.stderr
    assert "scene_009" in res.stderr, res.stderr
