"""Navigation metrics: exact DTW vs a memoised reference, nDTW/sDTW/SPL cases, measures, aggregation."""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from image2sim.eval.metrics.nav import (
    AgentState,
    AggregationError,
    EpisodeResult,
    EpisodeSpec,
    IncrementalNDTW,
    Measure,
    MeasureError,
    Measurements,
    aggregate,
    dedupe_consecutive,
    dtw,
    dtw_from_costs,
    dtw_from_costs_antidiagonal,
    evaluate_episode,
    ndtw,
    path_length,
    sdtw,
    spl,
)
from image2sim.eval.protocols import IMAGE2SIM, VLNCE, ProtocolMismatchError
from image2sim.simulator.conventions import Action


def reference_dtw(path: np.ndarray, ref: np.ndarray) -> float:
    """Slow textbook DTW: memoised recursion over (i, j) with pure-Python distances."""
    p = [tuple(map(float, x)) for x in path]
    r = [tuple(map(float, x)) for x in ref]

    @cache
    def d(i: int, j: int) -> float:
        c = math.sqrt(sum((a - b) ** 2 for a, b in zip(p[i], r[j], strict=True)))
        if i == 0 and j == 0:
            return c
        options = []
        if i > 0:
            options.append(d(i - 1, j))
        if j > 0:
            options.append(d(i, j - 1))
        if i > 0 and j > 0:
            options.append(d(i - 1, j - 1))
        return c + min(options)

    return d(len(p) - 1, len(r) - 1)


def _paths(dim: int) -> st.SearchStrategy[np.ndarray]:
    return st.integers(1, 25).flatmap(
        lambda n: arrays(np.float64, (n, dim), elements=st.floats(-20, 20, allow_nan=False, width=32))
    )


@settings(max_examples=150)
@given(st.integers(2, 3).flatmap(lambda d: st.tuples(_paths(d), _paths(d))))
def test_dtw_matches_memoised_reference(pair: tuple[np.ndarray, np.ndarray]) -> None:
    path, ref = pair
    expected = reference_dtw(path, ref)
    assert dtw(path, ref) == pytest.approx(expected, rel=1e-12, abs=1e-9)
    cost = np.linalg.norm(path[:, None] - ref[None], axis=-1)
    assert dtw_from_costs_antidiagonal(cost) == pytest.approx(expected, rel=1e-12, abs=1e-9)
    # Growing the path point by point gives the same DTW at every prefix.
    inc = IncrementalNDTW(ref, threshold=2.0)
    for k in range(len(path)):
        inc.append(path[k])
    assert inc.dtw == pytest.approx(expected, rel=1e-12, abs=1e-9)
    assert inc.value == pytest.approx(ndtw(path, ref, threshold=2.0), rel=1e-12)
    # DTW with symmetric steps is symmetric in its arguments.
    assert dtw(ref, path) == pytest.approx(dtw(path, ref), rel=1e-12, abs=1e-9)


def test_dtw_hand_computed() -> None:
    # path (0,0),(1,0),(2,0) vs ref (0,0),(2,0): best warp matches (0,0)-(0,0), (1,0)-(0,0) or (2,0): 1.
    assert dtw([[0, 0], [1, 0], [2, 0]], [[0, 0], [2, 0]]) == pytest.approx(1.0)
    # A single point against a line: sum of distances to every reference point.
    assert dtw([[0, 0]], [[0, 0], [3, 4], [6, 8]]) == pytest.approx(0 + 5 + 10)
    # Cost matrix where the diagonal is not optimal.
    cost = np.array([[1.0, 1.0, 9.0], [9.0, 9.0, 1.0], [9.0, 9.0, 1.0]])
    assert dtw_from_costs(cost) == pytest.approx(4.0)  # (0,0)(0,1)(1,2)(2,2), not the diagonal's 11
    assert dtw_from_costs(np.array([[0.0, 5.0], [5.0, 0.0]])) == 0.0


def test_dtw_rejects_degenerate_inputs() -> None:
    with pytest.raises(ValueError, match="path: is empty"):
        dtw(np.zeros((0, 3)), [[0, 0, 0]])
    with pytest.raises(ValueError, match="reference: contains NaN"):
        dtw([[0, 0, 0]], [[0, np.nan, 0]])
    with pytest.raises(ValueError, match="dimensions differ"):
        dtw([[0, 0, 0]], [[0, 0]])
    with pytest.raises(ValueError, match="non-negative"):
        dtw_from_costs([[1.0, -1.0]])
    with pytest.raises(ValueError, match="non-empty 2-D"):
        dtw_from_costs(np.zeros((0, 2)))
    with pytest.raises(ValueError, match="no point appended"):
        IncrementalNDTW([[0, 0, 0]]).value  # noqa: B018


@given(_paths(3))
def test_ndtw_identical_paths_is_one(path: np.ndarray) -> None:
    assert ndtw(path, path) == 1.0
    assert sdtw(path, path, True) == 1.0
    assert sdtw(path, path, False) == 0.0


def test_ndtw_hand_computed() -> None:
    path = [[0, 0, 0], [1, 0, 0], [2, 0, 0]]
    ref = [[0, 0, 0], [2, 0, 0]]
    assert ndtw(path, ref, threshold=3.0) == pytest.approx(math.exp(-1.0 / (2 * 3.0)))
    assert ndtw(path, ref, threshold=0.5) == pytest.approx(math.exp(-1.0 / (2 * 0.5)))
    assert sdtw(path, ref, 1, threshold=3.0) == pytest.approx(math.exp(-1.0 / 6.0))
    with pytest.raises(ValueError, match="threshold"):
        ndtw(path, ref, threshold=0.0)
    with pytest.raises(ValueError, match="success"):
        sdtw(path, ref, 0.5)


def test_spl_edge_cases() -> None:
    assert spl(True, 10.0, 10.0) == 1.0
    assert spl(True, 10.0, 20.0) == 0.5
    assert spl(False, 10.0, 10.0) == 0.0
    # Path shorter than d0 (success radius lets the agent stop early): capped at 1.
    assert spl(True, 10.0, 8.0) == 1.0
    # d0 = 0: any movement gives 0; no movement is the optimal (empty) path.
    assert spl(True, 0.0, 2.0) == 0.0
    assert spl(True, 0.0, 0.0) == 1.0
    assert spl(False, 0.0, 0.0) == 0.0
    # Path length 0 with d0 > 0 (only possible if success radius covers the start).
    assert spl(True, 2.0, 0.0) == 1.0
    with pytest.raises(ValueError, match="shortest_distance"):
        spl(True, math.inf, 1.0)
    with pytest.raises(ValueError, match="path_length"):
        spl(True, 1.0, -1.0)


def test_path_length_and_dedupe() -> None:
    pts = [[0, 0, 0], [3, 4, 0], [3, 4, 0], [3, 4, 2]]
    assert path_length(pts) == pytest.approx(7.0)
    assert path_length([[1, 2, 3]]) == 0.0
    np.testing.assert_array_equal(dedupe_consecutive(pts), [[0, 0, 0], [3, 4, 0], [3, 4, 2]])


# ---------------------------------------------------------------------------------------------- measures

def _straight_episode(distances: list[float], actions: list[int], step: float = 1.0):
    """Agent moves +x by ``step`` on FORWARD, stays otherwise; distances given per state."""
    pos = np.zeros(3)
    states = [AgentState(pos.copy(), distances[0])]
    for a, d in zip(actions, distances[1:], strict=True):
        if a == Action.MOVE_FORWARD:
            pos = pos + np.array([step, 0.0, 0.0])
        states.append(AgentState(pos.copy(), d))
    return states


def test_episode_measures_success_and_spl() -> None:
    F, L, S = Action.MOVE_FORWARD, Action.TURN_LEFT, Action.STOP
    actions = [F, L, F, F, S]
    dists = [5.0, 4.0, 4.0, 3.0, 2.0, 2.0]
    states = _straight_episode(dists, actions)
    ref = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], dtype=float)
    res = evaluate_episode(EpisodeSpec("ep1", ref), states, actions, VLNCE)
    m = res.metrics
    assert m["distance_to_goal"] == 2.0
    assert m["steps"] == 5.0
    assert m["path_length"] == pytest.approx(3.0)
    assert m["success"] == 1.0 and m["oracle_success"] == 1.0
    assert m["spl"] == pytest.approx(5.0 / 5.0)  # d0 = 5 > path length 3 -> capped at 1
    # Turn in place is de-duplicated: positions 0,1,2,3 match the reference exactly.
    assert m["ndtw"] == pytest.approx(1.0)
    assert m["sdtw"] == pytest.approx(1.0)


def test_success_is_strict_and_needs_stop() -> None:
    F, S = Action.MOVE_FORWARD, Action.STOP
    at_radius = evaluate_episode(EpisodeSpec("a"), _straight_episode([4.0, 3.0, 3.0], [F, S]), [F, S], VLNCE)
    assert at_radius.metrics["success"] == 0.0  # 3.0 is not < 3.0
    assert at_radius.metrics["oracle_success"] == 0.0
    no_stop = evaluate_episode(EpisodeSpec("b"), _straight_episode([4.0, 2.0], [F]), [F], VLNCE)
    assert no_stop.metrics["success"] == 0.0 and no_stop.metrics["spl"] == 0.0
    assert no_stop.metrics["oracle_success"] == 1.0
    assert no_stop.metrics["ndtw"] is None and no_stop.metrics["sdtw"] is None


def test_oracle_success_latches() -> None:
    F, S = Action.MOVE_FORWARD, Action.STOP
    acts = [F, F, F, S]
    res = evaluate_episode(EpisodeSpec("c"), _straight_episode([5.0, 2.9, 4.0, 6.0, 6.0], acts), acts, VLNCE)
    assert res.metrics["oracle_success"] == 1.0
    assert res.metrics["success"] == 0.0
    assert res.metrics["distance_to_goal"] == 6.0
    # The start state counts for oracle success.
    res0 = evaluate_episode(EpisodeSpec("d"), _straight_episode([1.0, 4.0], [F]), [F], VLNCE)
    assert res0.metrics["oracle_success"] == 1.0


def test_measurements_guard_misuse() -> None:
    ms = Measurements(VLNCE)
    with pytest.raises(MeasureError, match="before reset"):
        ms.update(Action.STOP, AgentState(np.zeros(3), 1.0))
    ms.reset(EpisodeSpec("e"), AgentState(np.zeros(3), 1.0))
    ms.update(Action.STOP, AgentState(np.zeros(3), 1.0))
    with pytest.raises(MeasureError, match="episode e: action after STOP"):
        ms.update(Action.MOVE_FORWARD, AgentState(np.zeros(3), 1.0))
    ms.reset(EpisodeSpec("f"), AgentState(np.zeros(3), 1.0))
    with pytest.raises(MeasureError, match="episode f: position"):
        ms.update(Action.MOVE_FORWARD, AgentState(np.array([0.0, np.nan, 0.0]), 1.0))
    with pytest.raises(MeasureError, match="unknown action"):
        ms.update(7, AgentState(np.zeros(3), 1.0))
    ms = Measurements(IMAGE2SIM)
    ms.reset(EpisodeSpec("g"), AgentState(np.zeros(3), 10.0))
    for _ in range(IMAGE2SIM.max_steps):
        ms.update(Action.TURN_LEFT, AgentState(np.zeros(3), 10.0))
    assert ms.values()["steps"] == IMAGE2SIM.max_steps
    with pytest.raises(MeasureError, match="episode g: more than max_steps=300"):
        ms.update(Action.TURN_LEFT, AgentState(np.zeros(3), 10.0))


def test_dependency_resolution_errors() -> None:
    class NeedsGhost(Measure):
        uuid = "needs_ghost"
        dependencies = ("ghost",)

        def reset(self, episode, state, deps):  # noqa: ANN001
            pass

        def update(self, action, state, deps):  # noqa: ANN001
            pass

    class A(NeedsGhost):
        uuid = "a"
        dependencies = ("b",)

    class B(NeedsGhost):
        uuid = "b"
        dependencies = ("a",)

    with pytest.raises(MeasureError, match="'needs_ghost' depends on 'ghost'"):
        Measurements(VLNCE, [NeedsGhost])
    with pytest.raises(MeasureError, match="cycle"):
        Measurements(VLNCE, [A, B])
    # Dependencies come first whatever order the classes are given in.
    order = Measurements(VLNCE).uuids
    assert order.index("distance_to_goal") < order.index("success") < order.index("spl")
    assert order.index("ndtw") < order.index("sdtw")


# ---------------------------------------------------------------------------------------------- aggregation

def test_aggregate_counts_and_means() -> None:
    rs = [
        EpisodeResult("1", {"success": 1.0, "ndtw": 0.5}, VLNCE),
        EpisodeResult("2", {"success": 0.0, "ndtw": None}, VLNCE),
        EpisodeResult("3", {"success": 1.0, "ndtw": 0.7}, VLNCE),
    ]
    rep = aggregate(rs)
    assert rep.num_episodes == 3
    assert rep.metrics["success"].mean == pytest.approx(2 / 3) and rep.metrics["success"].count == 3
    assert rep.metrics["ndtw"].mean == pytest.approx(0.6)
    assert rep.metrics["ndtw"].count == 2 and rep.metrics["ndtw"].missing == 1
    # Standard error: sample std / sqrt(n); success values 1, 0, 1 -> std 0.57735, sem 0.33333.
    assert rep.metrics["success"].sem == pytest.approx(math.sqrt(1 / 3) / math.sqrt(3))
    assert aggregate(rs[:1]).metrics["success"].sem is None
    d = rep.to_dict()
    assert d["protocol"]["name"] == "vlnce" and d["metrics"]["ndtw"]["count"] == 2


def test_aggregate_refuses_bad_inputs() -> None:
    good = EpisodeResult("ok", {"x": 1.0}, VLNCE)
    with pytest.raises(AggregationError, match="episode bad: metric 'x' is nan"):
        aggregate([good, EpisodeResult("bad", {"x": math.nan}, VLNCE)])
    with pytest.raises(AggregationError, match="episode inf: metric 'x' is inf"):
        aggregate([good, EpisodeResult("inf", {"x": math.inf}, VLNCE)])
    with_inf = aggregate([good, EpisodeResult("inf", {"x": math.inf}, VLNCE)], allow_inf={"x"})
    assert with_inf.metrics["x"].count == 2 and with_inf.metrics["x"].mean == math.inf
    with pytest.raises(AggregationError, match="appears more than once"):
        aggregate([good, good])
    with pytest.raises(AggregationError, match="episode other: metric keys"):
        aggregate([good, EpisodeResult("other", {"y": 1.0}, VLNCE)])
    with pytest.raises(AggregationError, match="no episode"):
        aggregate([])
    with pytest.raises(ProtocolMismatchError):
        aggregate([good, EpisodeResult("p", {"x": 1.0}, IMAGE2SIM)])


def test_unreachable_goal_is_an_error_in_aggregation() -> None:
    F, S = Action.MOVE_FORWARD, Action.STOP
    res = evaluate_episode(EpisodeSpec("lost"), _straight_episode([math.inf, math.inf, math.inf], [F, S]),
                           [F, S], VLNCE)
    with pytest.raises(AggregationError, match="episode lost: metric 'distance_to_goal' is inf"):
        aggregate([res])


@settings(max_examples=60)
@given(
    st.booleans(),
    st.floats(0, 100, allow_nan=False),
    st.floats(0, 100, allow_nan=False),
)
def test_spl_bounds(success: bool, d0: float, length: float) -> None:
    value = spl(success, d0, length)
    assert 0.0 <= value <= 1.0
    if not success:
        assert value == 0.0
    elif length <= d0:
        assert value == 1.0


@settings(max_examples=60)
@given(st.tuples(_paths(3), _paths(3)), st.floats(0.1, 10.0))
def test_ndtw_bounds_and_threshold_monotone(pair: tuple[np.ndarray, np.ndarray], threshold: float) -> None:
    path, ref = pair
    low, high = ndtw(path, ref, threshold), ndtw(path, ref, threshold * 2)
    assert 0.0 <= low <= high <= 1.0
