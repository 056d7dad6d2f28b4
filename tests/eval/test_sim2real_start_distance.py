"""The sim2real report's SR split by the start's geodesic distance to the goal (``by_start_distance``):
counts against a hand-made table, bin edges, refusals, and the CLI's ``--episodes``."""

from __future__ import annotations

import gzip
import json

import pytest
from image2sim.eval.sim2real import gather, sr_by_start_distance
from image2sim.eval.sim2real_report import sim2real_markdown

# episode -> start distance (m): two per bin of (3, 4, 6, 10), one exactly on each inner edge
DISTANCES = {"a": 3.0, "b": 3.9, "c": 4.0, "d": 5.5, "e": 6.0, "f": 9.0, "g": 10.0, "h": 14.0}


def test_counts_per_bin_match_a_hand_made_table():
    successes = {
        "neural": dict.fromkeys(DISTANCES, False) | {"a": True, "b": True, "d": True, "h": True},
        "forward": dict.fromkeys(DISTANCES, False) | {"a": True},
    }
    out = sr_by_start_distance(successes, DISTANCES)
    assert [(b["low"], b["high"], b["episodes"]) for b in out["bins"]] == [
        (3.0, 4.0, 2),
        (4.0, 6.0, 2),  # 4.0 sits on the edge: it belongs to the bin above
        (6.0, 10.0, 2),
        (10.0, None, 2),  # open above
    ]
    assert [c["sr"] for c in out["rows"]["neural"]] == [100.0, 50.0, 0.0, 50.0]
    assert [c["sr"] for c in out["rows"]["forward"]] == [50.0, 0.0, 0.0, 0.0]
    for cell in out["rows"]["neural"]:
        lo, hi = cell["sr_ci"]
        assert 0.0 <= lo <= cell["sr"] <= hi <= 100.0 and cell["episodes"] == 2


def test_a_bin_no_row_reaches_has_no_rate():
    out = sr_by_start_distance({"neural": {"a": True, "b": False}}, DISTANCES)
    assert [c["sr"] for c in out["rows"]["neural"]] == [50.0, None, None, None]
    assert out["rows"]["neural"][1]["sr_ci"] is None and out["bins"][1]["episodes"] == 0


@pytest.mark.parametrize(
    "distances,edges,match",
    [
        ({"a": 3.5}, (3.0, 4.0), "'b' has no start distance"),
        ({"a": 3.5, "b": float("nan")}, (3.0, 4.0), "'b' has no start distance"),
        ({"a": 3.5, "b": 2.0}, (3.0, 4.0), "'b' starts 2.00 m from its goal, below 3.0 m"),
        ({"a": 3.5, "b": 3.5}, (3.0, 3.0), "must be increasing"),
        ({"a": 3.5, "b": 3.5}, (), "must be increasing"),
    ],
)
def test_refusals_name_the_episode_or_the_edges(distances, edges, match):
    with pytest.raises(ValueError, match=match):
        sr_by_start_distance({"neural": {"a": True, "b": False}}, distances, edges)


def _rows():
    from tests.navpolicy.test_sim2real_loop import _nav_doc

    neural = dict.fromkeys(DISTANCES, False) | {"a": True, "h": True}
    return {
        "neural": {"doc": _nav_doc({"image2nav": (2, 8)}), "agent": "image2nav", "successes": neural},
        "random": {"doc": _nav_doc({"random": (0, 8)}), "agent": "random", "successes": None},
    }


def test_the_report_shows_the_split_only_when_given_distances():
    plain = gather(_rows())
    assert "by_start_distance" not in plain
    assert "start's distance" not in sim2real_markdown(plain)
    doc = gather(_rows(), start_distances=DISTANCES)
    assert list(doc["by_start_distance"]["rows"]) == ["neural"]  # random has no per-episode results
    text = sim2real_markdown(doc)
    assert "| row | 3-4 m | 4-6 m | 6-10 m | >= 10 m |" in text
    assert "| episodes | 2 | 2 | 2 | 2 |" in text
    assert "| neural | 50.0 | 0.0 | 0.0 | 50.0 |" in text


def test_cli_splits_by_the_episode_files_distances(tmp_path):
    from image2sim.eval.cli import app
    from image2sim.eval.metrics.nav import EpisodeResult
    from image2sim.eval.nav_summary import nav_summary
    from image2sim.eval.protocols import get_protocol
    from image2sim.eval.results import write_metrics_file
    from typer.testing import CliRunner

    protocol = get_protocol("image2sim")
    results = dict.fromkeys(DISTANCES, False) | {"c": True}
    logs = tmp_path / "neural" / "image2nav"
    logs.mkdir(parents=True)
    lines = [json.dumps({"format": "image2sim-eval-episodes", "version": 1, "protocol": protocol.to_dict()})]
    lines += [json.dumps({"episode_id": e, "metrics": {"success": float(s)}}) for e, s in results.items()]
    (logs / "scene_000.jsonl").write_text("\n".join(lines) + "\n")
    rs = [EpisodeResult(e, {"success": float(s)}, protocol) for e, s in results.items()]
    doc = {"protocol": protocol.to_dict(), "agents": {"image2nav": nav_summary(rs)}}
    write_metrics_file(tmp_path / "neural" / "nav.json", doc)

    def episode(eid: str, d: float) -> dict:
        return {
            "episode_id": eid,
            "trajectory_id": eid,
            "scene_id": "scene_000",
            "start_position": [0.0, 0.0, 0.0],
            "start_rotation": [0.0, 0.0, 0.0, 1.0],
            "goals": [{"position": [d, 0.0, 0.0], "radius": 3.0}],
            "reference_path": [[0.0, 0.0, 0.0], [d, 0.0, 0.0]],
            "instruction": {"instruction_text": "go to the sofa"},
            "info": {"geodesic_distance": d},
        }

    episodes = tmp_path / "heldout.json.gz"
    with gzip.open(episodes, "wt") as f:
        json.dump({"episodes": [episode(e, d) for e, d in DISTANCES.items()]}, f)
    base = ["sim2real", "--row", f"neural=image2nav@{tmp_path / 'neural' / 'nav.json'}"]
    base += [
        "--out",
        str(tmp_path / "m.json"),
        "--report",
        str(tmp_path / "r.md"),
        "--plot",
        str(tmp_path / "p.png"),
    ]
    # a scaling point too: its HOUSES:EPISODES spec once overwrote the --episodes file in the command
    scaling = ["--scaling", f"1:40=image2nav@{tmp_path / 'neural' / 'nav.json'}"]
    res = CliRunner().invoke(app, [*base, *scaling, "--episodes", str(episodes)])
    assert res.exit_code == 0, res.output
    assert "| neural | 0.0 | 50.0 | 0.0 | 0.0 |" in (tmp_path / "r.md").read_text()
    saved = json.loads((tmp_path / "m.json").read_text())
    assert saved["by_start_distance"]["rows"]["neural"][1]["sr"] == 50.0

    (tmp_path / "bad.json.gz").write_bytes(b"not gzip")
    res = CliRunner().invoke(app, [*base, "--episodes", str(tmp_path / "bad.json.gz")])
    assert res.exit_code != 0 and "bad.json.gz" in " ".join(res.output.replace("│", " ").split())
