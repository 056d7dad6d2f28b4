"""SE(3)/SO(3) helpers on torch tensors: quaternions (w, x, y, z), rotation matrices, poses.

Every function broadcasts over leading dimensions and keeps the input dtype and device.
Poses are 4x4 homogeneous matrices; in Image2Sim they are camera-to-world (see
:mod:`image2sim.simulator.conventions`), but nothing here depends on that reading.
"""

from __future__ import annotations

import torch

__all__ = [
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_multiply",
    "quat_conjugate",
    "normalize_quat",
    "quat_apply",
    "quat_wxyz_to_xyzw",
    "quat_xyzw_to_wxyz",
    "make_pose",
    "invert_pose",
    "transform_points",
    "rotation_error",
    "rotation_angle",
    "so3_exp",
    "so3_log",
]


def _check_last(x: torch.Tensor, size: int, name: str) -> None:
    if x.shape[-1] != size:
        raise ValueError(f"{name}: expected a trailing dimension of {size}, got shape {tuple(x.shape)}")


def _check_matrix(x: torch.Tensor, size: int, name: str) -> None:
    if x.ndim < 2 or x.shape[-2:] != (size, size):
        raise ValueError(f"{name}: expected (..., {size}, {size}), got shape {tuple(x.shape)}")


def normalize_quat(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions q / |q| (..., 4); an all-zero quaternion stays zero (no NaN)."""
    _check_last(q, 4, "normalize_quat")
    norm = torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return q / norm.clamp_min(torch.finfo(q.dtype).tiny)


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (w, -x, -y, -z); the inverse rotation for unit quaternions."""
    _check_last(q, 4, "quat_conjugate")
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of (w, x, y, z) quaternions; rotation b is applied first."""
    _check_last(a, 4, "quat_multiply(a)")
    _check_last(b, 4, "quat_multiply(b)")
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """(w, x, y, z) quaternions (..., 4) -> rotation matrices (..., 3, 3).

    Non-unit quaternions are normalised implicitly (the formula uses 2/|q|^2), so q and s*q give
    the same rotation for any s != 0.
    """
    _check_last(q, 4, "quat_to_matrix")
    w, x, y, z = q.unbind(-1)
    s = 2.0 / (q * q).sum(-1).clamp_min(torch.finfo(q.dtype).tiny)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    rows = (
        torch.stack((1 - yy - zz, xy - wz, xz + wy), dim=-1),
        torch.stack((xy + wz, 1 - xx - zz, yz - wx), dim=-1),
        torch.stack((xz - wy, yz + wx, 1 - xx - yy), dim=-1),
    )
    return torch.stack(rows, dim=-2)


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) -> unit (w, x, y, z) quaternions with w >= 0.

    Shepperd's method: of the four algebraically equivalent formulas, each element uses the one
    whose divisor (4 * the largest of |w|, |x|, |y|, |z|) is largest, so it is accurate near
    180-degree rotations where the trace formula breaks down.
    """
    _check_matrix(R, 3, "matrix_to_quat")
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    # 4*w^2, 4*x^2, 4*y^2, 4*z^2 from the diagonal.
    sq = torch.stack(
        (1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22), dim=-1
    )
    # Candidate k = 4 * q_k * q (unnormalised), one per choice of pivot component.
    cands = torch.stack(
        (
            torch.stack((sq[..., 0], m21 - m12, m02 - m20, m10 - m01), dim=-1),
            torch.stack((m21 - m12, sq[..., 1], m10 + m01, m02 + m20), dim=-1),
            torch.stack((m02 - m20, m10 + m01, sq[..., 2], m21 + m12), dim=-1),
            torch.stack((m10 - m01, m02 + m20, m21 + m12, sq[..., 3]), dim=-1),
        ),
        dim=-2,
    )
    best = sq.argmax(dim=-1)
    idx = best[..., None, None].expand(*best.shape, 1, 4)
    q = torch.gather(cands, -2, idx).squeeze(-2)
    q = normalize_quat(q)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_apply(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4)."""
    _check_last(v, 3, "quat_apply(v)")
    return (quat_to_matrix(q) @ v.unsqueeze(-1)).squeeze(-1)


def quat_wxyz_to_xyzw(q: torch.Tensor) -> torch.Tensor:
    """Our (w, x, y, z) order -> scipy's / ROS (x, y, z, w) order."""
    _check_last(q, 4, "quat_wxyz_to_xyzw")
    return torch.cat((q[..., 1:], q[..., :1]), dim=-1)


def quat_xyzw_to_wxyz(q: torch.Tensor) -> torch.Tensor:
    """scipy's / ROS (x, y, z, w) order -> our (w, x, y, z) order."""
    _check_last(q, 4, "quat_xyzw_to_wxyz")
    return torch.cat((q[..., 3:], q[..., :3]), dim=-1)


def make_pose(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Rotation (..., 3, 3) and translation (..., 3) -> homogeneous pose (..., 4, 4)."""
    _check_matrix(R, 3, "make_pose(R)")
    _check_last(t, 3, "make_pose(t)")
    batch = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = torch.zeros(*batch, 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert_pose(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid poses (..., 4, 4): [R^T, -R^T t] (exact for orthonormal R, no solve)."""
    _check_matrix(T, 4, "invert_pose")
    Rt = T[..., :3, :3].transpose(-1, -2)
    t = T[..., :3, 3]
    return make_pose(Rt, -(Rt @ t.unsqueeze(-1)).squeeze(-1))


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply poses (..., 4, 4) to point sets (..., N, 3): p' = R p + t."""
    _check_matrix(T, 4, "transform_points(T)")
    _check_last(points, 3, "transform_points(points)")
    R = T[..., :3, :3]
    t = T[..., None, :3, 3]
    return points @ R.transpose(-1, -2) + t


def rotation_error(R: torch.Tensor) -> float:
    """How far matrices (..., 3, 3) are from SO(3): max over the batch of max|R^T R - I| and |det R - 1|.

    Returns 0.0 for an empty batch and ``inf`` if any entry is non-finite. Readers use it to reject
    non-orthonormal rotations with a clear error.
    """
    _check_matrix(R, 3, "rotation_error")
    if R.numel() == 0:
        return 0.0
    if not torch.isfinite(R).all():
        return float("inf")
    Rd = R.double()
    eye = torch.eye(3, dtype=torch.float64, device=R.device)
    ortho = (Rd.transpose(-1, -2) @ Rd - eye).abs().amax()
    det = (torch.linalg.det(Rd) - 1.0).abs().amax()
    return float(torch.maximum(ortho, det))


def rotation_angle(R: torch.Tensor) -> torch.Tensor:
    """Geodesic angle (radians, in [0, pi]) of rotation matrices (..., 3, 3).

    Uses atan2(|skew part|, trace part), which stays accurate near 0 and pi unlike acos.
    """
    _check_matrix(R, 3, "rotation_angle")
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    skew = torch.stack(
        (R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]), dim=-1
    )
    return torch.atan2(0.5 * torch.linalg.vector_norm(skew, dim=-1), 0.5 * (trace - 1.0))


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors (..., 3) (direction = axis, norm = angle in radians) -> rotations (..., 3, 3).

    Goes through the quaternion (cos(a/2), sin(a/2) * axis) with sin(a/2)/a written via sinc so the
    map is smooth (and differentiable) at a = 0.
    """
    _check_last(omega, 3, "so3_exp")
    angle = torch.linalg.vector_norm(omega, dim=-1, keepdim=True)
    # sin(a/2)/a = 0.5 * sinc(a / (2 pi)) with torch's normalised sinc.
    scale = 0.5 * torch.sinc(angle / (2.0 * torch.pi))
    q = torch.cat((torch.cos(0.5 * angle), scale * omega), dim=-1)
    return quat_to_matrix(q)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotations (..., 3, 3) -> axis-angle vectors (..., 3) with angle in [0, pi].

    Goes through the quaternion (w >= 0): angle = 2 atan2(|v|, w), so it is accurate at 0 and at pi.
    """
    q = matrix_to_quat(R)
    w, v = q[..., :1], q[..., 1:]
    vnorm = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(vnorm, w)
    # angle / |v| -> 2 / w as |v| -> 0 (w -> 1); use that limit where |v| underflows.
    tiny = vnorm <= torch.finfo(R.dtype).eps
    factor = torch.where(tiny, 2.0 / w.clamp_min(0.5), angle / vnorm.clamp_min(torch.finfo(R.dtype).tiny))
    return factor * v
