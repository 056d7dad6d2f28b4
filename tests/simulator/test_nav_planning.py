"""Graph, directed costs, planner, distance fields and the oracle follower."""

from __future__ import annotations

import functools
import heapq
import math

import numpy as np
import pytest
from image2sim.simulator.conventions import Action
from image2sim.simulator.navigation import synthetic as syn
from image2sim.simulator.navigation.agent import Agent, CollisionWorld
from image2sim.simulator.navigation.extract import extract_navmap_from_points
from image2sim.simulator.navigation.follower import OracleFollower, ReferencePathFollower, smooth_path
from image2sim.simulator.navigation.graph import NavGraph, edge_costs, ray_march_free
from image2sim.simulator.navigation.planner import Planner

SPACING = 0.04


@functools.cache
def setup(name: str):
    w = {
        "box": lambda: syn.box_room(spacing=SPACING),
        "gap": lambda: syn.wall_with_gap(spacing=SPACING),
        "narrow": lambda: syn.wall_with_gap(gap_width=0.25, spacing=SPACING),
        "L": lambda: syn.l_room(spacing=SPACING),
        "stairs": lambda: syn.two_levels_with_stairs(spacing=SPACING),
        "rooms": lambda: syn.rooms_grid(2, 2, seed=3, furniture=2),
    }[name]()
    m = extract_navmap_from_points(w.points, w.normals, camera_positions=w.camera_positions)
    g = NavGraph.build(m)
    return w, m, g, Planner(g)


def random_pairs(g: NavGraph, n: int, seed: int, same_component: bool = True):
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        a, b = rng.integers(0, g.num_nodes, 2)
        if not same_component or g.components[a] == g.components[b]:
            out.append((int(a), int(b)))
    return out


def test_edges_connect_nearby_nodes_only_and_never_cross_walls():
    w, m, g, _ = setup("gap")
    assert g.num_edges > 0
    assert g.lengths.max() <= g.config.neighbor_radius + 1e-9
    a, b = g.nodes[g.edges[:, 0]], g.nodes[g.edges[:, 1]]
    # Edges crossing the wall plane x = 3 must pass through the door gap (y in [1.55, 2.45]).
    cross = (a[:, 0] - 3.0) * (b[:, 0] - 3.0) < 0
    t = (3.0 - a[cross, 0]) / (b[cross, 0] - a[cross, 0])
    y = a[cross, 1] + t * (b[cross, 1] - a[cross, 1])
    assert cross.any() and np.all((y > 1.55) & (y < 2.45))


def test_ray_march_matches_slow_reference():
    w, m, g, _ = setup("L")
    keys, masks = m.blocked_stack()
    rng = np.random.default_rng(0)
    a = g.nodes[rng.integers(0, g.num_nodes, 120)]
    b = a + np.column_stack((rng.uniform(-0.6, 0.6, (120, 2)), np.zeros(120)))
    fast = ray_march_free(a, b, masks, keys, m.origin, m.voxel_size, 0.025)
    assert 0 < fast.sum() < len(fast)  # both outcomes are exercised
    for k in range(120):
        n = int(max(2, np.ceil(np.linalg.norm(b[:, :2] - a[:, :2], axis=1).max() / 0.025) + 1))
        free = True
        for t in np.linspace(0, 1, n):
            p = a[k] + t * (b[k] - a[k])
            i, j = np.floor((p[:2] - m.origin[:2]) / m.voxel_size).astype(int)
            kz = math.floor((p[2] - m.origin[2]) / m.voxel_size)
            bin_ = int(np.argmin(np.abs(keys - kz)))
            if not (0 <= i < masks.shape[1] and 0 <= j < masks.shape[2]) or masks[bin_, i, j]:
                free = False
                break
        assert fast[k] == free


def test_clearance_shortcut_keeps_exactly_the_fully_marched_edges():
    from scipy.spatial import cKDTree

    _, m, g, _ = setup("stairs")  # risers, storeys and a drop: every branch of the march
    pairs = cKDTree(g.nodes).query_pairs(r=g.config.neighbor_radius, output_type="ndarray")
    pairs = pairs[
        np.abs(g.nodes[pairs[:, 0], 2] - g.nodes[pairs[:, 1], 2]) <= g.embodiment.max_step_height + 0.01
    ]
    # A random fifth of the candidate pairs keeps the full march cheap; the check is per pair.
    pairs = pairs[np.random.default_rng(11).random(len(pairs)) < 0.2]
    bin_keys, masks = m.blocked_stack()
    full = ray_march_free(
        g.nodes[pairs[:, 0]],
        g.nodes[pairs[:, 1]],
        masks,
        bin_keys,
        m.origin,
        m.voxel_size,
        g.config.march_step,
    )

    def keys(e):
        e = np.sort(e, axis=1).astype(np.int64)
        return np.sort(e[:, 0] * g.num_nodes + e[:, 1])

    assert np.array_equal(np.intersect1d(keys(g.edges), keys(pairs)), keys(pairs[full]))


def test_directed_costs_are_asymmetric_next_to_walls_and_follow_the_formula():
    _, m, g, _ = setup("box")
    cfg, r = g.config, g.embodiment.radius
    i, j = g.edges[:, 0], g.edges[:, 1]
    differ = np.abs(g.clearance[i] - g.clearance[j]) > 0.02
    assert differ.any()
    k = np.flatnonzero(differ)[0]
    a, b = int(i[k]), int(j[k])
    assert g.arc_cost(a, b) != pytest.approx(g.arc_cost(b, a))
    r_safe = cfg.r_safe_factor * r
    for s, t in ((a, b), (b, a)):
        c = g.clearance[t]
        expect = (
            g.lengths[k]
            + cfg.w_safe * max(0.0, (r_safe - c) / r_safe) ** 2
            + cfg.w_collision * max(0.0, (r - c) / r)
        )
        assert g.arc_cost(s, t) == pytest.approx(expect)
    # Soft linear penetration penalty below the radius.
    assert edge_costs(np.array([0.1]), np.array([0.075]), r, cfg)[0] == pytest.approx(
        0.1 + cfg.w_safe * ((r_safe - 0.075) / r_safe) ** 2 + cfg.w_collision * 0.5
    )


def reference_dijkstra(g: NavGraph, s: int, t: int) -> float:
    """Slow heapq Dijkstra over the directed arcs (cost of entering the target node)."""
    cost = g.cost.tocsr()
    dist = {s: 0.0}
    heap = [(0.0, s)]
    done = set()
    while heap:
        d, u = heapq.heappop(heap)
        if u in done:
            continue
        if u == t:
            return d
        done.add(u)
        for v, w in zip(
            cost.indices[cost.indptr[u] : cost.indptr[u + 1]],
            cost.data[cost.indptr[u] : cost.indptr[u + 1]],
            strict=True,
        ):
            nd = d + w
            if nd < dist.get(int(v), math.inf):
                dist[int(v)] = nd
                heapq.heappush(heap, (nd, int(v)))
    return math.inf


def test_planner_uses_directed_weights_parity_with_reference():
    _, _, g, pl = setup("gap")
    for a, b in random_pairs(g, 4, seed=1):
        res = pl.shortest_path(g.nodes[a], g.nodes[b])
        assert res.cost == pytest.approx(reference_dijkstra(g, a, b), rel=1e-9)
        forward = sum(g.arc_cost(u, v) for u, v in zip(res.nodes[:-1], res.nodes[1:], strict=False))
        backward = sum(g.arc_cost(v, u) for u, v in zip(res.nodes[:-1], res.nodes[1:], strict=False))
        assert forward == pytest.approx(res.cost)
        if len(res.nodes) > 2:
            assert backward != pytest.approx(forward)
    # The weighted distance field (Dijkstra on the transposed graph) agrees with forward planning.
    a, b = random_pairs(g, 1, seed=2)[0]
    field = pl.distance_field(g.nodes[b], weighted=True)
    assert field.node_distance[a] == pytest.approx(pl.shortest_path(g.nodes[a], g.nodes[b]).cost)


@pytest.mark.parametrize("name", ["gap", "L"])
def test_planned_paths_stay_in_free_known_space(name):
    w, m, g, pl = setup(name)
    for a, b in random_pairs(g, 8, seed=3):
        res = pl.shortest_path(g.nodes[a], g.nodes[b])
        assert res.reachable
        pts = res.waypoints
        seg = np.concatenate(
            [
                p0 + np.linspace(0, 1, 13)[:, None] * (p1 - p0)
                for p0, p1 in zip(pts[:-1], pts[1:], strict=True)
            ]
        )
        assert np.isfinite(w.floor_height(seg[:, :2])).all()
        assert w.obstacle_distance(seg[:, :2]).min() >= g.embodiment.radius - 0.03


@pytest.mark.parametrize("name", ["box", "gap", "L", "stairs"])
def test_geodesic_is_at_least_euclidean(name):
    _, _, g, pl = setup(name)
    # One Dijkstra per source covers many targets: the distance field of a node is its geodesics.
    for a, _ in random_pairs(g, 3, seed=4):
        field = pl.distance_field(g.nodes[a])
        d = field.node_distance
        assert np.all(d + 1e-9 >= np.linalg.norm(g.nodes - g.nodes[a], axis=1))
    for a, b in random_pairs(g, 5, seed=4):
        geo, why = pl.geodesic_distance(g.nodes[a], g.nodes[b])
        assert not why
        assert geo >= np.linalg.norm(g.nodes[a] - g.nodes[b]) - 1e-9


def test_geodesic_close_to_euclidean_in_an_empty_room():
    _, _, g, pl = setup("box")
    ratios = []
    for a, _ in random_pairs(g, 4, seed=5):
        d = pl.distance_field(g.nodes[a]).node_distance
        e = np.linalg.norm(g.nodes - g.nodes[a], axis=1)
        far = e > 1.0
        ratios.append((d[far] / e[far]).max())
    assert max(ratios) <= 1.03, ratios


def test_distance_field_matches_point_queries():
    _, _, g, pl = setup("L")
    goal = g.nodes[random_pairs(g, 1, seed=6)[0][0]] + np.array([0.01, -0.02, 0.0])
    field = pl.distance_field(goal)
    rng = np.random.default_rng(7)
    for idx in rng.integers(0, g.num_nodes, 10):
        p = g.nodes[idx] + np.array([0.02, 0.01, 0.0])
        geo, _ = pl.geodesic_distance(p, goal)
        assert field(p) == pytest.approx(geo, rel=1e-9)
    assert field(np.array([100.0, 0.0, 0.0])) == math.inf


def test_unreachable_and_off_map_queries_return_inf_with_reason():
    _, _, g, pl = setup("narrow")
    left = g.nodes[g.nodes[:, 0] < 2.5][0]
    right = g.nodes[g.nodes[:, 0] > 3.5][0]
    res = pl.shortest_path(left, right)
    assert not res.reachable and res.length == math.inf and "component" in res.reason
    geo, why = pl.geodesic_distance(left, right)
    assert geo == math.inf and why
    res = pl.shortest_path(left, np.array([50.0, 50.0, 0.0]))
    assert res.length == math.inf and "off the navigable map" in res.reason
    res = pl.shortest_path(np.array([np.nan, 0.0, 0.0]), right)
    assert res.length == math.inf and "not finite" in res.reason
    assert pl.distance_field(np.array([50.0, 0.0, 0.0])).distance(left) == math.inf


def test_stairs_connect_the_storeys():
    w, m, g, pl = setup("stairs")
    low, high = w.camera_positions[0] - [0, 0, 1.5], w.camera_positions[1] - [0, 0, 1.5]
    res = pl.shortest_path(low, high)
    assert res.reachable
    assert np.all(np.abs(np.diff(res.waypoints[1:-1, 2])) <= g.embodiment.max_step_height + 0.011)
    # The path climbs in the stair lane (y < 1.2) between the storeys.
    mid = res.waypoints[(res.waypoints[:, 2] > 0.1) & (res.waypoints[:, 2] < 1.1)]
    assert len(mid) and mid[:, 1].max() < 1.2


def test_graph_save_load_round_trip(tmp_path):
    _, _, g, pl = setup("L")
    back = NavGraph.load(g.save(tmp_path / "navgraph.npz"))
    assert back.num_edges == g.num_edges
    assert abs(back.cost - g.cost).max() < 1e-12
    with pytest.raises(FileNotFoundError):
        NavGraph.load(tmp_path / "nope.npz")


def test_smooth_path_keeps_endpoints_and_is_a_moving_average():
    rng = np.random.default_rng(8)
    pts = np.cumsum(rng.normal(size=(20, 3)), axis=0)
    out = smooth_path(pts, 5)
    assert np.allclose(out[0], pts[0]) and np.allclose(out[-1], pts[-1])
    assert np.allclose(out[5], pts[3:8].mean(axis=0))
    assert np.allclose(out[1], pts[0:3].mean(axis=0))
    assert np.allclose(smooth_path(pts, 1), pts)
    assert smooth_path(pts[:2], 5).shape == (2, 3)


def run_follower(name: str, n_pairs: int, seed: int):
    w, m, g, pl = setup(name)
    world = CollisionWorld(m)
    ok = collided = 0
    for a, b in random_pairs(g, n_pairs, seed):
        agent = Agent(world)
        rng = np.random.default_rng(a)
        agent.reset(g.nodes[a], rng.uniform(-math.pi, math.pi))
        follower = OracleFollower(pl, kinematics=agent.kinematics)
        follower.reset(g.nodes[a], g.nodes[b])
        hit = False
        action = None
        for _ in range(600):
            action = follower.act(agent.state, hit)
            if action == Action.STOP:
                break
            hit = agent.step(action).collided
            collided += hit
        d = np.linalg.norm(agent.state.position[:2] - g.nodes[b][:2])
        ok += action == Action.STOP and d <= 0.25
    return ok / n_pairs, collided


@pytest.mark.slow  # 200 episodes: ~25 s on the shared machine
def test_oracle_follower_reaches_goals_without_collisions():
    rate, collisions = run_follower("rooms", 200, seed=9)
    assert rate >= 0.99
    assert collisions == 0


def test_oracle_follower_smoke():
    rate, collisions = run_follower("gap", 15, seed=10)
    assert rate == 1.0 and collisions == 0


def test_reference_follower_walks_a_detour_that_passes_its_own_end():
    """A route out to W and back to its end G, which it passed on the way out: the follower must
    neither stop at G on the way out nor skip to the way back where both legs run side by side."""
    w, m, g, pl = setup("box")
    world = CollisionWorld(m)
    z = float(g.nodes[0, 2])
    start, end, far = np.array([1.0, 2.0, z]), np.array([2.2, 2.0, z]), np.array([4.5, 2.0, z])
    out = np.linspace(start, far, 36)
    back = np.linspace(far, end, 24)[1:]
    route = np.vstack((out, back))
    agent = Agent(world)
    agent.reset(start, 0.0)
    follower = ReferencePathFollower(pl, route, kinematics=agent.kinematics)
    follower.reset(start)
    xs, hit, action = [], False, None
    for _ in range(400):
        action = follower.act(agent.state, hit)
        if action == Action.STOP:
            break
        hit = agent.step(action).collided
        xs.append(agent.state.position[0])
    assert action == Action.STOP
    assert max(xs) > far[0] - 0.3  # went out to W
    assert np.linalg.norm(agent.state.position[:2] - end[:2]) <= 0.25  # and stopped at the end
