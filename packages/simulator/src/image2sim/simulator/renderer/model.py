"""PixelFlowRenderer: SemanticAligner + RenderingDecoder + MeanFlow objective and samplers.

Inference: ``render(C_p)`` builds the alpha-gated source from the condition's RGB-D prior and
alpha and maps it to a clean panoramic RGB-D observation in one (or N) network evaluations.
Training: ``losses(...)`` returns every term of the objective for one batch (the Lightning
module weights and sums them per curriculum stage).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from image2sim.simulator.renderer import meanflow as mf
from image2sim.simulator.renderer.aligner import SemanticAligner, alignment_loss
from image2sim.simulator.renderer.condition import from_state, prior_state, to_state
from image2sim.simulator.renderer.config import CONDITION_CHANNELS, STATE_CHANNELS, RendererConfig
from image2sim.simulator.renderer.decoder import DecoderOutput, RenderingDecoder
from image2sim.simulator.renderer.distill import distillation_loss
from image2sim.simulator.renderer.losses import reconstruction_loss, relative_depth_error, saturation_penalty
from torch import nn

__all__ = ["RenderOutput", "PixelFlowRenderer", "save_renderer", "load_renderer"]


@dataclass
class RenderOutput:
    """A rendered panoramic RGB-D observation."""

    rgb: torch.Tensor
    """``(B, 3, H, W)`` in [0, 1] (clamped)."""
    depth: torch.Tensor
    """``(B, 1, H, W)`` metric range, >= 0."""


class PixelFlowRenderer(nn.Module):
    """The geometry-aware one-step pixel-flow renderer (takes tensors; no splatting dependency)."""

    def __init__(self, cfg: RendererConfig, panoramic: bool = True) -> None:
        super().__init__()
        self.cfg = cfg
        ab = cfg.ablation
        self.aligner = (
            None if ab.no_semantic or ab.no_pixel_flow else SemanticAligner(cfg.aligner, panoramic=panoramic)
        )
        token_dim = None if self.aligner is None else cfg.aligner.token_dim
        self.decoder = (
            None
            if ab.no_pixel_flow
            else RenderingDecoder(
                cfg.decoder,
                token_dim,
                gated_skips=not ab.no_alpha_gate,
                panoramic=panoramic,
                depth_scale=cfg.meanflow.depth_scale,
            )
        )

    # ----------------------------------------------------------------------------------------
    def _check_condition(self, condition: torch.Tensor) -> None:
        if condition.dim() != 4 or condition.shape[1] != CONDITION_CHANNELS:
            raise ValueError(
                f"condition must be (B, {CONDITION_CHANNELS}, H, W), got {tuple(condition.shape)}"
            )

    def tokens(self, condition: torch.Tensor) -> torch.Tensor | None:
        """Aligned semantic tokens (None with ``no_semantic``)."""
        return None if self.aligner is None else self.aligner(condition)

    def predict(
        self,
        z: torch.Tensor,
        condition: torch.Tensor,
        r: torch.Tensor,
        t: torch.Tensor,
        tokens: torch.Tensor | None,
    ) -> DecoderOutput:
        """x_theta(z, r, t | C_p, tokens)."""
        if self.decoder is None:
            raise RuntimeError("no_pixel_flow renderer has no network")
        return self.decoder(z, condition, r, t, tokens)

    def source(self, condition: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Alpha-gated source z_src from C_p's RGB-D prior and alpha."""
        prior, alpha = prior_state(condition, self.cfg.meanflow.depth_scale)
        return mf.alpha_gated_source(
            prior, alpha, noise, self.cfg.meanflow.sigma_small, self.cfg.meanflow.sigma_large
        )

    def privileged_source(self, target_state: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """The teacher's source from the ground truth: alpha = 1 everywhere (X + sigma_small eps)."""
        ones = torch.ones_like(target_state[:, :1])
        return mf.alpha_gated_source(
            target_state, ones, noise, self.cfg.meanflow.sigma_small, self.cfg.meanflow.sigma_large
        )

    # ----------------------------------------------------------------------------------------
    @torch.no_grad()
    def render(
        self,
        condition: torch.Tensor,
        steps: int | None = None,
        noise: torch.Tensor | None = None,
        poses: Sequence | torch.Tensor | None = None,
        seed: int = 0,
        generator: torch.Generator | None = None,
    ) -> RenderOutput:
        """Render ``(B, 24, H, W)`` conditions in ``steps`` network evaluations (default: config).

        Noise: ``noise`` if given; else deterministic per-pose noise when ``poses`` (B 4x4
        camera-to-world matrices) are given, so the same pose renders the same image; else drawn
        from ``generator``. ``no_pixel_flow`` returns the splatted prior unchanged.
        """
        self._check_condition(condition)
        ds = self.cfg.meanflow.depth_scale
        prior, _ = prior_state(condition, ds)
        if self.decoder is None:
            rgb, depth = from_state(prior, ds)
            return RenderOutput(rgb.clamp(0, 1), depth.clamp_min(0))
        shape = (STATE_CHANNELS, *condition.shape[-2:])
        if noise is None:
            if poses is not None:
                if len(poses) != condition.shape[0]:
                    raise ValueError(f"{len(poses)} poses for a batch of {condition.shape[0]}")
                noise = mf.pose_noise(poses, shape, seed, condition.dtype, condition.device)
            else:
                noise = torch.randn((condition.shape[0], *shape), generator=generator).to(condition)
        z_src = self.source(condition, noise)
        tokens = self.tokens(condition)

        def x_fn(z, r, t):
            return self.predict(z, condition, r, t, tokens).x

        n = steps if steps is not None else self.cfg.meanflow.sample_steps
        state = mf.sample_n_steps(x_fn, z_src, n, eps=self.cfg.meanflow.t_eps)
        rgb, depth = from_state(state, ds)
        return RenderOutput(rgb.clamp(0, 1), depth.clamp_min(0))

    # ----------------------------------------------------------------------------------------
    def losses(
        self,
        condition: torch.Tensor,
        target_rgb: torch.Tensor,
        target_depth: torch.Tensor,
        noise: torch.Tensor,
        r: torch.Tensor,
        t: torch.Tensor,
        teacher: PixelFlowRenderer | None = None,
        target_tokens: torch.Tensor | None = None,
        perceptual: nn.Module | None = None,
        spatial_focus: bool = True,
    ) -> dict[str, torch.Tensor]:
        """Unweighted loss terms for one batch: ``flow`` (adaptively normalised, includes the
        saturation penalty), ``flow_raw`` (per-batch mean of W ||V - v||^2, for logging), ``rec``,
        ``align``, ``distill``, ``pixel`` (adaptively normalised one-step RGB MSE), ``perc``
        (zeros when not applicable) and the one-step prediction
        ``x_one_step`` (detached, for PSNR/logging).

        The flow term uses one JVP at (z_t, r, t); rec / pixel / perc / distill use the one-step rendering
        path x_theta(z_src, 0, 1) so they supervise exactly what :meth:`render` produces.
        """
        self._check_condition(condition)
        if self.decoder is None:
            raise RuntimeError("no_pixel_flow renderer has nothing to train")
        cfg, m = self.cfg, self.cfg.meanflow
        target = to_state(target_rgb, target_depth.clamp_min(0), m.depth_scale)
        prior, alpha = prior_state(condition, m.depth_scale)
        z_src = mf.alpha_gated_source(prior, alpha, noise, m.sigma_small, m.sigma_large)
        tokens = self.tokens(condition)
        zero = target.new_zeros((), dtype=torch.float32)

        # --- MeanFlow term -------------------------------------------------------------------
        z_t = mf.interpolate(target, z_src, t)
        v = mf.target_velocity(target, z_src)

        def x_fn(z, r_, t_):
            return self.predict(z, condition, r_, t_, tokens).x

        if m.tangent == "model":
            with torch.no_grad():
                tangent = mf.average_velocity(z_t, x_fn(z_t, t, t), t, m.t_eps)
        else:
            tangent = v
        u, dudt = mf.total_derivative(x_fn, z_t, r, t, tangent, m.t_eps)
        V = mf.compound_velocity(u, dudt, t, r)
        weight = mf.opacity_weight(alpha, m.weight_k) if spatial_focus else None
        flow, flow_raw = mf.flow_loss(V, v, weight, m.norm_c, m.norm_power)
        # Saturation: the clean colour implied by V (jump from z_t to t = 0) must stay in [0, 1].
        implied = z_t[:, :3] - t.view(-1, 1, 1, 1) * V[:, :3]
        flow = flow + cfg.loss.saturation * saturation_penalty(implied)

        # --- one-step rendering path ----------------------------------------------------------
        ones, zeros = torch.ones_like(t), torch.zeros_like(t)
        out = self.predict(z_src, condition, zeros, ones, tokens)
        rgb, depth = from_state(out.x, m.depth_scale)
        rec = reconstruction_loss(
            rgb,
            depth / m.depth_scale,
            target_rgb,
            target_depth / m.depth_scale,
            cfg.loss.rgb_weight_in_rec,
            cfg.loss.depth_weight_in_rec,
        )
        align = zero
        if tokens is not None and target_tokens is not None:
            align = alignment_loss(self.aligner.project(tokens), target_tokens)
        distill = zero
        if teacher is not None and teacher.decoder is not None:
            with torch.no_grad():
                z_gt = teacher.privileged_source(target, noise)
                t_out = teacher.predict(z_gt, condition, zeros, ones, teacher.tokens(condition))
            distill = distillation_loss(
                out.features,
                t_out.features,
                cfg.distill.level_weights,
                cfg.distill.beta,
                normalise=cfg.distill.normalise_features,
            )
        pixel = mf.adaptive_normalise(
            (rgb.float() - target_rgb.float()).pow(2).flatten(1).mean(1), cfg.loss.pixel_norm_c
        ).mean()
        if cfg.loss.pixel_depth_weight > 0:
            pixel = pixel + cfg.loss.pixel_depth_weight * mf.adaptive_normalise(
                relative_depth_error(depth, target_depth), cfg.loss.pixel_norm_c
            ).mean()
        perc = zero
        if perceptual is not None:
            perc = perceptual(rgb.float(), target_rgb.float()).mean()
        return {
            "flow": flow,
            "flow_raw": flow_raw.mean(),
            "rec": rec,
            "align": align,
            "distill": distill,
            "pixel": pixel,
            "perc": perc,
            "x_one_step": out.x.detach(),
        }


def save_renderer(model: PixelFlowRenderer, path) -> None:
    """Inference weights as one ``.safetensors`` file; the resolved config rides in its metadata
    (JSON), so :func:`load_renderer` needs nothing else. Written atomically (temp + rename)."""
    import json
    from dataclasses import asdict

    from image2sim.simulator.io.atomic import atomic_path
    from safetensors.torch import save_file

    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    with atomic_path(path) as tmp:
        save_file(
            tensors,
            str(tmp),
            metadata={"format": "image2sim-renderer-v1", "config": json.dumps(asdict(model.cfg))},
        )


def _saved_config(data: dict) -> dict:
    """A saved renderer config as it was trained: files written before ``decoder.residual_heads``
    existed trained the paper's plain heads, so a missing key means False (the new default is True)."""
    data = dict(data)
    decoder = dict(data.get("decoder") or {})
    decoder.setdefault("residual_heads", False)
    data["decoder"] = decoder
    return data


def load_renderer(path, map_location: str = "cpu") -> PixelFlowRenderer:
    """Inverse of :func:`save_renderer`; also accepts a Lightning checkpoint of ``RendererModule``
    (read with ``weights_only=True``)."""
    import json
    from pathlib import Path

    from image2sim.simulator.renderer.config import renderer_config_from_dict

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"renderer weights {path} do not exist")
    if path.suffix == ".safetensors":
        from safetensors import safe_open
        from safetensors.torch import load_file

        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
        if meta.get("format") != "image2sim-renderer-v1" or "config" not in meta:
            raise ValueError(
                f"{path}: not an image2sim renderer file (metadata format {meta.get('format')!r})"
            )
        cfg = renderer_config_from_dict(_saved_config(json.loads(meta["config"])))
        state = load_file(str(path), device=map_location)
    else:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
        try:
            cfg = renderer_config_from_dict(_saved_config(ckpt["hyper_parameters"]["config"]))
        except KeyError as exc:
            raise ValueError(f"{path}: checkpoint has no renderer config in hyper_parameters") from exc
        state = {k[len("renderer.") :]: v for k, v in ckpt["state_dict"].items() if k.startswith("renderer.")}
    model = PixelFlowRenderer(cfg)
    missing, unexpected = model.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise ValueError(
            f"{path}: weights do not match the config (missing {missing[:3]}, unexpected {unexpected[:3]})"
        )
    return model.eval()
