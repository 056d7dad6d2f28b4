"""``image2sim data synth``: write procedural scenes as canonical captures with exact ground truth."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer()
"""This module's commands; :mod:`image2sim.dataengine.cli` gathers them into ``image2sim data``."""


@app.command("synth")
def synth(
    out: Path = typer.Option(
        Path("data/synthetic"), "--out", help="Output folder; scenes go to OUT/scene_XXX."
    ),
    scenes: int = typer.Option(8, "--scenes", min=1, help="Number of scenes."),
    views: int | None = typer.Option(
        None, "--views", min=1, help="Views per scene (before the noise tier's view fraction)."
    ),
    noise: str | None = typer.Option(
        None, "--noise", help="Noise tier: none, middle or high (default: preset's, none)."
    ),
    seed: int = typer.Option(0, "--seed", min=0, help="Base seed; scene i uses an independent stream."),
    preset_name: str = typer.Option("default", "--preset", help="Config preset: default or tiny."),
    config: Path | None = typer.Option(None, "--config", help="JSON/YAML file overriding preset fields."),
    height: int | None = typer.Option(None, "--height", help="Image height (default from the preset)."),
    width: int | None = typer.Option(None, "--width", help="Image width (default from the preset)."),
    camera: str | None = typer.Option(None, "--camera", help="equirect or pinhole."),
    caster: str | None = typer.Option(None, "--caster", help="auto, embree or numpy."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing scene folders."),
    workers: int = typer.Option(
        1, "--workers", min=1, help="Scenes generated in parallel processes (same output as 1)."
    ),
) -> None:
    """Generate procedural indoor scenes (RGB-D + semantics + instances, exact GT in gt/)."""
    from dataclasses import replace

    from image2sim.dataengine.procedural.capture import synthesize
    from image2sim.dataengine.procedural.config import ConfigError, preset, synth_config_from_dict
    from image2sim.simulator.config import read_mapping

    try:
        cfg = preset(preset_name)
        if config is not None:
            cfg = synth_config_from_dict(read_mapping(config), base=cfg)
        cap = {
            k: v
            for k, v in (("views", views), ("height", height), ("width", width), ("camera", camera))
            if v is not None
        }
        top = {k: v for k, v in (("noise", noise), ("caster", caster)) if v is not None}
        cfg = replace(cfg, capture=replace(cfg.capture, **cap), **top).validate()
    except ConfigError as err:
        typer.echo(f"error: {err}", err=True)
        raise typer.Exit(2) from None
    paths = synthesize(
        cfg, out, scenes=scenes, seed=seed, overwrite=overwrite, progress=True, workers=workers
    )
    for p in paths:
        typer.echo(str(p))


@app.command("views")
def views(
    scenes: Path = typer.Option(..., "--scenes", help="Folder of procedural captures (from `data synth`)."),
    out: Path = typer.Option(..., "--out", help="Output folder (views/<scene>.npz, categories.json)."),
    per_scene: int = typer.Option(400, "--per-scene", min=1, help="Views per house."),
    size: int = typer.Option(64, "--size", min=8, help="Square view side (the policy's observation)."),
    hfov: float = typer.Option(90.0, "--hfov", help="Field of view in degrees (the policy's camera)."),
    seed: int = typer.Option(0, "--seed", min=0, help="Base seed (each house its own stream)."),
) -> None:
    """Recognition views: random agent views of procedural houses with per-pixel category ids, for
    `image2sim nav pretrain-vision`. Rerun with the same options to resume."""
    from image2sim.dataengine.procedural.exact import is_procedural_capture
    from image2sim.dataengine.procedural.views import ViewsConfig, write_views

    if not scenes.is_dir():
        raise typer.BadParameter(f"{scenes} is not a folder", param_hint="--scenes")
    dirs = sorted(d for d in scenes.iterdir() if (d / "manifest.json").is_file())
    if not dirs:
        raise typer.BadParameter(f"{scenes} holds no capture folders (sub-folders with manifest.json)")
    foreign = [d.name for d in dirs if not is_procedural_capture(d)]
    if foreign:
        raise typer.BadParameter(
            f"{', '.join(foreign[:3])}: not procedural captures; views need the generator's per-pixel "
            "categories (make captures with `image2sim data synth`)",
            param_hint="--scenes",
        )
    try:
        manifest = write_views(dirs, out, ViewsConfig(per_scene, size, hfov, seed), progress=True)
    except ValueError as err:
        typer.echo(f"error: {err}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"{sum(manifest['scenes'].values())} views of {len(manifest['scenes'])} houses -> {out}")
