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
from image2sim.simulator.renderer.condition import from_state, prior_state, to_state, without_features
from image2sim.simulator.renderer.config import CONDITION_CHANNELS, STATE_CHANNELS, RendererConfig
from image2sim.simulator.renderer.decoder import DecoderOutput, RenderingDecoder
from image2sim.simulator.renderer.distill import distillation_loss
from image2sim.simulator.renderer.losses import reconstruction_loss, relative_depth_error, saturation_penalty
from torch import nn

__all__ = ["RenderOutput", "PixelFlowRenderer", "save_renderer", "export_renderer", "load_renderer"]


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
        """x_theta(z, r, t | C_p, tokens). With ``no_semantic`` the condition's projected feature
        map is zeroed first: Table 4's "w/o semantic features" removes the features, not only the
        aligner and injectors (otherwise a learned encoder's features still enter the decoder's
        input convolution)."""
        if self.decoder is None:
            raise RuntimeError("no_pixel_flow renderer has no network")
        if self.cfg.ablation.no_semantic:
            condition = without_features(condition)
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
            pixel = (
                pixel
                + cfg.loss.pixel_depth_weight
                * mf.adaptive_normalise(
                    relative_depth_error(depth, target_depth), cfg.loss.pixel_norm_c
                ).mean()
            )
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


RENDERER_FORMAT = "image2sim-renderer-v1"
"""Format tag of saved renderer weights (safetensors metadata and ``renderer.json``)."""

RENDERER_WEIGHTS, RENDERER_CONFIG = "renderer.safetensors", "renderer.json"
"""File names inside an exported renderer folder (:func:`export_renderer`)."""


def _state_tensors(model: PixelFlowRenderer) -> dict[str, torch.Tensor]:
    """The inference weights as contiguous CPU tensors (what safetensors stores)."""
    return {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}


def save_renderer(model: PixelFlowRenderer, path) -> None:
    """Inference weights as one ``.safetensors`` file; the resolved config rides in its metadata
    (JSON), so :func:`load_renderer` needs nothing else. Written atomically (temp + rename)."""
    import json

    from image2sim.simulator.io.atomic import atomic_path
    from image2sim.simulator.renderer.config import config_to_dict
    from safetensors.torch import save_file

    with atomic_path(path) as tmp:
        save_file(
            _state_tensors(model),
            str(tmp),
            metadata={"format": RENDERER_FORMAT, "config": json.dumps(config_to_dict(model.cfg))},
        )


def export_renderer(
    model: PixelFlowRenderer, out_dir, extra: dict | None = None, training_record: dict | None = None
):
    """The renderer as a folder: ``renderer.safetensors`` (weights, no pickle) and ``renderer.json``
    (``format``, the resolved ``config``, plus ``extra`` such as the source checkpoint); with
    ``training_record`` also the run's ``training_data.json``, so evaluations of the folder compare
    their conditions with the training ones as they do for the checkpoint.

    :func:`load_renderer` reads the folder back; the folder is written whole (temp folder + rename,
    :func:`~image2sim.simulator.io.atomic.atomic_dir`). Returns the folder.
    """
    import json
    from pathlib import Path

    from image2sim.simulator.io.atomic import atomic_dir
    from image2sim.simulator.renderer.config import config_to_dict
    from safetensors.torch import save_file

    doc = {"format": RENDERER_FORMAT, "config": config_to_dict(model.cfg), **(extra or {})}
    with atomic_dir(out_dir) as tmp:
        save_file(_state_tensors(model), str(tmp / RENDERER_WEIGHTS), metadata={"format": RENDERER_FORMAT})
        (tmp / RENDERER_WEIGHTS).chmod(0o644)  # safetensors creates 0600; exports are shared artifacts
        (tmp / RENDERER_CONFIG).write_text(json.dumps(doc, indent=2) + "\n")
        if training_record is not None:
            from image2sim.simulator.renderer.splat_data import TRAINING_RECORD

            (tmp / TRAINING_RECORD).write_text(json.dumps(training_record, indent=2) + "\n")
    return Path(out_dir)


def _saved_config(data: dict) -> dict:
    """A saved renderer config as it was trained: files written before ``decoder.residual_heads``
    existed trained the paper's plain heads, files written before ``decoder.depth_gate`` existed
    trained an ungated depth correction, files written before ``decoder.prior_filter`` had no
    filter and the grey prior, and files written before ``decoder.prior_hidden`` had no MLP path,
    so a missing key means that (the presets may say otherwise)."""
    data = dict(data)
    decoder = dict(data.get("decoder") or {})
    decoder.setdefault("residual_heads", False)
    decoder.setdefault("depth_gate", False)
    decoder.setdefault("prior_filter", 0)
    decoder.setdefault("prior_hidden", 0)
    decoder.setdefault("prior_fill", "grey")
    data["decoder"] = decoder
    return data


def _read_weights_file(path, map_location: str) -> tuple[dict, dict]:
    """(config dict, state) of a :func:`save_renderer` file (config in the safetensors metadata)."""
    import json

    from safetensors import safe_open
    from safetensors.torch import load_file

    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
    if meta.get("format") != RENDERER_FORMAT or "config" not in meta:
        raise ValueError(f"{path}: not an image2sim renderer file (metadata format {meta.get('format')!r})")
    return json.loads(meta["config"]), load_file(str(path), device=map_location)


def _read_export_folder(folder, map_location: str) -> tuple[dict, dict]:
    """(config dict, state) of an :func:`export_renderer` folder."""
    from image2sim.simulator.config import read_mapping
    from safetensors.torch import load_file

    weights, config = folder / RENDERER_WEIGHTS, folder / RENDERER_CONFIG
    for p in (weights, config):
        if not p.is_file():
            raise FileNotFoundError(
                f"{p} not found: a renderer folder holds {RENDERER_WEIGHTS} and {RENDERER_CONFIG}"
            )
    doc = read_mapping(config)
    if doc.get("format") != RENDERER_FORMAT or "config" not in doc:
        raise ValueError(
            f"{config}: not an image2sim renderer config (format {doc.get('format')!r}, needs 'config')"
        )
    return doc["config"], load_file(str(weights), device=map_location)


def _read_lightning_checkpoint(path, map_location: str) -> tuple[dict, dict]:
    """(config dict, state) of a Lightning checkpoint of ``RendererModule`` (``weights_only=True``)."""
    ckpt = torch.load(path, map_location=map_location, weights_only=True)
    try:
        config = ckpt["hyper_parameters"]["config"]
        state_dict = ckpt["state_dict"]
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{path}: checkpoint has no renderer config in hyper_parameters") from exc
    prefix = "renderer."
    return config, {k[len(prefix) :]: v for k, v in state_dict.items() if k.startswith(prefix)}


def load_renderer(path, map_location: str = "cpu") -> PixelFlowRenderer:
    """A renderer in eval mode from any of its saved forms: an :func:`export_renderer` folder
    (``renderer.safetensors`` + ``renderer.json``), a :func:`save_renderer` ``.safetensors`` file, or a
    Lightning checkpoint of ``RendererModule`` (read with ``weights_only=True``)."""
    from pathlib import Path

    from image2sim.simulator.renderer.config import renderer_config_from_dict

    path = Path(path)
    if path.is_dir():
        data, state = _read_export_folder(path, map_location)
    elif not path.is_file():
        raise FileNotFoundError(f"renderer weights {path} do not exist")
    elif path.suffix == ".safetensors":
        data, state = _read_weights_file(path, map_location)
    else:
        data, state = _read_lightning_checkpoint(path, map_location)
    model = PixelFlowRenderer(renderer_config_from_dict(_saved_config(data)))
    missing, unexpected = model.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise ValueError(
            f"{path}: weights do not match the config (missing {missing[:3]}, unexpected {unexpected[:3]})"
        )
    return model.eval()
