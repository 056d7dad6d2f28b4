"""Every DVC stage declares all the code it runs (issue 22): editing any module a stage's command may
import must change `dvc status` for that stage. The code is derived from the command by
`scripts/stage_deps.py` (Typer callback -> transitive imports, scripts and shell scripts followed)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DVC_FILES = [REPO / "dvc.yaml", REPO / "pipelines" / "sim2real" / "dvc.yaml"]


def _stage_deps():
    spec = importlib.util.spec_from_file_location("stage_deps", REPO / "scripts" / "stage_deps.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("dvc_file", DVC_FILES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_stage_declares_the_code_it_runs(dvc_file):
    sd = _stage_deps()
    missing = {}
    for name, (cmd, deps) in sd.stage_commands(dvc_file).items():
        code = sd.stage_code(cmd)
        gaps = sd.uncovered(code, deps)
        if gaps:
            missing[name] = gaps[:5]
    assert not missing, f"stages missing code deps (run scripts/stage_deps.py): {missing}"


def test_the_derivation_follows_lazy_imports_scripts_and_the_callback():
    sd = _stage_deps()
    sim = "packages/simulator/src/image2sim"
    code = sd.stage_code("python scripts/timed.py -- image2sim sim navmap x")
    files = {str(p.relative_to(REPO)) for p in code}
    assert "scripts/timed.py" in files
    assert f"{sim}/simulator/navigation/cli.py" in files  # the command's callback module
    assert f"{sim}/simulator/navigation/navmap.py" in files  # imported inside the callback (lazily)
    assert not any(f.startswith("packages/navpolicy/") for f in files)  # nothing it cannot reach
    assert sd.uncovered({REPO / sim / "simulator/io/atomic.py"}, [sim]) == []
    assert sd.uncovered({REPO / "packages/eval/src/image2sim/eval/cli.py"}, [sim])
