"""Momentum self-distillation: an EMA teacher and the multi-level feature distillation loss.

The teacher is an exponential moving average of the student,
``theta_T <- d * theta_T + (1 - d) * theta_S`` (buffers are copied), never trained by gradient.
It sees the *privileged* source built from the ground-truth panorama (alpha = 1 everywhere),
the student the noisy alpha-gated source; the student matches the teacher's decoder features:
``sum_k w~_k [1 - cos(f_k^S, f_k^T) + beta ||f_k^S - f_k^T||^2]``.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["ema_update_", "EMATeacher", "normalised_level_weights", "distillation_loss"]


@torch.no_grad()
def ema_update_(teacher: nn.Module, student: nn.Module, decay: float) -> None:
    """In place: floating parameters ``T <- decay * T + (1 - decay) * S``; buffers copied.

    The two modules must have identical parameter names and shapes (a deepcopy of each other).
    """
    if not 0.0 <= decay <= 1.0:
        raise ValueError(f"EMA decay must lie in [0, 1], got {decay}")
    t_params = dict(teacher.named_parameters())
    s_params = dict(student.named_parameters())
    if t_params.keys() != s_params.keys():
        missing = sorted(set(s_params) ^ set(t_params))[:5]
        raise ValueError(f"EMA teacher and student differ in parameters, e.g. {missing}")
    for name, s in s_params.items():
        t = t_params[name]
        if t.shape != s.shape:
            raise ValueError(f"EMA parameter {name}: teacher {tuple(t.shape)} vs student {tuple(s.shape)}")
        t.lerp_(s.detach().to(t.dtype), 1.0 - decay)  # T + (1-d)(S - T) = d T + (1-d) S
    t_bufs = dict(teacher.named_buffers())
    for name, s in student.named_buffers():
        t_bufs[name].copy_(s)


class EMATeacher(nn.Module):
    """A frozen copy of ``student`` updated by :func:`ema_update_`; always in eval mode."""

    def __init__(self, student: nn.Module, decay: float = 0.999) -> None:
        super().__init__()
        if not 0.0 <= decay <= 1.0:
            raise ValueError(f"EMA decay must lie in [0, 1], got {decay}")
        self.decay = float(decay)
        self.module = copy.deepcopy(student)
        self.module.requires_grad_(False)
        self.module.eval()
        self.register_buffer("num_updates", torch.zeros((), dtype=torch.long))

    def train(self, mode: bool = True) -> EMATeacher:
        # The teacher never switches to training mode (no dropout / batch statistics drift).
        super().train(False)
        return self

    @torch.no_grad()
    def update(self, student: nn.Module, decay: float | None = None) -> None:
        ema_update_(self.module, student, self.decay if decay is None else decay)
        self.num_updates += 1

    def forward(self, *args, **kwargs):
        with torch.no_grad():
            return self.module(*args, **kwargs)


def normalised_level_weights(weights: Sequence[float]) -> list[float]:
    """w~_k = w_k / sum(w); weights are non-negative and not all zero."""
    w = [float(x) for x in weights]
    if not w or any(x < 0 for x in w) or sum(w) <= 0:
        raise ValueError(f"distillation level weights must be non-negative with a positive sum, got {w}")
    total = sum(w)
    return [x / total for x in w]


def _standardise(f: torch.Tensor, eps: float = 1e-5) -> torch.Tensor:
    """Zero mean, unit variance over the channel dimension of ``(B, C, H, W)`` at each pixel."""
    mean = f.mean(dim=1, keepdim=True)
    var = f.var(dim=1, unbiased=False, keepdim=True)
    return (f - mean) / torch.sqrt(var + eps)


def distillation_loss(
    student: Sequence[torch.Tensor],
    teacher: Sequence[torch.Tensor],
    weights: Sequence[float],
    beta: float,
    normalise: bool = False,
) -> torch.Tensor:
    """sum_k w~_k mean_pixels[1 - cos(f_S, f_T) + beta * mean_c (f_S - f_T)^2] over feature maps
    ``(B, C_k, H_k, W_k)``. The squared distance is averaged over channels so levels of different
    widths are comparable; the teacher features are constants. Computed in float32.

    ``normalise``: the squared distance is taken between features standardised over channels at
    each pixel (no affine), so the whole loss is invariant to the activations' scale and at most
    ``2 + 4 beta`` per level."""
    if not (len(student) == len(teacher) == len(weights)):
        raise ValueError(
            f"distillation_loss: {len(student)} student, {len(teacher)} teacher levels, "
            f"{len(weights)} weights"
        )
    w = normalised_level_weights(weights)
    total = student[0].new_zeros((), dtype=torch.float32)
    for fs, ft, wk in zip(student, teacher, w, strict=False):
        if fs.shape != ft.shape:
            raise ValueError(f"distillation level shapes differ: {tuple(fs.shape)} vs {tuple(ft.shape)}")
        fs32, ft32 = fs.float(), ft.detach().float()
        cos = F.cosine_similarity(fs32, ft32, dim=1, eps=1e-6)
        if normalise:
            fs32, ft32 = _standardise(fs32), _standardise(ft32)
        sq = (fs32 - ft32).pow(2).mean(dim=1)
        total = total + wk * (1.0 - cos + beta * sq).mean()
    return total
