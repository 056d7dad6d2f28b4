"""W&B logging of headline metrics: flattening (pure) and an offline run on disk."""

from __future__ import annotations

import math

import pytest
from image2sim.eval.tracking import flatten_metrics, log_metrics_wandb

NAV = {
    "protocol": {"name": "image2sim"},
    "agents": {
        "oracle": {"sr": 1.0, "spl": 0.97, "ndtw": None, "sr_ci": [0.72, 1.0], "n_episodes": 10},
        "random": {
            "sr": 0.0,
            "spl": 0.0,
            "ne": math.inf,
            "sr_ci": [0.0, 0.28],
            "ci_method": {"sr_ci": "wilson"},
        },
    },
}


def test_flatten_nav_drops_na_and_non_finite_and_splits_intervals():
    flat = flatten_metrics(NAV, "nav")
    assert flat["nav/oracle/sr"] == 1.0 and flat["nav/oracle/n_episodes"] == 10.0
    assert flat["nav/oracle/sr_ci_low"] == 0.72 and flat["nav/oracle/sr_ci_high"] == 1.0
    assert "nav/oracle/ndtw" not in flat  # n/a is absent, never 0
    assert "nav/random/ne" not in flat  # inf is not a loggable scalar
    assert not any("ci_method" in k for k in flat)


def test_flatten_render_and_errors():
    flat = flatten_metrics(
        {"methods": {"flow_1step": {"psnr": 21.5, "fps": 3.0, "lpips": None, "tiers": {}}}}, "render"
    )
    assert flat == {"render/flow_1step/psnr": 21.5, "render/flow_1step/fps": 3.0}
    with pytest.raises(ValueError, match="kind"):
        flatten_metrics(NAV, "both")
    with pytest.raises(ValueError, match="agents"):
        flatten_metrics({"methods": {}}, "nav")


@pytest.mark.slow
def test_offline_wandb_run_holds_metrics_and_run_metadata(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    for var in ("WANDB_DIR", "WANDB_CACHE_DIR", "WANDB_CONFIG_DIR", "WANDB_DATA_DIR"):
        monkeypatch.setenv(var, str(tmp_path / var.lower()))
    monkeypatch.setenv("WANDB_MODE", "offline")
    run_dir = log_metrics_wandb(NAV, "nav", stage="eval_nav", profile="ci", directory=tmp_path)
    assert run_dir.name.startswith("offline-run-")
    # wandb 0.31 has no reader for the .wandb log: the keys are plain strings inside it.
    blob = b"".join(p.read_bytes() for p in run_dir.glob("*.wandb"))
    for needle in (b"nav/oracle/sr_ci_low", b"eval_nav", b"git_commit", b"params_profile"):
        assert needle in blob
