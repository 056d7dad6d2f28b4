"""Every pipeline profile resolves to a complete DAG (issue 20: the `paper` profile had a stage reading
an encoder checkpoint that no stage wrote). DVC interpolates each stage's `${...}` parameters from the
profile and checks that every dependency is a tracked output or a file in the repository."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
PROFILES = sorted((REPO / "configs" / "profiles").glob("*.yaml"))
dvc = shutil.which("dvc") or (
    str(REPO / ".venv" / "bin" / "dvc") if (REPO / ".venv/bin/dvc").exists() else None
)


def _repo_with(profile: Path, tmp: Path) -> Path:
    """A scratch DVC repo holding the pipeline, the profile as params.yaml and the source tree's
    tracked inputs that stages depend on (code folders are symlinked: only their existence matters)."""
    root = tmp / "repo"
    root.mkdir()
    shutil.copy(REPO / "dvc.yaml", root / "dvc.yaml")
    shutil.copy(profile, root / "params.yaml")
    for top in ("packages", "scripts", "configs", "pipelines"):
        (root / top).symlink_to(REPO / top)
    subprocess.run([dvc, "init", "--no-scm", "-q"], cwd=root, check=True)
    return root


@pytest.mark.skipif(dvc is None, reason="dvc is not installed (requirements-pipeline.txt)")
@pytest.mark.parametrize("profile", PROFILES, ids=lambda p: p.stem)
def test_profile_resolves_to_a_complete_dag(profile, tmp_path):
    root = _repo_with(profile, tmp_path)
    out = subprocess.run([dvc, "dag", "--md"], cwd=root, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    for name in stages:
        assert name in out.stdout, f"{profile.name}: stage {name} missing from the DAG"
    # Every dependency is produced by a stage or exists in the repository.
    outs = {o if isinstance(o, str) else next(iter(o)) for s in stages.values() for o in s.get("outs", [])}
    params = yaml.safe_load(profile.read_text())
    for name, stage in stages.items():
        for dep in stage.get("deps", []):
            dep = dep if isinstance(dep, str) else next(iter(dep))
            if "${" in dep:  # a parameterised dependency, e.g. ${train_nav.config}
                section, key = dep.strip("${}").split(".")
                dep = params[section][key]
            assert dep in outs or (REPO / dep).exists(), (
                f"{profile.name}: {name} depends on {dep}, which nothing makes"
            )
    # The stage-1 encoder that scenes and the renderer read (when not identity) is the stage's output.
    for section in ("build_scenes", "train_sim"):
        encoder = params[section]["encoder"]
        assert encoder == "identity" or encoder in outs, (
            f"{profile.name}: {section}.encoder {encoder} is no stage's output"
        )
