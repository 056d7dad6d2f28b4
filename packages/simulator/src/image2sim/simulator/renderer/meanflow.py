"""MeanFlow maths of the pixel-flow renderer, as small pure functions.

Notation (paper, "Geometry-Aware One-Step Pixel Flow Rendering"):

* ``X``      target panoramic RGB-D state ``(B, 4, H, W)`` (RGB in [0, 1], depth / depth_scale)
* ``X~, A``  projected (splatted) prior and its opacity ``(B, 1, H, W)`` in [0, 1]
* ``z_src = A * X~ + Sigma(A) * eps``, ``Sigma(A) = A * s_small + (1 - A) * s_large`` per channel
  group (RGB, depth)
* path ``z_t = (1 - t) X + t z_src`` (t = 0: target, t = 1: source), velocity ``v = z_src - X``
* x-prediction ``u = (z_t - x_theta(z_t, r, t)) / max(t, eps)``: average velocity on [r, t]
  (``z_r = z_t - (t - r) u``)
* ``V = u + (t - r) sg(du/dt)`` with the total derivative along the path
  ``du/dt = d/dt u(z_t, r, t) = J_z u . v + d_t u`` from one forward-mode JVP with tangents
  ``(v, 1, 0)`` for ``(z, t, r)``
* flow loss ``W(A) * ||V - v||^2`` with ``W(A) = 1 + k (1 - A)`` and adaptive normalisation
  ``l / sg(l + c)^p``

Times ``t`` and ``r`` are ``(B,)`` tensors. Nothing here owns parameters: the network enters as a
callable ``x_fn(z, r, t) -> x_pred``.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from contextlib import nullcontext

import numpy as np
import torch
from torch.nn.attention import SDPBackend, sdpa_kernel

__all__ = [
    "GROUPS",
    "noise_scale",
    "alpha_gated_source",
    "interpolate",
    "target_velocity",
    "average_velocity",
    "compound_velocity",
    "total_derivative",
    "opacity_weight",
    "adaptive_normalise",
    "flow_loss",
    "sample_time_pairs",
    "sample_one_step",
    "sample_n_steps",
    "pose_seed",
    "pose_noise",
]

GROUPS: tuple[int, ...] = (3, 1)
"""Channel groups of the RGB-D state: RGB (3) then depth (1); sigmas are given per group."""


def _bcast_time(t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """(B,) or scalar time -> broadcastable (B, 1, 1, 1) in the dtype of ``like``."""
    t = torch.as_tensor(t, dtype=like.dtype, device=like.device)
    return t.reshape(-1, *([1] * (like.dim() - 1))) if t.dim() > 0 else t


def _per_channel(values: Sequence[float], groups: Sequence[int], like: torch.Tensor) -> torch.Tensor:
    """Expand per-group scalars to a (1, C, 1, 1) tensor."""
    if len(values) != len(groups):
        raise ValueError(f"expected {len(groups)} per-group values, got {len(values)}")
    if sum(groups) != like.shape[1]:
        raise ValueError(f"channel groups {tuple(groups)} do not cover {like.shape[1]} channels")
    vals = [float(v) for v, n in zip(values, groups, strict=False) for _ in range(n)]
    return torch.tensor(vals, dtype=like.dtype, device=like.device).view(1, -1, 1, 1)


def noise_scale(
    alpha: torch.Tensor,
    sigma_small: Sequence[float],
    sigma_large: Sequence[float],
    groups: Sequence[int] = GROUPS,
    like: torch.Tensor | None = None,
) -> torch.Tensor:
    """Sigma(A) = A * sigma_small + (1 - A) * sigma_large, per channel group -> (B, C, H, W).

    ``alpha`` is clamped to [0, 1] (splatting accumulates opacity that can exceed 1 numerically).
    """
    ref = like if like is not None else alpha.expand(-1, sum(groups), -1, -1)
    a = alpha.clamp(0.0, 1.0)
    s_small = _per_channel(sigma_small, groups, ref)
    s_large = _per_channel(sigma_large, groups, ref)
    return a * s_small + (1.0 - a) * s_large


def alpha_gated_source(
    prior: torch.Tensor,
    alpha: torch.Tensor,
    noise: torch.Tensor,
    sigma_small: Sequence[float],
    sigma_large: Sequence[float],
    groups: Sequence[int] = GROUPS,
) -> torch.Tensor:
    """z_src = A * X~ + Sigma(A) * eps for prior X~ (B, C, H, W), alpha (B, 1, H, W), eps like X~."""
    if prior.shape != noise.shape:
        raise ValueError(f"prior {tuple(prior.shape)} and noise {tuple(noise.shape)} differ in shape")
    if alpha.shape[1] != 1 or alpha.shape[-2:] != prior.shape[-2:]:
        raise ValueError(f"alpha must be (B, 1, H, W) matching the prior, got {tuple(alpha.shape)}")
    a = alpha.clamp(0.0, 1.0)
    return a * prior + noise_scale(a, sigma_small, sigma_large, groups, like=prior) * noise


def interpolate(x: torch.Tensor, z_src: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Linear path z_t = (1 - t) X + t z_src."""
    tb = _bcast_time(t, x)
    return (1.0 - tb) * x + tb * z_src


def target_velocity(x: torch.Tensor, z_src: torch.Tensor) -> torch.Tensor:
    """Conditional velocity dz_t/dt = z_src - X."""
    return z_src - x


def average_velocity(z_t: torch.Tensor, x_pred: torch.Tensor, t: torch.Tensor, eps: float) -> torch.Tensor:
    """x-prediction parameterisation u = (z_t - x_pred) / max(t, eps)."""
    return (z_t - x_pred) / _bcast_time(t, z_t).clamp_min(eps)


def compound_velocity(u: torch.Tensor, dudt: torch.Tensor, t: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """V = u + (t - r) * sg(du/dt): the instantaneous velocity implied by the average velocity."""
    return u + _bcast_time(t - r, u) * dudt.detach()


def total_derivative(
    x_fn: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
    z: torch.Tensor,
    r: torch.Tensor,
    t: torch.Tensor,
    tangent: torch.Tensor,
    eps: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(u, du/dt) at (z_t, r, t) along the path, with one forward-mode JVP.

    ``u(z, r, t) = (z - x_fn(z, r, t)) / max(t, eps)``; the JVP uses tangents ``(tangent, 1, 0)``
    for ``(z, t, r)``, i.e. ``du/dt = J_z u . dz/dt + d_t u``. ``u`` keeps its autograd graph to the
    network parameters; ``du/dt`` is returned detached (the stop-gradient of the objective). The
    math attention backend is forced because the CPU flash kernel has no forward-mode rule.
    """

    def u_fn(z_: torch.Tensor, t_: torch.Tensor, r_: torch.Tensor) -> torch.Tensor:
        return average_velocity(z_, x_fn(z_, r_, t_), t_, eps)

    ones = torch.ones_like(t)
    zeros = torch.zeros_like(r)
    with sdpa_kernel([SDPBackend.MATH]):
        u, dudt = torch.func.jvp(u_fn, (z, t, r), (tangent, ones, zeros))
    return u, dudt.detach()


def opacity_weight(alpha: torch.Tensor, k: float) -> torch.Tensor:
    """W(A) = 1 + k (1 - A): larger weight where the projection is unreliable (A ~ 0)."""
    return 1.0 + k * (1.0 - alpha.clamp(0.0, 1.0))


def adaptive_normalise(loss: torch.Tensor, c: float, power: float = 1.0) -> torch.Tensor:
    """loss / sg(loss + c)^power per sample: every sample contributes a gradient of bounded scale,
    so the 1/t blow-up of x-prediction near t = 0 cannot dominate (power 0 = unchanged)."""
    if power == 0:
        return loss
    return loss / (loss.detach() + c).pow(power)


def flow_loss(
    V: torch.Tensor,
    v: torch.Tensor,
    weight: torch.Tensor | None = None,
    norm_c: float = 1e-3,
    norm_power: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(normalised mean loss, raw per-sample loss) of ``W * ||V - v||^2`` averaged over pixels.

    Computed in float32 whatever the autocast dtype, so bf16 cannot overflow the 1/t^2 terms.
    """
    err = (V.float() - v.float()).pow(2).sum(dim=1, keepdim=True)
    if weight is not None:
        err = err * weight.float()
    per_sample = err.flatten(1).mean(dim=1)
    return adaptive_normalise(per_sample, norm_c, norm_power).mean(), per_sample.detach()


def sample_time_pairs(
    batch: int, p_equal: float, generator: torch.Generator | None = None, device=None, dtype=torch.float32
) -> tuple[torch.Tensor, torch.Tensor]:
    """(r, t): t ~ U(0, 1); r = t with probability ``p_equal``, else r = t * U(0, 1) (so r <= t)."""
    t = torch.rand(batch, generator=generator, dtype=dtype, device=device)
    frac = torch.rand(batch, generator=generator, dtype=dtype, device=device)
    equal = torch.rand(batch, generator=generator, dtype=dtype, device=device) < p_equal
    r = torch.where(equal, t, t * frac)
    return r, t


def sample_one_step(
    x_fn: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor], z_src: torch.Tensor
) -> torch.Tensor:
    """One network evaluation from t = 1 to r = 0: z_0 = z_1 - (1 - 0) u = x_theta(z_src, 0, 1)."""
    return sample_n_steps(x_fn, z_src, 1, eps=1.0)


def sample_n_steps(
    x_fn: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
    z_src: torch.Tensor,
    steps: int,
    eps: float = 1e-2,
    times: Sequence[float] | None = None,
) -> torch.Tensor:
    """Integrate from t = 1 to 0 in ``steps`` uniform jumps (or along ``times``, decreasing from 1
    to 0): ``z_r = z_t - (t - r) u(z_t, r, t)`` with ``u = (z_t - x_theta) / max(t, eps)``."""
    if times is None:
        if steps < 1:
            raise ValueError(f"sampler needs at least one step, got {steps}")
        times = np.linspace(1.0, 0.0, steps + 1).tolist()
    times = [float(s) for s in times]
    if len(times) < 2 or any(b >= a for a, b in zip(times, times[1:], strict=False)):
        raise ValueError(f"sampler times must decrease strictly, got {times}")
    z = z_src
    b = z.shape[0]
    for t_val, r_val in zip(times, times[1:], strict=False):
        t = torch.full((b,), t_val, dtype=z.dtype, device=z.device)
        r = torch.full((b,), r_val, dtype=z.dtype, device=z.device)
        u = average_velocity(z, x_fn(z, r, t), t, eps)
        z = z - (t_val - r_val) * u
    return z


def pose_seed(pose: torch.Tensor | np.ndarray, base_seed: int = 0, decimals: int = 4) -> int:
    """A 63-bit seed from a camera-to-world pose rounded to ``decimals`` (0.1 mm / 1e-4 rad): the
    same pose always gets the same seed, independent of device, dtype and process."""
    arr = np.asarray(
        pose.detach().cpu().numpy() if isinstance(pose, torch.Tensor) else pose, dtype=np.float64
    )
    if arr.shape != (4, 4):
        raise ValueError(f"pose must be a 4x4 camera-to-world matrix, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError("pose contains NaN or inf")
    rounded = np.round(arr, decimals) + 0.0  # + 0.0 folds -0.0 into 0.0
    digest = hashlib.sha256(rounded.tobytes() + int(base_seed).to_bytes(8, "little", signed=True)).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def pose_noise(
    poses: torch.Tensor | np.ndarray | Sequence,
    shape: Sequence[int],
    base_seed: int = 0,
    dtype: torch.dtype = torch.float32,
    device=None,
) -> torch.Tensor:
    """Standard normal noise ``(B, *shape)``, one deterministic draw per pose (B poses, 4x4 each),
    so a simulator renders the same image every time it revisits a pose."""
    out = []
    for pose in poses:
        gen = torch.Generator(device="cpu").manual_seed(pose_seed(pose, base_seed))
        out.append(torch.randn(tuple(shape), generator=gen, dtype=torch.float32))
    if not out:
        return torch.empty((0, *shape), dtype=dtype, device=device)
    return torch.stack(out).to(dtype=dtype, device=device)


def maybe_autocast(enabled: bool, device_type: str = "cpu"):
    """bf16 autocast context when ``enabled`` (CPU and CUDA), else a no-op."""
    return torch.autocast(device_type, dtype=torch.bfloat16) if enabled else nullcontext()
