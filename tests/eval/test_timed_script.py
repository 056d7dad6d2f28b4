"""scripts/timed.py: the budget records of the sim2real pipeline's training stages."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _timed():
    spec = importlib.util.spec_from_file_location("timed", REPO / "scripts" / "timed.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_records_wall_and_child_cpu_time(tmp_path):
    out = tmp_path / "b" / "t.json"
    burn = "s = 0\nfor i in range(3_000_000):\n    s += i"
    assert _timed().main(["--out", str(out), "--", sys.executable, "-c", burn]) == 0
    rec = json.loads(out.read_text())
    assert rec["wall_s"] > 0 and rec["cpu_s"] > 0.05
    assert rec["command"].startswith(sys.executable)


def test_a_failing_command_passes_its_status_on_and_writes_nothing(tmp_path):
    out = tmp_path / "t.json"
    assert _timed().main(["--out", str(out), "--", sys.executable, "-c", "raise SystemExit(3)"]) == 3
    assert not out.exists()
