"""The sim2real report's training seeds (``training_seeds``, ``eval sim2real --seed-run``): a row
retrained with other seeds on the same episodes, summarised against hand-computed numbers, paired
with the best baseline, refused when it is not the same evaluation, and read by the CLI."""

from __future__ import annotations

import json
from statistics import stdev

import pytest
from image2sim.eval.nav_summary import wilson_interval
from image2sim.eval.sim2real import gather, training_seeds
from image2sim.eval.sim2real_report import sim2real_markdown

from tests.navpolicy.test_sim2real_loop import _nav_doc

N = 20
EPISODES = [f"e{i:02d}" for i in range(N)]


def _succ(k: int, offset: int = 0) -> dict[str, bool]:
    """k successes among the N episodes, starting at ``offset`` (wrapping)."""
    hits = {EPISODES[(offset + i) % N] for i in range(k)}
    return {e: e in hits for e in EPISODES}


def _spec(agent: str, k: int, offset: int = 0, successes: bool = True) -> dict:
    return {
        "doc": _nav_doc({agent: (k, N)}),
        "agent": agent,
        "where": f"{agent}-{k}.json",
        "successes": _succ(k, offset) if successes else None,
    }


def _rows() -> dict:
    return {
        "neural": _spec("image2nav", 4),  # seed 0: 20 %
        "random": _spec("random", 2, offset=10),
        "forward": _spec("forward", 3, offset=2),  # the best baseline: 15 %
    }


def test_mean_spread_pooled_interval_and_ratio_match_hand_computed_values():
    runs = {"neural": {"1": _spec("image2nav", 6, offset=1), "2": _spec("image2nav", 2, offset=5)}}
    doc = gather(_rows(), seed_runs=runs)
    e = doc["training_seeds"]["neural"]
    assert list(e["seeds"]) == ["0", "1", "2"]
    assert [e["seeds"][s]["sr"] for s in ("0", "1", "2")] == pytest.approx([20.0, 30.0, 10.0])
    assert e["mean_sr"] == pytest.approx(20.0)
    assert (e["min_sr"], e["max_sr"]) == pytest.approx((10.0, 30.0))
    assert e["sd_sr"] == pytest.approx(stdev([20.0, 30.0, 10.0]))
    lo, hi = wilson_interval(12, 3 * N)  # 4 + 6 + 2 successes over 60 episode runs
    assert e["pooled_sr_ci"] == pytest.approx([100 * lo, 100 * hi])
    assert e["pooled_episodes"] == 3 * N
    assert e["best_baseline"] == "forward"
    assert e["mean_ratio_to_best_baseline"] == pytest.approx(20.0 / 15.0)


def test_each_seed_is_paired_with_the_best_baseline_on_the_same_episodes():
    # seed 1 succeeds exactly where forward does (offset 2, 3 episodes) plus three more
    runs = {"neural": {"1": _spec("image2nav", 6, offset=2)}}
    e = gather(_rows(), seed_runs=runs)["training_seeds"]["neural"]
    c = e["seeds"]["1"]["paired"]
    assert (c["both"], c["policy_only"], c["baseline_only"], c["neither"]) == (3, 3, 0, 14)
    assert c["sr_difference"] == pytest.approx(15.0)
    # seed 0 (the row itself) is paired too: offsets 0..3 against forward's 2..4
    c0 = e["seeds"]["0"]["paired"]
    assert (c0["both"], c0["policy_only"], c0["baseline_only"]) == (2, 2, 1)


def test_without_per_episode_results_there_is_no_paired_comparison():
    runs = {"neural": {"1": _spec("image2nav", 6, successes=False)}}
    e = gather(_rows(), seed_runs=runs)["training_seeds"]["neural"]
    assert "paired" not in e["seeds"]["1"] and "paired" in e["seeds"]["0"]
    assert "n/a" in sim2real_markdown(gather(_rows(), seed_runs=runs))


def test_one_seed_has_no_spread_and_no_seed_runs_no_section():
    assert "training_seeds" not in gather(_rows())
    assert "Training seeds" not in sim2real_markdown(gather(_rows()))
    e = training_seeds({"neural": gather(_rows())["rows"]["neural"]}, {"neural": {}})["neural"]
    assert e["sd_sr"] is None and "best_baseline" not in e and list(e["seeds"]) == ["0"]


@pytest.mark.parametrize(
    "runs,match",
    [
        ({"exact": {"1": _spec("image2nav", 4)}}, "'exact', which is not a row"),
        ({"neural": {"0": _spec("image2nav", 4)}}, "label '0' is the row itself"),
        (
            {"neural": {"1": {"doc": _nav_doc({"image2nav": (4, N + 1)}), "agent": "image2nav"}}},
            "21 episodes, row 'neural' has 20",
        ),
        ({"neural": {"1": {**_spec("random", 4), "agent": "image2nav"}}}, "no agent 'image2nav'"),
    ],
)
def test_refusals_name_the_row_or_the_run(runs, match):
    with pytest.raises(ValueError, match=match):
        gather(_rows(), seed_runs=runs)


def test_the_report_lists_every_seed_and_the_mean():
    runs = {"neural": {"1": _spec("image2nav", 6, offset=2), "2": _spec("image2nav", 2, offset=5)}}
    text = sim2real_markdown(gather(_rows(), seed_runs=runs))
    assert "## Training seeds" in text
    assert "| neural | 1 | 30.0 [" in text and "| +15.0 [" in text
    assert (
        "`neural` over 3 seeds: mean SR 20.0 (min 10.0, max 30.0, sd 10.0), 1.33x the best baseline" in text
    )


def test_cli_reads_seed_runs_and_refuses_a_malformed_spec(tmp_path):
    from image2sim.eval.cli import app
    from image2sim.eval.results import write_metrics_file
    from typer.testing import CliRunner

    for name, agents in (("neural", {"image2nav": (4, N)}), ("s1", {"image2nav": (6, N)}), ("b", None)):
        doc = _nav_doc(agents or {"random": (2, N), "forward": (3, N)})
        (tmp_path / name).mkdir()
        write_metrics_file(tmp_path / name / "nav.json", doc)
    out = [
        "--out",
        str(tmp_path / "m.json"),
        "--report",
        str(tmp_path / "r.md"),
        "--plot",
        str(tmp_path / "p.png"),
    ]
    rows = [
        "--row",
        f"neural=image2nav@{tmp_path / 'neural' / 'nav.json'}",
        "--row",
        f"forward=forward@{tmp_path / 'b' / 'nav.json'}",
    ]
    res = CliRunner().invoke(
        app, ["sim2real", *rows, "--seed-run", f"neural/1=image2nav@{tmp_path / 's1' / 'nav.json'}", *out]
    )
    assert res.exit_code == 0, res.output
    saved = json.loads((tmp_path / "m.json").read_text())
    assert saved["training_seeds"]["neural"]["mean_sr"] == pytest.approx(25.0)
    assert "| neural | 1 | 30.0 [" in (tmp_path / "r.md").read_text()
    res = CliRunner().invoke(app, ["sim2real", *rows, "--seed-run", "neural=image2nav@x.json", *out])
    assert res.exit_code != 0 and "ROW/SEED" in " ".join(res.output.replace("│", " ").split())


def test_the_gap_over_seeds_needs_both_rows_seeded():
    rows = {**_rows(), "exact": _spec("image2nav", 2)}  # exact seed 0: 10 %
    runs = {"neural": {"1": _spec("image2nav", 6, offset=1)}}  # neural seeds: 20, 30 -> 25
    assert "gap_over_seeds" not in gather(rows, seed_runs=runs)
    runs["exact"] = {"1": _spec("image2nav", 4), "2": _spec("image2nav", 6)}  # 10, 20, 30 -> 20
    doc = gather(rows, seed_runs=runs)
    assert doc["gap_over_seeds"] == {"sr": pytest.approx(-5.0), "neural_seeds": 2, "exact_seeds": 3}
    assert doc["gap"]["sr"] == pytest.approx(-10.0)  # the single runs' gap stays beside it
    assert "(`exact` mean of 3 - `neural` mean of 2): SR -5.0 points" in sim2real_markdown(doc)
