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


def _lightning_csv(run: Path, rows: str, version: int = 0) -> None:
    """A ``logs/version_N/metrics.csv`` as Lightning's CSV logger writes it (blank unlogged cells)."""
    log = run / "logs" / f"version_{version}"
    log.mkdir(parents=True)
    (log / "metrics.csv").write_text("epoch,step,train/action_acc,train/loss\n" + rows, encoding="utf-8")


def test_loss_curve_joins_runs_in_order_with_plain_column_names(tmp_path):
    from image2sim.simulator.tracking import write_loss_curve

    _lightning_csv(tmp_path / "bc", "0,0,0.5,2.0\n0,1,,1.5\n0,2,0.7,\n")
    _lightning_csv(tmp_path / "round_00", "0,0,0.8,1.2\n0,1,0.9,1.0\n")
    _lightning_csv(tmp_path / "round_00", "0,0,0.8,0.9\n", version=1)  # a later version wins
    out = write_loss_curve([tmp_path / "bc", tmp_path / "round_00"], tmp_path / "plots" / "loss.csv")
    lines = out.read_text().splitlines()
    assert lines[0] == "step,run,train_loss"  # "/" is not a plain field name for DVC's templates
    assert lines[1:] == ["0,0,2.0", "1,0,1.5", "2,1,0.9"]  # the round continues after BC's last step


def test_loss_curve_errors_name_the_run(tmp_path):
    from image2sim.simulator.tracking import write_loss_curve

    with pytest.raises(FileNotFoundError, match="nothing: no logs"):
        write_loss_curve([tmp_path / "nothing"], tmp_path / "x.csv")
    (tmp_path / "r" / "logs" / "version_0").mkdir(parents=True)
    (tmp_path / "r" / "logs" / "version_0" / "metrics.csv").write_text("step,acc\n0,1\n")
    with pytest.raises(ValueError, match="no column ending in 'loss'"):
        write_loss_curve([tmp_path / "r"], tmp_path / "x.csv")


def test_loss_curve_script_exits_2_on_a_missing_log(tmp_path, capsys):
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "loss_curve", Path(__file__).parents[2] / "scripts/loss_curve.py"
    )
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.main(["--out", str(tmp_path / "c.csv"), str(tmp_path / "none")]) == 2
    assert "none: no logs" in capsys.readouterr().err


def test_wandb_mode_from_params_never_goes_online_against_the_environment():
    from image2sim.simulator.tracking import wandb_mode

    assert wandb_mode("disabled", env="") is None
    assert wandb_mode("offline", env="") == "offline"
    assert wandb_mode("online", env="") == "online"
    assert wandb_mode("online", env="offline") == "offline"  # `make` exports WANDB_MODE=offline
    assert wandb_mode("offline", env="online") == "offline"  # the environment cannot add the network
    assert wandb_mode("online", env="disabled") is None
    with pytest.raises(ValueError, match="tracking.wandb: expected one of disabled, offline, online"):
        wandb_mode("yes", env="")


def test_wandb_logger_from_params_has_project_group_tags_and_stage_config(tmp_path, monkeypatch):
    """``tracking.wandb: offline`` through a trainer's --wandb: the logger's project, group and tags."""
    import lightning.pytorch.loggers as loggers
    from image2sim.simulator.tracking import wandb_logger, wandb_mode

    made = {}

    class FakeWandbLogger:  # records what the real one would pass to wandb.init; no run, no network
        def __init__(self, **kwargs):
            made.update(kwargs)

    monkeypatch.setattr(loggers, "WandbLogger", FakeWandbLogger)
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("DVC_STAGE", "train_nav")
    monkeypatch.setenv("DVC_EXP_NAME", "exp-1234")
    (tmp_path / "params.yaml").write_text("profile: ci\ntrain_nav:\n  dagger_scenes: 2\n", encoding="utf-8")
    monkeypatch.chdir(tmp_path)
    wandb_logger(tmp_path / "out", "image2sim", {"lr": 0.1}, mode=wandb_mode("offline"))
    assert made["project"] == "image2sim" and made["offline"] is True and made["log_model"] is False
    assert made["group"] == "exp-1234" and made["tags"] == ["train_nav"] and made["job_type"] == "train_nav"
    assert made["config"]["resolved_config"]["params"] == {"dagger_scenes": 2}  # the stage's params
    monkeypatch.delenv("DVC_EXP_NAME")
    wandb_logger(tmp_path / "out", "image2sim", {}, stage="train_sim", mode="offline")
    assert made["group"].startswith("commit-") or made["group"] == "local"
    assert made["tags"] == ["train_sim"]


def test_nav_train_wandb_option_sets_the_config(tmp_path):
    from image2sim.navpolicy.train_cli import _tracking_overrides

    assert _tracking_overrides("", "") == {}
    assert _tracking_overrides("disabled", "p") == {
        "wandb": False,
        "wandb_mode": "offline",
        "wandb_project": "p",
    }
    assert _tracking_overrides("offline", "") == {"wandb": True, "wandb_mode": "offline"}


@pytest.mark.slow
def test_tracking_does_not_import_wandb():
    import subprocess
    import sys

    modules = "image2sim.simulator.tracking, image2sim.simulator.renderer.module, image2sim.navpolicy.train"
    code = f"import sys, {modules}; print('wandb' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
