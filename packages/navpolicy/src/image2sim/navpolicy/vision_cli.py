"""``image2sim nav pretrain-vision``: recognition pretraining of the tiny policy's vision tower.

Its own small Typer registry, gathered into ``image2sim nav`` by :mod:`image2sim.navpolicy.cli`
(which this module never imports, so there is no cycle).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer()


@app.command("pretrain-vision")
def pretrain_vision_cmd(
    views: Annotated[Path, typer.Option(help="`image2sim data views` output folder.")],
    out: Annotated[Path, typer.Option(help="Output folder (vision.safetensors, pretrain.json).")],
    config: Annotated[
        str, typer.Option(help="Policy preset or YAML: its model.tiny sizes and observation size.")
    ] = "tiny",
    steps: Annotated[int, typer.Option(help="Optimiser steps.")] = 1500,
    batch_size: Annotated[int, typer.Option(help="Views per step.")] = 64,
    lr: Annotated[float, typer.Option(help="Peak learning rate.")] = 2e-3,
    seed: Annotated[int, typer.Option(help="Seed of the tower's initialisation and the batch order.")] = 0,
    probe_only: Annotated[
        bool,
        typer.Option(help="Keep the random tower frozen and train only merger + head (the baseline)."),
    ] = False,
    threads: Annotated[int, typer.Option(help="torch threads (0 = torch default).")] = 0,
) -> None:
    """Teach the vision tower which categories each token's cell shows; set model.vision_weights to
    the output folder to start a policy from it (docs/navpolicy.md)."""
    from image2sim.navpolicy.vision_pretrain import VisionPretrainConfig, pretrain_vision

    report = _run(
        pretrain_vision,
        config,
        views,
        out,
        threads,
        lambda: VisionPretrainConfig(
            steps=steps, batch_size=batch_size, lr=lr, seed=seed, train_tower=not probe_only
        ),
    )
    typer.echo(json.dumps({"out": str(out), **report["final"], "seconds": round(report["seconds"], 1)}))


@app.command("pretrain-grounding")
def pretrain_grounding_cmd(
    views: Annotated[Path, typer.Option(help="`image2sim data views` output folder.")],
    out: Annotated[Path, typer.Option(help="Output policy export (use as model.source for BC).")],
    config: Annotated[
        str,
        typer.Option(help="Policy preset or YAML (set model.vision_weights to a pretrain-vision output)."),
    ] = "tiny",
    steps: Annotated[int, typer.Option(help="Optimiser steps.")] = 2400,
    batch_size: Annotated[int, typer.Option(help="Questions per step.")] = 32,
    lr: Annotated[float, typer.Option(help="Learning rate.")] = 2e-3,
    seed: Annotated[int, typer.Option(help="Seed of the questions and the head.")] = 0,
    threads: Annotated[int, typer.Option(help="torch threads (0 = torch default).")] = 0,
) -> None:
    """Teach the policy to tell whether the object its instruction names is in view (one view per
    question), before behaviour cloning (docs/navpolicy.md)."""
    from image2sim.navpolicy.vision_pretrain import GroundingConfig, pretrain_grounding

    report = _run(
        pretrain_grounding,
        config,
        views,
        out,
        threads,
        lambda: GroundingConfig(steps=steps, batch_size=batch_size, lr=lr, seed=seed),
    )
    typer.echo(json.dumps({"out": str(out), **report["final"]}))


def _run(stage, config: str, views: Path, out: Path, threads: int, make_stage_config) -> dict:
    """The two pretraining commands' shell: threads, the policy config and the stage's config checked
    (bad values are usage errors), a fresh --out, then ``stage(policy config, views, out, stage
    config)``; missing or bad inputs end with exit code 2 and the message."""
    import torch
    from image2sim.navpolicy.config import ConfigError, load_config

    if threads:
        torch.set_num_threads(threads)
    try:
        cfg = load_config(config)
        stage_cfg = make_stage_config().validate()
    except (ConfigError, ValueError) as exc:
        raise typer.BadParameter(str(exc)) from exc
    if out.exists():
        raise typer.BadParameter(f"{out} exists; choose another --out or delete it", param_hint="--out")
    try:
        return stage(cfg, views, out, stage_cfg, progress=True)
    except (FileNotFoundError, ValueError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
