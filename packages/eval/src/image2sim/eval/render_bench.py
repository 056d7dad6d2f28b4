"""Rendering benchmark, the protocol of the paper's Table 1: splat-only vs pixel flow with 1/2/4/8 steps.

Held-out target panoramas (every ``holdout_every``-th frame of each capture, the split of
``image2sim sim train`` / ``sim renderer-eval``) are turned into splat-like conditions at three noise
tiers (none / middle / high) and rendered by each method:

* ``splat_only``: the projected RGB-D prior, no network (the renderer's ``no_pixel_flow`` switch);
* ``splat_fill``: the same prior with its holes filled by normalised convolution
  (:func:`~image2sim.simulator.renderer.holefill.fill_holes`), a non-learned reference, so a
  renderer's gain over interpolation shows, not only its gain over empty holes;
* ``flow_{n}step``: the pixel-flow renderer sampled in ``n`` network evaluations;
* ablations: further checkpoints trained with a Table-4 switch (``no_semantic``, ``no_alpha_gate``,
  ``no_distill``), scored at one step as ``ablation_<switch>``.

Every view is scored with :func:`image2sim.eval.render_scores.score_views` (PSNR, SSIM of Wang et al.,
LPIPS when weights are configured else n/a, depth AbsRel / RMSE / δ<1.25); frame rate comes from
:func:`image2sim.eval.metrics.timing.measure_fps` (median over timed runs **after** warm-up).

Pinhole-input variant (``input_views="pinhole6"``, the paper's Table 1 pinhole rows): each input
panorama is replaced by its six 90° cubemap faces
(:func:`~image2sim.eval.render_samples.pinhole_faces`, pinhole frames with z-depth and their own
poses) before the Gaussians are built; the held-out panorama targets, conditions and metrics stay
the same. The samples (targets and conditions) are built in :mod:`image2sim.eval.render_samples`.

The data path (targets, split, degradations, checkpoint format) is the renderer's own
(:mod:`image2sim.simulator.renderer`), reused rather than re-implemented, so ``sim renderer-eval``
and this benchmark evaluate the same views. Until cached splats of Gaussian scenes are wired in, the
conditions are the renderer's :class:`~image2sim.simulator.renderer.data.DegradedPanoramaDataset`
degradations, with the tier's noise levels below; the output records this as ``condition_source``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from image2sim.eval.metrics.lpips import LPIPS
from image2sim.eval.metrics.timing import hardware_string, measure_fps
from image2sim.eval.render_samples import (
    INPUT_VIEWS,
    NOISE_TIERS,
    RenderBenchError,
    splat_samples,
    tier_samples,
)
from image2sim.eval.render_scores import RenderCell, score_views, summarize_views
from image2sim.eval.results import write_metrics_file
from image2sim.simulator.config import ConfigError, config_from_dict

logger = logging.getLogger(__name__)

__all__ = [
    "HEADLINE_METHODS",
    "NOISE_TIERS",
    "RenderBenchConfig",
    "RenderBenchError",
    "MethodFn",
    "benchmark_methods",
    "load_renderer",
    "method_record",
    "render_markdown",
    "run_render_bench",
]

HEADLINE_METHODS = ("splat_only", "flow_1step", "flow_2step", "flow_4step", "flow_8step")
"""Method names ``metrics/render.json`` always carries (outside checks read them)."""

ABLATIONS = ("no_semantic", "no_alpha_gate", "no_distill")
"""Table-4 switches that need their own trained checkpoint."""

MethodFn = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""``fn(condition (B, 24, H, W), poses (B, 4, 4)) -> (rgb (B, 3, H, W), depth (B, 1, H, W))``."""


@dataclass
class RenderBenchConfig:
    """One rendering benchmark run."""

    renderer_config: str = "tiny"
    """Renderer preset name or YAML file (the one the checkpoint was trained with)."""
    checkpoint: str | None = None
    """Renderer weights (Lightning checkpoint, ``save_renderer`` file or ``export-renderer`` folder);
    None = an untrained model (recorded as ``trained: false``)."""
    data: list[str] = field(default_factory=list)
    """Capture folders with target panoramas; empty = the renderer's procedural box-room panoramas."""
    holdout_every: int = 8
    """Every n-th frame is a held-out target (the training split of ``sim train``)."""
    max_frames: int | None = None
    """At most this many frames per capture (None = all)."""
    max_views: int | None = None
    """Score at most this many held-out views per tier (None = all)."""
    steps: list[int] = field(default_factory=lambda: [1, 2, 4, 8])
    """Pixel-flow step counts (each gives ``flow_{n}step``)."""
    tiers: list[str] = field(default_factory=lambda: list(NOISE_TIERS))
    """Noise tiers to evaluate (keys of :data:`NOISE_TIERS`)."""
    ablations: dict[str, str] = field(default_factory=dict)
    """Ablation switch -> checkpoint trained with it (scored at one step as ``ablation_<switch>``)."""
    condition_source: str = "degraded"
    """``degraded``: the renderer's splat-like degradations of the targets, noise per tier;
    ``gaussians``: identity Gaussian scenes built from each capture's training frames, splatted at
    the held-out poses (the tier is the capture's own noise, see ``tier_data``)."""
    tier_data: dict[str, list[str]] = field(default_factory=dict)
    """``gaussians`` source: tier name -> capture folders captured at that noise tier (e.g. the
    procedural ``--noise none/middle/high`` captures); empty = ``data`` as one tier ``capture``."""
    gaussian_config: str = "tiny"
    """``gaussians`` source: Gaussian scene preset or YAML/JSON."""
    encoder: str = "identity"
    """``gaussians`` source: ``identity`` or a stage-1 encoder checkpoint (file or folder) whose
    feature Gaussians build the scenes (what a renderer trained with ``sim train --encoder`` saw)."""
    source_every: int = 1
    """``gaussians`` source: only every n-th training frame builds the Gaussians (1: all, a dense
    capture; n > 1: a sparse capture with holes). Same rule as ``sim train --source-every``."""
    target: str = "auto"
    """``gaussians`` source: what a view is scored against. ``exact``: the noise-free rendering of a
    procedural capture's scene at the queried pose (exact ground truth; needs image2sim-dataengine);
    ``capture``: the held-out captured frame (sensor noise, depth holes); ``auto``: exact for
    procedural captures, the captured frame otherwise."""
    input_views: str = "pano"
    """``gaussians`` source: the input captures as ``pano`` (the training panoramas) or ``pinhole6``
    (six 90° cubemap-face pinhole views cut from each training panorama, the paper's pinhole-input
    variant); targets are the held-out panoramas either way."""
    lpips_weights: str | None = None
    """LPIPS weight file (safetensors); None = LPIPS reported as n/a."""
    warmup: int = 2
    """Untimed calls before the FPS measurement."""
    runs: int = 5
    """Timed calls (FPS = 1 / median)."""
    threads: int = 1
    """torch threads during the benchmark."""
    seed: int = 12345
    """Degradation seed (differs from every training sample's, as in ``sim renderer-eval``)."""

    def __post_init__(self) -> None:
        if self.holdout_every < 1:
            raise RenderBenchError(f"holdout_every must be >= 1, got {self.holdout_every}")
        if self.source_every < 1:
            raise RenderBenchError(f"source_every must be >= 1, got {self.source_every}")
        if not self.steps or any(int(s) < 1 for s in self.steps):
            raise RenderBenchError(f"steps must be positive integers, got {self.steps}")
        if self.target not in ("auto", "exact", "capture"):
            raise RenderBenchError(f"target must be 'auto', 'exact' or 'capture', got {self.target!r}")
        if self.condition_source not in ("degraded", "gaussians"):
            raise RenderBenchError(
                f"condition_source must be 'degraded' or 'gaussians', got {self.condition_source!r}"
            )
        if self.input_views not in INPUT_VIEWS:
            raise RenderBenchError(
                f"input_views must be one of {list(INPUT_VIEWS)}, got {self.input_views!r}"
            )
        if self.input_views != "pano" and self.condition_source != "gaussians":
            raise RenderBenchError(
                f"input_views {self.input_views!r} needs condition_source 'gaussians' (degraded conditions "
                "are made from the targets, not from input views)"
            )
        if self.condition_source == "gaussians":
            if not (self.tier_data or self.data):
                raise RenderBenchError("condition_source 'gaussians' needs captures (data or tier_data)")
        else:
            unknown = [t for t in self.tiers if t not in NOISE_TIERS]
            if unknown or not self.tiers:
                raise RenderBenchError(f"tiers: unknown {unknown} (known: {list(NOISE_TIERS)})")
            if self.tier_data:
                raise RenderBenchError("tier_data is only used with condition_source 'gaussians'")
        bad = [a for a in self.ablations if a not in ABLATIONS]
        if bad:
            raise RenderBenchError(f"ablations: unknown switch(es) {bad} (known: {list(ABLATIONS)})")
        if self.warmup < 0 or self.runs < 1 or self.threads < 1:
            raise RenderBenchError("need warmup >= 0, runs >= 1, threads >= 1")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "render bench config") -> RenderBenchConfig:
        """Build from a mapping with the shared config mechanism; unknown keys, wrong types and invalid
        values are a :class:`RenderBenchError` naming the field."""
        try:
            return config_from_dict(cls, data)
        except ConfigError as err:
            raise RenderBenchError(f"{where}: {err}") from err


def load_renderer(cfg: Any, checkpoint: str | Path | None):
    """A :class:`PixelFlowRenderer` of ``cfg`` in eval mode; weights from any form the simulator's
    ``load_renderer`` reads: a Lightning checkpoint of ``sim train``, a ``save_renderer`` file or an
    ``export-renderer`` folder."""
    from image2sim.simulator.renderer.model import PixelFlowRenderer
    from image2sim.simulator.renderer.model import load_renderer as load_weights

    model = PixelFlowRenderer(cfg)
    if checkpoint is not None:
        path = Path(checkpoint)
        if not path.exists():
            raise RenderBenchError(f"checkpoint {path}: file not found")
        try:
            state = load_weights(path).state_dict()
        except (ValueError, OSError) as exc:
            raise RenderBenchError(f"checkpoint {path}: {exc}") from exc
        model.load_state_dict(state)
    return model.eval()


def _methods(cfg: Any, bench: RenderBenchConfig) -> dict[str, MethodFn]:
    """The benchmark's methods as render functions (splat-only, n-step flow, ablations)."""
    from image2sim.simulator.renderer.config import load_renderer_config

    def as_fn(model, steps: int) -> MethodFn:
        def fn(cond: torch.Tensor, poses: torch.Tensor):
            out = model.render(cond, steps=steps, poses=list(poses))
            return out.rgb, out.depth

        return fn

    def splat_fill(cond: torch.Tensor, poses: torch.Tensor):
        from image2sim.simulator.renderer.holefill import fill_condition

        rgb, depth = fill_condition(cond)
        return rgb.clamp(0, 1), depth.clamp_min(0)

    splat = load_renderer(replace(cfg, ablation=replace(cfg.ablation, no_pixel_flow=True)), None)
    methods: dict[str, MethodFn] = {"splat_only": as_fn(splat, 1), "splat_fill": splat_fill}
    flow = load_renderer(cfg, bench.checkpoint)
    for n in sorted({int(s) for s in bench.steps}):
        methods[f"flow_{n}step"] = as_fn(flow, n)
    for switch, ckpt in bench.ablations.items():
        acfg = load_renderer_config(bench.renderer_config)
        acfg = replace(acfg, ablation=replace(acfg.ablation, **{switch: True}))
        methods[f"ablation_{switch}"] = as_fn(load_renderer(acfg, ckpt), 1)
    return methods


def benchmark_methods(
    methods: Mapping[str, MethodFn],
    samples_by_tier: Mapping[str, Sequence[dict]],
    *,
    warmup: int = 2,
    runs: int = 5,
    lpips_model: LPIPS | None = None,
    progress: Callable[[], None] | None = None,
) -> dict[str, dict[str, RenderCell]]:
    """Score every method on every tier's samples; FPS on the first sample, timed after ``warmup`` calls.

    ``samples`` are dicts with ``condition`` (24, H, W), ``target_rgb`` (3, H, W), ``target_depth``
    (1, H, W) and ``index``; the pose of sample ``i`` is a translation by ``i`` metres along x (the
    renderer seeds its noise by pose, so repeated runs give identical images).
    """
    out: dict[str, dict[str, RenderCell]] = {}
    for tier, samples in samples_by_tier.items():
        if not samples:
            raise RenderBenchError(f"tier {tier!r}: no held-out views")
        # Splatting time of the tier's views, view-weighted over their captures (None: precomputed).
        splat_times = [s["condition_seconds"] for s in samples if s.get("condition_seconds") is not None]
        splat_seconds = float(np.mean(splat_times)) if splat_times else None
        for name, fn in methods.items():
            # Time first: the warm-up calls are the method's very first calls (JIT, allocator, caches).
            cond0 = samples[0]["condition"][None]
            pose0 = torch.eye(4, dtype=torch.float64)[None]
            with torch.no_grad():
                timing = measure_fps(lambda f=fn, c=cond0, p=pose0: f(c, p), warmup=warmup, runs=runs)
            records = []
            for s in samples:
                pose = torch.eye(4, dtype=torch.float64)
                pose[0, 3] = float(s["index"])
                with torch.no_grad():
                    rgb, depth = fn(s["condition"][None], pose[None])
                records += score_views(
                    [f"{tier}/{s['index']}"],
                    rgb.float(),
                    s["target_rgb"][None].float(),
                    pred_depth=depth.float(),
                    target_depth=s["target_depth"][None].float(),
                    lpips_model=lpips_model,
                )
                if progress is not None:
                    progress()
            fps = timing.fps
            if splat_seconds is not None:  # end to end: splatting the condition + the method
                fps = 1.0 / (1.0 / timing.fps + splat_seconds)
            out.setdefault(name, {})[tier] = summarize_views(records, fps, timing.hardware)
    return out


def _mean(cells: Sequence[RenderCell], key: str) -> tuple[float | None, int]:
    """View-weighted mean of one metric over tiers (n/a if any tier has it n/a)."""
    total, n = 0.0, 0
    for c in cells:
        s = c.metrics.get(key)
        if s is None or s.mean is None:
            return None, 0
        total += s.mean * s.count
        n += s.count
    return (total / n if n else None), n


def method_record(cells: Mapping[str, RenderCell]) -> dict[str, Any]:
    """Headline record of one method: view-weighted means over the tiers, median FPS, per-tier detail."""
    cs = list(cells.values())
    rec: dict[str, Any] = {}
    for key, out_key in (
        ("psnr", "psnr"),
        ("ssim", "ssim"),
        ("lpips", "lpips"),
        ("abs_rel", "depth_absrel"),
        ("rmse", "depth_rmse"),
        ("delta1", "depth_delta1"),
    ):
        value, _ = _mean(cs, key)
        rec[out_key] = None if value is None or not math.isfinite(value) else float(value)
    fps = sorted(c.fps for c in cs if c.fps is not None)
    rec["fps"] = fps[len(fps) // 2] if fps else None
    rec["n_views"] = int(sum(c.num_views for c in cs))
    rec["tiers"] = {
        tier: {
            "psnr": c.metrics["psnr"].mean,
            "ssim": c.metrics["ssim"].mean,
            "lpips": c.metrics["lpips"].mean,
            "depth_absrel": c.metrics["abs_rel"].mean if "abs_rel" in c.metrics else None,
            "fps": c.fps,
            "n_views": c.num_views,
            "psnr_per_view": dict(c.psnr_per_view),
        }
        for tier, c in cells.items()
    }
    return rec


def _training_protocol(bench: RenderBenchConfig) -> dict[str, Any] | None:
    """The checkpoint's training record (``sim train`` writes it) and how this benchmark's splat
    conditions differ from it; each difference is also logged as a warning, since a renderer scored
    on conditions unlike its training ones measures the mismatch, not the renderer."""
    if bench.checkpoint is None:
        return None
    from image2sim.simulator.gaussians.config import load_gaussian_config
    from image2sim.simulator.renderer.splat_data import find_training_record, protocol_mismatches

    record = find_training_record(bench.checkpoint)
    if record is None:
        return None
    mismatches: list[str] = []
    if bench.condition_source == "gaussians":
        gcfg = load_gaussian_config(bench.gaussian_config)
        mismatches = protocol_mismatches(record, gcfg, bench.source_every, bench.holdout_every)
        for line in mismatches:
            logger.warning("%s: conditions differ from training: %s", bench.checkpoint, line)
    return {"record": record, "mismatches": mismatches}


def run_render_bench(
    bench: RenderBenchConfig, out_json: str | Path, show_progress: bool = True
) -> dict[str, Any]:
    """Run the benchmark and write ``metrics/render.json`` (numbers only) and ``render.protocol.json``
    (protocol and configuration) beside it, atomically; returns the whole document."""
    from image2sim.simulator.renderer.cli import _split, _targets  # the renderer's own split and sources
    from image2sim.simulator.renderer.config import config_to_dict, load_renderer_config

    torch.set_num_threads(bench.threads)
    cfg = load_renderer_config(bench.renderer_config)
    held: list = []
    trained_on = _training_protocol(bench)
    if bench.condition_source == "degraded":
        targets = _targets([Path(d) for d in bench.data], cfg.height, cfg.width, bench.max_frames)
        _, held = _split(targets, bench.holdout_every)
        if not held:
            raise RenderBenchError(
                f"no held-out views: {len(targets)} targets with holdout_every={bench.holdout_every}"
            )
    lpips_model = None
    if bench.lpips_weights:
        from image2sim.eval.metrics.lpips import load_lpips

        lpips_model = load_lpips(bench.lpips_weights)
    methods = _methods(cfg, bench)
    if bench.condition_source == "gaussians":
        tier_data = bench.tier_data or {"capture": list(bench.data)}
        samples = {
            t: splat_samples(
                paths,
                cfg.height,
                cfg.width,
                bench.holdout_every,
                bench.gaussian_config,
                bench.max_views,
                encoder=bench.encoder,
                target=bench.target,
                input_views=bench.input_views,
                source_every=bench.source_every,
                warmup=bench.warmup,
                runs=bench.runs,
            )
            for t, paths in tier_data.items()
        }
        empty = [t for t, v in samples.items() if not v]
        if empty:
            raise RenderBenchError(
                f"tier(s) {empty}: no held-out views (holdout_every={bench.holdout_every})"
            )
        held_views = sum(len(v) for v in samples.values())
        tiers_doc: dict[str, Any] = {
            t: {"captures": list(p), "targets": sorted({s["target_kind"] for s in samples[t]})}
            for t, p in tier_data.items()
        }
        inputs = (
            "the training panoramas"
            if bench.input_views == "pano"
            else "six 90° pinhole views (cubemap faces) of each training panorama"
        )
        if bench.source_every > 1:
            inputs = f"every {bench.source_every}th of {inputs} (a sparse capture)"
        source = (
            f"gaussians: identity Gaussian scenes ({bench.gaussian_config}) of {inputs}, "
            "splatted at the held-out poses"
        )
    else:
        samples = {t: tier_samples(held, t, bench.seed, bench.max_views) for t in bench.tiers}
        held_views = len(held)
        tiers_doc = {t: dict(NOISE_TIERS[t]) for t in bench.tiers}
        source = "renderer.data.DegradedPanoramaDataset (splat-like degradation of targets)"
    bar = None
    advance = None
    if show_progress:
        from rich.progress import Progress

        bar = Progress(transient=True)
        bar.start()
        task = bar.add_task("render bench", total=len(methods) * sum(len(s) for s in samples.values()))

        def advance() -> None:
            bar.advance(task)

    try:
        cells = benchmark_methods(
            methods, samples, warmup=bench.warmup, runs=bench.runs, lpips_model=lpips_model, progress=advance
        )
    finally:
        if bar is not None:
            bar.stop()
    doc = {
        "protocol": {
            "name": "image2sim-table1",
            "renderer_config": cfg.name,
            "resolution": [cfg.height, cfg.width],
            "checkpoint": bench.checkpoint,
            "trained": bench.checkpoint is not None,
            "data": list(bench.data)
            or sorted({c for tier in tiers_doc.values() for c in tier.get("captures", [])})
            or ["procedural box-room panoramas (renderer.data.smooth_test_panorama)"],
            "holdout_every": bench.holdout_every,
            "source_every": bench.source_every,
            "input_views": bench.input_views,
            "held_out_views": held_views,
            "tiers": tiers_doc,
            "condition_source": source,
            "fps": {
                "warmup": bench.warmup,
                "runs": bench.runs,
                "statistic": "median after warm-up",
                "threads": bench.threads,
                "batch": 1,
                "scope": (
                    "end to end: splatting the condition (median per capture, view-weighted) + the method"
                    if bench.condition_source == "gaussians"
                    else "renderer only: conditions are precomputed, splatting time is not included"
                ),
                "hardware": hardware_string(),
            },
            "lpips": "configured" if lpips_model is not None else "n/a (no weights configured)",
            "config": asdict(bench),
            "renderer": config_to_dict(cfg),
        },
        "methods": {name: method_record(c) for name, c in cells.items()},
    }
    if trained_on is not None:
        doc["protocol"]["training_data"] = trained_on
    missing = [m for m in HEADLINE_METHODS if m not in doc["methods"]]
    if missing:
        doc["protocol"]["not_evaluated"] = missing
    write_metrics_file(out_json, doc)
    return doc


def _fmt(v: Any, digits: int) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def render_markdown(doc: Mapping[str, Any]) -> str:
    """Table-1 layout of a render.json document: one row per method, a group per noise tier."""
    methods = doc.get("methods") or {}
    if not methods:
        raise RenderBenchError("render metrics document has no 'methods'")
    proto = doc.get("protocol") or {}
    tiers = list(proto.get("tiers") or next(iter(methods.values())).get("tiers", {}))
    header = ["Method"]
    for t in tiers:
        header += [f"LPIPS↓ ({t})", f"PSNR↑ ({t})", f"SSIM↑ ({t})", f"AbsRel↓ ({t})"]
    header += ["FPS↑", "Views"]
    lines = ["| " + " | ".join(header) + " |", "|---" + "|---:" * (len(header) - 1) + "|"]
    for name, rec in methods.items():
        row = [name]
        for t in tiers:
            c = (rec.get("tiers") or {}).get(t)
            if c is None:
                row += ["–"] * 4
                continue
            psnr = c.get("psnr")
            row += [
                _fmt(c.get("lpips"), 3),
                "inf" if psnr == math.inf else _fmt(psnr, 2),
                _fmt(c.get("ssim"), 3),
                _fmt(c.get("depth_absrel"), 3),
            ]
        row += [_fmt(rec.get("fps"), 1), str(rec.get("n_views"))]
        lines.append("| " + " | ".join(row) + " |")
    notes = []
    if proto:
        res = proto.get("resolution")
        notes.append(f"Renderer `{proto.get('renderer_config')}` at {res[0]}×{res[1]}" if res else "")
        notes.append("trained checkpoint" if proto.get("trained") else "**untrained model** (plumbing run)")
        fps = proto.get("fps") or {}
        if fps:
            notes.append(
                f"FPS: {fps.get('statistic')} ({fps.get('runs')} runs, {fps.get('warmup')} warm-up, "
                f"batch {fps.get('batch')}, {fps.get('threads')} thread(s)) on {fps.get('hardware')}"
                + (f"; {fps['scope']}" if fps.get("scope") else "")
            )
        notes.append(f"conditions: {proto.get('condition_source')}")
        for line in (proto.get("training_data") or {}).get("mismatches", []):
            notes.append(f"**conditions differ from the checkpoint's training**: {line}")
        kinds = sorted({k for t in (proto.get("tiers") or {}).values() for k in t.get("targets", [])})
        if kinds:
            notes.append(
                "targets: "
                + ", ".join(
                    {"exact": "exact noise-free GT at the queried pose", "capture": "captured frames"}[k]
                    for k in kinds
                )
            )
    return "\n".join(lines) + "\n\n" + "\n".join(f"- {n}" for n in notes if n) + "\n"
