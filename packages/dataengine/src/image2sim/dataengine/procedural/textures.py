"""Procedural surface textures (solid patterns evaluated at 3D hit points) and Lambertian shading.

A material is a pattern id, two colours, a scale (metres per period) and a seed. Patterns are
evaluated in world coordinates on the face plane (so they are identical from every viewpoint,
which keeps multi-view photometry consistent); value noise uses a wrapping uint32 integer hash, so
results are bit-identical across runs and machines.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "category_hue",
    "PATTERNS",
    "FAMILIES",
    "MaterialTable",
    "value_noise",
    "fbm",
    "evaluate_albedo",
    "detail_factor",
    "DETAIL_PERIODS",
]

PATTERNS = ("plain", "stripes", "checker", "noise", "wood", "tiles")
"""Pattern ids are indices into this tuple."""

# family -> (pattern choices, hue range, saturation range, value range, scale range (m), contrast range)
FAMILIES: dict[
    str,
    tuple[
        tuple[str, ...],
        tuple[float, float],
        tuple[float, float],
        tuple[float, float],
        tuple[float, float],
        tuple[float, float],
    ],
] = {
    "wall_paint": (
        ("plain", "noise", "stripes"),
        (0.0, 1.0),
        (0.05, 0.3),
        (0.7, 0.95),
        (0.15, 0.5),
        (0.05, 0.15),
    ),
    "floor_wood": (("wood",), (0.05, 0.1), (0.35, 0.7), (0.35, 0.75), (0.1, 0.25), (0.2, 0.4)),
    "floor_tile": (("tiles", "checker"), (0.0, 1.0), (0.0, 0.25), (0.5, 0.95), (0.3, 0.6), (0.15, 0.45)),
    "carpet": (("noise",), (0.0, 1.0), (0.1, 0.5), (0.3, 0.7), (0.03, 0.1), (0.15, 0.3)),
    "ceiling": (("plain", "noise"), (0.08, 0.15), (0.0, 0.06), (0.88, 0.97), (0.4, 1.0), (0.02, 0.06)),
    "wood": (("wood",), (0.04, 0.11), (0.3, 0.75), (0.25, 0.8), (0.05, 0.2), (0.2, 0.45)),
    "fabric": (
        ("noise", "stripes", "checker", "plain"),
        (0.0, 1.0),
        (0.2, 0.7),
        (0.25, 0.8),
        (0.04, 0.15),
        (0.1, 0.35),
    ),
    "metal": (("plain", "noise"), (0.55, 0.65), (0.0, 0.1), (0.5, 0.85), (0.02, 0.08), (0.03, 0.1)),
    "ceramic": (("plain", "noise"), (0.0, 1.0), (0.0, 0.15), (0.8, 0.97), (0.05, 0.2), (0.02, 0.08)),
    "plastic": (("plain", "noise", "stripes"), (0.0, 1.0), (0.3, 0.9), (0.4, 0.95), (0.02, 0.1), (0.05, 0.2)),
    "plant": (("noise",), (0.22, 0.38), (0.45, 0.85), (0.2, 0.55), (0.02, 0.06), (0.3, 0.5)),
    "screen": (("plain", "noise"), (0.55, 0.7), (0.1, 0.4), (0.05, 0.2), (0.05, 0.2), (0.05, 0.2)),
    "art": (("stripes", "checker", "noise"), (0.0, 1.0), (0.4, 0.95), (0.3, 0.95), (0.04, 0.2), (0.4, 0.8)),
    "glass": (("noise",), (0.5, 0.6), (0.05, 0.15), (0.6, 0.85), (0.1, 0.4), (0.05, 0.15)),
    "paper": (("stripes", "plain"), (0.0, 1.0), (0.2, 0.8), (0.4, 0.9), (0.01, 0.03), (0.1, 0.3)),
}
"""Material families: which patterns they use and the HSV/scale/contrast ranges they sample from."""


FIXED_HUE_MIN_SATURATION = 0.65
"""Saturation floor of a material with a fixed (category) hue, so the hue is what one sees."""


def category_hue(category_id: int) -> float:
    """The typical hue of an object category: ids spread over the colour wheel by the golden ratio,
    so categories with nearby ids get clearly different hues."""
    return float((int(category_id) * 0.6180339887498949) % 1.0)


@dataclass
class MaterialTable:
    """Append-only table of materials; ids index the arrays returned by :meth:`arrays`."""

    pattern: list[int] = field(default_factory=list)
    color_a: list[tuple[float, float, float]] = field(default_factory=list)
    color_b: list[tuple[float, float, float]] = field(default_factory=list)
    scale: list[float] = field(default_factory=list)
    direction: list[int] = field(default_factory=list)
    seed: list[int] = field(default_factory=list)
    family: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.pattern)

    def add(self, family: str, rng: np.random.Generator, hue: float | None = None) -> int:
        """Sample a material of ``family`` and return its id. ``hue`` (in [0, 1)) fixes the hue and
        raises the saturation to at least :data:`FIXED_HUE_MIN_SATURATION` (a category's typical
        colour); the generator draws the same numbers either way, so the rest of a scene is
        unchanged."""
        patterns, hue_range, sat, val, scale, contrast = FAMILIES[family]
        pattern = patterns[int(rng.integers(0, len(patterns)))]
        h = rng.uniform(*hue_range)
        s = rng.uniform(*sat)
        v = rng.uniform(*val)
        c = rng.uniform(*contrast)
        if hue is not None:
            h, s, v = float(hue) % 1.0, max(s, FIXED_HUE_MIN_SATURATION), min(max(v, 0.45), 0.9)
        a = colorsys.hsv_to_rgb(h % 1.0, s, v)
        # Second colour: darker (or lighter) and slightly hue-shifted so patterns show in luminance too.
        shift = (
            rng.uniform(-0.06, 0.06) if family not in ("art", "fabric", "plastic") else rng.uniform(-0.5, 0.5)
        )
        v2 = v * (1 - c) if v > 0.5 else min(1.0, v + c)
        b = colorsys.hsv_to_rgb((h + shift) % 1.0, min(1.0, s * rng.uniform(0.8, 1.3)), v2)
        self.pattern.append(PATTERNS.index(pattern))
        self.color_a.append(tuple(float(x) for x in a))
        self.color_b.append(tuple(float(x) for x in b))
        self.scale.append(float(rng.uniform(*scale)))
        self.direction.append(int(rng.integers(0, 2)))
        self.seed.append(int(rng.integers(0, 2**31 - 1)))
        self.family.append(family)
        return len(self.pattern) - 1

    def arrays(self) -> dict[str, np.ndarray]:
        """Column arrays for vectorised evaluation (cached until the next :meth:`add`)."""
        cached = self.__dict__.get("_arrays")
        if cached is not None and cached[0] == len(self):
            return cached[1]
        arrays = {
            "pattern": np.asarray(self.pattern, dtype=np.int64),
            "color_a": np.asarray(self.color_a, dtype=np.float64).reshape(-1, 3),
            "color_b": np.asarray(self.color_b, dtype=np.float64).reshape(-1, 3),
            "scale": np.asarray(self.scale, dtype=np.float64),
            "direction": np.asarray(self.direction, dtype=np.int64),
            "seed": np.asarray(self.seed, dtype=np.uint64),
        }
        self.__dict__["_arrays"] = (len(self), arrays)
        return arrays

    def to_list(self) -> list[dict]:
        """JSON-friendly description of every material."""
        return [
            {
                "id": i,
                "family": self.family[i],
                "pattern": PATTERNS[self.pattern[i]],
                "color_a": list(self.color_a[i]),
                "color_b": list(self.color_b[i]),
                "scale": self.scale[i],
            }
            for i in range(len(self))
        ]


def _hash(ix: np.ndarray, iy: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """Integer lattice hash -> uniform [0, 1) floats (uint32 arithmetic wraps, identical everywhere)."""
    h = ix.astype(np.uint32) * np.uint32(0x8DA6B343)
    h ^= iy.astype(np.uint32) * np.uint32(0xD8163841)
    h ^= seed.astype(np.uint32)
    h ^= h >> np.uint32(16)
    h *= np.uint32(0x7FEB352D)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x846CA68B)
    h ^= h >> np.uint32(16)
    return h.astype(np.float64) * (1.0 / 4294967296.0)


def value_noise(u: np.ndarray, v: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """Smooth 2D value noise in [0, 1) (bilinear, smoothstep-weighted lattice values)."""
    bu, bv = np.floor(u), np.floor(v)
    fu, fv = u - bu, v - bv
    wu, wv = fu * fu * (3.0 - 2.0 * fu), fv * fv * (3.0 - 2.0 * fv)
    iu, iv = bu.astype(np.int64), bv.astype(np.int64)
    n00 = _hash(iu, iv, seed)
    n10 = _hash(iu + 1, iv, seed)
    n01 = _hash(iu, iv + 1, seed)
    n11 = _hash(iu + 1, iv + 1, seed)
    return (n00 * (1 - wu) + n10 * wu) * (1 - wv) + (n01 * (1 - wu) + n11 * wu) * wv


def fbm(u: np.ndarray, v: np.ndarray, seed: np.ndarray, octaves: int = 2) -> np.ndarray:
    """Fractal sum of :func:`value_noise` octaves, normalised to [0, 1)."""
    total = np.zeros(np.shape(u))
    amp, norm = 1.0, 0.0
    for k in range(octaves):
        f = 2.0**k
        total += amp * value_noise(u * f, v * f, seed + np.uint64(1013 * k))
        norm += amp
        amp *= 0.5
    return total / norm


def _face_coords(p: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane coordinates: (horizontal, z) on vertical faces, (x, y) on horizontal ones."""
    u = np.where(axis == 0, p[:, 1], p[:, 0])
    v = np.where(axis == 2, p[:, 1], p[:, 2])
    return u, v


def evaluate_albedo(
    points: np.ndarray, face_axis: np.ndarray, material: np.ndarray, table: dict
) -> np.ndarray:
    """Albedo (N, 3) in [0, 1] of materials ``material`` (N,) at world hit ``points`` (N, 3).

    ``face_axis`` (N,) is the axis of the hit face's normal (0, 1, 2); ``table`` is
    :meth:`MaterialTable.arrays`.
    """
    n = points.shape[0]
    out = np.zeros((n, 3))
    if n == 0:
        return out
    pattern = table["pattern"][material]
    a = table["color_a"][material]
    b = table["color_b"][material]
    scale = table["scale"][material]
    direction = table["direction"][material]
    seed = table["seed"][material]
    u, v = _face_coords(points, face_axis)
    us, vs = u / scale, v / scale
    mix = np.zeros(n)
    q = np.where(direction == 0, us, vs)
    sel = pattern == PATTERNS.index("stripes")
    mix[sel] = np.floor(q[sel]) % 2
    sel = pattern == PATTERNS.index("checker")
    mix[sel] = (np.floor(us[sel]) + np.floor(vs[sel])) % 2
    # Different seeds per face orientation so adjacent faces of a box do not repeat each other.
    fseed = seed + face_axis.astype(np.uint64) * np.uint64(7919)
    sel = pattern == PATTERNS.index("noise")
    if sel.any():
        mix[sel] = fbm(us[sel], vs[sel], fseed[sel], octaves=3)
    sel = pattern == PATTERNS.index("wood")
    if sel.any():
        # Grain: stripes along the board direction, bent by low-frequency noise; planks by hashing.
        warp = fbm(0.25 * us[sel], 0.25 * vs[sel], fseed[sel], octaves=2)
        ring = 0.5 + 0.5 * np.sin(2.0 * np.pi * (1.5 * q[sel] + 2.0 * warp))
        plank = _hash(np.floor(q[sel]).astype(np.int64), np.zeros(int(sel.sum()), dtype=np.int64), fseed[sel])
        mix[sel] = np.clip(0.4 * ring + 0.6 * plank, 0.0, 1.0)
    sel = pattern == PATTERNS.index("tiles")
    if sel.any():
        fu, fv = us[sel] - np.floor(us[sel]), vs[sel] - np.floor(vs[sel])
        grout = (fu < 0.05) | (fv < 0.05)
        tile = _hash(np.floor(us[sel]).astype(np.int64), np.floor(vs[sel]).astype(np.int64), fseed[sel])
        mix[sel] = np.where(grout, 1.0, 0.25 * tile)
    out = a * (1.0 - mix[:, None]) + b * mix[:, None]
    return np.clip(out, 0.0, 1.0)


DETAIL_PERIODS = (0.045, 0.018)
"""Periods (metres) of the two value-noise octaves of :func:`detail_factor`: grain a few pixels wide
at room distances, the scale at which SIFT-like detectors find corners and blobs."""


def detail_factor(points: np.ndarray, face_axis: np.ndarray, seed: np.ndarray, amount: float) -> np.ndarray:
    """Multiplicative fine albedo detail (N,) in ``[1 - amount, 1 + amount]`` at world hit ``points``.

    Real surfaces (paint roller marks, wood pores, fabric weave) carry fine texture; the smooth
    patterns above do not, and feature-based structure-from-motion finds almost nothing on them.
    Evaluated in world coordinates on the face plane like every pattern, so it is identical from
    every viewpoint; ``seed`` (N,) is the material's, so each material has its own grain.
    """
    u, v = _face_coords(points, face_axis)
    fseed = seed.astype(np.uint64) * np.uint64(31) + face_axis.astype(np.uint64) + np.uint64(0x51ED)
    coarse = value_noise(u / DETAIL_PERIODS[0], v / DETAIL_PERIODS[0], fseed)
    fine = value_noise(u / DETAIL_PERIODS[1], v / DETAIL_PERIODS[1], fseed + np.uint64(7))
    return 1.0 + amount * (2.0 * (0.6 * coarse + 0.4 * fine) - 1.0)
