"""Traversable voxel graph M = (V, E) with directed, collision-aware edge costs.

Nodes are the navigable cells of a :class:`~image2sim.simulator.navigation.navmap.NavMap` (map frame,
floor height). Candidate neighbours lie within ``neighbor_radius`` (scipy cKDTree); an edge is kept
when the height change is within the maximum step height and a vectorised ray march between the pair
never enters a blocked column: an obstacle voxel in the body band above the (interpolated) floor
height, or a column without floor within the step height (holes, drops, unknown space). The cost of
entering node j is

    cost(i -> j) = d_ij + w_safe * (max(0, (r_safe - c_j) / r_safe))^2
                        + w_collision * max(0, (radius - c_j) / radius)

with c_j the EDT clearance of j and r_safe = r_safe_factor x radius; it depends on the target only, so
cost(i -> j) != cost(j -> i) whenever c_i != c_j (e.g. next to a wall).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from image2sim.simulator.io.atomic import atomic_open
from image2sim.simulator.navigation.embodiment import Embodiment, GraphConfig
from image2sim.simulator.navigation.navmap import HEIGHT_TOLERANCE, NavMap
from scipy import sparse
from scipy.spatial import cKDTree

__all__ = ["NavGraph", "edge_costs", "joined_storeys", "nearest_bin", "ray_march_free"]

GRAPH_FORMAT_VERSION = 1


def edge_costs(
    lengths: np.ndarray, target_clearance: np.ndarray, radius: float, config: GraphConfig
) -> np.ndarray:
    """Directed cost of edges of length ``lengths`` (m) entering nodes of clearance ``target_clearance``."""
    r_safe = config.r_safe_factor * radius
    safe = np.maximum(0.0, (r_safe - target_clearance) / r_safe) ** 2
    penetration = np.maximum(0.0, (radius - target_clearance) / radius)
    return lengths + config.w_safe * safe + config.w_collision * penetration


def nearest_bin(k: np.ndarray, bin_keys: np.ndarray) -> np.ndarray:
    """Index of the bin whose key is nearest to each integer height index ``k`` (ties: lower)."""
    pos = np.searchsorted(bin_keys, k)
    lo = np.clip(pos - 1, 0, len(bin_keys) - 1)
    hi = np.clip(pos, 0, len(bin_keys) - 1)
    return np.where(np.abs(bin_keys[hi] - k) < np.abs(bin_keys[lo] - k), hi, lo)


def ray_march_free(
    a: np.ndarray,
    b: np.ndarray,
    masks: np.ndarray,
    bin_keys: np.ndarray,
    origin: np.ndarray,
    voxel_size: float,
    step: float,
) -> np.ndarray:
    """True for segments a[i] -> b[i] (map frame, floor height) whose samples avoid blocked columns.

    ``masks`` (B, nx, ny) are the blocked columns of each floor-height bin; ``bin_keys`` (B,) the
    sorted height indices k = floor((z - origin_z) / voxel) of the bins. A sample at interpolated
    floor height z reads the mask of the bin nearest to its k. Samples are spaced at most ``step``
    apart and include both end points.
    """
    n = len(a)
    if n == 0:
        return np.zeros(0, dtype=bool)
    length = np.linalg.norm(b[:, :2] - a[:, :2], axis=1)
    n_samples = int(max(2, np.ceil(length.max() / step) + 1))
    t = np.linspace(0.0, 1.0, n_samples)
    # (n, S) sample coordinates; short edges are simply over-sampled.
    x = a[:, 0:1] + (b[:, 0:1] - a[:, 0:1]) * t
    y = a[:, 1:2] + (b[:, 1:2] - a[:, 1:2]) * t
    z = a[:, 2:3] + (b[:, 2:3] - a[:, 2:3]) * t
    i = np.floor((x - origin[0]) / voxel_size).astype(np.int64)
    j = np.floor((y - origin[1]) / voxel_size).astype(np.int64)
    _, nx, ny = masks.shape
    inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
    kb = nearest_bin(np.floor((z - origin[2]) / voxel_size).astype(np.int64), bin_keys)
    blocked = np.ones_like(inside)
    blocked[inside] = masks[kb[inside], i[inside], j[inside]]
    return ~blocked.any(axis=1)


def joined_storeys(graph: NavGraph, level_heights: np.ndarray, tolerance: float) -> list[tuple[int, int]]:
    """Pairs (a, b), a < b, of storeys that one graph component reaches both of.

    A storey is reached through its nodes within ``tolerance`` of its height (its floor plane), not
    through the nodes merely labelled with it: the lower treads of a flight cut off from the lower
    storey carry that storey's label, yet reach nothing there.
    """
    heights = np.asarray(level_heights, dtype=np.float64).reshape(-1)
    if graph.num_nodes == 0 or len(heights) < 2:
        return []
    on = np.abs(graph.nodes[:, 2, None] - heights[None, :]) <= tolerance  # (V, L)
    comp = graph.components
    # reached[c, l]: component c holds a node on storey l.
    reached = np.zeros((int(comp.max()) + 1, len(heights)), dtype=bool)
    rows, cols = np.nonzero(on)
    reached[comp[rows], cols] = True
    together = reached.T.astype(np.int64) @ reached.astype(np.int64)  # (L, L) shared components
    a, b = np.nonzero(np.triu(together, k=1))
    return [(int(i), int(j)) for i, j in zip(a, b, strict=True)]


@dataclass
class NavGraph:
    """The directed navigation graph; build it with :meth:`NavGraph.build`.

    Attributes:
        nodes: (V, 3) map-frame node positions (cell centres at floor height).
        clearance: (V,) EDT clearance of each node in metres.
        level: (V,) storey index of each node.
        edges: (E, 2) undirected node pairs (i < j) that passed the ray march.
        lengths: (E,) physical length of each edge in metres.
        cost: (V, V) CSR matrix of directed costs (both directions of every edge).
        length_matrix: (V, V) CSR matrix of physical lengths (symmetric).
        embodiment: the body the graph was built for.
        config: graph settings.
        voxel_size: cell size of the source map.
    """

    nodes: np.ndarray
    clearance: np.ndarray
    level: np.ndarray
    edges: np.ndarray
    lengths: np.ndarray
    cost: sparse.csr_matrix
    length_matrix: sparse.csr_matrix
    embodiment: Embodiment
    config: GraphConfig
    voxel_size: float = 0.05

    def __post_init__(self) -> None:
        self._tree: cKDTree | None = None
        self._components: np.ndarray | None = None

    # --- construction ---------------------------------------------------------------------
    @classmethod
    def build(cls, navmap: NavMap, config: GraphConfig | None = None, progress: bool = False) -> NavGraph:
        """Build the graph of a navigable map (see the module docstring for the rules)."""
        cfg = config or GraphConfig()
        emb = navmap.embodiment
        nodes = navmap.map_points
        clearance = navmap.clearance[navmap.navigable]
        level = navmap.floor_level[navmap.navigable]
        n = len(nodes)
        if n == 0:
            empty = sparse.csr_matrix((0, 0))
            return cls(
                nodes,
                clearance,
                level,
                np.zeros((0, 2), np.int64),
                np.zeros(0),
                empty,
                empty,
                emb,
                cfg,
                navmap.voxel_size,
            )
        pairs = cKDTree(nodes).query_pairs(r=cfg.neighbor_radius, output_type="ndarray").astype(np.int64)
        dz = np.abs(nodes[pairs[:, 0], 2] - nodes[pairs[:, 1], 2]) if len(pairs) else np.zeros(0)
        pairs = pairs[dz <= emb.max_step_height + HEIGHT_TOLERANCE]
        bin_keys, masks = navmap.blocked_stack()
        # Exact shortcut: if an endpoint's clearance exceeds the edge length plus one cell, no blocked
        # column can touch the segment (clearance bounds the distance to every blocked cell's points
        # and to unsupported cells' edges); only pairs in the same height bin qualify, so the march
        # would read that bin's mask at every sample.
        kz = np.floor((nodes[:, 2] - navmap.origin[2]) / navmap.voxel_size).astype(np.int64)
        d = np.linalg.norm(nodes[pairs[:, 0], :2] - nodes[pairs[:, 1], :2], axis=1)
        c = np.maximum(clearance[pairs[:, 0]], clearance[pairs[:, 1]])
        keep = (kz[pairs[:, 0]] == kz[pairs[:, 1]]) & (c >= d + navmap.voxel_size)
        todo = np.flatnonzero(~keep)
        chunks = range(0, len(todo), int(cfg.chunk_edges))
        bar = None
        if progress:
            from rich.progress import Progress

            bar = Progress(transient=True)
            bar.start()
            task = bar.add_task("ray-marching edges", total=len(chunks))
        try:
            for s in chunks:
                sel = todo[s : s + int(cfg.chunk_edges)]
                p = pairs[sel]
                keep[sel] = ray_march_free(
                    nodes[p[:, 0]],
                    nodes[p[:, 1]],
                    masks,
                    bin_keys,
                    navmap.origin,
                    navmap.voxel_size,
                    cfg.march_step,
                )
                if bar is not None:
                    bar.advance(task)
        finally:
            if bar is not None:
                bar.stop()
        edges = pairs[keep]
        lengths = np.linalg.norm(nodes[edges[:, 0]] - nodes[edges[:, 1]], axis=1)
        cost, length_matrix = cls._matrices(n, edges, lengths, clearance, emb.radius, cfg)
        return cls(nodes, clearance, level, edges, lengths, cost, length_matrix, emb, cfg, navmap.voxel_size)

    @staticmethod
    def _matrices(n, edges, lengths, clearance, radius, cfg):
        src = np.concatenate((edges[:, 0], edges[:, 1]))
        dst = np.concatenate((edges[:, 1], edges[:, 0]))
        d = np.concatenate((lengths, lengths))
        c = edge_costs(d, clearance[dst], radius, cfg)
        cost = sparse.csr_matrix((c, (src, dst)), shape=(n, n))
        length_matrix = sparse.csr_matrix((d, (src, dst)), shape=(n, n))
        return cost, length_matrix

    # --- queries --------------------------------------------------------------------------
    @property
    def num_nodes(self) -> int:
        return int(len(self.nodes))

    @property
    def num_edges(self) -> int:
        """Number of undirected edges (each contributes two directed arcs)."""
        return int(len(self.edges))

    @property
    def tree(self) -> cKDTree:
        """KD-tree over node positions with heights scaled x4 (snapping prefers the same storey)."""
        if self._tree is None:
            self._tree = cKDTree(self.nodes * np.array([1.0, 1.0, 4.0]))
        return self._tree

    @property
    def components(self) -> np.ndarray:
        """(V,) connected-component id of every node (weakly connected; the graph is symmetric)."""
        if self._components is None:
            from scipy.sparse.csgraph import connected_components

            _, self._components = connected_components(self.length_matrix, directed=False)
        return self._components

    @property
    def largest_component_nodes(self) -> np.ndarray:
        """Ids of the nodes in the largest connected component (sorted; empty for an empty graph):
        where episodes start and end, since an isolated node may stand under furniture."""
        if self.num_nodes == 0:
            return np.zeros(0, dtype=np.int64)
        comp = self.components
        return np.nonzero(comp == int(np.bincount(comp).argmax()))[0]

    def snap(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest node of map-frame feet positions (N, 3) -> (node ids (N,), horizontal offsets (N,)).

        Nodes farther than ``max_snap_distance`` horizontally, or more than a body height away
        vertically, give id -1 and offset inf.
        """
        p = np.atleast_2d(np.asarray(points, dtype=np.float64))
        if self.num_nodes == 0:
            return np.full(len(p), -1, np.int64), np.full(len(p), np.inf)
        finite = np.isfinite(p).all(axis=1)
        idx = np.zeros(len(p), dtype=np.int64)
        if finite.any():  # the KD-tree rejects non-finite queries
            idx[finite] = self.tree.query(p[finite] * np.array([1.0, 1.0, 4.0]))[1]
        off = np.linalg.norm(self.nodes[idx, :2] - p[:, :2], axis=1)
        dz = np.abs(self.nodes[idx, 2] - p[:, 2])
        bad = (off > self.config.max_snap_distance) | (dz > self.embodiment.height) | ~finite
        idx[bad] = -1
        off[bad] = np.inf
        return idx, off

    def arc_cost(self, i: int, j: int) -> float:
        """Directed cost of arc i -> j (inf when there is no edge)."""
        v = self.cost[i, j]
        return float(v) if v != 0 else float("inf")

    # --- persistence ----------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> Path:
        """Write ``navgraph.npz`` (no pickle) atomically."""
        path = Path(path)
        meta = {
            "format_version": GRAPH_FORMAT_VERSION,
            "embodiment": self.embodiment.to_dict(),
            "config": self.config.to_dict(),
            "voxel_size": self.voxel_size,
        }
        with atomic_open(path, "wb") as fh:
            np.savez_compressed(
                fh,
                meta_json=np.array(json.dumps(meta)),
                nodes=self.nodes,
                clearance=self.clearance,
                level=self.level,
                edges=self.edges.astype(np.int32),
                lengths=self.lengths,
            )
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> NavGraph:
        """Read a graph written by :meth:`save` (costs are recomputed from the stored config)."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: navigation graph file not found")
        with np.load(path, allow_pickle=False) as data:
            try:
                meta = json.loads(str(data["meta_json"]))
                if meta.get("format_version") != GRAPH_FORMAT_VERSION:
                    raise ValueError(
                        f"{path}: unsupported navgraph format_version {meta.get('format_version')!r}"
                    )
                emb = Embodiment.from_dict(meta["embodiment"], where=str(path))
                cfg = GraphConfig.from_dict(meta["config"], where=str(path))
                nodes = np.asarray(data["nodes"], np.float64)
                clearance = np.asarray(data["clearance"], np.float64)
                edges = np.asarray(data["edges"], np.int64)
                lengths = np.asarray(data["lengths"], np.float64)
                level = np.asarray(data["level"], np.int64)
            except KeyError as err:
                raise ValueError(f"{path}: navgraph file is missing field {err.args[0]!r}") from None
        cost, length_matrix = cls._matrices(len(nodes), edges, lengths, clearance, emb.radius, cfg)
        return cls(
            nodes, clearance, level, edges, lengths, cost, length_matrix, emb, cfg, float(meta["voxel_size"])
        )
