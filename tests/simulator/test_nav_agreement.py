"""``navmap_agreement``: navigable-area precision, recall and F-score of two maps in one world frame."""

from __future__ import annotations

import math

import numpy as np
import pytest
from image2sim.simulator.navigation import navmap_agreement

CELL = 0.05


def lattice(x0: float, x1: float, y0: float, y1: float, z: float = 0.0, angle_deg: float = 0.0) -> np.ndarray:
    """Cell centres of an axis-aligned rectangle at ``CELL`` spacing, rotated about its centre."""
    xs = np.arange(x0 + CELL / 2, x1, CELL)
    ys = np.arange(y0 + CELL / 2, y1, CELL)
    xy = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    c = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    a = math.radians(angle_deg)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    xy = (xy - c) @ R.T + c
    return np.column_stack((xy, np.full(len(xy), z)))


def test_identical_maps_agree_fully():
    a = lattice(0, 2, 0, 1)
    r = navmap_agreement(a, a.copy(), CELL)
    assert r["precision"] == r["recall"] == r["f_score"] == 1.0
    assert r["area_a"] == pytest.approx(2.0) and r["area_b"] == pytest.approx(2.0)


def test_a_rotated_or_shifted_lattice_of_the_same_area_agrees():
    # The lattice of a map from a lifted capture lands rotated and shifted after alignment.
    a = lattice(0, 3, 0, 2, angle_deg=0.0)
    b = lattice(0, 3, 0, 2, angle_deg=0.0) + np.array([0.021, -0.013, 0.0])
    assert navmap_agreement(b, a, CELL)["f_score"] == 1.0
    # A square of the same area rotated by 37 degrees: only its corners stick out.
    sq = lattice(0, 2, 0, 2)
    rot = lattice(0, 2, 0, 2, angle_deg=37.0)
    r = navmap_agreement(rot, sq, CELL)
    # Exact area overlap of two concentric squares 37 degrees apart: 0.833 of each (measured by
    # sampling); the 0.75-cell tolerance adds about a percent along the boundary.
    assert r["precision"] == pytest.approx(0.833, abs=0.02) and r["recall"] == pytest.approx(0.833, abs=0.02)


def test_partial_overlap_gives_precision_and_recall():
    a = lattice(0, 2, 0, 1)  # estimate: 2 m^2
    b = lattice(1, 4, 0, 1)  # reference: 3 m^2, 1 m^2 shared
    r = navmap_agreement(a, b, CELL)
    # The 0.75-cell tolerance adds one boundary column of cells to each side's covered part.
    assert r["precision"] == pytest.approx(0.5, abs=0.03)
    assert r["recall"] == pytest.approx(1 / 3, abs=0.03)
    assert r["f_score"] == pytest.approx(2 * 0.5 * (1 / 3) / (0.5 + 1 / 3), abs=0.03)


def test_storeys_stay_apart_and_empty_maps_score_zero():
    ground = lattice(0, 2, 0, 2, z=0.0)
    upstairs = lattice(0, 2, 0, 2, z=2.6)
    assert navmap_agreement(upstairs, ground, CELL)["f_score"] == 0.0
    both = np.concatenate([ground, upstairs])
    r = navmap_agreement(ground, both, CELL)
    assert r["precision"] == 1.0 and r["recall"] == pytest.approx(0.5)
    empty = np.zeros((0, 3))
    assert navmap_agreement(empty, ground, CELL) == {
        "precision": 0.0,
        "recall": 0.0,
        "f_score": 0.0,
        "area_a": 0.0,
        "area_b": pytest.approx(4.0),
    }
    with pytest.raises(ValueError, match="cell must be a finite positive size"):
        navmap_agreement(ground, ground, 0.0)
