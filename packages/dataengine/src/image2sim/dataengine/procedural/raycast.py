"""First-hit ray casting against a set of axis-aligned boxes.

Two interchangeable casters return, for every ray, the exact distance ``t`` (float64, along unit
directions), the index of the box hit (-1 for a miss) and the face (``2 * axis + side``; side 0 =
the box's min face, normal ``-e_axis``; side 1 = its max face, normal ``+e_axis``):

* :class:`BoxCaster` — vectorised slab test in numpy. With ``cull=False`` it tests every ray
  against every box (the slow, readable reference); with ``cull=True`` rays are grouped in image
  tiles and each tile only tests the boxes whose bounding sphere meets the tile's cone of rays.
* :class:`EmbreeCaster` — Intel Embree through ``embreex`` on the triangulated
  boxes; the triangle it reports names the box and face, and ``t`` is then recomputed exactly in
  float64 from that face's plane, so depth is exact rather than float32-accurate.

``benchmarks/synth.py`` measures both; :func:`make_caster` picks Embree when it is importable.
"""

from __future__ import annotations

import numpy as np
from image2sim.dataengine.procedural.gt import mesh_arrays

__all__ = ["BoxCaster", "EmbreeCaster", "make_caster", "embree_available", "exact_face_distance"]

_TINY = 1e-15


def embree_available() -> bool:
    """True when Embree is importable (``embreex`` installed)."""
    try:
        import embreex.rtcore_scene  # noqa: F401
    except Exception:
        return False
    return True


def _safe_dirs(dirs: np.ndarray) -> np.ndarray:
    """Replace exactly-zero direction components by a tiny signed value (keeps slabs finite)."""
    out = np.array(dirs, dtype=np.float64, copy=True)
    small = np.abs(out) < _TINY
    out[small] = _TINY
    return out


def exact_face_distance(
    origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray, box: np.ndarray, face: np.ndarray
) -> np.ndarray:
    """Distance along each ray to the plane of its hit face (float64); NaN where ``box < 0``."""
    t = np.full(dirs.shape[0], np.nan)
    ok = box >= 0
    if not ok.any():
        return t
    b, f = box[ok], face[ok]
    axis, side = f // 2, f % 2
    plane = np.where(side == 1, hi[b, axis], lo[b, axis])
    d = _safe_dirs(dirs[ok])[np.arange(b.size), axis]
    t[ok] = (plane - origin[axis]) / d
    return t


class BoxCaster:
    """Vectorised (numpy) slab-test caster over axis-aligned boxes ``lo``/``hi`` (M, 3)."""

    def __init__(
        self, lo: np.ndarray, hi: np.ndarray, *, cull: bool = True, chunk: int = 1024, tile: int = 16
    ):
        self.lo = np.asarray(lo, dtype=np.float64)
        self.hi = np.asarray(hi, dtype=np.float64)
        self.cull = cull
        self.chunk = chunk
        self.tile = tile
        centre = 0.5 * (self.lo + self.hi)
        self._centre = centre
        self._radius = 0.5 * np.linalg.norm(self.hi - self.lo, axis=1)

    @staticmethod
    def _slab(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray):
        """Nearest entry distance, box index and face for rays ``d`` (N, 3) vs boxes (M, 3)."""
        inv = 1.0 / d
        tmin, tmax = [], []
        for a in range(3):
            t1 = (lo[None, :, a] - o[a]) * inv[:, a, None]
            t2 = (hi[None, :, a] - o[a]) * inv[:, a, None]
            tmin.append(np.minimum(t1, t2))
            tmax.append(np.maximum(t1, t2))
        t_enter = np.maximum(np.maximum(tmin[0], tmin[1]), tmin[2])
        t_exit = np.minimum(np.minimum(tmax[0], tmax[1]), tmax[2])
        hit = (t_enter <= t_exit) & (t_enter > 0)
        t_enter = np.where(hit, t_enter, np.inf)
        box = np.argmin(t_enter, axis=1)
        rows = np.arange(d.shape[0])
        t_best = t_enter[rows, box]
        # The entering slab is the axis whose near plane is farthest (ties -> lowest axis).
        ax = np.argmax(np.stack([tm[rows, box] for tm in tmin], axis=1), axis=1)
        side = (d[rows, ax] < 0).astype(np.int64)
        box = np.where(np.isfinite(t_best), box, -1)
        return t_best, box, 2 * ax + side

    def _cast_all(self, origin: np.ndarray, dirs: np.ndarray):
        n = dirs.shape[0]
        t = np.empty(n)
        box = np.empty(n, dtype=np.int64)
        face = np.empty(n, dtype=np.int64)
        for s in range(0, n, self.chunk):
            t[s : s + self.chunk], box[s : s + self.chunk], face[s : s + self.chunk] = self._slab(
                origin, dirs[s : s + self.chunk], self.lo, self.hi
            )
        return t, box, face

    def _cast_culled(self, origin: np.ndarray, dirs: np.ndarray, image_shape: tuple[int, int]):
        h, w = image_shape
        ts = self.tile
        n = dirs.shape[0]
        t_out = np.full(n, np.inf)
        box_out = np.full(n, -1, dtype=np.int64)
        face_out = np.zeros(n, dtype=np.int64)
        idx = np.arange(n).reshape(h, w)
        v = self._centre - origin
        dist = np.linalg.norm(v, axis=1)
        vhat = v / np.maximum(dist, 1e-12)[:, None]
        inside = dist <= self._radius
        sub = np.arcsin(np.clip(self._radius / np.maximum(dist, 1e-12), 0.0, 1.0))
        for r0 in range(0, h, ts):
            for c0 in range(0, w, ts):
                pix = idx[r0 : r0 + ts, c0 : c0 + ts].reshape(-1)
                dd = dirs[pix]
                c = dd.mean(axis=0)
                c /= max(np.linalg.norm(c), 1e-12)
                half = np.arccos(np.clip(dd @ c, -1.0, 1.0)).max()
                beta = np.arccos(np.clip(vhat @ c, -1.0, 1.0))
                cand = np.nonzero(inside | (beta <= half + sub + 1e-9))[0]
                if cand.size == 0:
                    continue
                t, b, f = self._slab(origin, dd, self.lo[cand], self.hi[cand])
                ok = b >= 0
                t_out[pix[ok]] = t[ok]
                box_out[pix[ok]] = cand[b[ok]]
                face_out[pix[ok]] = f[ok]
        return t_out, box_out, face_out

    def cast(self, origin: np.ndarray, dirs: np.ndarray, image_shape: tuple[int, int] | None = None):
        """``(t, box, face)`` for unit ``dirs`` (N, 3) from ``origin`` (3,); see the module docstring.

        ``image_shape`` (H, W) with ``H * W == N`` enables tile culling (rays in row-major image order).
        """
        dirs = _safe_dirs(np.asarray(dirs, dtype=np.float64).reshape(-1, 3))
        origin = np.asarray(origin, dtype=np.float64)
        if dirs.shape[0] == 0:
            return np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        if self.cull and image_shape is not None and image_shape[0] * image_shape[1] == dirs.shape[0]:
            t, box, face = self._cast_culled(origin, dirs, image_shape)
        else:
            t, box, face = self._cast_all(origin, dirs)
        # Recompute t from the face plane so both casters agree to the last bit.
        t = np.where(box >= 0, exact_face_distance(origin, dirs, self.lo, self.hi, box, face), np.nan)
        return t, box, face


class EmbreeCaster:
    """Embree first-hit caster on the triangulated boxes (12 triangles per box), via ``embreex``."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self.lo = np.asarray(lo, dtype=np.float64)
        self.hi = np.asarray(hi, dtype=np.float64)
        verts, tris = mesh_arrays(self.lo, self.hi)
        # Shift to the scene's corner so float32 keeps sub-micrometre resolution.
        self._shift = verts.min(axis=0) if len(verts) else np.zeros(3)
        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(
            scene=self._scene,
            vertices=(verts - self._shift).astype(np.float32),
            indices=tris.astype(np.int32),
        )

    def cast(self, origin: np.ndarray, dirs: np.ndarray, image_shape: tuple[int, int] | None = None):
        """``(t, box, face)`` like :meth:`BoxCaster.cast` (``image_shape`` is ignored)."""
        dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        origin = np.asarray(origin, dtype=np.float64)
        if dirs.shape[0] == 0:
            return np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        origins = np.broadcast_to((origin - self._shift).astype(np.float32), dirs.shape)
        tri = np.asarray(
            self._scene.run(np.ascontiguousarray(origins), dirs.astype(np.float32)), dtype=np.int64
        )
        box = np.where(tri >= 0, tri // 12, -1)
        face = np.where(tri >= 0, (tri % 12) // 2, 0)
        miss = np.nonzero(box < 0)[0]
        if miss.size:
            # float32 triangles can let a ray slip through a shared edge; re-cast those exactly.
            _, box[miss], face[miss] = self._fallback().cast(origin, dirs[miss])
        t = exact_face_distance(origin, dirs, self.lo, self.hi, box, face)
        return t, box, face

    def _fallback(self) -> BoxCaster:
        if getattr(self, "_exact", None) is None:
            self._exact = BoxCaster(self.lo, self.hi, cull=False)
        return self._exact


def make_caster(kind: str, lo: np.ndarray, hi: np.ndarray):
    """Build a caster: "embree", "numpy" (tile-culled slab test), "numpy-brute" or "auto"."""
    if kind == "auto":
        kind = "embree" if embree_available() else "numpy"
    if kind == "embree":
        if not embree_available():
            raise RuntimeError(
                "caster 'embree' needs the embreex package (pip install embreex); use caster='numpy'"
            )
        return EmbreeCaster(lo, hi)
    if kind == "numpy":
        return BoxCaster(lo, hi, cull=True)
    if kind == "numpy-brute":
        return BoxCaster(lo, hi, cull=False)
    raise ValueError(f"unknown caster {kind!r} (expected 'auto', 'embree', 'numpy' or 'numpy-brute')")
