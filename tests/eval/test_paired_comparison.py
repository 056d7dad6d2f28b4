"""Paired comparison of two agents on the same episodes (Newcombe's paired interval, exact McNemar) and
its place in the sim2real report."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from image2sim.eval.nav_summary import mcnemar_exact_p, paired_success_comparison


def _pairs(both: int, policy_only: int, baseline_only: int, neither: int) -> tuple[dict, dict]:
    cells = [(True, True)] * both + [(True, False)] * policy_only
    cells += [(False, True)] * baseline_only + [(False, False)] * neither
    ids = [f"ep{i:04d}" for i in range(len(cells))]
    return {e: a for e, (a, _) in zip(ids, cells, strict=True)}, {
        e: b for e, (_, b) in zip(ids, cells, strict=True)
    }


@pytest.mark.parametrize("b,c", [(0, 0), (1, 0), (39, 17), (17, 39), (5, 5), (0, 12), (60, 2)])
def test_mcnemar_matches_scipys_binomial_test(b, c):
    from scipy.stats import binomtest

    want = 1.0 if b + c == 0 else binomtest(b, b + c, 0.5).pvalue
    assert mcnemar_exact_p(b, c) == pytest.approx(want, rel=1e-12, abs=1e-15)


def test_mcnemar_refuses_negative_counts():
    with pytest.raises(ValueError, match=">= 0"):
        mcnemar_exact_p(-1, 3)


def test_counts_difference_and_symmetry():
    a, b = _pairs(9, 39, 17, 194)
    r = paired_success_comparison(a, b)
    assert (r["both"], r["policy_only"], r["baseline_only"], r["neither"]) == (9, 39, 17, 194)
    assert r["episodes"] == 259
    assert r["sr_difference"] == pytest.approx((39 - 17) / 259)
    lo, hi = r["difference_ci"]
    assert lo < r["sr_difference"] < hi and lo > 0  # a clear paired win
    swapped = paired_success_comparison(b, a)
    assert swapped["sr_difference"] == pytest.approx(-r["sr_difference"])
    assert swapped["difference_ci"] == pytest.approx([-hi, -lo])
    assert swapped["mcnemar_p"] == pytest.approx(r["mcnemar_p"])


def test_identical_agents_differ_by_nothing():
    a, _ = _pairs(30, 0, 0, 70)
    r = paired_success_comparison(a, dict(a))
    assert r["sr_difference"] == 0.0 and r["mcnemar_p"] == 1.0
    lo, hi = r["difference_ci"]
    assert lo < 0 < hi and lo == pytest.approx(-hi)


@pytest.mark.parametrize("cells", [(0, 0, 0, 20), (20, 0, 0, 0), (0, 20, 0, 0), (0, 0, 20, 0), (0, 1, 0, 0)])
def test_degenerate_tables_give_finite_bounded_intervals(cells):
    a, b = _pairs(*cells)
    r = paired_success_comparison(a, b)
    lo, hi = r["difference_ci"]
    assert all(math.isfinite(v) for v in (lo, hi, r["mcnemar_p"]))
    assert -1.0 <= lo <= r["sr_difference"] <= hi <= 1.0


def test_interval_agrees_with_a_paired_bootstrap():
    """The slow reference: resample episodes (pairs kept together) and take the percentile interval."""
    a, b = _pairs(9, 39, 17, 194)
    r = paired_success_comparison(a, b)
    x = np.array([a[e] for e in a], float) - np.array([b[e] for e in a], float)
    idx = np.random.default_rng(0).integers(0, len(x), size=(20000, len(x)))
    boot = np.quantile(x[idx].mean(axis=1), [0.025, 0.975])
    assert r["difference_ci"] == pytest.approx(list(boot), abs=0.006)


def test_interval_covers_the_true_difference_about_95_percent_of_the_time():
    """Coverage over simulated evaluations of a known joint distribution (and narrower than the
    marginal intervals' difference would suggest, because the pairs are correlated)."""
    rng = np.random.default_rng(1)
    probs = [0.05, 0.14, 0.06, 0.75]  # both, policy only, baseline only, neither
    truth = probs[1] - probs[2]
    hits = 0
    reps = 600
    for _ in range(reps):
        a, b = _pairs(*rng.multinomial(259, probs))
        lo, hi = paired_success_comparison(a, b)["difference_ci"]
        hits += lo <= truth <= hi
    assert 0.92 <= hits / reps <= 0.98


def test_different_episode_sets_are_refused_with_examples():
    a, b = _pairs(2, 1, 1, 2)
    b.pop("ep0000")
    b["other"] = True
    with pytest.raises(ValueError, match="same episodes.*ep0000.*other"):
        paired_success_comparison(a, b)
    with pytest.raises(ValueError, match="no episodes"):
        paired_success_comparison({}, {})


# ------------------------------------------------------------------------------- in the sim2real report


def _log(folder, agent: str, results: dict[str, bool], protocol: dict) -> None:
    d = folder / agent
    d.mkdir(parents=True)
    lines = [json.dumps({"format": "image2sim-eval-episodes", "version": 1, "protocol": protocol})]
    lines += [json.dumps({"episode_id": e, "metrics": {"success": float(s)}}) for e, s in results.items()]
    (d / "scene_000.jsonl").write_text("\n".join(lines) + "\n")


def test_sim2real_report_adds_the_paired_comparison_from_the_episode_logs(tmp_path):
    from image2sim.eval.protocols import get_protocol
    from image2sim.eval.sim2real import episode_successes, gather
    from image2sim.eval.sim2real_report import write_outputs

    from tests.navpolicy.test_sim2real_loop import _nav_doc

    protocol = get_protocol("image2sim").to_dict()
    policy, base = _pairs(9, 39, 17, 194)
    _log(tmp_path / "neural", "image2nav", policy, protocol)
    _log(tmp_path / "baselines", "forward", base, protocol)
    assert episode_successes(tmp_path / "neural" / "nav.json", "image2nav") == policy
    assert episode_successes(tmp_path / "baselines" / "nav.json", "random") is None  # no logs: no pairs

    rows = {
        "neural": {
            "doc": _nav_doc({"image2nav": (48, 259)}),
            "agent": "image2nav",
            "successes": episode_successes(tmp_path / "neural" / "nav.json", "image2nav"),
        },
        "forward": {
            "doc": _nav_doc({"forward": (26, 259)}),
            "agent": "forward",
            "successes": episode_successes(tmp_path / "baselines" / "nav.json", "forward"),
        },
        "random": {"doc": _nav_doc({"random": (25, 259)}), "agent": "random", "successes": None},
    }
    doc = gather(rows)
    chk = doc["checks"]["heldout"]
    assert chk["met"] is False  # the bar stays the marginal one
    assert list(chk["paired"]) == ["forward"]  # random has no logs
    p = chk["paired"]["forward"]
    assert p["sr_difference"] == pytest.approx(100 * 22 / 259) and p["difference_ci"][0] > 0
    write_outputs(doc, tmp_path / "m.json", tmp_path / "r.md", None)
    text = (tmp_path / "r.md").read_text()
    assert "- paired (`heldout`): on the same 259 episodes `neural` - `forward` SR = +8.5 points" in text
    assert "only `neural` succeeded in 39, only `forward` in 17" in text


def test_episode_logs_with_a_repeated_episode_are_refused(tmp_path):
    from image2sim.eval.protocols import get_protocol
    from image2sim.eval.sim2real import episode_successes

    protocol = get_protocol("image2sim").to_dict()
    _log(tmp_path / "run", "image2nav", {"a": True}, protocol)
    (tmp_path / "run" / "image2nav" / "scene_001.jsonl").write_text(
        (tmp_path / "run" / "image2nav" / "scene_000.jsonl").read_text()
    )
    with pytest.raises(ValueError, match="logged twice"):
        episode_successes(tmp_path / "run" / "nav.json", "image2nav")


def test_another_evaluations_check_says_what_its_rows_scored_and_stands_as_its_own_paragraph(tmp_path):
    from image2sim.eval.sim2real import gather
    from image2sim.eval.sim2real_report import sim2real_markdown

    from tests.navpolicy.test_sim2real_loop import _nav_doc

    policy, base = _pairs(5, 21, 15, 145)
    heldout = {
        "neural": {"doc": _nav_doc({"image2nav": (48, 259)}), "agent": "image2nav"},
        "forward": {"doc": _nav_doc({"forward": (26, 259)}), "agent": "forward"},
    }
    fresh = {
        "rows": {
            "neural": {"doc": _nav_doc({"image2nav": (26, 186)}), "agent": "image2nav", "successes": policy},
            "random": {"doc": _nav_doc({"random": (20, 186)}), "agent": "random", "successes": base},
        }
    }
    text = sim2real_markdown(gather(heldout, extra_checks={"fresh_seed": fresh}))
    assert "Check `fresh_seed` (neural 14.0 [9.7, 19.7], random 10.8 [7.1, 16.0]; 186 episodes)" in text
    assert "exact McNemar p = 0.41." in text
    assert "target not met.\n\nCheck `fresh_seed`" in text  # each check is its own paragraph


def test_cli_reads_logs_beside_the_metrics_or_where_episode_logs_points(tmp_path):
    """`eval sim2real` on the pipeline's layouts: eval@* runs keep their logs beside nav.json, the
    scaling stage's run keeps them under eval/ (report.sh passes --episode-logs for it)."""
    from image2sim.eval.cli import app
    from image2sim.eval.metrics.nav import EpisodeResult
    from image2sim.eval.nav_summary import nav_summary
    from image2sim.eval.protocols import get_protocol
    from image2sim.eval.results import write_metrics_file
    from typer.testing import CliRunner

    protocol = get_protocol("image2sim")

    def run(folder, agent, results, logs=None):
        _log(logs or folder, agent, results, protocol.to_dict())
        rs = [EpisodeResult(e, {"success": float(s)}, protocol) for e, s in results.items()]
        doc = {"protocol": protocol.to_dict(), "agents": {agent: nav_summary(rs)}}
        write_metrics_file(folder / "nav.json", doc)
        return folder / "nav.json"

    bc, blind = _pairs(10, 30, 12, 148)
    nbc = run(tmp_path / "hall", "image2nav", bc, logs=tmp_path / "hall" / "eval")
    nbl = run(tmp_path / "blind", "image2nav", blind)
    args = ["sim2real", "--row", f"neural_bc=image2nav@{nbc}", "--row", f"blind=image2nav@{nbl}"]
    args += ["--out", str(tmp_path / "m.json"), "--report", str(tmp_path / "r.md")]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "Paired" not in (tmp_path / "r.md").read_text()  # neural_bc's logs are not beside it
    res = CliRunner().invoke(
        app, [*args, "--episode-logs", f"neural_bc={tmp_path / 'hall' / 'eval' / 'image2nav'}"]
    )
    assert res.exit_code == 0, res.output
    assert (
        "Paired: on the same 200 episodes `neural_bc` - `blind` SR = +9.0 points"
        in (tmp_path / "r.md").read_text()
    )

    def flat(text: str) -> str:  # the error box wraps long lines
        return " ".join(text.replace("│", " ").split())

    res = CliRunner().invoke(app, [*args, "--episode-logs", f"nope={tmp_path}"])
    assert res.exit_code != 0 and "no row 'nope'" in flat(res.output)
    res = CliRunner().invoke(app, [*args, "--episode-logs", f"neural_bc={tmp_path / 'empty'}"])
    assert res.exit_code != 0 and "no per-episode logs" in flat(res.output)
