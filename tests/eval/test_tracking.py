"""W&B logging of headline metrics: flattening (pure) and an offline run on disk."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import pytest
from image2sim.eval.tracking import flatten_metrics, log_metrics_wandb, read_offline_run, run_metadata

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


def test_run_metadata_reads_profile_and_stage_section_from_params(tmp_path, monkeypatch):
    monkeypatch.delenv("IMAGE2SIM_PROFILE", raising=False)
    monkeypatch.delenv("DVC_STAGE", raising=False)
    params = tmp_path / "params.yaml"
    params.write_text("profile: demo\neval_nav:\n  seed: 3\n  protocol: vlnce\n", encoding="utf-8")
    meta = run_metadata("eval_nav", config={"agent": ["oracle"]}, params_file=params)
    assert meta["dvc_stage"] == "eval_nav" and meta["params_profile"] == "demo"
    assert meta["resolved_config"] == {
        "command": {"agent": ["oracle"]},
        "params": {"seed": 3, "protocol": "vlnce"},
    }
    assert run_metadata("eval_nav", profile="ci", params_file=params)["params_profile"] == "ci"
    none = run_metadata(None, params_file=tmp_path / "absent.yaml")
    assert none["params_profile"] is None and none["resolved_config"]["params"] is None
    params.write_text("- a list\n", encoding="utf-8")
    with pytest.raises(ValueError, match="params.yaml"):
        run_metadata("eval_nav", params_file=params)


def _head() -> str:
    return subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=Path(__file__).parent
    ).stdout.strip()


CHECKPOINT_SUFFIXES = (".ckpt", ".pt", ".pth", ".safetensors", ".bin", ".npz")


def test_offline_wandb_run_holds_metrics_and_run_metadata(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    for var in ("WANDB_DIR", "WANDB_CACHE_DIR", "WANDB_CONFIG_DIR", "WANDB_DATA_DIR"):
        monkeypatch.setenv(var, str(tmp_path / var.lower()))
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.delenv("IMAGE2SIM_PROFILE", raising=False)
    params = tmp_path / "params.yaml"
    params.write_text("profile: ci\neval_nav:\n  episodes_per_scene: 2\n  seed: 0\n", encoding="utf-8")
    # A checkpoint lying in the working tree must not end up in the run.
    (tmp_path / "model.ckpt").write_bytes(b"weights")
    monkeypatch.chdir(tmp_path)
    command = {"agent": ["oracle", "random"], "seed": 0, "model": "outputs/nav/dagger/export"}
    before = _head()
    run_dir = log_metrics_wandb(
        NAV, "nav", stage="eval_nav", config=command, params_file=params, directory=tmp_path / "wb"
    )
    assert run_dir.name.startswith("offline-run-")
    records = read_offline_run(run_dir)
    kinds = [k for k, _ in records]
    assert kinds[0] == "header" and "run" in kinds and kinds[-1] == "exit"
    run = next(r for k, r in records if k == "run")
    config = {u.key: json.loads(u.value_json) for u in run.config.update}
    # params.yaml lies outside any repository here: the commit is that of this checkout (other
    # sessions may commit meanwhile, so HEAD before or after the run).
    assert config["git_commit"] in {before, _head()} and len(before) >= 7
    assert config["dvc_stage"] == "eval_nav" and config["params_profile"] == "ci"
    assert config["resolved_config"] == {
        "command": command,
        "params": {"episodes_per_scene": 2, "seed": 0},
    }
    assert config["protocol"] == NAV["protocol"] and config["kind"] == "nav"
    summary = {
        u.key: json.loads(u.value_json) for k, r in records if k == "summary" for u in r.update if u.key
    }
    assert summary["nav/oracle/sr_ci_low"] == 0.72 and summary["nav/oracle/sr"] == 1.0
    # DVC owns artifacts: no artifact record, and no checkpoint among the run's files.
    assert not {"artifact", "use_artifact", "link_artifact"} & set(kinds)
    saved = [f.path for k, r in records if k == "files" for f in r.files]
    assert saved and not [p for p in saved if p.endswith(CHECKPOINT_SUFFIXES)]
    on_disk = [p.name for p in run_dir.rglob("*") if p.is_file()]
    assert not [p for p in on_disk if p.endswith(CHECKPOINT_SUFFIXES)]


def test_read_offline_run_rejects_foreign_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="run-"):
        read_offline_run(tmp_path)
    (tmp_path / "run-x.wandb").write_bytes(b"NOPE" + bytes(20))
    with pytest.raises(ValueError, match="not a W&B run log"):
        read_offline_run(tmp_path)
