"""SE(3)/quaternion helpers against scipy (ground truth) and their algebraic identities."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from image2sim.simulator.geometry.se3 import (
    invert_pose,
    make_pose,
    matrix_to_quat,
    normalize_quat,
    quat_apply,
    quat_conjugate,
    quat_multiply,
    quat_to_matrix,
    quat_wxyz_to_xyzw,
    quat_xyzw_to_wxyz,
    rotation_angle,
    rotation_error,
    so3_exp,
    so3_log,
    transform_points,
)
from scipy.spatial.transform import Rotation

F64 = torch.float64
seeds = st.integers(0, 2**31 - 1)


def random_quats(seed: int, n: int = 64) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return normalize_quat(torch.randn(n, 4, generator=gen, dtype=F64))


def canonical(q: torch.Tensor) -> torch.Tensor:
    return torch.where(q[..., :1] < 0, -q, q)


@settings(max_examples=50)
@given(seeds)
def test_quat_to_matrix_matches_scipy(seed):
    q = random_quats(seed)
    ours = quat_to_matrix(q)
    ref = Rotation.from_quat(quat_wxyz_to_xyzw(q).numpy()).as_matrix()
    assert np.allclose(ours.numpy(), ref, atol=1e-14)
    # Non-unit quaternions describe the same rotation.
    assert torch.allclose(quat_to_matrix(3.7 * q), ours, atol=1e-14)
    assert rotation_error(ours) < 1e-14


@settings(max_examples=50)
@given(seeds)
def test_matrix_to_quat_roundtrip_and_w_nonnegative(seed):
    q = random_quats(seed)
    back = matrix_to_quat(quat_to_matrix(q))
    assert (back[:, 0] >= 0).all()
    assert torch.allclose(back, canonical(q), atol=1e-14)
    ref = quat_xyzw_to_wxyz(torch.from_numpy(Rotation.from_matrix(quat_to_matrix(q).numpy()).as_quat()))
    assert torch.allclose(back, canonical(ref), atol=1e-14)


def test_matrix_to_quat_near_180_degrees_and_identity():
    # Rotations by pi (trace = -1): the trace-only formula divides by ~0 here.
    axes = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 0]], dtype=F64)
    axes = axes / axes.norm(dim=1, keepdim=True)
    for angle in (math.pi, math.pi - 1e-9, 0.0, 1e-12):
        q = torch.cat((torch.full((4, 1), math.cos(angle / 2), dtype=F64), math.sin(angle / 2) * axes), dim=1)
        R = quat_to_matrix(q)
        back = matrix_to_quat(R)
        assert torch.allclose(quat_to_matrix(back), R, atol=1e-14)
        assert torch.allclose(torch.linalg.vector_norm(back, dim=1), torch.ones(4, dtype=F64))


@settings(max_examples=50)
@given(seeds)
def test_quat_multiply_is_matrix_product(seed):
    a, b = random_quats(seed).chunk(2)
    assert torch.allclose(
        quat_to_matrix(quat_multiply(a, b)), quat_to_matrix(a) @ quat_to_matrix(b), atol=1e-14
    )
    ident = torch.tensor([1.0, 0, 0, 0], dtype=F64)
    assert torch.allclose(quat_multiply(a, quat_conjugate(a)), ident.expand_as(a), atol=1e-14)
    v = torch.randn(32, 3, dtype=F64)
    assert torch.allclose(quat_apply(a, v), (quat_to_matrix(a) @ v[..., None])[..., 0], atol=1e-14)
    ref = Rotation.from_quat(quat_wxyz_to_xyzw(a).numpy()).apply(v.numpy())
    assert np.allclose(quat_apply(a, v).numpy(), ref, atol=1e-13)


def test_xyzw_conversion_roundtrip_and_order():
    q = torch.tensor([0.1, 0.2, 0.3, 0.4])
    assert quat_wxyz_to_xyzw(q).tolist() == pytest.approx([0.2, 0.3, 0.4, 0.1])
    assert torch.equal(quat_xyzw_to_wxyz(quat_wxyz_to_xyzw(q)), q)


def test_normalize_quat_keeps_dtype_and_zero():
    q = torch.tensor([[0.0, 0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.0]], dtype=torch.float32)
    out = normalize_quat(q)
    assert out.dtype == torch.float32
    assert out.tolist() == [[0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]


@settings(max_examples=50)
@given(seeds)
def test_pose_inverse_and_transform(seed):
    gen = torch.Generator().manual_seed(seed)
    R = quat_to_matrix(random_quats(seed, 8))
    t = torch.randn(8, 3, generator=gen, dtype=F64) * 5
    T = make_pose(R, t)
    assert T.shape == (8, 4, 4)
    assert torch.equal(T[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=F64).expand(8, 4))
    eye = torch.eye(4, dtype=F64).expand(8, 4, 4)
    assert torch.allclose(T @ invert_pose(T), eye, atol=1e-13)
    assert torch.allclose(invert_pose(T), torch.linalg.inv(T), atol=1e-13)
    pts = torch.randn(8, 10, 3, generator=gen, dtype=F64)
    homog = torch.cat((pts, torch.ones(8, 10, 1, dtype=F64)), dim=-1)
    ref = (T @ homog.transpose(1, 2)).transpose(1, 2)[..., :3]
    assert torch.allclose(transform_points(T, pts), ref, atol=1e-13)
    assert torch.allclose(transform_points(invert_pose(T), transform_points(T, pts)), pts, atol=1e-12)
    # One pose broadcast over a batch of point sets.
    assert transform_points(T[0], pts).shape == (8, 10, 3)


def test_rotation_error_detects_bad_matrices():
    R = quat_to_matrix(random_quats(0, 4))
    assert rotation_error(R) < 1e-14
    assert rotation_error(torch.zeros(0, 3, 3)) == 0.0
    scaled = R.clone()
    scaled[1] *= 1.01
    # max(|R^T R - I|, |det - 1|) = max(1.01^2 - 1, 1.01^3 - 1)
    assert rotation_error(scaled) == pytest.approx(1.01**3 - 1, rel=1e-9)
    reflect = R.clone()
    reflect[2, :, 0] *= -1  # orthonormal but det = -1
    assert rotation_error(reflect) == pytest.approx(2.0)
    bad = R.clone()
    bad[3, 0, 0] = float("nan")
    assert rotation_error(bad) == float("inf")
    with pytest.raises(ValueError, match="expected"):
        rotation_error(torch.zeros(4, 4))


@settings(max_examples=50)
@given(seeds)
def test_so3_exp_log_roundtrip_and_angle(seed):
    gen = torch.Generator().manual_seed(seed)
    axis = torch.nn.functional.normalize(torch.randn(16, 3, generator=gen, dtype=F64), dim=1)
    angle = torch.rand(16, 1, generator=gen, dtype=F64) * (math.pi - 1e-6)
    angle[0] = 0.0
    angle[1] = 1e-10
    omega = axis * angle
    R = so3_exp(omega)
    ref = Rotation.from_rotvec(omega.numpy()).as_matrix()
    assert np.allclose(R.numpy(), ref, atol=1e-14)
    assert torch.allclose(so3_log(R), omega, atol=1e-12)
    assert torch.allclose(rotation_angle(R), angle[:, 0], atol=1e-12)


def test_so3_exp_gradient_at_zero_is_finite():
    omega = torch.zeros(3, dtype=F64, requires_grad=True)
    so3_exp(omega).sum().backward()
    assert torch.isfinite(omega.grad).all()


@pytest.mark.parametrize(
    ("fn", "arg"),
    [(quat_to_matrix, torch.zeros(3)), (matrix_to_quat, torch.zeros(4, 4)), (invert_pose, torch.zeros(3, 3))],
)
def test_shape_errors(fn, arg):
    with pytest.raises(ValueError, match="expected"):
        fn(arg)
