"""Optional per-scene refinement: photometric + depth optimisation of fused Gaussians, with pruning.

The feed-forward scene (:func:`image2sim.simulator.gaussians.build.build_scene`) places each
Gaussian from one frame's depth and colour. Refinement renders the scene at the capture's own
poses through the differentiable splat and optimises, with Adam, the means, log-scales, rotations,
opacity logits and colour logits against those frames: L1 on RGB plus ``depth_weight`` x the
relative depth error on pixels with valid depth that the scene covers (alpha > 0.5). Every
``prune_every`` steps Gaussians whose opacity fell under ``prune_opacity`` are removed (their Adam
moments with them). Feature channels (learned encoders) are carried along, not optimised.

This is the optimisation the seed paper's feed-forward lifting avoids, reported as error against
seconds (``benchmarks/scene_fidelity.py``). The library leaves it off (``steps: 0``), and so does
``data episodes`` unless given ``--refine-steps`` (it builds many scenes for throughput);
``sim build-scene``, the command that makes one scene to look at and navigate, refines
:func:`default_refine_steps` steps unless told otherwise: 50 steps bring a fused scene within 1 dB
of each source frame.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from image2sim.simulator.gaussians.frames import prepare_frame
from image2sim.simulator.gaussians.primitives import FrameInputs, GaussianSet

__all__ = [
    "COMPILE_WORK",
    "DEFAULT_MAX_STEPS",
    "DEFAULT_STEPS_PER_FRAME",
    "default_refine_steps",
    "RefineConfig",
    "RefineLog",
    "frame_loss",
    "initial_parameters",
    "refine_gaussians",
    "refine_scene",
    "refine_scene_steps",
]

_EPS = 1e-4  # opacities and colours are kept in (eps, 1 - eps) so their logits stay finite

DEFAULT_MAX_STEPS = 50
"""The most steps of the default refinement (``sim build-scene``; ``data episodes --refine-steps
-1``): on the fidelity benchmark's captures (HM3D sample, three procedural houses) 50 steps close
the own-pose gap to the single-frame scene to <= 0.5 dB (from 2.2-3.4 dB) and gain 0.3-1.6 dB on
held-out panoramas, in ~45 s for the HM3D sample's 612 k Gaussians and ~19 s for a 184 k
procedural house (one thread, 2-core CPU)."""

DEFAULT_STEPS_PER_FRAME = 2
"""... and at most this many steps per source frame (each step fits one frame), so that a scene of
few frames is not fitted to them far beyond what a large capture gets. On the HM3D sample a
single-frame scene refined 50 steps scores 32.9 dB at its own pose (26.3-28.3 unrefined) but loses
0.1-0.7 dB at its neighbours' poses in 4 of 6 views; 2 steps change those views by < 0.1 dB."""


def default_refine_steps(frames: int) -> int:
    """The default refinement's steps for a scene of ``frames`` source frames (``--refine-steps -1``
    of ``sim build-scene`` and ``data episodes``): two steps per frame, at most 50."""
    return min(DEFAULT_MAX_STEPS, DEFAULT_STEPS_PER_FRAME * max(frames, 0))


COMPILE_WORK = 2e7
"""Gaussians x steps from which ``compile_projection: auto`` compiles: each compiled step saves about
1.5 us per Gaussian (2-core CPU), so the ~30 s compile pays back from about this much work."""


@dataclass
class RefineConfig:
    """Per-scene refinement settings (``sim build-scene --refine-steps``)."""

    steps: int = 0
    """Optimisation steps (0: off). Each step renders ``views_per_step`` frames of the capture."""
    views_per_step: int = 1
    """Frames rendered (and averaged in the loss) per step, drawn without replacement per epoch."""
    lr_means: float = 1e-3
    """Adam step of the means, metres (about a fifth of a typical Gaussian's size). The learning rates
    are twice those of the first version: on the fidelity benchmark's four captures 50 steps then
    close the own-pose gap to 0.5 dB or less (1.2 dB on HM3D before) and gain 0.0-0.3 dB held out;
    four times overshoots on the noisy-pose houses (docs/scenes.md)."""
    lr_scales: float = 1e-2
    """Adam step of the log-scales."""
    lr_quats: float = 2e-3
    """Adam step of the (renormalised) rotation quaternions."""
    lr_opacities: float = 4e-2
    """Adam step of the opacity logits."""
    lr_colors: float = 2e-2
    """Adam step of the colour logits."""
    depth_weight: float = 0.5
    """Weight of the relative depth error (|d - d_gt| / d_gt) against the RGB L1."""
    prune_every: int = 50
    """Prune every this many steps (0: never)."""
    prune_opacity: float = 0.02
    """Gaussians whose opacity falls under this are removed at a prune."""
    seed: int = 0
    """Seed of the frame order."""
    compile_projection: str = "auto"
    """Project through ``torch.compile`` (``splat(..., compile_projection=True)``): ``always``,
    ``never`` or ``auto`` (when Gaussians x steps reach :data:`COMPILE_WORK`). Compiled steps are
    ~2x faster (630 k Gaussians: 0.76-0.87 s against 1.62-1.65 s, one thread; ``benchmarks/refine_step.py``)
    after a one-off compile of ~30 s (cached on disk by inductor), so only long refinements of large
    scenes gain; eager if compiling fails."""

    def validate(self) -> RefineConfig:
        problems = []
        if self.steps < 0:
            problems.append(f"steps must be >= 0, got {self.steps}")
        if self.views_per_step < 1:
            problems.append(f"views_per_step must be >= 1, got {self.views_per_step}")
        for name in ("lr_means", "lr_scales", "lr_quats", "lr_opacities", "lr_colors", "depth_weight"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                problems.append(f"{name} must be finite and >= 0, got {v}")
        if self.compile_projection not in ("auto", "always", "never"):
            problems.append(
                f"compile_projection must be auto, always or never, got {self.compile_projection!r}"
            )
        if self.prune_every < 0:
            problems.append(f"prune_every must be >= 0, got {self.prune_every}")
        if not 0 <= self.prune_opacity < 1:
            problems.append(f"prune_opacity must be in [0, 1), got {self.prune_opacity}")
        if problems:
            raise ValueError("RefineConfig: " + "; ".join(problems))
        return self


@dataclass
class RefineLog:
    """What a refinement did: losses per step, Gaussians before/after, seconds."""

    steps: int = 0
    seconds: float = 0.0
    gaussians_before: int = 0
    gaussians_after: int = 0
    losses: list[float] = field(default_factory=list)
    pruned: list[int] = field(default_factory=list)
    """Gaussians removed at each prune."""

    def to_dict(self) -> dict:
        first = self.losses[: max(1, len(self.losses) // 10)]
        last = self.losses[-max(1, len(self.losses) // 10) :]
        return {
            "steps": self.steps,
            "seconds": round(self.seconds, 2),
            "gaussians_before": self.gaussians_before,
            "gaussians_after": self.gaussians_after,
            "pruned": int(sum(self.pruned)),
            "loss_first": round(sum(first) / len(first), 5) if self.losses else None,
            "loss_last": round(sum(last) / len(last), 5) if self.losses else None,
        }


def _logit(p: torch.Tensor) -> torch.Tensor:
    p = p.clamp(_EPS, 1 - _EPS)
    return torch.log(p) - torch.log1p(-p)


def initial_parameters(gaussians: GaussianSet) -> dict[str, torch.nn.Parameter]:
    """The optimised parameters of a set, raw (means, log-scales, unit quaternions, opacity and colour
    logits), as fresh leaves: what :func:`frame_loss` reads."""
    g = gaussians.detach()
    raw = {
        "means": g.means.clone(),
        "log_scales": g.scales.clamp_min(1e-8).log(),
        "quats": F.normalize(g.quats, dim=-1).clone(),
        "opacity_logits": _logit(g.opacities),
        "color_logits": _logit(g.colors),
    }
    return {k: torch.nn.Parameter(v) for k, v in raw.items()}


def frame_loss(
    g: dict[str, torch.Tensor],
    features: torch.Tensor,
    view: FrameInputs,
    depth_weight: float,
    compile_projection: bool = False,
) -> torch.Tensor:
    """The refinement loss of one frame: RGB L1 + ``depth_weight`` x relative depth L1 (covered,
    valid pixels only). ``g`` holds the optimised parameters (raw: log-scales and logits)."""
    from image2sim.simulator.splatting import splat

    out = splat(
        g["means"],
        g["log_scales"].exp(),
        F.normalize(g["quats"], dim=-1),
        torch.sigmoid(g["opacity_logits"]),
        torch.sigmoid(g["color_logits"]),
        features,
        view.camera,
        view.cam_to_world.to(g["means"].dtype),
        background=0.0,
        compile_projection=compile_projection,
    )
    loss = (out.rgb[0] - view.rgb[0].to(out.rgb.dtype)).abs().mean()
    if depth_weight > 0:
        alpha = out.alpha[0, 0]
        gt = view.depth[0, 0].to(out.depth.dtype)
        m = (gt > 0) & (alpha > 0.5)
        if bool(m.any()):
            depth = out.depth[0, 0][m] / alpha[m]
            loss = loss + depth_weight * ((depth - gt[m]).abs() / gt[m]).mean()
    return loss


def refine_gaussians(
    gaussians: GaussianSet,
    views: Sequence[FrameInputs],
    cfg: RefineConfig,
    progress: bool = False,
    checkpoints: Sequence[int] = (),
    on_checkpoint: Callable[[int, GaussianSet, float], None] | None = None,
) -> tuple[GaussianSet, RefineLog]:
    """Optimise ``gaussians`` against ``views`` (frames at the scene's encoding resolution).

    Returns the refined set (footprints, weights and levels carried over for the survivors) and its
    log. ``cfg.steps == 0`` returns the input unchanged. ``on_checkpoint(step, gaussians, seconds)``
    is called after each step count in ``checkpoints`` with the set as it stands (one run read at
    several lengths, as the fidelity benchmark does; its seconds exclude the callback's own time).
    """
    cfg.validate()
    log = RefineLog(gaussians_before=len(gaussians), gaussians_after=len(gaussians))
    if cfg.steps == 0 or len(gaussians) == 0:
        return gaussians, log
    if not views:
        raise ValueError("refine_gaussians: no frames to refine against")
    t0 = time.perf_counter()
    g0 = gaussians.detach()
    params = initial_parameters(g0)
    lrs = {
        "means": cfg.lr_means,
        "log_scales": cfg.lr_scales,
        "quats": cfg.lr_quats,
        "opacity_logits": cfg.lr_opacities,
        "color_logits": cfg.lr_colors,
    }
    opt = torch.optim.Adam([{"params": [p], "lr": lrs[k], "name": k} for k, p in params.items()], eps=1e-15)
    carried = {k: getattr(g0, k) for k in ("features", "footprints", "weights", "levels")}
    compiled = cfg.compile_projection == "always" or (
        cfg.compile_projection == "auto" and len(gaussians) * cfg.steps >= COMPILE_WORK
    )
    rng = torch.Generator().manual_seed(cfg.seed)
    wanted = {int(c) for c in checkpoints if 0 < int(c) <= cfg.steps}
    excluded = 0.0  # seconds spent in on_checkpoint, not refining
    order: list[int] = []
    it = range(cfg.steps)
    if progress:
        from rich.progress import track

        it = track(it, description=f"refining {len(gaussians)} Gaussians, {cfg.steps} steps")
    for step in it:
        opt.zero_grad(set_to_none=True)
        loss_value = 0.0
        for _ in range(cfg.views_per_step):
            if not order:
                order = torch.randperm(len(views), generator=rng).tolist()
            loss = frame_loss(params, carried["features"], views[order.pop()], cfg.depth_weight, compiled)
            (loss / cfg.views_per_step).backward()
            loss_value += float(loss.detach()) / cfg.views_per_step
        opt.step()
        log.losses.append(loss_value)
        last = step + 1 == cfg.steps
        if cfg.prune_every and ((step + 1) % cfg.prune_every == 0 or last):
            with torch.no_grad():
                keep = torch.sigmoid(params["opacity_logits"]) >= cfg.prune_opacity
            if not bool(keep.all()):
                log.pruned.append(int((~keep).sum()))
                params, opt = _prune(params, opt, keep)
                carried = {k: v[keep] for k, v in carried.items()}
        if on_checkpoint is not None and step + 1 in wanted and not last:
            paused = time.perf_counter()
            on_checkpoint(step + 1, _current_set(params, carried), paused - t0 - excluded)
            excluded += time.perf_counter() - paused
    log.steps = cfg.steps
    refined = _current_set(params, carried)
    log.gaussians_after = len(refined)
    log.seconds = time.perf_counter() - t0 - excluded
    if on_checkpoint is not None and cfg.steps in wanted:
        on_checkpoint(cfg.steps, refined, log.seconds)
    return refined, log


class _PreparedFrames(Sequence):
    """Frames prepared on first use, then kept: a refinement of N steps reads at most N of them, so a
    large capture does not decode every frame up front."""

    def __init__(self, prepare: Callable[[int], FrameInputs], indices: list[int]) -> None:
        self._prepare, self._indices, self._done = prepare, indices, {}

    def __len__(self) -> int:
        return len(self._indices)

    def __getitem__(self, k):
        k = range(len(self._indices))[k]  # negative indices and bounds as a list's
        if k not in self._done:
            self._done[k] = self._prepare(self._indices[k])
        return self._done[k]


def _current_set(params: dict[str, torch.Tensor], carried: dict[str, torch.Tensor]) -> GaussianSet:
    """The optimised parameters as a detached :class:`GaussianSet` (activations applied)."""
    with torch.no_grad():
        return GaussianSet(
            means=params["means"].detach().clone(),
            scales=params["log_scales"].detach().exp(),
            quats=F.normalize(params["quats"].detach(), dim=-1),
            opacities=torch.sigmoid(params["opacity_logits"].detach()),
            colors=torch.sigmoid(params["color_logits"].detach()),
            **carried,
        )


def _prune(params: dict, opt: torch.optim.Adam, keep: torch.Tensor):
    """Drop rows ``~keep`` from every parameter and its Adam moments (the optimiser is rebuilt with
    the same step counts, so bias correction continues where it was)."""
    new = {k: torch.nn.Parameter(p.detach()[keep].clone()) for k, p in params.items()}
    groups = []
    for group in opt.param_groups:
        name = group["name"]
        groups.append({"params": [new[name]], "lr": group["lr"], "name": name})
    new_opt = torch.optim.Adam(groups, eps=1e-15)
    for group in opt.param_groups:
        old_p = group["params"][0]
        state = opt.state.get(old_p)
        if state:
            new_opt.state[new[group["name"]]] = {
                "step": state["step"],
                "exp_avg": state["exp_avg"][keep].clone(),
                "exp_avg_sq": state["exp_avg_sq"][keep].clone(),
            }
    return new, new_opt


def refine_scene(
    scene,
    capture,
    frames: Sequence[int] | None,
    cfg: RefineConfig,
    progress: bool = False,
    checkpoints: Sequence[int] = (),
    on_checkpoint: Callable[[int, GaussianSet, float], None] | None = None,
):
    """Refine a :class:`~image2sim.simulator.gaussians.scene.GaussianScene` in place against the
    ``frames`` of ``capture`` (default: the frames the scene was built from) at its encoding
    resolution; records the log in ``scene.info["refine"]`` and returns it. ``checkpoints`` and
    ``on_checkpoint``: as :func:`refine_gaussians`."""
    if scene.gaussians is None:
        raise ValueError("refine_scene: the scene is empty")
    enc = scene.info.get("encoding") or {}
    h, w = enc.get("height"), enc.get("width")
    if not h or not w:
        raise ValueError("refine_scene: the scene has no encoding resolution (scene.info['encoding'])")
    if frames is None:
        frames = [f["index"] for f in scene.frames if f.get("index") is not None]
    edge = scene.fusion.edge_tolerance
    views = _PreparedFrames(lambda i: prepare_frame(capture[i], h, w, edge), list(frames))
    refined, log = refine_gaussians(
        scene.gaussians, views, cfg, progress=progress, checkpoints=checkpoints, on_checkpoint=on_checkpoint
    )
    scene.gaussians = refined
    scene.info["refine"] = {**log.to_dict(), "frames": len(views), "resolution": [w, h]}
    return log


def refine_scene_steps(scene, capture, steps: int, progress: bool = False) -> RefineLog | None:
    """Refine ``scene`` against its own frames of ``capture`` for ``steps`` steps as the commands
    count them (``sim build-scene --refine-steps``, ``data episodes --refine-steps``): -1 is
    :func:`default_refine_steps` of its frames, 0 leaves it feed-forward (returns None)."""
    if steps < 0:
        steps = default_refine_steps(len(scene.frames))
    if steps == 0:
        return None
    return refine_scene(scene, capture, None, RefineConfig(steps=steps), progress=progress)
