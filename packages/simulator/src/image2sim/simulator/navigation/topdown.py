"""Top-down pictures of a :class:`~.navmap.NavMap` (storeys, obstacles, clearance, an optional path)
and the PNG writer ``sim navmap --png`` uses."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from image2sim.simulator.io.atomic import atomic_path
from image2sim.simulator.navigation.navmap import NavMap

__all__ = ["render_topdown", "write_png"]

# ----------------------------------------------------------------------------------------------
# Visualisation
# ----------------------------------------------------------------------------------------------

_LEVEL_COLOURS = np.array(
    [[66, 135, 245], [245, 135, 66], [80, 190, 90], [200, 80, 200], [220, 200, 60], [60, 200, 200]],
    dtype=np.uint8,
)


def render_topdown(navmap: NavMap, path: np.ndarray | None = None, scale: int = 2) -> np.ndarray:
    """Top-down RGB image (uint8, rows = +y downwards flipped so +y is up) with three panels.

    Left: navigable cells coloured by storey over obstacles (grey) and non-navigable floor (dark);
    middle: clearance heat map (black 0 m -> white >= r_safe); right: floor height. An optional
    (P, 3) map-frame ``path`` is drawn in red on the left panel.
    """
    nx, ny = navmap.shape2d
    base = np.full((nx, ny, 3), 255, dtype=np.uint8)
    occ = np.zeros((nx, ny), dtype=bool)
    occ[navmap.obstacle_ij[:, 0], navmap.obstacle_ij[:, 1]] = True
    base[occ] = (150, 150, 150)
    fi, fj = navmap.floor_ij[:, 0], navmap.floor_ij[:, 1]
    # Draw lower storeys first so the top storey is visible where they overlap.
    order = np.argsort(navmap.floor_z)
    nav = navmap.navigable[order]
    base[fi[order][~nav], fj[order][~nav]] = (60, 60, 60)
    base[fi[order][nav], fj[order][nav]] = _LEVEL_COLOURS[
        navmap.floor_level[order][nav] % len(_LEVEL_COLOURS)
    ]
    clear = np.zeros((nx, ny, 3), dtype=np.uint8)
    r_safe = 5.0 * navmap.embodiment.radius
    val = np.clip(navmap.clearance[order] / r_safe, 0, 1)
    clear[fi[order], fj[order]] = (val[:, None] * 255).astype(np.uint8)
    height = np.zeros((nx, ny, 3), dtype=np.uint8)
    z = navmap.floor_z[order]
    span = max(1e-6, float(z.max() - z.min())) if len(z) else 1.0
    t = (z - (z.min() if len(z) else 0)) / span
    height[fi[order], fj[order]] = np.column_stack((40 + 215 * t, 80 + 100 * (1 - t), 255 * (1 - t))).astype(
        np.uint8
    )
    if path is not None and len(path):
        p = np.asarray(path, dtype=np.float64)[:, :2]
        # Draw segments, not just waypoints: sample every quarter cell along the polyline.
        seg = [p[:1]] + [
            a
            + np.linspace(0, 1, max(2, int(np.linalg.norm(b - a) / (0.25 * navmap.voxel_size)) + 1))[1:, None]
            * (b - a)
            for a, b in zip(p[:-1], p[1:], strict=False)
        ]
        ij = navmap.xy_to_ij(np.concatenate(seg))
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < nx) & (ij[:, 1] >= 0) & (ij[:, 1] < ny)
        base[ij[ok, 0], ij[ok, 1]] = (220, 30, 30)

    def _to_image(panel: np.ndarray) -> np.ndarray:
        # Array axis 0 is x, axis 1 is y: rows = y, flipped so +y points up in the image.
        return np.transpose(panel, (1, 0, 2))[::-1]

    sep = np.full((ny, 2, 3), 255, dtype=np.uint8)
    img = np.ascontiguousarray(
        np.concatenate((_to_image(base), sep, _to_image(clear), sep, _to_image(height)), axis=1)
    )
    if scale > 1:
        img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)
    return img


def write_png(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Atomically write an RGB uint8 image as PNG."""
    import cv2

    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[..., ::-1])):
            raise OSError(f"{path}: could not encode PNG")
    return path
