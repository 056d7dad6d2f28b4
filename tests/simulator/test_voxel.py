"""Voxel downsampling invariants against a slow dict-of-lists reference."""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from image2sim.simulator.geometry.se3 import normalize_quat, quat_to_matrix
from image2sim.simulator.geometry.voxel import voxel_downsample, voxel_groups, voxel_keys

F64 = torch.float64


def ref_groups(points: np.ndarray, size: float) -> dict[tuple[int, int, int], list[int]]:
    """Voxel -> row indices, one point at a time."""
    groups: dict[tuple[int, int, int], list[int]] = defaultdict(list)
    for i, p in enumerate(points):
        groups[tuple(int(math.floor(c / size)) for c in p)].append(i)
    return dict(sorted(groups.items()))


@st.composite
def clouds(draw):
    seed = draw(st.integers(0, 2**31 - 1))
    n = draw(st.integers(0, 400))
    extent = draw(st.floats(0.01, 100.0))
    size = draw(st.floats(0.005, 5.0))
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-extent, extent, size=(n, 3)) + rng.uniform(-1e3, 1e3, size=3)
    return torch.from_numpy(pts), size, rng


@settings(max_examples=60)
@given(clouds())
def test_matches_reference_means_per_voxel(cloud):
    points, size, rng = cloud
    colours = torch.from_numpy(rng.uniform(0, 1, size=(len(points), 3)))
    labels = torch.from_numpy(rng.integers(0, 255, size=(len(points),)).astype(np.uint8))
    out, attrs = voxel_downsample(points, size, {"rgb": colours, "label": labels})
    groups = ref_groups(points.numpy(), size)
    assert out.shape == (len(groups), 3) and len(groups) <= len(points)
    assert out.dtype == F64 and attrs["rgb"].dtype == F64 and attrs["label"].dtype == torch.uint8
    for row, members in enumerate(groups.values()):  # output ordered by voxel key
        assert np.allclose(out[row].numpy(), points[members].numpy().mean(axis=0), rtol=0, atol=1e-9)
        assert np.allclose(attrs["rgb"][row].numpy(), colours[members].numpy().mean(axis=0), atol=1e-12)
        assert int(attrs["label"][row]) == int(np.round(labels[members].numpy().astype(float).mean()))
    keys, inverse, counts = voxel_groups(points, size)
    assert [tuple(k) for k in keys.tolist()] == list(groups)
    assert counts.tolist() == [len(m) for m in groups.values()]
    assert int(counts.sum()) == len(points)


@settings(max_examples=40)
@given(clouds())
def test_idempotent_on_a_downsampled_cloud(cloud):
    points, size, _ = cloud
    once, _ = voxel_downsample(points, size)
    twice, _ = voxel_downsample(once, size)
    # Each mean lies inside its own voxel, so a second pass finds one point per voxel.
    assert torch.allclose(twice, once, rtol=0, atol=1e-12)
    assert torch.equal(voxel_keys(once, size), voxel_keys(twice, size))


def test_quaternion_signs_are_aligned_before_averaging():
    q = normalize_quat(torch.tensor([[0.9, 0.1, -0.2, 0.3]], dtype=F64))
    # Same rotation twice with opposite signs, plus a nearby rotation: naive mean would cancel.
    quats = torch.cat((q, -q, normalize_quat(q + 0.01)), dim=0)
    pts = torch.tensor([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.3, 0.3, 0.3]], dtype=F64)
    _, naive = voxel_downsample(pts, 1.0, {"q": quats})
    assert naive["q"].norm() < 0.5  # what goes wrong without alignment
    _, attrs = voxel_downsample(pts, 1.0, {"q": quats}, quaternion_keys=["q"])
    avg = attrs["q"][0]
    assert abs(float(avg.norm()) - 1.0) < 1e-14
    expected = normalize_quat(2 * q[0] + normalize_quat(q + 0.01)[0])
    assert torch.allclose(avg, expected, atol=1e-14) or torch.allclose(avg, -expected, atol=1e-14)


def test_quaternion_pair_q_and_minus_q_gives_the_same_rotation():
    gen = torch.Generator().manual_seed(0)
    q = normalize_quat(torch.randn(50, 4, generator=gen, dtype=F64))
    cells = torch.randperm(50, generator=gen).to(F64)
    pts = torch.stack(((cells + 0.5) * 0.01, torch.zeros(50, dtype=F64), torch.zeros(50, dtype=F64)), dim=1)
    pts = torch.cat((pts, pts + 0.002))  # a second point in each voxel, carrying -q
    quats = torch.cat((q, -q))
    out, attrs = voxel_downsample(pts, 0.01, {"q": quats}, quaternion_keys=("q",))
    assert out.shape[0] == 50
    R_out = quat_to_matrix(attrs["q"])
    order = torch.argsort(cells)  # output is sorted by voxel key = cell
    assert torch.allclose(R_out, quat_to_matrix(q[order]), atol=1e-12)


def test_empty_input():
    out, attrs = voxel_downsample(
        torch.zeros(0, 3), 0.1, {"rgb": torch.zeros(0, 3), "q": torch.zeros(0, 4)}, quaternion_keys=["q"]
    )
    assert out.shape == (0, 3) and attrs["rgb"].shape == (0, 3) and attrs["q"].shape == (0, 4)
    keys, inverse, counts = voxel_groups(torch.zeros(0, 3), 0.1)
    assert keys.shape == (0, 3) and inverse.shape == (0,) and counts.shape == (0,)


def test_float32_and_bool_attributes_and_negative_coordinates():
    pts = torch.tensor([[-0.05, 0.0, 0.0], [-0.01, 0.0, 0.0], [0.01, 0.0, 0.0]], dtype=torch.float32)
    out, attrs = voxel_downsample(pts, 0.1, {"seen": torch.tensor([True, True, False])})
    # floor(-0.05 / 0.1) = -1 and floor(0.01 / 0.1) = 0: the origin splits voxels.
    assert out.dtype == torch.float32 and out.shape == (2, 3)
    assert torch.allclose(out[:, 0], torch.tensor([-0.03, 0.01]))
    assert attrs["seen"].tolist() == [True, False]


def test_huge_extent_falls_back_to_unique_rows():
    # 2^40 voxels per axis: packing three coordinates into one int64 would overflow.
    pts = torch.tensor([[0.0, 0.0, 0.0], [2.0**40, 2.0**40, 2.0**40], [0.5, 0.5, 0.5]], dtype=F64)
    out, _ = voxel_downsample(pts, 1.0)
    assert out.tolist() == [[0.25, 0.25, 0.25], [2.0**40] * 3]
    keys, _, _ = voxel_groups(pts, 1.0)
    assert keys.tolist() == [[0, 0, 0], [2**40, 2**40, 2**40]]


@pytest.mark.parametrize(
    ("points", "size", "attributes", "qkeys", "message"),
    [
        (torch.zeros(4, 2), 0.1, None, (), r"\(N, 3\)"),
        (torch.zeros(4, 3), 0.0, None, (), "positive finite"),
        (torch.zeros(4, 3), float("nan"), None, (), "positive finite"),
        (torch.tensor([[0.0, float("nan"), 0.0]]), 0.1, None, (), "NaN/inf"),
        (torch.zeros(4, 3, dtype=torch.int64), 0.1, None, (), "floating"),
        (torch.zeros(4, 3), 0.1, {"rgb": torch.zeros(3, 3)}, (), "'rgb' must be a tensor with 4 rows"),
        (torch.zeros(4, 3), 0.1, {"q": torch.zeros(4, 4)}, ("rot",), "'rot' is not among"),
        (torch.zeros(4, 3), 0.1, {"q": torch.zeros(4, 3)}, ("q",), "floating \\(N, 4\\)"),
        (torch.tensor([[1e30, 0.0, 0.0]]), 1e-3, None, (), "too large"),
    ],
)
def test_errors(points, size, attributes, qkeys, message):
    with pytest.raises(ValueError, match=message):
        voxel_downsample(points, size, attributes, quaternion_keys=qkeys)
