"""Floors of navigable-area extraction (:mod:`.extract`, steps 3-5 of its pipeline): floor voxels
covered from above, merged into one cell per column, connected into components (kept when under a
capture camera), clustered into storeys by height, and each storey's occlusion holes filled."""

from __future__ import annotations

import numpy as np
from image2sim.simulator.navigation.clearance import disk
from image2sim.simulator.navigation.embodiment import Embodiment, NavMapConfig
from image2sim.simulator.navigation.navmap import HEIGHT_TOLERANCE
from image2sim.simulator.navigation.pointcloud import band_columns, pack_keys
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = [
    "cluster_levels",
    "covered_from_above",
    "drop_furniture_tops",
    "fill_holes",
    "floor_components",
    "merge_floor_columns",
    "select_components",
]


def covered_from_above(f_ijk: np.ndarray, o_ijk: np.ndarray, n_above: int) -> np.ndarray:
    """True for floor voxels that have an obstacle voxel 1..n_above voxels above in their column."""
    if len(f_ijk) == 0 or len(o_ijk) == 0:
        return np.zeros(len(f_ijk), dtype=bool)
    okeys = np.sort(pack_keys(o_ijk))
    out = np.zeros(len(f_ijk), dtype=bool)
    for dk in range(1, n_above + 1):
        q = pack_keys(f_ijk + np.array([0, 0, dk]))
        pos = np.clip(np.searchsorted(okeys, q), 0, len(okeys) - 1)
        out |= okeys[pos] == q
    return out


def merge_floor_columns(
    f_ijk: np.ndarray, f_z: np.ndarray, f_w: np.ndarray, shape: tuple[int, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge floor voxels of one column whose k differ by <= 1 into cells (weighted mean height).

    Returns (cell index of every voxel, cell columns (C, 2), cell heights (C,)).
    """
    if len(f_ijk) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2), np.int64), np.zeros(0)
    col = f_ijk[:, 0] * shape[1] + f_ijk[:, 1]
    order = np.lexsort((f_ijk[:, 2], col))
    col_s, k_s = col[order], f_ijk[order, 2]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (col_s[1:] != col_s[:-1]) | (k_s[1:] - k_s[:-1] > 1)
    cell_sorted = np.cumsum(new) - 1
    cell = np.empty(len(order), dtype=np.int64)
    cell[order] = cell_sorted
    n_cells = int(cell_sorted[-1]) + 1
    wsum = np.bincount(cell, weights=f_w, minlength=n_cells)
    z = np.bincount(cell, weights=f_z * f_w, minlength=n_cells) / wsum
    ij = np.zeros((n_cells, 2), dtype=np.int64)
    ij[cell] = f_ijk[:, :2]
    return cell, ij, z


def floor_components(
    c_ij: np.ndarray, c_z: np.ndarray, max_step: float, planar_tol: float = 0.03, bridge: int = 3
) -> np.ndarray:
    """Connected-component id of every floor cell.

    Cells whose 8-neighbours (within the step height) all lie within ``planar_tol`` in height are
    *planar*. Planar cells connect when they lie within ``bridge`` cells (Chebyshev) of each other
    and their heights differ by at most ``max_step``: this crosses the two non-planar cells around a
    stair riser, but not the steep "ramps" that blended normals leave on the sides of beds and
    tables (those would chain the floor to furniture tops in steps below ``max_step``). Each
    non-planar cell then joins the component of its planar neighbour closest in height.
    """
    n = len(c_z)
    if n == 0:
        return np.zeros(0, np.int64)
    step = max(max_step + HEIGHT_TOLERANCE, 1e-6)
    # Chebyshev ball in (i, j, z * bridge / step): |di|, |dj| <= bridge and |dz| <= step.
    coords = np.column_stack((c_ij.astype(np.float64), c_z * (bridge / step)))
    pairs = cKDTree(coords).query_pairs(r=bridge + 1e-9, p=np.inf, output_type="ndarray")
    if len(pairs) == 0:
        return np.arange(n, dtype=np.int64)
    a, b = pairs[:, 0], pairs[:, 1]
    cheb = np.abs(c_ij[a] - c_ij[b]).max(axis=1)
    dz = np.abs(c_z[a] - c_z[b])
    adjacent = cheb <= 1
    spread = np.zeros(n)
    np.maximum.at(spread, a[adjacent], dz[adjacent])
    np.maximum.at(spread, b[adjacent], dz[adjacent])
    planar = spread <= planar_tol
    both = planar[a] & planar[b]
    adj = coo_matrix((np.ones(int(both.sum())), (a[both], b[both])), shape=(n, n))
    _, labels = connected_components(adj, directed=False)
    labels = labels.astype(np.int64)
    # Non-planar cells take the label of the planar neighbour (<= 2 cells) closest in height.
    labels[~planar] = n + np.flatnonzero(~planar)  # singletons unless attached below
    near = (cheb <= 2) & (planar[a] != planar[b])
    src = np.where(planar[a[near]], a[near], b[near])
    dst = np.where(planar[a[near]], b[near], a[near])
    order = np.argsort(-dz[near], kind="stable")  # the smallest |dz| is written last and wins
    labels[dst[order]] = labels[src[order]]
    return labels


TYPICAL_HEIGHT_BAND = 0.2
"""Metres a camera's drop to a cell may differ from the typical camera height for the cell to seed
at that height. It covers cameras held higher or lower than the others; a bed or a sofa top
(0.4-0.6 m) must stay outside it for a camera raised by a decimetre or two: at 0.3 m, a camera
0.12 m above the others over a bed with noisy low cells seeded the bed (procedural house 9202,
pinhole, tier middle; docs/navigation.md, session 52)."""


def select_components(
    comp: np.ndarray,
    c_ij: np.ndarray,
    c_z: np.ndarray,
    cams: np.ndarray | None,
    origin: np.ndarray,
    vox: float,
    cfg: NavMapConfig,
    notes: list[str],
    emb: Embodiment,
) -> np.ndarray:
    """Component ids to keep: those supporting a capture camera, else the large enough ones that
    are not furniture tops (:func:`drop_furniture_tops`)."""
    xy = origin[:2] + (c_ij + 0.5) * vox
    if cams is not None and len(cams):
        tree = cKDTree(xy)
        cands = []
        for cam in cams:
            cand = np.asarray(tree.query_ball_point(cam[:2], r=cfg.camera_support_radius), dtype=np.int64)
            cands.append(cand[c_z[cand] <= cam[2] - cfg.min_camera_height])
        # Pass 1: the typical camera height of the capture, from each camera's drop to the lowest
        # surface within reach. Not the drop to its nearest cell: a forward-looking camera often
        # sees no floor at its feet, and its nearest cell is then a bed or a table beside it.
        typical = typical_camera_height(cands, cams, c_z, vox)
        # Pass 2: prefer cells at that height below the camera (on stairs the nearest cell may be
        # another flight); fall back to the nearest cell.
        seeds, fallback = [], []
        for cand, cam in zip(cands, cams, strict=True):
            if not len(cand):
                continue
            d = np.linalg.norm(xy[cand] - cam[:2], axis=1)
            at_typical = typical is not None and bool(
                (ok := np.abs(cam[2] - c_z[cand] - typical) <= TYPICAL_HEIGHT_BAND).any()
            )
            if at_typical:
                cand, d = cand[ok], d[ok]
            (seeds if at_typical or typical is None else fallback).append(comp[cand[np.argmin(d)]])
        missing = len(cams) - len(seeds) - len(fallback)
        if missing:
            notes.append(
                f"{missing} of {len(cams)} cameras have no floor below within {cfg.camera_support_radius} m"
            )
        if seeds or fallback:
            return _keep_seeded(np.unique(seeds), np.unique(fallback), comp, c_z, emb, notes)
        notes.append("no camera lies above a floor: kept components by area instead")
    area = np.bincount(comp) * vox * vox
    keep = np.flatnonzero(area >= cfg.min_component_area)
    if len(keep) == 0 and len(area):
        keep = np.array([int(np.argmax(area))])
    return drop_furniture_tops(keep, comp, c_z, emb, notes)


def typical_camera_height(
    cands: list[np.ndarray], cams: np.ndarray, c_z: np.ndarray, vox: float, min_cells: int = 5
) -> float | None:
    """The height of the capture's cameras above their floor, or None without candidates.

    Per camera, its drop to the lowest surface among the floor cells ``cands`` within its reach that
    holds at least ``min_cells`` cells in a band of three ``vox`` bins (a floor is the lowest surface
    under a camera; the count keeps stray cells below it out), as the median drop in that band;
    the median over the cameras (a camera beside a stairwell sees a lower storey). A camera whose
    cells are too few or too scattered to form such a surface says nothing."""
    per_camera = []
    for c, cam in zip(cands, cams, strict=True):
        if not len(c):
            continue
        d = cam[2] - c_z[c]
        bins = np.floor((d - d.min()) / vox).astype(np.int64)
        counts = np.convolve(np.bincount(bins), np.ones(3))[1:-1]  # cells in bins b-1..b+1
        surfaces = np.flatnonzero(counts >= min(min_cells, len(d)))
        if not len(surfaces):
            continue
        lowest = int(surfaces.max())
        per_camera.append(float(np.median(d[np.abs(bins - lowest) <= 1])))
    return float(np.median(per_camera)) if per_camera else None


def _keep_seeded(
    seeds: np.ndarray, fallback: np.ndarray, comp: np.ndarray, c_z: np.ndarray, emb: Embodiment, notes: list
) -> np.ndarray:
    """Components seeded at the capture's typical camera height, and those seeded by the nearest
    cell of a camera that has no floor at that height within reach, unless they are furniture tops
    above a typically seeded one. A forward-looking camera often sees no floor near its feet, and
    its nearest cell is then a bed or a table beside it."""
    extra = np.setdiff1d(fallback, seeds)
    if not len(extra) or not len(seeds):
        return np.union1d(seeds, fallback)
    kept = drop_furniture_tops(np.concatenate((seeds, extra)), comp, c_z, emb, notes)
    return np.union1d(seeds, kept)


def drop_furniture_tops(
    keep: np.ndarray, comp: np.ndarray, c_z: np.ndarray, emb: Embodiment, notes: list[str]
) -> np.ndarray:
    """``keep`` without the components that stand above another kept one by more than a step and
    less than the body height: a bed or a large table passes an area test, but no storey is that
    close above another floor (the body would not fit between them). Stairs joining two storeys
    make them one component, so they stay."""
    if len(keep) < 2:
        return keep
    height = np.array([float(np.median(c_z[comp == k])) for k in keep])
    rise = height[:, None] - height[None, :]  # row above column
    tops = ((rise > emb.max_step_height) & (rise < emb.height)).any(axis=1)
    if tops.any():
        notes.append(
            f"dropped {int(tops.sum())} large floor-like component(s) {emb.max_step_height}-{emb.height} m "
            "above another (furniture tops)"
        )
    return keep[~tops]


def cluster_levels(c_z: np.ndarray, vox: float, min_area: float, min_separation: float) -> np.ndarray:
    """Storey heights from a height histogram of floor cells (peaks >= min_area, >= min_separation apart)."""
    lo = float(c_z.min())
    bins = np.floor((c_z - lo) / vox).astype(np.int64)
    area = np.bincount(bins).astype(np.float64) * vox * vox
    # Sum over 3 neighbouring bins so a floor straddling a bin edge counts once, whole.
    smooth = np.convolve(area, np.ones(3), mode="same")
    order = np.argsort(-smooth, kind="stable")
    peaks: list[int] = []
    for b in order:
        if smooth[b] < min_area:
            break
        if all(abs(int(b) - p) * vox >= min_separation for p in peaks):
            peaks.append(int(b))
    if not peaks:  # a small scene: its single most populated height is the storey
        peaks = [int(order[0])]
    heights = []
    for p in sorted(peaks):
        sel = np.abs(bins - p) <= 1
        heights.append(float(np.median(c_z[sel])))
    return np.asarray(heights)


def fill_holes(
    c_ij: np.ndarray,
    c_z: np.ndarray,
    c_level: np.ndarray,
    level_heights: np.ndarray,
    level_planes: np.ndarray,
    obstacle_ij: np.ndarray,
    obstacle_z: np.ndarray,
    origin: np.ndarray,
    vox: float,
    shape: tuple[int, ...],
    emb: Embodiment,
    cfg: NavMapConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Morphological closing of each storey's floor mask; new cells lie on the storey plane.

    Cells are not added in columns that already hold a floor within a body height of the storey
    (stairs, the storey itself) nor where an obstacle stands in the storey's body band.
    """
    r = int(cfg.closing_radius_cells)
    shape2d = (int(shape[0]), int(shape[1]))
    empty = (np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0, np.int64))
    if r <= 0 or len(level_heights) == 0:
        return empty
    out_ij, out_z, out_l = [], [], []
    struct = disk(r)
    for li, h in enumerate(level_heights):
        a, b, c, d = level_planes[li]
        member = (c_level == li) & (np.abs(c_z - h) <= cfg.level_tolerance)
        if not member.any():
            continue
        mask = np.zeros(shape2d, dtype=bool)
        mask[c_ij[member, 0], c_ij[member, 1]] = True
        closed = ndimage.binary_closing(np.pad(mask, r), structure=struct)[r:-r, r:-r]
        near = np.abs(c_z - h) < emb.height
        occupied = np.zeros(shape2d, dtype=bool)
        occupied[c_ij[near, 0], c_ij[near, 1]] = True
        occupied |= band_columns(
            obstacle_ij, obstacle_z, h + emb.max_step_height + HEIGHT_TOLERANCE, h + emb.height, shape2d
        )
        new = closed & ~mask & ~occupied
        ij = np.argwhere(new)
        if len(ij) == 0:
            continue
        xy = origin[:2] + (ij + 0.5) * vox
        z = -(d + a * xy[:, 0] + b * xy[:, 1]) / c
        out_ij.append(ij)
        out_z.append(z)
        out_l.append(np.full(len(ij), li, dtype=np.int64))
    if not out_ij:
        return empty
    return np.concatenate(out_ij), np.concatenate(out_z), np.concatenate(out_l)
