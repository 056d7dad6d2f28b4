"""Topologically-aware trajectory sampling (paper appendix).

Per scene: a capacity from the navigable area (clamped to [50, 1000]); for each episode a path-length
bucket drawn by roulette (short 3-6 m 20 %, medium 6-10 m 30 %, long 10-15 m 50 %, geodesic
metres); a start chosen by furthest-point sampling against earlier starts (coverage); a goal object
drawn with IDF weights over categories (rare categories favoured); a goal standing point within the
object's radius (1.5 m small items, 3.0 m large objects, Euclidean) that passes a geodesic check
(its geodesic distance to the object's nearest navigable point is at most ``geodesic_slack`` times
the radius, so a point behind a wall is rejected), preferring points far from earlier goals (FPS).
Everything draws from one seeded generator, so a scene's plans are reproducible.

Positions are map-frame feet positions of the :class:`NavGraph` (see :mod:`..navigation`).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

__all__ = [
    "Bucket",
    "SamplingConfig",
    "EpisodePlan",
    "DEFAULT_BUCKETS",
    "episode_capacity",
    "draw_buckets",
    "sample_path_plans",
    "idf_weights",
    "farthest_point",
    "coverage_radius",
    "sample_plans",
    "ApproachConfig",
    "sample_approach_plans",
    "switch_plans",
]


@dataclass(frozen=True)
class Bucket:
    """A geodesic path-length bucket."""

    name: str
    """Bucket name (short, medium, long)."""
    min_length: float
    """Lower bound in metres (inclusive)."""
    max_length: float
    """Upper bound in metres (exclusive)."""
    weight: float
    """Roulette weight."""


DEFAULT_BUCKETS = (
    Bucket("short", 3.0, 6.0, 0.2),
    Bucket("medium", 6.0, 10.0, 0.3),
    Bucket("long", 10.0, 15.0, 0.5),
)


@dataclass(frozen=True)
class SamplingConfig:
    """Trajectory sampling knobs (defaults = the paper's)."""

    buckets: tuple[Bucket, ...] = DEFAULT_BUCKETS
    """Path-length buckets and their roulette weights."""
    episodes_per_m2: float = 2.0
    """Capacity = navigable area x this, clamped to [min_episodes, max_episodes]."""
    min_episodes: int = 50
    """Lower clamp of the area-based capacity."""
    max_episodes: int = 1000
    """Upper clamp of the area-based capacity."""
    small_radius: float = 1.5
    """Goal radius (metres, Euclidean) of small, manipulable items."""
    large_radius: float = 3.0
    """Goal radius (metres, Euclidean) of large objects."""
    geodesic_slack: float = 1.0
    """A standing point is valid when its geodesic distance to the object's nearest navigable point is
    at most this times the goal radius (rejects points behind walls)."""
    start_candidates: int = 32
    """Random candidate starts among which furthest-point sampling picks the best-covering one."""
    min_path_length: float = 3.0
    """Fallback lower bound (metres, geodesic) when no bucket is feasible in a small scene. Keep it at
    or above the evaluation's success distance (3 m in every protocol): a shorter episode starts
    inside the success radius and is solved by stopping at once."""
    bucket_fallback: bool = True
    """Small scenes: when the drawn bucket has no candidate, try the other buckets, then any length
    >= ``min_path_length`` (recorded as bucket ``fallback``)."""
    max_attempts: int = 20
    """Starts tried per episode before the episode is given up."""
    plan_oversample: float = 1.5
    """Plans drawn per wanted episode. Rollouts that collide or walk past the goal are dropped, and the
    extra plans replace them (in plan order), so a scene yields its capacity when it can."""
    path_endpoint_margin: float = 0.1
    """Path episodes (no goal object): start and goal nodes keep at least the agent radius plus this
    (metres) from obstacles. On the HM3D sample, 26 of 76 unfiltered episodes began or ended within
    0.25 m of a wall (clearance 0.15-0.25 m for a 0.15 m radius) and their rollouts collided."""
    goal_categories: tuple[str, ...] = ()
    """Object categories that may be an episode's goal (names as the detector reports them); empty:
    every detected category. Other objects stay in the scene and may still be named as landmarks.
    A task whose goals are few, large, visually distinct categories is one a small policy can
    learn to ground (docs/sim2real.md, "distinct goals" pilot)."""
    seed: int = 0
    """Base seed (combined with the scene id)."""

    def __post_init__(self) -> None:
        cats = self.goal_categories
        if isinstance(cats, str) or not all(isinstance(c, str) and c for c in cats):
            raise ValueError(f"SamplingConfig.goal_categories must be a list of category names, got {cats!r}")
        object.__setattr__(self, "goal_categories", tuple(cats))
        if not self.buckets:
            raise ValueError("SamplingConfig.buckets must not be empty")
        for b in self.buckets:
            if not (0 <= b.min_length < b.max_length and b.weight > 0):
                raise ValueError(f"SamplingConfig.buckets: invalid bucket {b}")
        if not (1 <= self.min_episodes <= self.max_episodes):
            raise ValueError("SamplingConfig: need 1 <= min_episodes <= max_episodes")
        for name in ("episodes_per_m2", "small_radius", "large_radius", "geodesic_slack", "min_path_length"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SamplingConfig.{name} must be positive, got {getattr(self, name)!r}")
        if not self.plan_oversample >= 1.0:
            raise ValueError(f"SamplingConfig.plan_oversample must be >= 1, got {self.plan_oversample!r}")
        if self.start_candidates < 1 or self.max_attempts < 1:
            raise ValueError("SamplingConfig.start_candidates and max_attempts must be >= 1")


@dataclass
class EpisodePlan:
    """A sampled start/goal pair (map frame) before the rollout."""

    start: np.ndarray
    heading: float
    goal: np.ndarray
    """Goal standing point (feet position)."""
    goal_object: dict
    """The goal object's record (category, position, object_id, small, radius)."""
    goal_radius: float
    bucket: str
    geodesic_distance: float
    extra: dict = field(default_factory=dict)


def bucket_of(geodesic: float, config: SamplingConfig) -> str | None:
    """The name of the bucket a path length falls in, ``"fallback"`` for any other length the config
    accepts (>= ``min_path_length`` with ``bucket_fallback``), else ``None`` (not a valid episode)."""
    for b in config.buckets:
        if b.min_length <= geodesic < b.max_length:
            return b.name
    if config.bucket_fallback and geodesic >= config.min_path_length:
        return "fallback"
    return None


def episode_capacity(navigable_area: float, config: SamplingConfig) -> int:
    """Per-scene episode count: area x density clamped to [min_episodes, max_episodes]."""
    if not math.isfinite(navigable_area) or navigable_area < 0:
        raise ValueError(f"navigable area must be a finite non-negative number, got {navigable_area!r}")
    n = int(round(navigable_area * config.episodes_per_m2))
    return int(min(config.max_episodes, max(config.min_episodes, n)))


def draw_buckets(n: int, buckets: Sequence[Bucket], rng: np.random.Generator) -> list[Bucket]:
    """``n`` independent roulette draws over the bucket weights."""
    w = np.array([b.weight for b in buckets], dtype=np.float64)
    idx = rng.choice(len(buckets), size=n, p=w / w.sum())
    return [buckets[int(i)] for i in idx]


def idf_weights(categories: Sequence[str]) -> dict[str, float]:
    """Per-object-category weight log(1 + N / n_c): categories with fewer instances weigh more."""
    counts = Counter(categories)
    total = sum(counts.values())
    return {c: math.log(1.0 + total / n) for c, n in counts.items()}


def farthest_point(candidates: np.ndarray, chosen: np.ndarray) -> int:
    """Index of the candidate whose distance to the nearest already-chosen point is largest."""
    if len(candidates) == 0:
        raise ValueError("farthest_point: no candidates")
    if len(chosen) == 0:
        return 0
    d = np.linalg.norm(candidates[:, None, :2] - np.asarray(chosen)[None, :, :2], axis=-1).min(axis=1)
    return int(np.argmax(d))


def coverage_radius(points: np.ndarray, domain: np.ndarray) -> float:
    """Largest distance from a domain point to its nearest chosen point (lower = better coverage)."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(np.asarray(points)[:, :2]).query(np.asarray(domain)[:, :2])
    return float(np.max(d))


def _object_radius(obj, config: SamplingConfig) -> float:
    return config.small_radius if obj.small else config.large_radius


def _goal_candidates(graph, objects: Sequence, config: SamplingConfig, to_map, stats: Counter):
    """(nodes of the largest connected component, per reachable object ``(object, radius, standing
    node ids)``): the standing nodes lie within the object's radius and pass the geodesic check."""
    from scipy.sparse.csgraph import dijkstra  # directed=True on the symmetric matrix: no conversion

    nodes = graph.nodes
    in_main = graph.largest_component_nodes  # every plan must be reachable
    conv = (lambda p: np.asarray(p, float)) if to_map is None else to_map
    obj_info = []
    for o in objects:
        p = conv(np.asarray(o.position, float))
        r = _object_radius(o, config)
        d_xy = np.linalg.norm(nodes[in_main, :2] - p[:2], axis=1)
        near = in_main[d_xy <= r]
        if len(near) == 0:
            stats["object_unreachable"] += 1
            continue
        anchor = int(in_main[np.argmin(d_xy)])
        # limit: nodes beyond the slack radius are never valid, so the search can stop there.
        d_geo = dijkstra(graph.length_matrix, directed=True, indices=anchor, limit=config.geodesic_slack * r)
        ok = near[d_geo[near] <= config.geodesic_slack * r]
        stats["stand_rejected_geodesic"] += int(len(near) - len(ok))
        if len(ok) == 0:
            continue
        obj_info.append((o, r, ok))
    return in_main, obj_info


def _goal_record(obj, radius: float) -> dict:
    return {
        "object_id": int(obj.object_id),
        "category": obj.category,
        "position": [float(v) for v in obj.position],
        "small": bool(obj.small),
        "radius": radius,
        "room_type": obj.room_type,
    }


def sample_plans(
    graph, planner, objects: Sequence, n: int, config: SamplingConfig, rng: np.random.Generator, to_map=None
) -> tuple[list[EpisodePlan], dict]:
    """Sample up to ``n`` episode plans on one scene -> (plans, statistics of rejections).

    ``objects`` are :class:`~image2sim.dataengine.mining.SceneObject` (world frame positions);
    ``to_map`` converts world points to the map frame (identity when None).
    """
    stats = Counter()
    if config.goal_categories:
        allowed = set(config.goal_categories)
        kept = [o for o in objects if o.category in allowed]
        stats["goal_category_excluded"] += len(objects) - len(kept)
        objects = kept
    if graph.num_nodes == 0 or not objects:
        stats["no_nodes" if graph.num_nodes == 0 else "no_objects"] += 1
        return [], dict(stats)
    in_main, obj_info = _goal_candidates(graph, objects, config, to_map, stats)
    if not obj_info:
        stats["no_valid_goal_object"] += 1
        return [], dict(stats)
    idf = idf_weights([o.category for o, _, _ in obj_info])
    w = np.array([idf[o.category] for o, _, _ in obj_info])
    w = w / w.sum()

    def targets(start):
        k = int(rng.choice(len(obj_info), p=w))
        obj, radius, stand = obj_info[k]
        return stand, _goal_record(obj, radius), radius

    return _draw_plans(n, graph, config, rng, in_main, targets, stats), dict(stats)


@dataclass(frozen=True)
class ApproachConfig:
    """Approach episodes: short training episodes that start with their goal object in view.

    From a random navigable pose, every visible object of a category seen once in the view becomes
    the goal of its own episode (up to ``per_view``), so the same first view is paired with
    different instructions and different expert actions. A policy cannot fit them without reading
    which object the instruction names: they ground category words in views, the grounding a
    pretrained VLM brings and a from-scratch policy lacks. Training data only: they are shorter
    than the evaluation's buckets and go to their own shard, never to the episode file.
    """

    views: int = 0
    """Start poses per scene (0: no approach episodes)."""
    per_view: int = 2
    """At most this many goal objects (of different categories) per start pose."""
    max_distance: float = 5.0
    """Objects farther than this from the eye (metres) do not count as in view."""
    hfov_deg: float = 90.0
    """Horizontal field of view that must contain the goal (the stored pinhole view's 90 degrees)."""
    min_length: float = 1.0
    """The goal standing point is the nearest one at least this far (metres, geodesic) from the start."""
    switch: bool = False
    """Also an episode from the end of each approach episode to the other goals seen from its start
    pose (:func:`switch_plans`): its first view shows an object close by, and the instruction names
    another, so the expert walks on. Meant to stop a policy from learning "stop near anything"; in
    the 32-house pilot it did not make stopping depend on the instruction, and held-out SR fell
    (docs/sim2real.md), so it is off by default."""

    def __post_init__(self) -> None:
        if self.views < 0 or self.per_view < 1:
            raise ValueError(
                f"ApproachConfig: need views >= 0 and per_view >= 1, got {self.views}, {self.per_view}"
            )
        for name in ("max_distance", "hfov_deg", "min_length"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"ApproachConfig.{name} must be a positive number, got {v!r}")


def sample_approach_plans(
    graph,
    objects: Sequence,
    config: ApproachConfig,
    sampling: SamplingConfig,
    rng: np.random.Generator,
    visible: Callable[[np.ndarray, float, np.ndarray], np.ndarray],
    to_map=None,
) -> tuple[list[EpisodePlan], dict]:
    """Plans of approach episodes (:class:`ApproachConfig`) -> (plans, statistics).

    ``visible(start, heading, positions)`` -> (N,) bool: which of the objects (map-frame
    ``positions``) a camera at the feet position ``start`` looking along ``heading`` sees (field of
    view, distance, occlusion: the caller's test). Each plan's bucket is ``"approach"``.
    """
    from scipy.sparse.csgraph import dijkstra

    stats = Counter()
    if config.views == 0 or graph.num_nodes == 0 or not objects:
        return [], dict(stats)
    in_main, obj_info = _goal_candidates(graph, objects, sampling, to_map, stats)
    if not obj_info:
        return [], dict(stats)
    conv = (lambda p: np.asarray(p, float)) if to_map is None else to_map
    pos = np.array([conv(np.asarray(o.position, float)) for o, _, _ in obj_info]).reshape(-1, 3)
    max_len = 2.0 * config.max_distance + max(r for _, r, _ in obj_info)
    plans: list[EpisodePlan] = []
    for _ in range(config.views):
        start = graph.nodes[int(rng.choice(in_main))].copy()
        heading = float(rng.uniform(-math.pi, math.pi))
        seen = np.nonzero(visible(start, heading, pos))[0]
        cats = Counter(obj_info[i][0].category for i in seen)
        # A category seen twice makes "the <category>" ambiguous in this view: skip it.
        seen = [int(i) for i in seen if cats[obj_info[i][0].category] == 1]
        if not seen:
            stats["approach_nothing_in_view"] += 1
            continue
        s_node = int(graph.snap(start[None])[0][0])
        dist = dijkstra(graph.length_matrix, directed=True, indices=s_node, limit=max_len)
        for i in rng.permutation(seen)[: config.per_view]:
            obj, radius, stand = obj_info[int(i)]
            d = dist[stand]
            ok = np.isfinite(d) & (d >= config.min_length)
            if not ok.any():
                stats["approach_too_close"] += 1
                continue
            j = np.nonzero(ok)[0][int(np.argmin(d[ok]))]
            plans.append(
                EpisodePlan(
                    start,
                    heading,
                    graph.nodes[stand[j]].copy(),
                    _goal_record(obj, radius),
                    radius,
                    "approach",
                    float(d[j]),
                )
            )
    stats["approach_planned"] = len(plans)
    return plans, dict(stats)


def switch_plans(
    done: Sequence[tuple[EpisodePlan, np.ndarray, float]], geodesic: Callable[[np.ndarray, np.ndarray], float]
) -> list[EpisodePlan]:
    """Goal-switch plans: for approach episodes ``done`` = (plan, end position, end heading) that share
    a start pose, one plan from the end of each to the goal of each other (bucket ``approach_switch``).
    ``geodesic(a, b)`` is the path length in metres (inf when unreachable: no plan)."""
    by_view: dict[tuple, list] = {}
    for item in done:
        p = item[0]
        by_view.setdefault((*np.round(np.asarray(p.start, float), 6), round(float(p.heading), 9)), []).append(
            item
        )
    out = []
    for group in by_view.values():
        for a, end, heading in group:
            for b, _, _ in group:
                if b is a or b.goal_object.get("object_id") == a.goal_object.get("object_id"):
                    continue
                geo = float(geodesic(end, b.goal))
                if math.isfinite(geo):
                    out.append(
                        replace(
                            b,
                            start=np.asarray(end, float).copy(),
                            heading=float(heading),
                            bucket="approach_switch",
                            geodesic_distance=geo,
                        )
                    )
    return out


def sample_path_plans(
    graph, n: int, config: SamplingConfig, rng: np.random.Generator
) -> tuple[list[EpisodePlan], dict]:
    """Object-free plans (``data episodes --detector none``): start and goal are navigable nodes of the
    largest connected component, the goal at a geodesic distance in the drawn bucket (farthest-point
    spread over earlier starts and goals, as :func:`sample_plans`). The goal radius is
    ``large_radius`` (3 m, VLN-CE's success distance); ``goal_object`` is empty."""

    stats = Counter()
    if graph.num_nodes == 0:
        stats["no_nodes"] += 1
        return [], dict(stats)
    in_main = graph.largest_component_nodes
    clear = graph.clearance[in_main] >= graph.embodiment.radius + config.path_endpoint_margin
    if clear.any():
        in_main = in_main[clear]
    else:
        stats["no_clear_endpoints"] += 1
        return [], dict(stats)
    return _draw_plans(
        n, graph, config, rng, in_main, lambda start: (in_main, {}, config.large_radius), stats
    ), dict(stats)


def _draw_plans(n: int, graph, config: SamplingConfig, rng, in_main, targets, stats) -> list[EpisodePlan]:
    """Up to ``n`` plans: per plan a bucket, then up to ``max_attempts`` starts (the best-covering of
    ``start_candidates`` random nodes of ``in_main``, farthest-point over earlier starts). For each,
    ``targets(start) -> (goal node ids, goal object record, goal radius)``; the goal is the target
    whose geodesic distance from the start falls in the bucket (:func:`_pick_goal`).

    One bucket draw per plan: plan i depends only on plans 0..i-1, so asking for more plans (the
    pipeline's ``plan_oversample``) keeps the first ones and only adds."""
    from scipy.sparse.csgraph import dijkstra

    nodes = graph.nodes
    max_len = max(b.max_length for b in config.buckets)
    starts: list[np.ndarray] = []
    goals: list[np.ndarray] = []
    plans: list[EpisodePlan] = []
    for _ in range(n):
        bucket = draw_buckets(1, config.buckets, rng)[0]
        plan = None
        for _ in range(config.max_attempts):
            cand = nodes[rng.choice(in_main, size=min(config.start_candidates, len(in_main)), replace=False)]
            start = cand[farthest_point(cand, np.array(starts).reshape(-1, 3))]
            ids, goal_object, radius = targets(start)
            s_node = int(graph.snap(start[None])[0][0])
            dist = dijkstra(graph.length_matrix, directed=True, indices=s_node, limit=max_len)[ids]
            picked = _pick_goal(start, nodes[ids], dist, bucket, config, goals, rng, stats)
            if picked is None:
                continue
            goal, geo, bname = picked
            heading = float(rng.uniform(-math.pi, math.pi))
            plan = EpisodePlan(start.copy(), heading, goal.copy(), goal_object, radius, bname, float(geo))
            break
        if plan is None:
            stats["episode_given_up"] += 1
            continue
        starts.append(plan.start)
        goals.append(plan.goal)
        plans.append(plan)
    stats["planned"] = len(plans)
    return plans


def _pick_goal(start, stand_pts, dist, bucket: Bucket, config: SamplingConfig, goals, rng, stats):
    """Choose a standing point whose geodesic distance falls in the bucket (FPS over earlier goals)."""
    finite = np.isfinite(dist)
    tries = [bucket]
    if config.bucket_fallback:
        tries += [b for b in config.buckets if b is not bucket]
    for b in tries:
        sel = finite & (dist >= b.min_length) & (dist < b.max_length)
        if sel.any():
            i = np.nonzero(sel)[0]
            j = i[farthest_point(stand_pts[i], np.array(goals).reshape(-1, 3))]
            return stand_pts[j], float(dist[j]), b.name
        stats[f"bucket_{b.name}_infeasible"] += 1
    if config.bucket_fallback:
        sel = finite & (dist >= config.min_path_length)
        if sel.any():
            i = np.nonzero(sel)[0]
            j = i[int(np.argmax(dist[i]))]  # longest feasible path in a small scene
            return stand_pts[j], float(dist[j]), "fallback"
    return None
