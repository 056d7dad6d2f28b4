"""scripts/goal_detector_probe.py: the AUC it reports and the detector it saves for the STOP gate."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "goal_detector_probe.py"


@pytest.fixture(scope="module")
def probe():
    spec = importlib.util.spec_from_file_location("goal_detector_probe", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_auc_equals_the_pair_count_with_ties(probe):
    rng = np.random.default_rng(0)
    scores = rng.integers(0, 5, 60).astype(float)  # many ties
    labels = rng.integers(0, 2, 60)
    pos, neg = scores[labels == 1], scores[labels == 0]
    pairs = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    assert probe.auc(scores, labels) == pytest.approx(pairs / (len(pos) * len(neg)))
    assert probe.auc(np.arange(4.0), np.array([0, 0, 1, 1])) == 1.0
    assert np.isnan(probe.auc(np.arange(3.0), np.ones(3, dtype=int)))  # one class only


def test_saved_detector_reloads_with_its_categories(probe, tmp_path):
    from safetensors.torch import save_model

    torch.manual_seed(0)
    model = probe.GoalDetector(["bed", "sofa", "tv"], width=4).eval()
    save_model(
        model,
        str(tmp_path / "detector.safetensors"),
        metadata={"categories": json.dumps(model.categories), "width": "4"},
    )
    again = probe.load_detector(tmp_path)
    x = torch.rand(2, 3, 64, 64)
    assert again.categories == ["bed", "sofa", "tv"]
    assert torch.equal(again(x), model(x))
    assert again(x).shape == (2, 3)


def test_load_detector_names_the_missing_file(probe, tmp_path):
    with pytest.raises(FileNotFoundError, match="detector.safetensors"):
        probe.load_detector(tmp_path)
