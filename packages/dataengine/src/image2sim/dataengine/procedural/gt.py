"""Exact ground truth: the navigable occupancy grid and the ``gt/`` folder (grid, objects, rooms, mesh).

Grid convention: ``grid[iy, ix]`` is the cell whose centre is
``(origin[0] + (ix + 0.5) * resolution, origin[1] + (iy + 0.5) * resolution)`` in world metres
(rows run along +Y, columns along +X). Occupancy codes: 0 = outside the floor (walls, exterior),
1 = free floor, 2 = covered by a non-walkable object's footprint (rasterised conservatively: every
cell the footprint overlaps). A cell is *navigable* when it is free and its centre keeps at least
the agent radius (+ half a cell, for the rasterisation) from every non-free cell centre.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from image2sim.dataengine.procedural.layout import Layout
from image2sim.simulator.io.npz import npz_bytes
from scipy import ndimage

if TYPE_CHECKING:  # pragma: no cover
    from image2sim.dataengine.procedural.scene import ProceduralScene

__all__ = [
    "OUTSIDE",
    "FREE",
    "OBSTACLE",
    "NavGrid",
    "grid_frame",
    "floor_mask",
    "rasterise_box",
    "navigable_from_free",
    "label_components",
    "write_gt",
    "mesh_arrays",
    "write_ply",
]

OUTSIDE, FREE, OBSTACLE = 0, 1, 2


@dataclass
class NavGrid:
    """Navigable floor of a scene at ``resolution`` metres per cell (see the module docstring)."""

    occupancy: np.ndarray
    """(H, W) uint8 codes: 0 outside/wall, 1 free floor, 2 object footprint."""
    navigable: np.ndarray
    """(H, W) bool: free and at least ``agent_radius`` from anything non-free."""
    components: np.ndarray
    """(H, W) int32 connected-component labels of ``navigable`` (4-connectivity), 0 = not navigable."""
    origin: np.ndarray
    """(2,) float64 world (x, y) of the grid's lower-left corner."""
    resolution: float
    """Cell size, metres."""
    agent_radius: float
    """Clearance used for ``navigable``, metres."""

    @property
    def num_components(self) -> int:
        return int(self.components.max(initial=0))

    def cell_centers(self, iy: np.ndarray, ix: np.ndarray) -> np.ndarray:
        """World (x, y) (N, 2) of cells ``(iy, ix)``."""
        return np.stack(
            (
                self.origin[0] + (np.asarray(ix) + 0.5) * self.resolution,
                self.origin[1] + (np.asarray(iy) + 0.5) * self.resolution,
            ),
            axis=-1,
        )

    def world_to_cell(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell indices ``(iy, ix)`` containing world points (N, 2) (may fall outside the grid)."""
        xy = np.asarray(xy, dtype=np.float64)
        ix = np.floor((xy[..., 0] - self.origin[0]) / self.resolution).astype(np.int64)
        iy = np.floor((xy[..., 1] - self.origin[1]) / self.resolution).astype(np.int64)
        return iy, ix


def grid_frame(layout: Layout, resolution: float) -> tuple[np.ndarray, tuple[int, int]]:
    """Origin (snapped to the resolution) and shape covering the plan with a one-cell margin."""
    x0, y0, x1, y1 = layout.bounds()
    ox = (np.floor(x0 / resolution) - 1) * resolution
    oy = (np.floor(y0 / resolution) - 1) * resolution
    w = int(np.ceil((x1 - ox) / resolution)) + 1
    h = int(np.ceil((y1 - oy) / resolution)) + 1
    return np.array([ox, oy], dtype=np.float64), (h, w)


def _centres(origin: np.ndarray, shape: tuple[int, int], resolution: float) -> tuple[np.ndarray, np.ndarray]:
    xs = origin[0] + (np.arange(shape[1]) + 0.5) * resolution
    ys = origin[1] + (np.arange(shape[0]) + 0.5) * resolution
    return xs, ys


def floor_mask(layout: Layout, origin: np.ndarray, shape: tuple[int, int], resolution: float) -> np.ndarray:
    """Cells whose centre lies on walkable floor: inside a room interior or a door passage."""
    xs, ys = _centres(origin, shape, resolution)
    mask = np.zeros(shape, dtype=bool)
    rects = [r.interior(layout.wall_thickness) for r in layout.rooms]
    rects += [d.passage(layout.wall_thickness) for d in layout.doors]
    for x0, y0, x1, y1 in rects:
        cols = (xs > x0) & (xs < x1)
        rows = (ys > y0) & (ys < y1)
        mask |= rows[:, None] & cols[None, :]
    return mask


def rasterise_box(
    shape: tuple[int, int], origin: np.ndarray, resolution: float, lo: np.ndarray, hi: np.ndarray
) -> tuple[slice, slice]:
    """Row/column slices of the cells whose square overlaps the footprint ``[lo, hi]`` (x, y) with
    positive area."""
    eps = 1e-9
    ix0 = int(np.floor((lo[0] - origin[0]) / resolution + eps))
    ix1 = int(np.ceil((hi[0] - origin[0]) / resolution - eps))
    iy0 = int(np.floor((lo[1] - origin[1]) / resolution + eps))
    iy1 = int(np.ceil((hi[1] - origin[1]) / resolution - eps))
    return slice(max(iy0, 0), max(min(iy1, shape[0]), 0)), slice(max(ix0, 0), max(min(ix1, shape[1]), 0))


def navigable_from_free(free: np.ndarray, agent_radius: float, resolution: float) -> np.ndarray:
    """Free cells whose centre is at least ``agent_radius + resolution / 2`` from every non-free centre."""
    if not free.any():
        return free.copy()
    dist = ndimage.distance_transform_edt(free) * resolution
    return free & (dist >= agent_radius + 0.5 * resolution - 1e-9)


def label_components(navigable: np.ndarray) -> tuple[np.ndarray, int]:
    """4-connected component labels (int32, 0 = background) and their count."""
    labels, n = ndimage.label(navigable)
    return labels.astype(np.int32), int(n)


# --- files ------------------------------------------------------------------------------------------


def mesh_arrays(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8N, 3) and outward-facing triangles (12N, 3) of N axis-aligned boxes.

    Triangle ``12 * b + 2 * f + k`` belongs to box ``b`` and face ``f`` (``f = 2 * axis + side``,
    side 0 = the min face with normal ``-e_axis``, 1 = the max face with normal ``+e_axis``).
    """
    lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
    n = lo.shape[0]
    # Corner c has bits (x, y, z): bit set -> hi on that axis.
    bits = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=bool)
    verts = np.where(bits[None], hi[:, None, :], lo[:, None, :]).reshape(-1, 3)
    # Per face: two triangles, counter-clockwise seen from outside.
    faces_local = np.array(
        [
            [0, 4, 6],
            [0, 6, 2],  # -x
            [1, 3, 7],
            [1, 7, 5],  # +x
            [0, 1, 5],
            [0, 5, 4],  # -y
            [2, 6, 7],
            [2, 7, 3],  # +y
            [0, 2, 3],
            [0, 3, 1],  # -z
            [4, 5, 7],
            [4, 7, 6],  # +z
        ],
        dtype=np.int64,
    )
    tris = (faces_local[None] + 8 * np.arange(n)[:, None, None]).reshape(-1, 3)
    return verts, tris


def write_ply(path: Path, verts: np.ndarray, tris: np.ndarray, face_props: dict[str, np.ndarray]) -> None:
    """Binary little-endian PLY with float32 vertices and per-face int32 properties (e.g. category)."""
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment image2sim procedural scene (world Z-up, metres)",
        f"element vertex {len(verts)}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(tris)}",
        "property list uchar int vertex_indices",
    ]
    header += [f"property int {name}" for name in face_props]
    header.append("end_header")
    dtype = [("n", "u1"), ("idx", "<i4", (3,))] + [(name, "<i4") for name in face_props]
    faces = np.zeros(len(tris), dtype=dtype)
    faces["n"] = 3
    faces["idx"] = tris
    for name, values in face_props.items():
        faces[name] = values
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(np.ascontiguousarray(verts, dtype="<f4").tobytes())
        fh.write(faces.tobytes())


def _json(path: Path, data) -> None:
    path.write_text(json.dumps(data, indent=1, sort_keys=False) + "\n", encoding="utf-8")


def write_gt(scene: ProceduralScene, gt_dir: Path, extra: dict | None = None) -> None:
    """Write ``navigable.npz``, ``objects.json``, ``rooms.json``, ``doors.json``, ``categories.json``,
    ``materials.json`` and ``mesh.ply`` (+ ``poses.json`` etc. from ``extra``) into ``gt_dir``."""
    from image2sim.dataengine.procedural.objects import category_table

    gt_dir.mkdir(parents=True, exist_ok=True)
    grid = scene.grid
    navigable = {
        "grid": grid.navigable.astype(np.uint8),
        "occupancy": grid.occupancy,
        "components": grid.components,
        "origin": grid.origin,
        "resolution": np.float64(grid.resolution),
        "agent_radius": np.float64(grid.agent_radius),
    }
    (gt_dir / "navigable.npz").write_bytes(npz_bytes(navigable))  # byte-identical across runs
    layout = scene.layout
    room_types = [r.room_type for r in layout.rooms]
    _json(gt_dir / "objects.json", {"objects": [o.to_json(room_types) for o in scene.objects]})
    _json(
        gt_dir / "rooms.json",
        {
            "ceiling_height": layout.ceiling_height,
            "wall_thickness": layout.wall_thickness,
            "door_height": layout.door_height,
            "rooms": [
                {
                    "id": r.index,
                    "type": r.room_type,
                    "polygon": r.polygon(layout.wall_thickness),
                    "centerline": [[r.x0, r.y0], [r.x1, r.y0], [r.x1, r.y1], [r.x0, r.y1]],
                    "area": float(
                        (r.x1 - r.x0 - layout.wall_thickness) * (r.y1 - r.y0 - layout.wall_thickness)
                    ),
                }
                for r in layout.rooms
            ],
            "doors": [
                {
                    "rooms": [d.a, d.b],
                    "axis": d.axis,
                    "line": d.line,
                    "span": [d.lo, d.hi],
                    "passage": list(d.passage(layout.wall_thickness)),
                }
                for d in layout.doors
            ],
        },
    )
    _json(gt_dir / "categories.json", {"categories": category_table()})
    _json(gt_dir / "materials.json", {"materials": scene.materials.to_list()})
    verts, tris = mesh_arrays(scene.box_lo, scene.box_hi)
    box_of_tri = np.arange(len(tris)) // 12
    write_ply(
        gt_dir / "mesh.ply",
        verts,
        tris,
        {"category": scene.box_category[box_of_tri], "instance": scene.box_instance[box_of_tri]},
    )
    for name, data in (extra or {}).items():
        _json(gt_dir / name, data)
