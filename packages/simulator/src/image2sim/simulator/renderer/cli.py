"""``image2sim sim train`` / ``renderer-eval`` / ``export-renderer``: train, measure and export the
pixel-flow renderer.

Training samples (``--condition-source``): ``splat`` (default) pairs every training frame with the
splat of the identity Gaussians of the capture's OTHER training frames at its pose
(:class:`~image2sim.simulator.renderer.splat_data.SplatConditionDataset`, cached per capture);
``degraded`` uses splat-like degradations of the targets
(:class:`~image2sim.simulator.renderer.data.DegradedPanoramaDataset`). Captures are anything
``open_capture`` understands (the HM3D sample, procedural captures).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import typer
from image2sim.simulator.io.atomic import write_text_atomic

__all__ = ["train_command", "eval_command", "export_command"]


def _targets(data: list[Path], height: int, width: int, max_frames: int | None):
    from image2sim.simulator.renderer.data import load_capture_targets, smooth_test_panorama

    if not data:
        typer.echo("no --data given: training on procedural box-room panoramas")
        return [smooth_test_panorama(height, width, seed=i) for i in range(16)]
    targets = []
    for path in data:
        targets += load_capture_targets(path, height, width, max_frames)
    return targets


def _split(targets: list, holdout_every: int) -> tuple[list, list]:
    held = [t for i, t in enumerate(targets) if holdout_every and i % holdout_every == holdout_every - 1]
    train = [
        t for i, t in enumerate(targets) if not (holdout_every and i % holdout_every == holdout_every - 1)
    ]
    return train, held


def train_command(
    config: str = typer.Option("tiny", help="Preset name (tiny, paper) or YAML file of overrides."),
    data: list[Path] = typer.Option([], help="Capture directories with target panoramas (repeatable)."),
    out: Path = typer.Option(Path("runs/renderer"), help="Output directory (config, checkpoints, logs)."),
    max_steps: int = typer.Option(-1, help="Stop after this many steps (-1: the config's total_steps)."),
    steps: int = typer.Option(
        0,
        help="Length of the curriculum: stage boundaries and the cosine schedule scaled to this many steps "
        "(0: the config's total_steps). Unlike --max-steps, the run ends at the schedule's end.",
    ),
    max_frames: int = typer.Option(-1, help="Use at most this many frames per capture (-1: all)."),
    holdout_every: int = typer.Option(8, help="Every n-th frame is held out from training (0: none)."),
    source_every: int = typer.Option(
        1, help="With splat: only every n-th training frame is a source (1: dense; >1: a sparse capture)."
    ),
    resume: str = typer.Option("", help="Checkpoint to resume from ('last' = out/checkpoints/last.ckpt)."),
    seed: int = typer.Option(0, help="Seed of data order, degradations, (r, t) and noise."),
    threads: int = typer.Option(1, help="torch threads (1 is fastest on a shared 2-core machine)."),
    data_workers: int = typer.Option(
        0, help="With splat: processes building the captures' conditions, one capture each (0: one per core)."
    ),
    bf16: bool = typer.Option(False, help="bf16 autocast."),
    accelerator: str = typer.Option("", help="Override trainer.accelerator: cpu, gpu or auto."),
    devices: int = typer.Option(0, help="Override trainer.devices (processes per node; >1 needs ddp)."),
    num_nodes: int = typer.Option(0, help="Override trainer.num_nodes."),
    strategy: str = typer.Option("", help="Override trainer.strategy: auto (one process) or ddp."),
    logger: str = typer.Option("csv", help="csv, or wandb (CSV and offline W&B; see --wandb)."),
    wandb: str = typer.Option(
        "", help="W&B besides CSV: disabled | offline | online (params: tracking.wandb; '' = --logger)."
    ),
    wandb_project: str = typer.Option("image2sim", help="W&B project (params: tracking.project)."),
    checkpoint_every: int = typer.Option(250, help="Checkpoint every n steps."),
    grid_every: int = typer.Option(250, help="Image grid (prior | one-step | target | alpha) every n steps."),
    condition_source: str = typer.Option(
        "splat",
        help="splat: leave-target-out splats of the capture's identity Gaussians (needs --data); "
        "degraded: synthetic degradations of the targets.",
    ),
    gaussian_config: str = typer.Option("tiny", help="Gaussian preset/YAML of the splat conditions."),
    encoder: str = typer.Option(
        "identity",
        help="Gaussians of the splat conditions: identity, or a stage-1 encoder checkpoint (sim "
        "train-geometry's encoder.safetensors or its folder): its 16 feature channels reach the renderer.",
    ),
    splat_cache: Path = typer.Option(
        Path("outputs/cache/splat_conditions"), help="Cache folder of the splat conditions."
    ),
    degraded_fraction: float = typer.Option(0.0, help="With splat: fraction of degraded samples mixed in."),
) -> None:
    """Train the pixel-flow renderer with the three-stage curriculum."""
    import torch
    from image2sim.simulator.renderer.config import load_renderer_config, scaled_curriculum
    from image2sim.simulator.renderer.data import DegradedPanoramaDataset
    from image2sim.simulator.renderer.module import fit
    from image2sim.simulator.renderer.splat_data import write_training_record

    torch.set_num_threads(threads)
    cfg = load_renderer_config(config)
    try:
        import dataclasses

        if steps:
            cfg = dataclasses.replace(cfg, curriculum=scaled_curriculum(cfg.curriculum, steps))

        from image2sim.simulator.trainer import with_overrides

        cfg = dataclasses.replace(
            cfg, trainer=with_overrides(cfg.trainer, accelerator, devices, num_nodes, strategy)
        )
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    if condition_source not in ("splat", "degraded"):
        raise typer.BadParameter(f"--condition-source must be splat or degraded, got {condition_source!r}")
    if wandb:
        from image2sim.simulator.tracking import wandb_mode

        try:
            wandb_mode(wandb)
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--wandb") from exc
    from image2sim.simulator.trainer import resume_checkpoint

    ckpt = resume_checkpoint(resume, out)  # checked before anything is written
    if condition_source == "splat" and not data:
        typer.echo("no --data given: splat conditions need captures, using degraded conditions instead")
        condition_source = "degraded"
    if condition_source == "splat":
        from image2sim.simulator.renderer.splat_data import (
            SplatConditionDataset,
            SplatDataConfig,
            training_record,
        )

        scfg = SplatDataConfig(
            gaussian_config=gaussian_config,
            encoder=encoder,
            holdout_every=holdout_every,
            source_every=source_every,
            degraded_fraction=degraded_fraction,
            cache_dir=str(splat_cache),
            max_frames=None if max_frames < 0 else max_frames,
        )
        if data_workers < 0:
            raise typer.BadParameter(f"must be >= 0, got {data_workers}", param_hint="--data-workers")
        ds = SplatConditionDataset(
            data, cfg.height, cfg.width, scfg, progress=True, workers=data_workers or (os.cpu_count() or 1)
        )
        write_training_record(out, training_record(data, scfg, ds.gaussian_config))
        cached = sum(s.cached for s in ds.sources)
        typer.echo(
            f"{ds.num_splat} splat + {ds.num_degraded} degraded training samples at {cfg.height}x{cfg.width} "
            f"({cached}/{len(ds.sources)} captures from the cache {splat_cache})"
        )
    else:
        targets = _targets(data, cfg.height, cfg.width, None if max_frames < 0 else max_frames)
        train, held = _split(targets, holdout_every)
        typer.echo(f"{len(train)} training / {len(held)} held-out panoramas at {cfg.height}x{cfg.width}")
        ds = DegradedPanoramaDataset(train, cfg.curriculum.total_steps * cfg.curriculum.batch_size)
        write_training_record(out, {"condition_source": "degraded", "captures": [str(d) for d in data]})
    fit(
        cfg,
        ds,
        str(out),
        max_steps=None if max_steps < 0 else max_steps,
        seed=seed,
        resume=ckpt,
        bf16=bf16,
        logger=logger,
        checkpoint_every=checkpoint_every,
        grid_every=grid_every,
        wandb=wandb,
        wandb_project=wandb_project,
    )


def eval_command(
    checkpoint: Path = typer.Argument(..., help="Lightning checkpoint (or .safetensors) of the renderer."),
    data: list[Path] = typer.Option([], help="Capture directories (the held-out split is evaluated)."),
    holdout_every: int = typer.Option(8, help="Same split as training."),
    max_frames: int = typer.Option(-1, help="At most this many frames per capture (-1: all)."),
    steps: list[int] = typer.Option([1, 2, 4, 8], help="Sampler steps to evaluate."),
    report: Path = typer.Option(
        Path("reports/renderer_eval"), help="Report path stem (.json and .md written)."
    ),
    threads: int = typer.Option(1, help="torch threads."),
    condition_source: str = typer.Option(
        "splat",
        help="splat: identity Gaussians of the training frames splatted at the held-out poses, scored "
        "against exact GT for procedural captures (the conditions of `eval render "
        "--condition-source gaussians`, needs image2sim-eval); degraded: synthetic degradations.",
    ),
    gaussian_config: str = typer.Option("tiny", help="splat: Gaussian preset/YAML of the conditions."),
) -> None:
    """PSNR / SSIM / depth AbsRel / FPS of splat-only vs 1..N-step rendering on held-out views."""
    import torch
    from image2sim.simulator.renderer.model import load_renderer

    if condition_source not in ("splat", "degraded"):
        raise typer.BadParameter(f"--condition-source must be splat or degraded, got {condition_source!r}")
    torch.set_num_threads(threads)
    model = load_renderer(checkpoint)  # the config travels with the weights
    if condition_source == "splat":
        if not data:
            raise typer.BadParameter("--condition-source splat needs --data captures")
        _eval_splat(
            model, checkpoint, data, holdout_every, max_frames, steps, report, threads, gaussian_config
        )
    else:
        _eval_degraded(model, checkpoint, data, holdout_every, max_frames, steps, report, threads)


def _eval_splat(model, checkpoint, data, holdout_every, max_frames, steps, report, threads, gaussian_config):
    """``renderer-eval`` on splatted conditions: the evaluation harness's render benchmark itself."""
    import tempfile

    import yaml
    from image2sim.simulator.renderer.config import config_to_dict

    try:
        from image2sim.eval.render_bench import RenderBenchConfig, render_markdown, run_render_bench
    except ImportError as err:  # the eval package is optional for the simulator
        raise typer.BadParameter(f"--condition-source splat needs image2sim-eval installed ({err})") from err
    with tempfile.TemporaryDirectory() as tmp:
        cfg_file = Path(tmp) / "renderer.yaml"  # the checkpoint's own config, for the benchmark
        cfg_file.write_text(yaml.safe_dump(config_to_dict(model.cfg)))
        bench = RenderBenchConfig(
            renderer_config=str(cfg_file),
            checkpoint=str(checkpoint),
            data=[str(d) for d in data],
            holdout_every=holdout_every,
            max_frames=None if max_frames < 0 else max_frames,
            steps=list(steps),
            condition_source="gaussians",
            gaussian_config=gaussian_config,
            threads=threads,
        )
        doc = run_render_bench(bench, report.with_suffix(".json"))
    text = f"# Renderer evaluation ({model.cfg.name}, checkpoint `{checkpoint}`)\n\n" + render_markdown(doc)
    write_text_atomic(report.with_suffix(".md"), text)
    typer.echo(text)


def _eval_degraded(model, checkpoint, data, holdout_every, max_frames, steps, report, threads) -> None:
    """``renderer-eval`` on the renderer's synthetic degradations of the held-out targets."""
    import time

    import torch
    from image2sim.simulator.renderer.data import DegradedPanoramaDataset
    from image2sim.simulator.renderer.metrics import abs_rel, psnr_per_image, ssim_per_image

    cfg = model.cfg
    targets = _targets(data, cfg.height, cfg.width, None if max_frames < 0 else max_frames)
    _, held = _split(targets, holdout_every)
    if not held:
        raise typer.BadParameter("no held-out frames (holdout_every = 0?)")
    ds = DegradedPanoramaDataset(held, len(held))
    ds.cfg.seed = 12345  # evaluation degradations differ from every training sample
    rows: dict[str, dict[str, list[float]]] = {}
    for i in range(len(ds)):
        s = ds[i]
        cond, rgb, depth = s["condition"][None], s["target_rgb"][None], s["target_depth"][None]
        pose = torch.eye(4, dtype=torch.float64)
        pose[0, 3] = float(i)
        cases = {"splat-only": lambda cond=cond: (cond[:, 16:19], cond[:, 19:20])}
        for n in steps:
            cases[f"{n}-step"] = lambda n=n, cond=cond, pose=pose: (lambda o: (o.rgb, o.depth))(
                model.render(cond, steps=n, poses=[pose])
            )
        for name, fn in cases.items():
            t0 = time.perf_counter()
            pred_rgb, pred_depth = fn()
            dt = time.perf_counter() - t0
            r = rows.setdefault(name, {"psnr": [], "ssim": [], "absrel": [], "seconds": []})
            r["psnr"].append(float(psnr_per_image(pred_rgb, rgb)[0]))
            r["ssim"].append(float(ssim_per_image(pred_rgb, rgb)[0]))
            r["absrel"].append(float(abs_rel(pred_depth, depth)[0]))
            r["seconds"].append(dt)
    summary = {
        name: {
            "psnr": sum(v["psnr"]) / len(v["psnr"]),
            "ssim": sum(v["ssim"]) / len(v["ssim"]),
            "depth_absrel": sum(v["absrel"]) / len(v["absrel"]),
            "fps": len(v["seconds"]) / max(sum(v["seconds"]), 1e-9),
        }
        for name, v in rows.items()
    }
    result = {
        "checkpoint": str(checkpoint),
        "config": cfg.name,
        "held_out_views": len(ds),
        "data": [str(d) for d in data] or ["procedural box rooms"],
        "threads": threads,
        "results": summary,
    }
    report.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(report.with_suffix(".json"), json.dumps(result, indent=2))
    lines = [
        f"# Renderer evaluation ({cfg.name}, {len(ds)} held-out views)",
        "",
        f"Checkpoint `{checkpoint}`; data {result['data']}; {threads} thread(s).",
        "",
        "| method | PSNR (dB) | SSIM | depth AbsRel | FPS |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, m in summary.items():
        lines.append(
            f"| {name} | {m['psnr']:.2f} | {m['ssim']:.4f} | {m['depth_absrel']:.4f} | {m['fps']:.2f} |"
        )
    write_text_atomic(report.with_suffix(".md"), "\n".join(lines) + "\n")
    typer.echo("\n".join(lines))


def export_command(
    checkpoint: Path = typer.Argument(
        ..., help="Renderer weights: a Lightning checkpoint of `sim train` (or a .safetensors file)."
    ),
    out: Path = typer.Option(..., "--out", help="Folder to write (replaced whole if it exists)."),
) -> None:
    """Export renderer weights as renderer.safetensors + renderer.json (read by load_renderer)."""
    from image2sim.simulator.renderer.model import export_renderer, load_renderer
    from image2sim.simulator.renderer.splat_data import find_training_record

    if checkpoint.resolve() == out.resolve():
        raise ValueError(f"{out}: --out must differ from the checkpoint it exports")
    model = load_renderer(checkpoint)
    record = find_training_record(checkpoint)
    export_renderer(model, out, extra={"source": checkpoint.name}, training_record=record)
    n = sum(p.numel() for p in model.parameters())
    typer.echo(f"wrote {out} ({model.cfg.name}, {n:,} parameters" + (", training record)" if record else ")"))
