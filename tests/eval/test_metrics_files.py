"""Metrics files hold measured numbers only (issue 22): protocol and configuration go beside them.

Every file a ``dvc.yaml`` lists under ``metrics:`` is written by ``write_metrics_file``; these tests
check its writers (nav, sim2real; the render writer in ``test_render_bench``), the split/join round
trip, reading older files that still carry their protocol, and the pipelines' declarations.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from image2sim.eval.protocols import IMAGE2SIM
from image2sim.eval.results import (
    CONTEXT_KEYS,
    join_metrics,
    protocol_path,
    read_metrics_file,
    read_result_file,
    result_document,
    split_metrics,
)

ROOT = Path(__file__).resolve().parents[2]
PIPELINES = [ROOT / "dvc.yaml", ROOT / "pipelines" / "sim2real" / "dvc.yaml"]


def non_numbers(value, where: str = "") -> list[str]:
    """Dotted paths of the leaves of ``value`` that are neither numbers nor null."""
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in non_numbers(v, f"{where}.{k}" if where else k)]
    if isinstance(value, list):
        return [p for i, v in enumerate(value) for p in non_numbers(v, f"{where}[{i}]")]
    return [] if value is None or isinstance(value, (int, float)) else [where]


def assert_metrics_only(path: Path) -> None:
    """``path`` holds numbers only and no context key; its sidecar holds the protocol."""
    doc = json.loads(path.read_text())
    assert non_numbers(doc) == [], f"{path}: non-numeric leaves"
    assert not set(CONTEXT_KEYS) & set(doc), f"{path}: context keys among the metrics"
    assert protocol_path(path).is_file()


def _agent(sr: float) -> dict:
    return {
        "sr": sr,
        "spl": sr / 2,
        "ne": 1.5,
        "ndtw": None,
        "steps": 10.0,
        "n_episodes": 20,
        "sr_ci": [max(sr - 0.1, 0.0), min(sr + 0.1, 1.0)],
        "spl_ci": [0.0, 0.5],
        "ci_method": {"sr_ci": "wilson 95%", "spl_ci": "bootstrap"},
    }


def test_split_keeps_numbers_and_join_restores_the_document():
    doc = {
        "format": "x",
        "version": 1,
        "protocol": {"name": "p", "max_steps": 300},
        "agents": {"a": _agent(0.5)},
        "checks": {"heldout": {"best_baseline": "forward", "sr_ratio": 1.5, "met": False}},
        "scaling": [{"sr": 1.0, "houses": 2}],
        "notes": ["a", 1],
        "budget": {},
    }
    metrics, context = split_metrics(doc)
    assert non_numbers(metrics) == []
    assert set(context) == {"format", "version", "protocol", "agents", "checks", "notes"}
    assert context["agents"] == {"a": {"ci_method": doc["agents"]["a"]["ci_method"]}}
    assert metrics["checks"] == {"heldout": {"sr_ratio": 1.5, "met": False}}
    assert join_metrics(metrics, context) == doc


def test_nav_writer_splits_and_reads_back(tmp_path):
    from image2sim.eval.nav_summary import nav_markdown, update_nav_metrics

    path = update_nav_metrics(tmp_path / "metrics" / "nav.json", IMAGE2SIM, "oracle", _agent(1.0))
    update_nav_metrics(path, IMAGE2SIM, "random", _agent(0.1))
    assert_metrics_only(path)
    side = json.loads(protocol_path(path).read_text())
    assert side["protocol"]["name"] == IMAGE2SIM.name and side["format"] == "image2sim-eval-result"
    protocol, payload = read_result_file(path)
    assert protocol == IMAGE2SIM and set(payload["agents"]) == {"oracle", "random"}
    assert payload["agents"]["oracle"]["ci_method"]["sr_ci"] == "wilson 95%"
    assert "Protocol `image2sim`" in nav_markdown(read_metrics_file(path))


def test_files_written_before_the_split_still_read(tmp_path):
    old = tmp_path / "nav.json"
    old.write_text(json.dumps(result_document(IMAGE2SIM, {"agents": {"oracle": _agent(1.0)}})))
    protocol, payload = read_result_file(old)
    assert protocol == IMAGE2SIM and payload["agents"]["oracle"]["sr"] == 1.0
    with pytest.raises(FileNotFoundError, match="missing.json"):
        read_metrics_file(tmp_path / "missing.json")


def test_sim2real_writer_splits(tmp_path):
    from image2sim.eval.sim2real import gather, load_json
    from image2sim.eval.sim2real_report import write_outputs

    nav = result_document(
        IMAGE2SIM, {"agents": {n: _agent(s) for n, s in [("image2nav", 0.6), ("random", 0.1)]}}
    )
    rows = {name: {"doc": nav, "agent": "image2nav"} for name in ("neural", "splat_only", "exact")}
    rows |= {name: {"doc": nav, "agent": "random"} for name in ("random", "forward")}
    doc = gather(rows, policies={"neural": "outputs/x"}, budget={"renderer": {"wall_s": 3.0, "cpu_s": 5.0}})
    doc["header"] = "# title"
    out = tmp_path / "metrics" / "sim2real.json"
    write_outputs(doc, out, tmp_path / "report.md", None)
    assert_metrics_only(out)
    back = load_json(out)
    assert back["policies"] == {"neural": "outputs/x"} and back["header"] == "# title"
    assert back["checks"]["heldout"]["best_baseline"] == "random"
    assert back["rows"] == doc["rows"]


def _declared(stage: dict, key: str) -> list[str]:
    return [next(iter(i)) if isinstance(i, dict) else i for i in stage.get(key, [])]


def test_pipelines_declare_metrics_beside_their_protocol_outs():
    """Each ``metrics:`` file of both pipelines has its ``.protocol.json`` among the stage's outs,
    and a committed copy holds numbers only."""
    checked = 0
    for dvc_file in PIPELINES:
        for name, stage in yaml.safe_load(dvc_file.read_text())["stages"].items():
            for metric in _declared(stage, "metrics"):
                assert str(protocol_path(metric)) in _declared(stage, "outs"), f"{dvc_file}: {name}"
                if (ROOT / metric).is_file() and protocol_path(ROOT / metric).is_file():
                    assert_metrics_only(ROOT / metric)
                checked += 1
    assert checked >= 3
