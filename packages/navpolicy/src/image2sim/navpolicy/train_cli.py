"""``image2sim nav train``: behaviour cloning and online DAgger from the command line.

Its own small Typer registry, gathered into ``image2sim nav`` by :mod:`image2sim.navpolicy.cli`
(which this module never imports, so there is no cycle); also the config helpers the other ``nav``
commands share (:func:`nav_config`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer()


def _set_overrides(items: list[str]) -> dict:
    """``--set KEY=VALUE`` options as nested overrides (a malformed one is a usage error)."""
    from image2sim.simulator.config import ConfigError, parse_overrides

    try:
        return parse_overrides(items)
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--set") from exc


def nav_config(config: str, overrides: dict | None = None, sets: dict | None = None):
    """The policy config: preset or YAML, then ``sets`` (``--set``), then ``overrides`` (the other
    options), each layer merged by the shared config mechanism; a bad one is a usage error naming the
    option to fix."""
    from image2sim.navpolicy.config import ConfigError, load_config
    from image2sim.simulator.config import merge_config

    try:
        cfg = load_config(config, sets)
        return merge_config(cfg, overrides).validate() if overrides else cfg
    except ConfigError as exc:
        hint = "--shard-weight" if "data.shard_weights" in str(exc) else "--config"
        raise typer.BadParameter(str(exc), param_hint=hint) from exc


def check_source(source: str, renderer) -> None:
    """``--source`` names an observation source, and ``neural`` comes with ``--renderer``."""
    from image2sim.navpolicy.rollout_scenes import SOURCES

    if source not in SOURCES:
        raise typer.BadParameter(
            f"must be one of {', '.join(SOURCES)}, got {source!r}", param_hint="--source"
        )
    if source == "neural" and renderer is None:
        raise typer.BadParameter(
            "source neural renders through the pixel-flow renderer: give --renderer <weights>, "
            "or --source splat_only / exact",
            param_hint="--renderer",
        )


def _tracking_overrides(wandb: str, project: str) -> dict:
    """``train`` config overrides from ``--wandb MODE`` / ``--wandb-project`` (empty: keep the config's)."""
    out: dict = {}
    if wandb:
        from image2sim.simulator.tracking import wandb_mode

        try:
            mode = wandb_mode(wandb)
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--wandb") from exc
        out = {"wandb": mode is not None, "wandb_mode": mode or "offline"}
    if project:
        out["wandb_project"] = project
    return out


def expand_shard_folders(paths: list[Path]) -> list[Path]:
    """Each path as it is, except a `data episodes` output folder (a ``shards.json`` and no shard
    manifest of its own), which stands for the shards its list names, in order."""
    out: list[Path] = []
    for p in paths:
        if (p / "shards.json").is_file() and not (p / "manifest.json").is_file():
            from image2sim.dataengine.distributed import read_shard_list

            out += read_shard_list(p)
        else:
            out.append(p)
    return out


@app.command("train")
def train_cmd(
    stage: Annotated[str, typer.Option(help="bc (behaviour cloning) or dagger.")] = "bc",
    config: Annotated[str, typer.Option(help="Preset (tiny|paper) or YAML file.")] = "tiny",
    shards: Annotated[
        list[Path] | None,
        typer.Option(
            "--shard",
            help="Shard folder(s), or a `data episodes` output folder (its shards.json: every scene's "
            "shard and approach shard); overrides data.shards.",
        ),
    ] = None,
    shard_weights: Annotated[
        list[float] | None,
        typer.Option(
            "--shard-weight",
            help="Sample ratio of each --shard, same order (repeatable; overrides data.shard_weights): "
            "e.g. --shard human --shard-weight 1 --shard generated --shard-weight 3. None: every "
            "trajectory equally likely.",
        ),
    ] = None,
    val_shards: Annotated[
        list[Path] | None,
        typer.Option(
            "--val-shard",
            help="bc: validation shard(s) (overrides data.val_shards): val/loss and val/action_acc "
            "every train.val_every steps.",
        ),
    ] = None,
    out: Annotated[Path, typer.Option(help="Run folder.")] = Path("outputs/nav-bc"),
    resume: Annotated[
        str, typer.Option(help="Checkpoint to resume from ('last' = the run folder's last).")
    ] = "",
    max_steps: Annotated[int, typer.Option(help="Override train.max_steps (0 = keep).")] = 0,
    max_trajectories: Annotated[
        int,
        typer.Option(help="bc: train on the first N trajectories of the shards (0 = all; scaling curves)."),
    ] = 0,
    threads: Annotated[
        int, typer.Option(help="torch threads (0 = torch default; tiny models prefer 1).")
    ] = 0,
    init: Annotated[
        str, typer.Option(help="dagger: policy to start from (exported folder, e.g. the BC export).")
    ] = "",
    scenes: Annotated[int, typer.Option(help="dagger: procedural scenes to roll out in.")] = 2,
    tasks_per_scene: Annotated[int, typer.Option(help="dagger: start/goal pairs per scene.")] = 16,
    scene_seed: Annotated[int, typer.Option(help="dagger: seed of the first procedural scene.")] = 100,
    fresh: Annotated[
        bool,
        typer.Option(help="dagger: discard a run recorded in --out and start over (default: continue it)."),
    ] = False,
    episodes: Annotated[
        Path | None,
        typer.Option(
            help="dagger: instruction episodes (the data engine's <out>/<split>/<split>.json.gz) to roll "
            "out, oracle following each reference path; scenes from --sim-scenes. Without it: "
            "procedural point-goal tasks (--scenes/--tasks-per-scene)."
        ),
    ] = None,
    sim_scenes: Annotated[
        Path | None,
        typer.Option(help="dagger with --episodes: folder of scene folders named by the episodes' scene_id."),
    ] = None,
    source: Annotated[
        str,
        typer.Option(
            help="dagger with --episodes: observations from 'neural' (built scenes + --renderer, the "
            "default), 'splat_only' (built scenes, no learned renderer) or 'exact' (procedural "
            "captures rendered exactly: an upper bound)."
        ),
    ] = "neural",
    renderer: Annotated[
        Path | None,
        typer.Option(
            help="dagger, source neural: pixel-flow renderer (export folder, .safetensors or .ckpt)."
        ),
    ] = None,
    wandb: Annotated[
        str,
        typer.Option(
            help="W&B besides CSV: disabled | offline | online (params: tracking.wandb; '' = the config's "
            "train.wandb)."
        ),
    ] = "",
    wandb_project: Annotated[
        str, typer.Option(help="W&B project (params: tracking.project; '' = train.wandb_project).")
    ] = "",
    sets: Annotated[
        list[str] | None,
        typer.Option(
            "--set",
            help="Config override KEY=VALUE (dotted key, YAML value; repeatable; applied after --config, "
            "before the other options), e.g. --set train.seed=1 --set data.shuffle_instructions=true.",
        ),
    ] = None,
) -> None:
    """Train the policy. Writes config.yaml, CSV/W&B logs, checkpoints and a merged export.

    ``--stage dagger`` runs online DAgger (``dagger`` section of the config) in NeuralSimulators on
    procedural scenes of the data engine, starting from ``--init`` (default: the config's model).
    """
    tracking = _tracking_overrides(wandb, wandb_project)
    set_layer = _set_overrides(sets or [])
    shards = expand_shard_folders(shards or [])
    if stage == "dagger":
        episode_source = None
        if episodes is not None:
            if sim_scenes is None:
                raise typer.BadParameter("--episodes needs --sim-scenes", param_hint="--sim-scenes")
            episode_source = (episodes, sim_scenes, source, renderer)
        if shard_weights:
            raise typer.BadParameter(
                "sample ratios apply to behaviour cloning (--stage bc); DAgger's aggregated buffer "
                "draws every trajectory equally",
                param_hint="--shard-weight",
            )
        _train_dagger(
            config,
            shards,
            out,
            max_steps,
            threads,
            init,
            scenes,
            tasks_per_scene,
            scene_seed,
            fresh,
            episode_source,
            tracking,
            set_layer,
        )
        return
    if stage != "bc":
        raise typer.BadParameter(f"unknown stage {stage!r}; use bc or dagger", param_hint="--stage")
    overrides: dict = {"train": dict(tracking)} if tracking else {}
    if shards:
        overrides.setdefault("data", {})["shards"] = [str(s) for s in shards]
    if shard_weights:
        overrides.setdefault("data", {})["shard_weights"] = [float(w) for w in shard_weights]
    if val_shards:
        overrides.setdefault("data", {})["val_shards"] = [str(s) for s in val_shards]
    if max_steps:
        overrides.setdefault("train", {})["max_steps"] = max_steps
    if max_trajectories:
        overrides.setdefault("data", {})["max_trajectories"] = max_trajectories
    cfg = nav_config(config, overrides, set_layer)
    if not cfg.data.shards:
        raise typer.BadParameter("no training shards: pass --shard or set data.shards", param_hint="--shard")
    if threads:
        import torch

        torch.set_num_threads(threads)
    from image2sim.navpolicy.data import ShardError
    from image2sim.navpolicy.train import train_bc

    try:
        res = train_bc(cfg, out, resume=resume or None)
    except (FileNotFoundError, ShardError) as exc:  # missing checkpoint/model folder, bad shard
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    typer.echo(
        json.dumps(
            {
                "out_dir": str(res.out_dir),
                "global_step": res.global_step,
                "last_checkpoint": str(res.last_checkpoint),
                "export": str(res.export_dir),
                "final_loss": res.module.losses[-1] if res.module.losses else None,
            },
            indent=2,
        )
    )


def _dagger_episode_scenes(episodes: Path, scenes_root: Path, source: str, renderer, marker, device="cpu"):
    from image2sim.navpolicy.rollout_scenes import episode_scenes

    check_source(source, renderer)
    from image2sim.eval.datasets import EpisodeFileError, load_image2sim_episodes

    gt = episodes.with_name(episodes.name.replace(".json.gz", "_gt.json.gz"))
    try:
        eps = list(load_image2sim_episodes(episodes, gt if gt.is_file() else None).episodes)
        return episode_scenes(eps, scenes_root, source, renderer, goal_marker=marker, device=device)
    except (EpisodeFileError, FileNotFoundError, ValueError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc


def _train_dagger(
    config,
    shards,
    out,
    max_steps,
    threads,
    init,
    scenes,
    tasks_per_scene,
    scene_seed,
    fresh=False,
    episode_source=None,
    tracking: dict | None = None,
    set_layer: dict | None = None,
) -> None:
    import torch

    overrides: dict = {"train": dict(tracking)} if tracking else {}
    if shards:
        overrides.setdefault("data", {})["shards"] = [str(s) for s in shards]
    if max_steps:
        overrides.setdefault("dagger", {})["train_steps_per_round"] = max_steps
    if init:
        if not Path(init).is_dir():
            typer.echo(f"error: --init {init}: no such model folder", err=True)
            raise typer.Exit(2)
        overrides.setdefault("model", {})["source"] = str(init)
    cfg = nav_config(config, overrides, set_layer)
    if threads:
        torch.set_num_threads(threads)
    from image2sim.navpolicy.dagger import run_dagger
    from image2sim.navpolicy.data import ShardError, ShardReader
    from image2sim.navpolicy.rollout_scenes import procedural_scenes

    base = []
    if cfg.dagger.include_bc_data:
        try:
            for sh in cfg.data.shards:
                reader = ShardReader(sh)
                base.extend(reader[i] for i in range(len(reader)))
        except ShardError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from exc
    if episode_source is not None:
        sc = _dagger_episode_scenes(
            *episode_source, marker=cfg.task.active_marker(), device=cfg.dagger.render_device
        )
    else:
        sc = procedural_scenes(scenes, tasks_per_scene, seed=scene_seed, goal_marker=cfg.task.active_marker())
    try:
        res = run_dagger(cfg, sc, out, base_trajectories=base, resume=not fresh)
    except ValueError as exc:  # a recorded run with other arguments in --out
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    ends: dict[str, int] = {}
    for e in res.episodes:
        ends[e["end"]] = ends.get(e["end"], 0) + 1
    typer.echo(
        json.dumps(
            {
                "out_dir": str(res.out_dir),
                "episodes": len(res.episodes),
                "episode_ends": ends,
                "dataset_sizes": res.dataset_sizes,
                "final_loss": res.losses[-1][-1] if res.losses and res.losses[-1] else None,
                "export": str(res.export_dir),
            },
            indent=2,
        )
    )
