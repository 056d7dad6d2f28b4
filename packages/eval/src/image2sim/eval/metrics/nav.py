"""Navigation metrics (pure numpy): exact DTW, nDTW, sDTW, SPL, episode-level measures, aggregation.

Definitions follow VLN-CE / Habitat (SPL: Anderson et al. 2018; nDTW: Magalhães et al. 2019,
arXiv:1907.05446):

* ``ndtw = exp(-DTW(path, reference) / (len(reference) * threshold))`` with **exact** DTW over
  Euclidean point distances (VLN-CE uses the approximate ``fastdtw``; we do not).
* ``sdtw = success * ndtw``.
* ``spl = success * d0 / max(d0, path_length)``.
* NE = geodesic distance to the goal at the end; oracle success = that distance was below the
  success radius at any visited state (the start included); SR = STOP called and the final
  distance strictly below the success radius; path length = sum of Euclidean step displacements;
  steps = number of actions taken (STOP included).

Episode measures are small :class:`Measure` units with explicit dependencies, run in dependency
order by :class:`Measurements` (the Habitat-lab pattern). :func:`aggregate` averages per-episode
results of one protocol and reports how many episodes entered every mean.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from image2sim.eval.protocols import Protocol, ensure_same_protocol
from image2sim.simulator.conventions import Action

# --------------------------------------------------------------------------------------------------
# Pure functions
# --------------------------------------------------------------------------------------------------


def _as_points(points: Any, name: str) -> np.ndarray:
    """Validate a path as a finite (N, D) float64 array with N >= 1 (a 1-D input is one point per entry)."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ValueError(f"{name}: expected an (N, D) array of points, got shape {arr.shape}")
    if arr.shape[0] == 0:
        raise ValueError(f"{name}: is empty; DTW needs at least one point")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or inf coordinates")
    return arr


def pairwise_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distance matrix ``(len(a), len(b))`` between point sets of equal dimension."""
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"point dimensions differ: {a.shape[1]} vs {b.shape[1]}")
    diff = a[:, None, :] - b[None, :, :]
    return np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))


def _check_costs(cost: Any) -> np.ndarray:
    cost = np.asarray(cost, dtype=np.float64)
    if cost.ndim != 2 or cost.shape[0] == 0 or cost.shape[1] == 0:
        raise ValueError(f"cost: expected a non-empty 2-D matrix, got shape {cost.shape}")
    return cost


def dtw_next_row(prev: np.ndarray | None, cost_row: np.ndarray) -> np.ndarray:
    """One row of the DTW accumulator: ``D[i, :]`` from ``D[i-1, :]`` (``None`` for ``i = 0``).

    The in-row recurrence ``x_j = c_j + min(a_j, x_{j-1})`` with ``a_j = min(D[i-1, j],
    D[i-1, j-1])`` unrolls to ``x_j = C_j + min_{k <= j}(a_k - C_{k-1})`` where ``C`` is the
    cumulative sum of ``c`` (costs are non-negative), i.e. one ``cumsum`` and one running minimum.
    """
    csum = np.cumsum(cost_row)
    if prev is None:
        return csum
    a = np.empty_like(cost_row)
    a[0] = prev[0]
    np.minimum(prev[1:], prev[:-1], out=a[1:])
    shifted = np.empty_like(csum)
    shifted[0] = 0.0
    shifted[1:] = csum[:-1]
    return csum + np.minimum.accumulate(a - shifted)


def dtw_from_costs(cost: Any) -> float:
    """Exact DTW cost of a non-negative local cost matrix ``(n, m)`` (steps (1,0), (0,1), (1,1)).

    ``D[i, j] = cost[i, j] + min(D[i-1, j], D[i, j-1], D[i-1, j-1])``, ``D[0, 0] = cost[0, 0]``,
    computed row by row with :func:`dtw_next_row` along the longer axis (DTW is symmetric under
    transposition), so there are min(n, m) vectorised Python steps and O(nm) work.
    """
    cost = _check_costs(cost)
    if np.any(cost < 0):
        raise ValueError("cost: DTW needs non-negative local costs")
    if cost.shape[0] > cost.shape[1]:
        cost = cost.T
    row = None
    for c in cost:
        row = dtw_next_row(row, c)
    return float(row[-1])


def dtw_from_costs_antidiagonal(cost: Any) -> float:
    """Same as :func:`dtw_from_costs`, one vectorised update per anti-diagonal (n + m - 1 steps).

    Independent second implementation (no cumulative sums); used as a cross-check and in the
    benchmark.
    """
    cost = _check_costs(cost)
    n, m = cost.shape
    # Padded accumulator: row/column 0 are +inf borders except the (0, 0) seed.
    acc = np.full((n + 1, m + 1), np.inf)
    acc[0, 0] = 0.0
    for k in range(2, n + m + 1):
        i = np.arange(max(1, k - m), min(n, k - 1) + 1)
        j = k - i
        best = np.minimum(np.minimum(acc[i - 1, j], acc[i, j - 1]), acc[i - 1, j - 1])
        acc[i, j] = cost[i - 1, j - 1] + best
    return float(acc[n, m])


class IncrementalNDTW:
    """nDTW of a growing path against a fixed reference, O(len(reference)) per appended point.

    Keeps the last accumulator row, so an episode of T steps costs O(T m) in total instead of
    recomputing DTW from scratch after every step (O(T^2 m)).
    """

    def __init__(self, reference: Any, threshold: float = 3.0) -> None:
        self.reference = _as_points(reference, "reference")
        self.threshold = _check_threshold(threshold)
        self._row: np.ndarray | None = None

    def append(self, point: Any) -> None:
        """Extend the path by one point."""
        p = np.asarray(point, dtype=np.float64).reshape(1, -1)
        self._row = dtw_next_row(self._row, pairwise_distances(p, self.reference)[0])

    @property
    def dtw(self) -> float:
        """DTW distance so far (error before the first point)."""
        if self._row is None:
            raise ValueError("IncrementalNDTW: no point appended yet")
        return float(self._row[-1])

    @property
    def value(self) -> float:
        """nDTW so far."""
        return float(math.exp(-self.dtw / (len(self.reference) * self.threshold)))


def dtw(path: Any, reference: Any) -> float:
    """Exact DTW distance between two point sequences under Euclidean point distances."""
    p = _as_points(path, "path")
    r = _as_points(reference, "reference")
    return dtw_from_costs(pairwise_distances(p, r))


def _check_threshold(threshold: float) -> float:
    if not (math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold: must be a finite positive distance, got {threshold!r}")
    return float(threshold)


def _check_success(success: Any) -> float:
    value = float(success)
    if value not in (0.0, 1.0):
        raise ValueError(f"success: expected a bool or 0/1, got {success!r}")
    return value


def ndtw(path: Any, reference: Any, threshold: float = 3.0) -> float:
    """Normalised DTW: ``exp(-DTW(path, reference) / (len(reference) * threshold))`` in (0, 1]."""
    threshold = _check_threshold(threshold)
    r = _as_points(reference, "reference")
    return float(math.exp(-dtw(path, r) / (len(r) * threshold)))


def sdtw(path: Any, reference: Any, success: Any, threshold: float = 3.0) -> float:
    """Success-weighted nDTW: ``success * ndtw(path, reference, threshold)``."""
    return _check_success(success) * ndtw(path, reference, threshold)


def spl(success: Any, shortest_distance: float, path_length: float) -> float:
    """Success weighted by (normalised inverse) path length: ``success * d0 / max(d0, path_length)``.

    ``d0`` is the geodesic start-to-goal distance. When both ``d0`` and ``path_length`` are 0 (the
    agent starts on the goal and stops at once) the ratio is taken as 1, because the agent's path is
    then the shortest one; Habitat would produce 0/0 = NaN there.
    """
    s = _check_success(success)
    d0 = float(shortest_distance)
    length = float(path_length)
    for name, value in (("shortest_distance", d0), ("path_length", length)):
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{name}: must be a finite non-negative distance, got {value!r}")
    denom = max(d0, length)
    return s if denom == 0.0 else s * d0 / denom


def path_length(positions: Any) -> float:
    """Sum of Euclidean displacements between consecutive positions (0 for a single point)."""
    p = _as_points(positions, "positions")
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def dedupe_consecutive(positions: Any) -> np.ndarray:
    """Drop positions equal to their predecessor (turns do not move the agent).

    VLN-CE's nDTW measure records a position only when it differs from the last one; a turn in
    place would otherwise add a DTW match and lower nDTW for agents that turn a lot.
    """
    p = _as_points(positions, "positions")
    keep = np.ones(len(p), dtype=bool)
    keep[1:] = np.any(p[1:] != p[:-1], axis=1)
    return p[keep]


# --------------------------------------------------------------------------------------------------
# Episode-level measures (Habitat-lab style units with explicit dependencies)
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AgentState:
    """What the measures see after reset and after every action."""

    position: np.ndarray
    """Agent position (3,) in world metres (Z-up)."""
    distance_to_goal: float | None
    """Geodesic distance to the goal in metres (inf if unreachable; None when the goal is unknown,
    which only the goal-free measures of :data:`GOAL_FREE_MEASURES` accept)."""


@dataclass(frozen=True)
class EpisodeSpec:
    """The per-episode inputs the measures need beyond the agent states."""

    episode_id: str
    """Episode identifier, used in every error message."""
    reference_path: np.ndarray | None = None
    """Ground-truth path (K, 3) for nDTW/sDTW; ``None`` makes them n/a for this episode. VLN-CE
    scores nDTW against the dense ``locations`` of ``{split}_gt.json.gz``, not the sparse
    ``reference_path`` of the episode file: pass those for comparable numbers."""


class MeasureError(RuntimeError):
    """A measure was misused (missing dependency, cycle, update after STOP, bad state)."""


class Measure(ABC):
    """One metric: reset at episode start, updated after every action, read at the end."""

    uuid: ClassVar[str]
    """Unique name; also the key in results."""
    dependencies: ClassVar[tuple[str, ...]] = ()
    """uuids of measures that must be updated before this one."""
    needs_goal: ClassVar[bool] = True
    """The measure reads the distance to the goal (n/a on episodes without a goal)."""

    def __init__(self, protocol: Protocol) -> None:
        self.protocol = protocol
        self._value: float | None = None

    @property
    def value(self) -> float | None:
        """Current value; ``None`` means not applicable to this episode."""
        return self._value

    @abstractmethod
    def reset(self, episode: EpisodeSpec, state: AgentState, deps: Mapping[str, Measure]) -> None:
        """Start a new episode at ``state``."""

    @abstractmethod
    def update(self, action: int, state: AgentState, deps: Mapping[str, Measure]) -> None:
        """Account for ``action`` having led to ``state``."""


class DistanceToGoal(Measure):
    """Geodesic distance to goal at the current state; its final value is NE."""

    uuid = "distance_to_goal"

    def reset(self, episode: EpisodeSpec, state: AgentState, deps: Mapping[str, Measure]) -> None:
        self.start_distance = float(state.distance_to_goal)
        self._value = self.start_distance

    def update(self, action: int, state: AgentState, deps: Mapping[str, Measure]) -> None:
        self._value = float(state.distance_to_goal)


class Steps(Measure):
    """Number of actions taken, STOP included."""

    uuid = "steps"
    needs_goal = False

    def reset(self, episode: EpisodeSpec, state: AgentState, deps: Mapping[str, Measure]) -> None:
        self._value = 0.0

    def update(self, action: int, state: AgentState, deps: Mapping[str, Measure]) -> None:
        self._value = (self._value or 0.0) + 1.0


class PathLength(Measure):
    """Sum of Euclidean displacements between consecutive agent positions."""

    uuid = "path_length"
    needs_goal = False

    def reset(self, episode: EpisodeSpec, state: AgentState, deps: Mapping[str, Measure]) -> None:
        self._last = np.asarray(state.position, dtype=np.float64)
        self._value = 0.0

    def update(self, action: int, state: AgentState, deps: Mapping[str, Measure]) -> None:
        pos = np.asarray(state.position, dtype=np.float64)
        self._value = (self._value or 0.0) + float(np.linalg.norm(pos - self._last))
        self._last = pos


class OracleSuccess(Measure):
    """1 once the distance to goal has been strictly below the success radius (latches)."""

    uuid = "oracle_success"
    dependencies = ("distance_to_goal",)

    def _check(self, deps: Mapping[str, Measure]) -> None:
        d = deps["distance_to_goal"].value
        hit = d is not None and d < self.protocol.success_distance_m
        self._value = 1.0 if (self._value == 1.0 or hit) else 0.0

    def reset(self, episode: EpisodeSpec, state: AgentState, deps: Mapping[str, Measure]) -> None:
        self._value = 0.0
        self._check(deps)

    def update(self, action: int, state: AgentState, deps: Mapping[str, Measure]) -> None:
        self._check(deps)


class Success(Measure):
    """1 iff STOP was called with the distance to goal strictly below the success radius."""

    uuid = "success"
    dependencies = ("distance_to_goal",)

    def reset(self, episode: EpisodeSpec, state: AgentState, deps: Mapping[str, Measure]) -> None:
        self._value = 0.0

    def update(self, action: int, state: AgentState, deps: Mapping[str, Measure]) -> None:
        if int(action) == Action.STOP:
            d = deps["distance_to_goal"].value
            self._value = 1.0 if (d is not None and d < self.protocol.success_distance_m) else 0.0


class SPL(Measure):
    """Success weighted by path length, with d0 = the distance to goal at reset."""

    uuid = "spl"
    dependencies = ("distance_to_goal", "success", "path_length")

    def reset(self, episode: EpisodeSpec, state: AgentState, deps: Mapping[str, Measure]) -> None:
        self._value = 0.0

    def update(self, action: int, state: AgentState, deps: Mapping[str, Measure]) -> None:
        d0 = deps["distance_to_goal"].start_distance  # type: ignore[attr-defined]
        if not math.isfinite(d0):
            self._value = math.nan  # surfaced by aggregate() with the episode id
            return
        self._value = spl(deps["success"].value, d0, deps["path_length"].value)


class NDTW(Measure):
    """nDTW of the (consecutively de-duplicated) visited positions against the reference path.

    The start position is part of the path (VLN-CE's measure only records positions after the
    first action; the two agree whenever the first action does not move the agent).
    """

    uuid = "ndtw"
    needs_goal = False

    def reset(self, episode: EpisodeSpec, state: AgentState, deps: Mapping[str, Measure]) -> None:
        self._last = np.asarray(state.position, dtype=np.float64)
        self._value = None
        self._acc: IncrementalNDTW | None = None
        if episode.reference_path is not None:
            ref = _as_points(episode.reference_path, f"episode {episode.episode_id}: reference_path")
            self._acc = IncrementalNDTW(ref, self.protocol.ndtw_threshold_m)
            self._acc.append(self._last)
            self._value = self._acc.value

    def update(self, action: int, state: AgentState, deps: Mapping[str, Measure]) -> None:
        pos = np.asarray(state.position, dtype=np.float64)
        if self._acc is not None and not np.array_equal(pos, self._last):
            self._acc.append(pos)
            self._value = self._acc.value
        self._last = pos


class SDTW(Measure):
    """success * nDTW (n/a when nDTW is)."""

    uuid = "sdtw"
    dependencies = ("success", "ndtw")

    def reset(self, episode: EpisodeSpec, state: AgentState, deps: Mapping[str, Measure]) -> None:
        self._value = None if deps["ndtw"].value is None else 0.0

    def update(self, action: int, state: AgentState, deps: Mapping[str, Measure]) -> None:
        n = deps["ndtw"].value
        self._value = None if n is None else float(deps["success"].value) * n


DEFAULT_MEASURES: tuple[type[Measure], ...] = (
    DistanceToGoal,
    Steps,
    PathLength,
    OracleSuccess,
    Success,
    SPL,
    NDTW,
    SDTW,
)
"""The VLN-CE measure set, in any order (dependencies fix the update order)."""

GOAL_FREE_MEASURES: tuple[type[Measure], ...] = tuple(m for m in DEFAULT_MEASURES if not m.needs_goal)
"""The measures an episode without a goal (a test split) still has: steps, path length, nDTW
(n/a without a reference path)."""


def _dependency_order(measures: Sequence[Measure]) -> list[Measure]:
    """Topologically sort ``measures``; raise on duplicates, missing dependencies and cycles."""
    by_id: dict[str, Measure] = {}
    for m in measures:
        if m.uuid in by_id:
            raise MeasureError(f"measure {m.uuid!r} given twice")
        by_id[m.uuid] = m
    for m in measures:
        for dep in m.dependencies:
            if dep not in by_id:
                raise MeasureError(f"measure {m.uuid!r} depends on {dep!r}, which is not in the measure set")
    order: list[Measure] = []
    state: dict[str, int] = {}  # 1 = visiting, 2 = done

    def visit(uid: str, chain: tuple[str, ...]) -> None:
        if state.get(uid) == 2:
            return
        if state.get(uid) == 1:
            raise MeasureError(f"dependency cycle: {' -> '.join((*chain, uid))}")
        state[uid] = 1
        for dep in by_id[uid].dependencies:
            visit(dep, (*chain, uid))
        state[uid] = 2
        order.append(by_id[uid])

    for m in measures:
        visit(m.uuid, ())
    return order


class Measurements:
    """Runs a set of measures in dependency order over one episode at a time."""

    def __init__(self, protocol: Protocol, measures: Iterable[type[Measure]] = DEFAULT_MEASURES) -> None:
        self.protocol = protocol
        self._order = _dependency_order([cls(protocol) for cls in measures])
        self._by_id = {m.uuid: m for m in self._order}
        self._episode: EpisodeSpec | None = None
        self._stopped = False
        self._steps = 0

    @property
    def uuids(self) -> list[str]:
        """Measure names in update order."""
        return [m.uuid for m in self._order]

    def _check_state(self, state: AgentState) -> None:
        pos = np.asarray(state.position, dtype=np.float64)
        eid = self._episode.episode_id if self._episode else "?"
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise MeasureError(f"episode {eid}: position must be 3 finite numbers, got {state.position!r}")
        d = state.distance_to_goal
        if d is None:
            needy = [m.uuid for m in self._order if m.needs_goal]
            if needy:
                raise MeasureError(f"episode {eid}: the goal is unknown but measures {needy} need it")
        elif math.isnan(d) or d < 0:
            raise MeasureError(f"episode {eid}: distance_to_goal must be >= 0 (inf allowed), got {d!r}")

    def reset(self, episode: EpisodeSpec, state: AgentState) -> None:
        """Start ``episode`` at ``state``."""
        self._episode = episode
        self._stopped = False
        self._steps = 0
        self._check_state(state)
        for m in self._order:
            m.reset(episode, state, self._by_id)

    def update(self, action: int, state: AgentState) -> None:
        """Record ``action`` and the state it led to. Nothing may follow STOP."""
        if self._episode is None:
            raise MeasureError("update() before reset()")
        eid = self._episode.episode_id
        if self._stopped:
            raise MeasureError(f"episode {eid}: action after STOP")
        if int(action) not in {a.value for a in Action}:
            raise MeasureError(f"episode {eid}: unknown action id {action!r}")
        self._steps += 1
        if self._steps > self.protocol.max_steps:
            raise MeasureError(
                f"episode {eid}: more than max_steps={self.protocol.max_steps} actions "
                f"under protocol {self.protocol.name!r}"
            )
        self._check_state(state)
        for m in self._order:
            m.update(action, state, self._by_id)
        self._stopped = int(action) == Action.STOP

    def values(self) -> dict[str, float | None]:
        """Current value of every measure."""
        return {uid: m.value for uid, m in self._by_id.items()}


@dataclass(frozen=True)
class EpisodeResult:
    """Per-episode metrics under one protocol."""

    episode_id: str
    """Episode identifier."""
    metrics: Mapping[str, float | None]
    """Metric name -> value; ``None`` = not applicable (counted as missing, never as 0)."""
    protocol: Protocol
    """Protocol the episode was run under."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record (protocol by full value)."""
        return {
            "episode_id": self.episode_id,
            "metrics": dict(self.metrics),
            "protocol": self.protocol.to_dict(),
        }


def evaluate_episode(
    episode: EpisodeSpec,
    states: Sequence[AgentState],
    actions: Sequence[int],
    protocol: Protocol,
    measures: Iterable[type[Measure]] = DEFAULT_MEASURES,
) -> EpisodeResult:
    """Run the measures over a finished trajectory.

    ``states[0]`` is the start state and ``states[t + 1]`` the state ``actions[t]`` led to.
    """
    if len(states) != len(actions) + 1:
        raise ValueError(
            f"episode {episode.episode_id}: need len(states) == len(actions) + 1, "
            f"got {len(states)} states and {len(actions)} actions"
        )
    ms = Measurements(protocol, measures)
    ms.reset(episode, states[0])
    for action, state in zip(actions, states[1:], strict=True):
        ms.update(action, state)
    return EpisodeResult(episode.episode_id, ms.values(), protocol)


# --------------------------------------------------------------------------------------------------
# Aggregation
# --------------------------------------------------------------------------------------------------


class AggregationError(ValueError):
    """Per-episode results cannot be aggregated as given (non-finite value, key mismatch, duplicates)."""


@dataclass(frozen=True)
class MetricSummary:
    """Mean of one metric and the number of episodes behind it."""

    mean: float | None
    """Mean over the episodes where the metric applies; ``None`` if it applies to none."""
    count: int
    """Episodes that entered the mean."""
    missing: int
    """Episodes where the metric is n/a (``None``); never silently dropped: they are counted here."""
    sem: float | None = None
    """Standard error of the mean (sample std / sqrt(count)); ``None`` for fewer than 2 episodes."""


def summarize(values: Sequence[float], missing: int = 0) -> MetricSummary:
    """Mean, count and standard error of finite ``values``."""
    n = len(values)
    if n == 0:
        return MetricSummary(None, 0, missing, None)
    arr = np.asarray(values, dtype=np.float64)
    mean = float(arr.mean())
    sem = float(arr.std(ddof=1) / math.sqrt(n)) if n > 1 and math.isfinite(mean) else None
    return MetricSummary(mean, n, missing, sem)


@dataclass(frozen=True)
class AggregateReport:
    """Means of per-episode metrics under a single protocol."""

    protocol: Protocol
    """The one protocol every aggregated episode was produced under."""
    num_episodes: int
    """Episodes aggregated."""
    metrics: Mapping[str, MetricSummary] = field(default_factory=dict)
    """Metric name -> summary."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record."""
        return {
            "protocol": self.protocol.to_dict(),
            "num_episodes": self.num_episodes,
            "metrics": {
                k: {"mean": s.mean, "count": s.count, "missing": s.missing, "sem": s.sem}
                for k, s in self.metrics.items()
            },
        }


def summarize_records(
    records: Sequence[tuple[str, Mapping[str, float | None]]],
    allow_inf: Collection[str] = (),
    kind: str = "episode",
) -> dict[str, MetricSummary]:
    """Per-metric :class:`MetricSummary` over ``(id, metrics)`` records, with the no-silent-drop rules.

    Raises :class:`AggregationError` on an empty input, duplicate ids, records whose metric keys
    differ, and non-finite values (naming the ``kind`` and id and the metric). Metrics named in
    ``allow_inf`` may be infinite (e.g. PSNR of identical images is +inf, and so is the mean then);
    they still refuse NaN. ``None`` values are n/a: counted as missing, never as 0.
    """
    if not records:
        raise AggregationError(f"no {kind} results to aggregate")
    first_id, first = records[0]
    keys = list(first)
    seen: set[str] = set()
    columns: dict[str, list[float]] = {k: [] for k in keys}
    missing = dict.fromkeys(keys, 0)
    for rid, metrics in records:
        if rid in seen:
            raise AggregationError(f"{kind} {rid}: appears more than once")
        seen.add(rid)
        if set(metrics) != set(keys):
            raise AggregationError(
                f"{kind} {rid}: metric keys {sorted(metrics)} differ from {kind} {first_id}'s {sorted(keys)}"
            )
        for k in keys:
            v = metrics[k]
            if v is None:
                missing[k] += 1
                continue
            v = float(v)
            if math.isnan(v) or (math.isinf(v) and k not in allow_inf):
                raise AggregationError(
                    f"{kind} {rid}: metric {k!r} is {v}; non-finite values are errors, not silently dropped"
                )
            columns[k].append(v)
    return {k: summarize(columns[k], missing[k]) for k in keys}


def aggregate(results: Sequence[EpisodeResult], allow_inf: Collection[str] = ()) -> AggregateReport:
    """Average per-episode metrics of one protocol, with an episode count for every mean.

    Applies :func:`summarize_records` (empty input, duplicate ids, key mismatches and non-finite
    values are errors naming the episode) and raises
    :class:`~image2sim.eval.protocols.ProtocolMismatchError` when protocols differ.
    """
    if not results:
        raise AggregationError("no episode results to aggregate")
    protocol = ensure_same_protocol(r.protocol for r in results)
    summaries = summarize_records([(r.episode_id, r.metrics) for r in results], allow_inf, "episode")
    return AggregateReport(protocol, len(results), summaries)
