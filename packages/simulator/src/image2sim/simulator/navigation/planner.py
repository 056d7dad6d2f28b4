"""Planning on a :class:`NavGraph`: snapped shortest paths, geodesic distances, goal distance fields.

Two metrics live on the same graph: the *planning cost* (directed, collision-aware, see
:mod:`.graph`) chooses paths; the *geodesic distance* (shortest path length in metres, symmetric)
is what navigation metrics report. Failures never raise: they return ``inf`` with a reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from image2sim.simulator.navigation.graph import NavGraph
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

__all__ = ["PathResult", "DistanceField", "Planner"]


@dataclass
class PathResult:
    """Outcome of a path query (map frame).

    Attributes:
        waypoints: (P, 3) start point, node positions along the path, goal point (empty if unreachable).
        nodes: (P - 2,) graph node ids along the path.
        length: metres along the waypoints (inf when unreachable).
        cost: summed directed arc costs between the snapped nodes (inf when unreachable).
        reason: "" on success, else why there is no path.
    """

    waypoints: np.ndarray
    nodes: np.ndarray
    length: float
    cost: float
    reason: str = ""

    @property
    def reachable(self) -> bool:
        return bool(np.isfinite(self.length))


@dataclass
class DistanceField:
    """Distances from every node to one goal (one Dijkstra), then cheap lookups per query.

    ``distance(p)`` = horizontal offset of ``p`` to its snapped node + the node's distance to the
    goal node + the goal point's offset to that node. When the snapped node cannot reach the goal
    (or ``p`` snaps to no node), ``p`` snaps instead to the nearest node that *can* reach it within
    :attr:`reach_radius` horizontally (and a body height vertically), plus the horizontal remainder:
    an agent that stops next to a wall, beside a pocket of nodes the graph left unconnected, still
    gets a finite distance. Otherwise the distance is inf and :meth:`query` says why.
    """

    graph: NavGraph
    goal: np.ndarray
    goal_node: int
    node_distance: np.ndarray
    goal_offset: float
    reason: str = ""
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def reach_radius(self) -> float:
        """Horizontal radius (m) of the fallback snap to a goal-connected node: the agent radius
        plus two cells (an agent stopped against a wall is within it of a node it can stand on)."""
        return float(self.graph.embodiment.radius + 2.0 * self.graph.voxel_size)

    def _reachable(self) -> tuple[np.ndarray, cKDTree | None]:
        """Ids of the nodes with a finite distance to the goal and a 2D KD-tree over them (cached)."""
        if "reach" not in self._cache:
            ids = np.flatnonzero(np.isfinite(self.node_distance))
            self._cache["reach"] = (ids, cKDTree(self.graph.nodes[ids, :2]) if len(ids) else None)
        return self._cache["reach"]

    def _snap_reachable(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest node with a finite distance to the goal within :attr:`reach_radius` horizontally
        and a body height vertically -> (node ids (N,), horizontal offsets (N,)); -1 / inf if none."""
        idx = np.full(len(p), -1, np.int64)
        off = np.full(len(p), np.inf)
        ids, tree = self._reachable()
        if tree is None:
            return idx, off
        for k, cand in enumerate(tree.query_ball_point(p[:, :2], self.reach_radius)):
            if not cand:
                continue
            nodes = ids[np.asarray(cand, dtype=np.int64)]
            d = np.linalg.norm(self.graph.nodes[nodes, :2] - p[k, :2], axis=1)
            d[np.abs(self.graph.nodes[nodes, 2] - p[k, 2]) > self.graph.embodiment.height] = np.inf
            best = int(np.argmin(d))
            if np.isfinite(d[best]):
                idx[k], off[k] = nodes[best], d[best]
        return idx, off

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Geodesic distance (metres) of map-frame feet positions (N, 3) or (3,) to the goal."""
        p = np.asarray(points, dtype=np.float64)
        single = p.ndim == 1
        p2 = np.atleast_2d(p)
        idx, off = self.graph.snap(p2)
        out = np.full(len(idx), np.inf)
        ok = idx >= 0
        out[ok] = self.node_distance[idx[ok]] + off[ok] + self.goal_offset
        miss = ~np.isfinite(out) & np.isfinite(p2).all(axis=1)
        if self.goal_node >= 0 and miss.any():
            j, o = self._snap_reachable(p2[miss])
            sel = np.flatnonzero(miss)[j >= 0]
            out[sel] = self.node_distance[j[j >= 0]] + o[j >= 0] + self.goal_offset
        return out[0] if single else out

    def query(self, point: np.ndarray) -> tuple[float, str]:
        """Distance of one position and, when it is inf, why ("" otherwise)."""
        p = np.asarray(point, dtype=np.float64).reshape(3)
        if not np.isfinite(p).all():
            return float("inf"), f"position {p.tolist()} is not finite"
        d = float(self.distance(p))
        if np.isfinite(d):
            return d, ""
        if self.goal_node < 0:
            return d, self.reason
        idx, _ = self.graph.snap(p[None])
        where = np.round(p, 3).tolist()
        if idx[0] < 0:
            return d, (
                f"position {where} is off the navigable map (no node within "
                f"{self.graph.config.max_snap_distance} m horizontally and a body height vertically)"
            )
        return d, (
            f"position {where} snaps to node {int(idx[0])}, which is not connected to goal node "
            f"{self.goal_node}, and no node connected to the goal lies within {self.reach_radius:.3f} m"
        )

    def approximate(self, point: np.ndarray) -> tuple[float, str]:
        """An upper-bound estimate for a position :meth:`query` cannot place: the nearest
        goal-connected node on the same storey (within a body height vertically), at any horizontal
        distance, plus the straight horizontal offset to it.

        For evaluation only: an agent whose kinematics squeezed it somewhere the conservative graph
        does not connect (a gap narrower than the graph's clearance, a pocket behind furniture) did
        get there from a connected start, so the goal is reachable; the estimate lets its episode
        count instead of aborting the run. Returns (inf, reason) when nothing is connected to the goal.
        """
        p = np.asarray(point, dtype=np.float64).reshape(3)
        if not np.isfinite(p).all():
            return float("inf"), f"position {p.tolist()} is not finite"
        if self.goal_node < 0:
            return float("inf"), self.reason
        ids, _ = self._reachable()
        same_storey = np.abs(self.graph.nodes[ids, 2] - p[2]) <= self.graph.embodiment.height
        if not same_storey.any():
            return float("inf"), (
                f"position {np.round(p, 3).tolist()}: no goal-connected node within a body height vertically"
            )
        ids = ids[same_storey]
        offsets = np.linalg.norm(self.graph.nodes[ids, :2] - p[:2], axis=1)
        best = int(np.argmin(offsets))
        node = int(ids[best])
        return float(self.node_distance[node] + offsets[best] + self.goal_offset), (
            f"approximate: position {np.round(p, 3).tolist()} is not connected to the goal on the graph; "
            f"nearest goal-connected node {node} is {offsets[best]:.3f} m away horizontally"
        )

    def __call__(self, point: np.ndarray) -> float:
        """Scalar distance of one position (fast path for per-step evaluation)."""
        return float(self.distance(np.asarray(point, dtype=np.float64).reshape(3)))


class Planner:
    """Shortest paths (planning cost) and geodesic distances (metres) on a navigation graph."""

    def __init__(self, graph: NavGraph) -> None:
        self.graph = graph
        self._cost_t = graph.cost.T.tocsr()

    # --- helpers --------------------------------------------------------------------------
    def _snap_one(self, point: np.ndarray, what: str) -> tuple[int, float, str]:
        p = np.asarray(point, dtype=np.float64).reshape(3)
        if not np.isfinite(p).all():
            return -1, np.inf, f"{what} {p.tolist()} is not finite"
        if self.graph.num_nodes == 0:
            return -1, np.inf, "the navigation graph is empty"
        idx, off = self.graph.snap(p[None])
        if idx[0] < 0:
            return (
                -1,
                np.inf,
                (
                    f"{what} {np.round(p, 3).tolist()} is off the navigable map "
                    f"(no node within {self.graph.config.max_snap_distance} m horizontally "
                    "and a body height vertically)"
                ),
            )
        return int(idx[0]), float(off[0]), ""

    def _unreachable(self, reason: str) -> PathResult:
        return PathResult(np.zeros((0, 3)), np.zeros(0, np.int64), float("inf"), float("inf"), reason)

    # --- queries --------------------------------------------------------------------------
    def shortest_path(self, start: np.ndarray, goal: np.ndarray) -> PathResult:
        """Minimum-cost path between two map-frame feet positions, as 3D waypoints."""
        s, s_off, why = self._snap_one(start, "start")
        if why:
            return self._unreachable(why)
        g, g_off, why = self._snap_one(goal, "goal")
        if why:
            return self._unreachable(why)
        if self.graph.components[s] != self.graph.components[g]:
            return self._unreachable(
                f"start node {s} and goal node {g} lie in different connected components"
            )
        dist, pred = dijkstra(self.graph.cost, directed=True, indices=s, return_predecessors=True)
        if not np.isfinite(dist[g]):
            return self._unreachable(f"goal node {g} is not reachable from start node {s}")
        chain = [g]
        while chain[-1] != s:
            chain.append(int(pred[chain[-1]]))
        nodes = np.asarray(chain[::-1], dtype=np.int64)
        pts = np.vstack(
            (
                np.asarray(start, float).reshape(1, 3),
                self.graph.nodes[nodes],
                np.asarray(goal, float).reshape(1, 3),
            )
        )
        length = float(np.linalg.norm(np.diff(pts[1:-1], axis=0), axis=1).sum()) + s_off + g_off
        return PathResult(pts, nodes, length, float(dist[g]))

    def geodesic_distance(self, start: np.ndarray, goal: np.ndarray) -> tuple[float, str]:
        """Shortest path length in metres (symmetric, ignores clearance penalties) and a reason if inf."""
        s, s_off, why = self._snap_one(start, "start")
        if why:
            return float("inf"), why
        g, g_off, why = self._snap_one(goal, "goal")
        if why:
            return float("inf"), why
        if self.graph.components[s] != self.graph.components[g]:
            return float("inf"), f"start node {s} and goal node {g} lie in different connected components"
        d = dijkstra(self.graph.length_matrix, directed=False, indices=s)[g]
        return float(d + s_off + g_off), ""

    def distance_field(self, goal: np.ndarray, weighted: bool = False) -> DistanceField:
        """Distance of every node to ``goal``: metres (default) or planning cost (``weighted``).

        The cost field runs Dijkstra on the transposed directed graph, i.e. it is the cost of
        travelling *to* the goal.
        """
        g, g_off, why = self._snap_one(goal, "goal")
        if why:
            return DistanceField(
                self.graph, np.asarray(goal, float), -1, np.full(self.graph.num_nodes, np.inf), np.inf, why
            )
        if weighted:
            d = dijkstra(self._cost_t, directed=True, indices=g)
        else:
            d = dijkstra(self.graph.length_matrix, directed=False, indices=g)
        return DistanceField(self.graph, np.asarray(goal, float), g, d, g_off)

    def path_from_field(
        self, field_: DistanceField, start: np.ndarray, max_nodes: int = 1_000_000
    ) -> PathResult:
        """Greedy descent of a *weighted* distance field from ``start`` (same path as Dijkstra ties aside)."""
        s, s_off, why = self._snap_one(start, "start")
        if why or field_.goal_node < 0:
            return self._unreachable(why or field_.reason)
        if not np.isfinite(field_.node_distance[s]):
            return self._unreachable(f"start node {s} cannot reach goal node {field_.goal_node}")
        cost = self.graph.cost
        chain = [s]
        while chain[-1] != field_.goal_node and len(chain) < max_nodes:
            i = chain[-1]
            nb = cost.indices[cost.indptr[i] : cost.indptr[i + 1]]
            w = cost.data[cost.indptr[i] : cost.indptr[i + 1]]
            chain.append(int(nb[np.argmin(w + field_.node_distance[nb])]))
        nodes = np.asarray(chain, dtype=np.int64)
        pts = np.vstack(
            (np.asarray(start, float).reshape(1, 3), self.graph.nodes[nodes], field_.goal.reshape(1, 3))
        )
        length = float(np.linalg.norm(np.diff(pts[1:-1], axis=0), axis=1).sum()) + s_off + field_.goal_offset
        return PathResult(pts, nodes, length, float(field_.node_distance[s]))
