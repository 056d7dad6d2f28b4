"""Distance-field lookups of positions just off the graph: snap to the nearest goal-connected node."""

from __future__ import annotations

import functools
import math

import numpy as np
from image2sim.simulator.navigation import synthetic as syn
from image2sim.simulator.navigation.extract import extract_navmap_from_points
from image2sim.simulator.navigation.graph import NavGraph
from image2sim.simulator.navigation.planner import Planner


@functools.cache
def graph(name: str) -> NavGraph:
    w = {
        "box": lambda: syn.box_room(spacing=0.04),
        "narrow": lambda: syn.wall_with_gap(gap_width=0.25, spacing=0.04),
    }[name]()
    m = extract_navmap_from_points(w.points, w.normals, camera_positions=w.camera_positions)
    return NavGraph.build(m)


def cut_pocket(g: NavGraph, centre: int, radius: float) -> tuple[NavGraph, np.ndarray]:
    """A copy of ``g`` whose nodes within ``radius`` of node ``centre`` keep only edges among
    themselves: a pocket the graph left unconnected (as a failed ray march next to a wall does)."""
    pocket = np.flatnonzero(np.linalg.norm(g.nodes[:, :2] - g.nodes[centre, :2], axis=1) <= radius)
    inside = np.zeros(g.num_nodes, bool)
    inside[pocket] = True
    keep = inside[g.edges[:, 0]] == inside[g.edges[:, 1]]
    edges, lengths = g.edges[keep], g.lengths[keep]
    cost, length_matrix = NavGraph._matrices(
        g.num_nodes, edges, lengths, g.clearance, g.embodiment.radius, g.config
    )
    cut = NavGraph(
        g.nodes,
        g.clearance,
        g.level,
        edges,
        lengths,
        cost,
        length_matrix,
        g.embodiment,
        g.config,
        g.voxel_size,
    )
    return cut, pocket


def test_position_next_to_a_wall_beside_an_unconnected_pocket_snaps_to_a_connected_node():
    g0 = graph("box")
    # The node hugging the wall (lowest clearance) at the middle of the room's y range.
    low = np.flatnonzero(g0.clearance <= g0.clearance.min() + 1e-9)
    mid = low[np.argmin(np.abs(g0.nodes[low, 1] - np.median(g0.nodes[:, 1])))]
    g, pocket = cut_pocket(g0, int(mid), 0.06)
    assert len(pocket) >= 2 and len(np.unique(g.components[pocket])) == 1
    assert g.components[pocket[0]] != g.components[np.argmax(g.clearance)]
    pl = Planner(g)
    goal = g.nodes[np.argmax(g.clearance)]  # room centre, in the main component
    field = pl.distance_field(goal)
    # Just off the graph: 2 cm from the wall-side node, towards the wall (away from the room centre).
    away = g.nodes[mid, :2] - goal[:2]
    p = g.nodes[mid] + np.append(0.02 * away / np.linalg.norm(away), 0.0)
    snap_idx, _ = g.snap(p[None])
    assert snap_idx[0] in pocket  # the plain snap lands in the pocket: the old lookup gave inf
    # Reference: brute force over every node connected to the goal (same storey here).
    conn = np.flatnonzero(g.components == g.components[np.argmax(g.clearance)])
    off = np.linalg.norm(g.nodes[conn, :2] - p[:2], axis=1)
    nearest = conn[np.argmin(off)]
    assert off.min() <= field.reach_radius
    geo, why = pl.geodesic_distance(g.nodes[nearest], goal)
    assert not why
    d, reason = field.query(p)
    assert reason == "" and math.isfinite(d)
    assert abs(d - (geo + off.min())) < 1e-9
    # Vectorised lookups agree with the scalar one; an on-graph point keeps the plain snap.
    on = g.nodes[np.argmax(g.clearance)] + np.array([0.3, 0.0, 0.0])
    both = field.distance(np.stack([p, on]))
    assert both[0] == d and both[1] == field(on) and math.isfinite(both[1])


def test_position_beyond_the_reach_radius_of_connected_nodes_stays_inf_with_reason():
    g0 = graph("box")
    centre = int(np.argmax(g0.clearance))
    g, pocket = cut_pocket(g0, centre, 0.6)  # a large island around the room centre
    pl = Planner(g)
    outside = np.flatnonzero(g.components != g.components[centre])
    goal = g.nodes[outside[0]]
    field = pl.distance_field(goal)
    d, reason = field.query(g.nodes[centre])
    assert d == math.inf
    assert "not connected to goal node" in reason and f"{field.reach_radius:.3f} m" in reason


def test_position_in_a_disconnected_component_gives_inf_with_a_reason():
    g = graph("narrow")  # a wall whose 0.25 m gap is too narrow for the body: two components
    pl = Planner(g)
    left = g.nodes[g.nodes[:, 0] < 2.5]
    right = g.nodes[g.nodes[:, 0] > 3.5]
    field = pl.distance_field(left[len(left) // 2])
    # The right-hand node nearest to the wall: as close to the goal's side as the body can get.
    p = right[np.argmin(right[:, 0])]
    d, reason = field.query(p)
    assert d == math.inf and field(p) == math.inf
    assert "not connected to goal node" in reason
    d, reason = field.query(np.array([50.0, 50.0, 0.0]))
    assert d == math.inf and "off the navigable map" in reason
    d, reason = field.query(np.array([np.nan, 0.0, 0.0]))
    assert d == math.inf and "not finite" in reason
    off_map_goal = pl.distance_field(np.array([50.0, 0.0, 0.0]))
    d, reason = off_map_goal.query(left[0])
    assert d == math.inf and "goal" in reason and "off the navigable map" in reason


def test_approximate_distance_of_a_cut_off_position_is_nearest_connected_node_plus_offset():
    g0 = graph("box")
    centre = int(np.argmax(g0.clearance))
    g, pocket = cut_pocket(g0, centre, 0.6)
    pl = Planner(g)
    outside = np.flatnonzero(g.components != g.components[centre])
    goal = g.nodes[outside[0]]
    field = pl.distance_field(goal)
    p = g.nodes[centre]
    assert field.query(p)[0] == math.inf
    d, reason = field.approximate(p)
    # Brute-force reference over the goal-connected nodes.
    off = np.linalg.norm(g.nodes[outside, :2] - p[:2], axis=1)
    nearest = outside[np.argmin(off)]
    geo, why = pl.geodesic_distance(g.nodes[nearest], goal)
    assert not why and off.min() > field.reach_radius
    assert abs(d - (geo + off.min())) < 1e-9
    assert reason.startswith("approximate:") and f"node {nearest}" in reason
    # Never for a goal off the map, a non-finite position, or another storey.
    assert pl.distance_field(np.array([50.0, 0.0, 0.0])).approximate(p)[0] == math.inf
    assert field.approximate(np.array([np.nan, 0.0, 0.0]))[0] == math.inf
    d, reason = field.approximate(p + np.array([0.0, 0.0, 5.0]))
    assert d == math.inf and "vertically" in reason


def test_largest_component_nodes_are_the_bigger_side_of_a_wall():
    g = graph("narrow")  # two components split by a wall the body cannot pass
    main = g.largest_component_nodes
    sizes = np.bincount(g.components)
    assert len(main) == sizes.max() and len(np.unique(g.components[main])) == 1
    assert np.all(np.diff(main) > 0)
