"""Procedural textures: pattern definitions, value-noise properties, determinism."""

from __future__ import annotations

import numpy as np
from image2sim.dataengine.procedural.textures import PATTERNS, MaterialTable, evaluate_albedo, value_noise


def _table(pattern: str, scale: float = 0.5) -> dict:
    table = MaterialTable()
    table.add("fabric", np.random.default_rng(0))
    table.pattern[0] = PATTERNS.index(pattern)
    table.color_a[0] = (0.9, 0.2, 0.1)
    table.color_b[0] = (0.1, 0.3, 0.8)
    table.scale[0] = scale
    table.direction[0] = 0
    return table.arrays()


def _points_on_floor(us: np.ndarray, vs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pts = np.stack([us, vs, np.zeros_like(us)], axis=1)
    return pts, np.full(len(us), 2)  # floor faces: normal along z, coordinates (x, y)


def test_plain_is_colour_a_and_checker_alternates_by_cell():
    us = np.array([0.1, 0.6, 0.1, 0.6, 1.1])
    vs = np.array([0.1, 0.1, 0.6, 0.6, 0.1])
    pts, axis = _points_on_floor(us, vs)
    mat = np.zeros(len(us), dtype=np.int64)
    plain = evaluate_albedo(pts, axis, mat, _table("plain"))
    np.testing.assert_allclose(plain, np.tile([0.9, 0.2, 0.1], (5, 1)))
    checker = evaluate_albedo(pts, axis, mat, _table("checker", scale=0.5))
    a, b = np.array([0.9, 0.2, 0.1]), np.array([0.1, 0.3, 0.8])
    np.testing.assert_allclose(checker, [a, b, b, a, a])


def test_stripes_follow_the_horizontal_coordinate_on_walls():
    # Wall facing x: in-plane coordinates are (y, z); direction 0 stripes along y, constant along z.
    ys = np.array([0.1, 0.6, 0.1, 0.6])
    zs = np.array([0.2, 0.2, 1.7, 1.7])
    pts = np.stack([np.zeros(4), ys, zs], axis=1)
    out = evaluate_albedo(pts, np.zeros(4, dtype=np.int64), np.zeros(4, dtype=np.int64), _table("stripes"))
    np.testing.assert_allclose(out[0], out[2])
    np.testing.assert_allclose(out[1], out[3])
    assert not np.allclose(out[0], out[1])


def test_value_noise_is_continuous_bounded_and_exact_on_lattice_corners():
    rng = np.random.default_rng(1)
    u = rng.uniform(-50, 50, 20000)
    v = rng.uniform(-50, 50, 20000)
    seed = np.full(u.shape, 12345, dtype=np.uint64)
    n = value_noise(u, v, seed)
    assert n.min() >= 0.0 and n.max() < 1.0
    assert 0.4 < n.mean() < 0.6 and n.std() > 0.1
    # Continuity: a 1e-6 step changes the value by at most ~1e-5 (smoothstep weights, bounded slope).
    assert np.abs(value_noise(u + 1e-6, v, seed) - n).max() < 1e-5
    # Seam-free across integer lattice lines (both sides agree in the limit).
    k = np.arange(-5, 5).astype(np.float64)
    s = np.full(k.shape, 7, dtype=np.uint64)
    np.testing.assert_allclose(
        value_noise(k - 1e-9, k * 0.37, s), value_noise(k + 1e-9, k * 0.37, s), atol=1e-6
    )
    # Different seeds give different fields; the same seed gives identical values.
    assert not np.allclose(value_noise(u, v, seed + np.uint64(1)), n)
    np.testing.assert_array_equal(value_noise(u, v, seed), n)


def test_every_pattern_stays_in_range_and_varies():
    rng = np.random.default_rng(2)
    pts = rng.uniform(-3, 3, (5000, 3))
    axis = rng.integers(0, 3, 5000)
    for pattern in PATTERNS:
        out = evaluate_albedo(pts, axis, np.zeros(5000, dtype=np.int64), _table(pattern, scale=0.3))
        assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0
        if pattern != "plain":
            assert out.std(axis=0).max() > 0.05, pattern
    assert evaluate_albedo(
        np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), _table("noise")
    ).shape == (0, 3)


def test_material_table_sampling_is_deterministic():
    a, b = MaterialTable(), MaterialTable()
    for table in (a, b):
        rng = np.random.default_rng(5)
        for family in ("wall_paint", "floor_wood", "fabric", "art", "plant"):
            table.add(family, rng)
    assert a.to_list() == b.to_list()
    assert len({m["pattern"] for m in a.to_list()}) >= 2
