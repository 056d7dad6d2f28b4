"""W&B is switched from params in both pipelines (issue 22): every training command passes the
`tracking` section (`--wandb ${tracking.wandb} --wandb-project ${tracking.project}`) and its stage
depends on it; no stage writes into another stage's output (the policy card has its own)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
PIPELINES = {
    REPO / "dvc.yaml": REPO / "params.yaml",
    REPO / "pipelines/sim2real/dvc.yaml": REPO / "pipelines/sim2real/params.yaml",
}
TRAINING = re.compile(r"image2sim (sim|nav) train\b")
FLAGS = "--wandb ${tracking.wandb} --wandb-project ${tracking.project}"


def _stages(dvc_file: Path) -> dict[str, dict]:
    """Stage name -> body (a ``foreach`` stage's ``do`` block)."""
    doc = yaml.safe_load(dvc_file.read_text())
    return {name: stage.get("do", stage) for name, stage in doc["stages"].items()}


def _param_keys(body: dict) -> set[str]:
    """Top-level params keys a stage declares (``- key`` or ``- file: [keys]``)."""
    keys: set[str] = set()
    for entry in body.get("params", []):
        if isinstance(entry, str):
            keys.add(entry.split(".")[0])
        else:
            for names in entry.values():
                keys.update(n.split(".")[0] for n in names)
    return keys


def _training_commands(cmd: str) -> list[str]:
    """Each ``image2sim sim|nav train`` invocation of a command, up to the next ``&&`` or ``||``."""
    return [re.split(r"&&|\|\|", cmd[m.start() :])[0] for m in TRAINING.finditer(cmd)]


@pytest.mark.parametrize("dvc_file", sorted(PIPELINES), ids=lambda p: str(p.relative_to(REPO)))
def test_training_stages_take_wandb_from_the_params(dvc_file):
    params = yaml.safe_load(PIPELINES[dvc_file].read_text())
    assert params["tracking"]["wandb"] in ("disabled", "offline", "online")
    assert params["tracking"]["project"] == "image2sim"  # one project for both pipelines
    trained = 0
    for name, body in _stages(dvc_file).items():
        commands = _training_commands(body["cmd"] if isinstance(body["cmd"], str) else " ".join(body["cmd"]))
        for command in commands:
            assert FLAGS in " ".join(command.split()), f"{name}: {command.strip()[:80]}... lacks {FLAGS}"
        if commands:
            trained += 1
            assert "tracking" in _param_keys(body), f"{name}: runs training but does not depend on `tracking`"
    assert trained >= 2


@pytest.mark.parametrize("dvc_file", sorted(PIPELINES), ids=lambda p: str(p.relative_to(REPO)))
def test_no_stage_writes_inside_another_stages_output(dvc_file):
    outs = {}
    for name, body in _stages(dvc_file).items():
        for out in body.get("outs", []) + body.get("metrics", []) + body.get("plots", []):
            path = out if isinstance(out, str) else next(iter(out))
            outs[path.rstrip("/")] = name
    for path, owner in outs.items():
        for other, other_owner in outs.items():
            if other_owner != owner:
                assert not path.startswith(other + "/"), (
                    f"{owner} writes {path} inside {other_owner}'s {other}"
                )
