"""Clearance of a navigation map's floor cells: how far each stands from what the agent must keep
away from (step 6 of :mod:`.extract`).

Per floor-height band: the exact horizontal distance to the obstacle points in the body band, and
the distance to unsupported columns (no floor at the cell's height). Drops (floor at another height,
and unseen columns within a buffer of one) count as they are; for floor on a storey's plane, other
unseen columns count as standing ``safety_buffer - unknown_clearance`` farther out, so with
``NavMapConfig.unknown_clearance`` 0 (the default, the paper's rule) only obstacles and drops
project the safety buffer.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

if TYPE_CHECKING:
    from image2sim.simulator.navigation.navmap import NavMap

__all__ = ["floor_clearance", "edge_distance", "disk"]


def disk(radius: int) -> np.ndarray:
    """Boolean (2r + 1, 2r + 1) disk of cells within ``radius`` cells of the centre."""
    r = int(radius)
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    return (xx * xx + yy * yy) <= r * r + 1e-9


def floor_clearance(navmap: NavMap) -> np.ndarray:
    """Clearance (metres) of every floor cell, per floor-height bin: the exact horizontal distance to
    the obstacle points in the body band, and the EDT distance to unsupported columns minus half a
    cell (the floor reaches the edge of its last cell). Unsupported columns holding floor at another
    height are drops and count as they are; for floor on a storey's plane, other columns with no
    floor (unseen) count as standing ``safety_buffer - unknown_clearance`` farther out."""
    vox, emb, cfg = navmap.voxel_size, navmap.embodiment, navmap.config
    floor_ij, floor_z, support_ij = navmap.floor_ij, navmap.floor_z, navmap.support_ij
    level_heights, obstacle_ij, obstacle_xyz = navmap.level_heights, navmap.obstacle_ij, navmap.obstacle_xyz
    heights, cell_bin = navmap.height_bins()
    clearance = np.zeros(len(floor_z))
    unknown_slack = navmap.safety_buffer - navmap.unknown_clearance
    if unknown_slack > 0:  # only then do drops and unseen columns differ
        floor_anywhere = np.zeros(navmap.shape2d, dtype=bool)
        floor_anywhere[floor_ij[:, 0], floor_ij[:, 1]] = True
        floor_anywhere[support_ij[:, 0], support_ij[:, 1]] = True
        near_drop = disk(int(math.ceil(navmap.safety_buffer / vox - 1e-9)))
        on_level = (
            np.abs(floor_z - level_heights[navmap.floor_level]) <= cfg.level_tolerance
            if len(level_heights)
            else np.zeros(len(floor_z), dtype=bool)
        )
    cell_xy = navmap.cell_xy(floor_ij)
    bound = 5.0 * emb.radius + 2.0 * vox
    for b, h in enumerate(heights):
        sel = np.flatnonzero(cell_bin == b)
        void = navmap.unsupported_mask(float(h))
        if unknown_slack > 0:
            # Unseen columns within a buffer of a drop (between stair treads seen at grazing angles,
            # at a landing's edge) may hide the same height change: they count as the drop does.
            drop = void & floor_anywhere
            if drop.any():
                drop |= void & ndimage.binary_dilation(drop, structure=near_drop)
            # Only floor on a storey's plane gets the slack: treads and ramps keep the buffer.
            slack = np.where(on_level[sel], unknown_slack, 0.0)
            c = np.minimum(
                edge_distance(drop, floor_ij[sel], vox),
                edge_distance(void & ~drop, floor_ij[sel], vox) + slack,
            )
        else:
            c = edge_distance(void, floor_ij[sel], vox)
        band = navmap.band_obstacles(float(h))
        if band.any():
            # Exact distance to the obstacle points near the cell; beyond ``bound`` (no effect on
            # navigability or costs) the column EDT is precise enough.
            d_obs, _ = cKDTree(obstacle_xyz[band, :2]).query(cell_xy[sel], distance_upper_bound=bound)
            far = ~np.isfinite(d_obs)
            if far.any():
                cols = np.zeros(navmap.shape2d, dtype=bool)
                cols[obstacle_ij[band, 0], obstacle_ij[band, 1]] = True
                edt = ndimage.distance_transform_edt(~cols) * vox - 0.5 * vox
                d_obs[far] = np.maximum(edt[floor_ij[sel[far], 0], floor_ij[sel[far], 1]], bound)
            c = np.minimum(c, d_obs)
        clearance[sel] = c
    return clearance


def edge_distance(blocked: np.ndarray, ij: np.ndarray, vox: float) -> np.ndarray:
    """Distance (metres) from the cells ``ij`` to the nearest ``blocked`` column's edge (its centre
    minus half a cell, at least 0); infinite when nothing is blocked."""
    if not blocked.any():
        return np.full(len(ij), np.inf)
    d = ndimage.distance_transform_edt(~blocked)[ij[:, 0], ij[:, 1]] * vox - 0.5 * vox
    return np.maximum(d, 0.0)
