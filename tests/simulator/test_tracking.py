"""Training runs logged to W&B carry the run metadata (commit, DVC stage, profile, resolved config)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from image2sim.simulator.tracking import run_metadata, wandb_logger


def test_training_logger_run_holds_commit_stage_profile_and_config_and_no_model(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    tracking = pytest.importorskip("image2sim.eval.tracking")  # the offline-run reader lives there
    for var in ("WANDB_DIR", "WANDB_CACHE_DIR", "WANDB_CONFIG_DIR", "WANDB_DATA_DIR"):
        monkeypatch.setenv(var, str(tmp_path / var.lower()))
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("DVC_STAGE", "train_sim")  # what `dvc repro` sets for a stage's command
    monkeypatch.delenv("IMAGE2SIM_PROFILE", raising=False)
    (tmp_path / "params.yaml").write_text("profile: demo\ntrain_sim:\n  steps: 300\n", encoding="utf-8")
    monkeypatch.chdir(tmp_path)
    logger = wandb_logger(tmp_path / "out", "image2sim-test", {"name": "tiny", "height": 128})
    assert logger._log_model is False  # DVC owns checkpoints: the logger never uploads one
    logger.log_metrics({"loss": 0.5}, step=0)
    run_dir = Path(logger.experiment.dir).parent
    logger.experiment.finish()
    import wandb

    wandb.teardown()
    records = tracking.read_offline_run(run_dir)
    run = next(r for k, r in records if k == "run")
    config = {u.key: json.loads(u.value_json) for u in run.config.update}
    expected = run_metadata(config={"name": "tiny", "height": 128})
    assert config["dvc_stage"] == "train_sim" and config["params_profile"] == "demo"
    assert config["git_commit"] == expected["git_commit"] and config["git_commit"]
    assert config["resolved_config"] == {"command": {"name": "tiny", "height": 128}, "params": {"steps": 300}}
    assert not {"artifact", "use_artifact", "link_artifact"} & {k for k, _ in records}
