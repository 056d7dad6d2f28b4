"""Dense depth for RGB-only views, in the units of their structure-from-motion reconstruction.

:func:`estimate_depth` is the one entry point of the lifting pipeline. Two sources:

- ``"mvs"``: plane-sweep multi-view stereo (:mod:`image2sim.simulator.lift.mvs`), no weights;
- ``"model"``: a monocular depth network loaded from a local folder through transformers
  (``AutoModelForDepthEstimation``, e.g. Depth Anything; safetensors only, no network). Its output
  is aligned to each view's sparse SfM depths: a relative (disparity-like) model gets a scale and a
  shift fitted in inverse depth, ``1/z = s * pred + t``; a metric model (config
  ``depth_estimation_type == "metric"``) gets a scale only, ``z = s * pred``. The fit is RANSAC
  over minimal samples followed by Huber IRLS on the inliers (:func:`fit_alignment`).
- ``"mvs+model"``: the stereo first; then the network, aligned to the SfM depths *and* the stereo's
  confident pixels (many more points than SfM gives), fills the pixels the stereo left without
  depth, at a confidence below every stereo pixel's (:data:`MODEL_FILL_CONFIDENCE`).

Confidence of a model's depth: the frame's fit quality (inlier fraction, and the inliers' robust
relative residual against ``inlier_threshold``) times a per-pixel term that falls at depth
discontinuities of the aligned depth (where monocular networks blur foreground into background).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from image2sim.simulator.io.resample import sample_bilinear
from image2sim.simulator.lift.mvs import MVSConfig, run_mvs, validate_sparse, validate_views
from image2sim.simulator.lift.types import DepthEstimate, PinholeView, SparseDepth

__all__ = [
    "SOURCES",
    "AlignmentFit",
    "fit_alignment",
    "DepthModel",
    "load_depth_model",
    "align_prediction",
    "estimate_depth",
]

log = logging.getLogger(__name__)

SOURCES = ("mvs", "model", "mvs+model")
"""Depth sources :func:`estimate_depth` knows."""
MIN_FIT_POINTS = 8
"""A view needs at least this many sparse depths to align a model's prediction."""
MIN_FIT_SPREAD = 0.1
"""A relative model's fit needs its inliers' inverse depths to spread by this much
(:attr:`AlignmentFit.usable`)."""
MODEL_FILL_CONFIDENCE = 0.4
"""``source="mvs+model"``: a model-filled pixel's confidence is its own times this, so it stays below
the 0.5 at which dense depth joins the floor search (``LiftOptions.min_confidence_floor``)."""
STEREO_FIT_CONFIDENCE = 0.5
"""``source="mvs+model"``: stereo pixels at or above this confidence join the model's alignment."""
STEREO_FIT_POINTS = 4000
"""At most this many stereo pixels per view join the alignment (a seeded random subset)."""


# ----------------------------------------------------------------------------------------- alignment


@dataclass
class AlignmentFit:
    """A robust fit of a model's output to sparse depths.

    ``space == "inverse"``: ``1/z = scale * pred + shift``; ``space == "depth"``: ``z = scale * pred``
    (shift 0). ``residual`` is the inliers' median absolute relative residual (in the fitted space,
    which to first order is the relative depth error).
    """

    scale: float
    shift: float
    space: str
    inliers: np.ndarray
    residual: float
    spread: float = math.inf
    """The inliers' spread of the fitted target, (90th - 10th percentile) / median of ``1/z``
    (``inverse``; infinite for ``depth``, whose scale-only fit is fixed by any one point)."""

    @property
    def usable(self) -> bool:
        """Whether the fit fixes the model's depth: a positive scale (a disparity-like output grows
        as things come nearer) and, in inverse depth, targets that spread by at least
        :data:`MIN_FIT_SPREAD`. Points on one surface facing the camera (a ceiling or a floor seen
        straight on) share one depth and leave the scale free: any scale fits them."""
        return math.isfinite(self.scale) and self.scale > 0 and self.spread >= MIN_FIT_SPREAD

    @property
    def num_points(self) -> int:
        return int(self.inliers.size)

    @property
    def num_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def inlier_fraction(self) -> float:
        return self.num_inliers / max(1, self.num_points)

    def apply(self, pred: np.ndarray) -> np.ndarray:
        """Depth from the model's output; 0 where the fitted inverse depth is not positive."""
        pred = np.asarray(pred, np.float64)
        if self.space == "depth":
            z = self.scale * pred
            return np.where(np.isfinite(z) & (z > 0), z, 0.0)
        inv = self.scale * pred + self.shift
        ok = np.isfinite(inv) & (inv > 0)
        return np.where(ok, 1.0 / np.where(ok, inv, 1.0), 0.0)


def _weighted_fit(x: np.ndarray, y: np.ndarray, w: np.ndarray, shift: bool) -> tuple[float, float]:
    """Weighted least squares of ``y ~ s x + t`` (``t = 0`` without shift), relative residuals.

    Each equation is divided by ``y`` so the residual is relative: ``(s x + t - y) / y``.
    """
    a = x / y
    sw = np.sqrt(w)
    if not shift:
        den = float(np.sum(w * a * a))
        return (float(np.sum(w * a)) / den if den > 0 else math.nan), 0.0
    M = np.stack([a, 1.0 / y], 1) * sw[:, None]
    sol, *_ = np.linalg.lstsq(M, sw, rcond=None)
    return float(sol[0]), float(sol[1])


def fit_alignment(
    pred: np.ndarray,
    depth: np.ndarray,
    *,
    space: str = "inverse",
    inlier_threshold: float = 0.1,
    iterations: int = 200,
    irls_steps: int = 10,
    seed: int = 0,
) -> AlignmentFit:
    """Fit a model's output ``pred`` (k,) to sparse depths ``depth`` (k,) robustly.

    ``space="inverse"``: ``1/depth = s * pred + t`` (relative, disparity-like models);
    ``space="depth"``: ``depth = s * pred`` (metric models, scale only). Residuals are relative
    (``(s pred + t - y) / y`` with ``y`` the target in that space); a point is an inlier when its
    residual is below ``inlier_threshold``. RANSAC (``iterations`` minimal samples of 2, or 1 for
    scale only, from a seeded generator: deterministic) picks the inlier set; Huber IRLS on it refines
    the fit, and the inliers are recounted. Noise-free data are recovered exactly (least squares).
    """
    if space not in ("inverse", "depth"):
        raise ValueError(f"alignment space must be 'inverse' or 'depth', got {space!r}")
    x = np.asarray(pred, np.float64).reshape(-1)
    z = np.asarray(depth, np.float64).reshape(-1)
    if x.shape != z.shape:
        raise ValueError(f"alignment: {x.size} predictions for {z.size} depths")
    ok = np.isfinite(x) & np.isfinite(z) & (z > 0)
    shift = space == "inverse"
    need = 2 if shift else 1
    if int(ok.sum()) < max(need, 2):
        raise ValueError(f"alignment needs at least {max(need, 2)} finite sparse depths, got {int(ok.sum())}")
    x, z = x[ok], z[ok]
    y = 1.0 / z if shift else z
    n = x.size
    rng = np.random.default_rng(seed)

    def residuals(s: float, t: float) -> np.ndarray:
        return np.abs(s * x + t - y) / y

    best_count, best = -1, (math.nan, math.nan)
    for _ in range(iterations):
        pick = rng.choice(n, need, replace=False)
        if shift:
            dx = x[pick[1]] - x[pick[0]]
            if abs(dx) < 1e-12:
                continue
            s = (y[pick[1]] - y[pick[0]]) / dx
            t = y[pick[0]] - s * x[pick[0]]
        else:
            if abs(x[pick[0]]) < 1e-12:
                continue
            s, t = y[pick[0]] / x[pick[0]], 0.0
        if not (math.isfinite(s) and s > 0):
            continue
        count = int(np.sum(residuals(s, t) < inlier_threshold))
        if count > best_count:
            best_count, best = count, (s, t)
    if best_count < need:
        s, t = _weighted_fit(x, y, np.ones(n), shift)
    else:
        s, t = best
    inliers = residuals(s, t) < inlier_threshold
    if inliers.sum() >= need:
        # Huber IRLS on the inliers, scale of the residuals from their MAD.
        weights = np.ones(int(inliers.sum()))
        xi, yi = x[inliers], y[inliers]
        for _ in range(irls_steps):
            s, t = _weighted_fit(xi, yi, weights, shift)
            r = np.abs(s * xi + t - yi) / yi
            delta = max(1.4826 * float(np.median(r)), 1e-12)
            weights = np.where(r <= delta, 1.0, delta / np.maximum(r, 1e-300))
        inliers = residuals(s, t) < inlier_threshold
    full = np.zeros(ok.size, dtype=bool)
    full[np.flatnonzero(ok)] = inliers
    residual = float(np.median(residuals(s, t)[inliers])) if inliers.any() else math.inf
    spread = math.inf
    if shift:
        spread = 0.0
        if inliers.sum() >= 2:
            lo, mid, hi = np.percentile(y[inliers], [10, 50, 90])
            spread = float((hi - lo) / mid)
    return AlignmentFit(
        scale=float(s), shift=float(t), space=space, inliers=full, residual=residual, spread=spread
    )


# ------------------------------------------------------------------------------------------- model


@dataclass
class DepthModel:
    """A transformers depth-estimation model with its image processor, on the CPU or a device."""

    model: torch.nn.Module
    processor: object
    metric: bool
    device: torch.device

    @torch.no_grad()
    def predict(self, image: np.ndarray) -> np.ndarray:
        """The model's raw output (H, W) float32 for an (H, W, 3) uint8 image, resized to it."""
        h, w = image.shape[:2]
        inputs = self.processor(images=image, return_tensors="pt")
        pixel_values = inputs["pixel_values"].to(self.device)
        out = self.model(pixel_values=pixel_values).predicted_depth
        if out.ndim == 3:
            out = out[:, None]
        out = torch.nn.functional.interpolate(out.float(), size=(h, w), mode="bilinear", align_corners=False)
        return out[0, 0].cpu().numpy().astype(np.float32)


def load_depth_model(model_dir: str | Path, *, device: str = "cpu") -> DepthModel:
    """Load a depth-estimation model and its image processor from a local folder (no network).

    The folder holds a transformers ``config.json``, ``model.safetensors`` (pickled ``.bin`` weights
    are refused) and ``preprocessor_config.json``. Whether the output is metric comes from the
    config's ``depth_estimation_type`` (Depth Anything) or ``is_metric``; anything else is relative.
    """
    from transformers import AutoImageProcessor, AutoModelForDepthEstimation

    folder = Path(model_dir)
    if not folder.is_dir():
        raise ValueError(f"depth model folder {folder} does not exist")
    for name in ("config.json", "preprocessor_config.json"):
        if not (folder / name).is_file():
            raise ValueError(f"depth model folder {folder} has no {name}")
    if not any(folder.glob("*.safetensors")):
        raise ValueError(
            f"depth model folder {folder} has no .safetensors weights (pickled weights are not loaded)"
        )
    try:
        model = AutoModelForDepthEstimation.from_pretrained(
            folder, local_files_only=True, use_safetensors=True
        )
        processor = AutoImageProcessor.from_pretrained(folder, local_files_only=True)
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"depth model folder {folder}: {exc}") from exc
    config = model.config
    metric = getattr(config, "depth_estimation_type", None) == "metric" or bool(
        getattr(config, "is_metric", False)
    )
    dev = torch.device(device)
    return DepthModel(model.to(dev).eval(), processor, metric, dev)


def _edge_confidence(depth: np.ndarray, scale: float = 0.1) -> np.ndarray:
    """exp(-(g / scale)^2), g = the largest relative depth step to a 4-neighbour (0 on invalid)."""
    valid = depth > 0
    log_d = np.log(np.where(valid, depth, 1.0))
    g = np.zeros_like(log_d)
    for axis in (0, 1):
        step = np.abs(np.diff(log_d, axis=axis))
        pad_lo = [(0, 0), (0, 0)]
        pad_hi = [(0, 0), (0, 0)]
        pad_lo[axis] = (1, 0)
        pad_hi[axis] = (0, 1)
        g = np.maximum(g, np.maximum(np.pad(step, pad_lo), np.pad(step, pad_hi)))
    return np.where(valid, np.exp(-((g / scale) ** 2)), 0.0)


def align_prediction(
    pred: np.ndarray,
    sparse: SparseDepth | None,
    *,
    metric: bool,
    inlier_threshold: float = 0.1,
    seed: int = 0,
) -> tuple[DepthEstimate, AlignmentFit | None]:
    """Aligned depth and confidence of one view from the model's raw output ``pred`` (H, W).

    A relative model needs at least :data:`MIN_FIT_POINTS` sparse depths (else depth 0, no fit);
    a metric model without them is used as it is (confidence from the edge term alone, halved).
    A fit that does not fix the depth (:attr:`AlignmentFit.usable`) leaves depth 0 and is returned
    for the record.
    """
    pred = np.asarray(pred, np.float64)
    n = 0 if sparse is None else int(sparse.depth.size)
    if n < MIN_FIT_POINTS:
        if not metric:
            zero = np.zeros(pred.shape, np.float32)
            return DepthEstimate(zero, zero.copy()), None
        depth = np.where(np.isfinite(pred) & (pred > 0), pred, 0.0)
        conf = 0.5 * _edge_confidence(depth)
        return DepthEstimate(depth.astype(np.float32), conf.astype(np.float32)), None
    at = sample_bilinear(pred, sparse.uv[:, 0], sparse.uv[:, 1])
    fit = fit_alignment(
        at, sparse.depth, space="depth" if metric else "inverse", inlier_threshold=inlier_threshold, seed=seed
    )
    if not fit.usable:
        zero = np.zeros(pred.shape, np.float32)
        return DepthEstimate(zero, zero.copy()), fit
    depth = fit.apply(pred)
    quality = fit.inlier_fraction * math.exp(-((fit.residual / inlier_threshold) ** 2))
    conf = np.clip(quality * _edge_confidence(depth), 0.0, 1.0)
    return DepthEstimate(depth.astype(np.float32), conf.astype(np.float32)), fit


# ----------------------------------------------------------------------------------------- entry point


def stereo_fit_points(
    sparse: SparseDepth | None, stereo: DepthEstimate, seed: int, max_points: int = STEREO_FIT_POINTS
) -> SparseDepth:
    """The view's SfM depths plus up to ``max_points`` of its confident stereo pixels (centres at +0.5)."""
    v, u = np.nonzero((stereo.depth > 0) & (stereo.confidence >= STEREO_FIT_CONFIDENCE))
    if u.size > max_points:
        pick = np.sort(np.random.default_rng(seed).choice(u.size, max_points, replace=False))
        u, v = u[pick], v[pick]
    uv = np.stack([u + 0.5, v + 0.5], axis=1).astype(np.float64)
    depth = stereo.depth[v, u].astype(np.float64)
    if sparse is not None and sparse.depth.size:
        uv = np.concatenate([np.asarray(sparse.uv, np.float64), uv])
        depth = np.concatenate([np.asarray(sparse.depth, np.float64), depth])
    return SparseDepth(uv, depth)


def fill_from_model(stereo: DepthEstimate, model: DepthEstimate) -> tuple[DepthEstimate, int]:
    """Stereo depth kept where it exists; elsewhere the aligned model's depth at
    :data:`MODEL_FILL_CONFIDENCE` times its confidence. Returns the fused estimate and the filled count."""
    fill = (stereo.depth <= 0) & (model.depth > 0) & (model.confidence > 0)
    depth = np.where(fill, model.depth, stereo.depth).astype(np.float32)
    conf = np.where(fill, np.float32(MODEL_FILL_CONFIDENCE) * model.confidence, stereo.confidence)
    return DepthEstimate(depth, conf.astype(np.float32)), int(fill.sum())


def _pop_model_options(kw: dict) -> tuple[str, float]:
    """The depth model's own options (``device``, ``inlier_threshold``), taken out of ``kw``."""
    device = str(kw.pop("device", "cpu"))
    threshold = float(kw.pop("inlier_threshold", 0.1))
    if not (math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"inlier_threshold must be finite and > 0, got {threshold}")
    return device, threshold


def estimate_depth(
    views: list[PinholeView],
    *,
    source: str = "mvs",
    model_dir: str | None = None,
    sparse: list[SparseDepth] | None = None,
    progress: bool = True,
    stats: list[dict] | None = None,
    **kw,
) -> list[DepthEstimate]:
    """Dense z-depth (reconstruction units, 0 = invalid) and confidence in [0, 1] for every view.

    ``source="mvs"``: plane-sweep stereo; ``kw`` are :class:`~image2sim.simulator.lift.mvs.MVSConfig`
    fields (unknown names are an error). Needs two or more overlapping views and a depth range
    (``sparse``, or ``near=`` and ``far=``). ``source="model"``: the depth network in ``model_dir``
    aligned to ``sparse`` (required for a relative model); ``kw``: ``device`` (default ``"cpu"``),
    ``inlier_threshold`` (0.1). ``source="mvs+model"``: both, the model aligned to the SfM and
    confident stereo depths and filling what the stereo left empty; ``kw`` may hold either's
    options. ``stats``, when given, receives one dict per view (timings, sources or fit: scale,
    shift, inliers, residual; for ``mvs+model`` the stereo's record with ``model_*`` keys added).
    """
    if source not in SOURCES:
        raise ValueError(f"unknown depth source {source!r}; expected one of {list(SOURCES)}")
    validate_views(views)
    sparse = validate_sparse(sparse, views)
    if source == "mvs":
        if model_dir is not None:
            raise ValueError("model_dir is only used by source='model' or 'mvs+model'")
        config = MVSConfig.from_kwargs(**kw)
        return run_mvs(views, sparse, config, progress=progress, stats=stats)

    if model_dir is None:
        raise ValueError(f"source={source!r} needs model_dir: a local folder with a transformers depth model")
    device, threshold = _pop_model_options(kw)
    if source == "model" and kw:
        raise ValueError(f"unknown depth-model option(s) {sorted(kw)}; known: ['device', 'inlier_threshold']")
    mvs_config = MVSConfig.from_kwargs(**kw) if source == "mvs+model" else None
    model = load_depth_model(model_dir, device=device)
    if not model.metric and (sparse is None or not any(sp.depth.size >= MIN_FIT_POINTS for sp in sparse)):
        raise ValueError(
            f"a relative depth model ({model_dir}) needs sparse SfM depths to fix its scale and shift "
            f"(at least {MIN_FIT_POINTS} points in a view)"
        )
    stereo: list[DepthEstimate] | None = None
    stereo_stats: list[dict] = []
    if mvs_config is not None:
        stereo = run_mvs(views, sparse, mvs_config, progress=progress, stats=stereo_stats)
    iterator = range(len(views))
    if progress:
        from rich.progress import track

        iterator = track(iterator, description="depth (model)", total=len(views))
    out = []
    for i in iterator:
        t0 = time.perf_counter()
        pred = model.predict(np.asarray(views[i].image))
        points = None if sparse is None else sparse[i]
        if stereo is not None:
            points = stereo_fit_points(points, stereo[i], seed=i)
        est, fit = align_prediction(pred, points, metric=model.metric, inlier_threshold=threshold, seed=i)
        filled = None
        if stereo is not None:
            est, filled = fill_from_model(stereo[i], est)
        record = {
            "view": i,
            "seconds": time.perf_counter() - t0,
            "confident_fraction": float((est.confidence > 0).mean()),
        }
        if fit is None:
            if not model.metric:
                log.warning("view %d: too few sparse depths to align the model; its depth is left invalid", i)
            record.update(scale=None, shift=None, inliers=0, points=0, residual=None, usable=False)
        else:
            record.update(
                scale=fit.scale,
                shift=fit.shift,
                inliers=fit.num_inliers,
                points=fit.num_points,
                residual=fit.residual,
                spread=fit.spread if math.isfinite(fit.spread) else None,
                usable=fit.usable,
            )
        if stereo is not None:
            base = dict(stereo_stats[i]) if i < len(stereo_stats) else {"view": i}
            record = {
                **base,
                **{f"model_{k}": v for k, v in record.items() if k != "view"},
                "model_filled_px": filled,
                "confident_fraction": record["confident_fraction"],
            }
        if stats is not None:
            stats.append(record)
        out.append(est)
    return out
