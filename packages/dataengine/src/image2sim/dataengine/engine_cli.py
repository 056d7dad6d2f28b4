"""``image2sim data mine | episodes | stats``: the navigation data engine commands."""
# ruff: noqa: B008  (typer declares options as argument defaults)

from __future__ import annotations

import json
from pathlib import Path

import typer

app = typer.Typer()
"""This module's commands; :mod:`image2sim.dataengine.cli` gathers them into ``image2sim data``."""


def _parse_options(items: list[str] | None) -> dict:
    """``key=value`` pairs; values are JSON when they parse (numbers, booleans), else strings."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise typer.BadParameter(f"expected key=value, got {item!r}")
        k, v = item.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


@app.command("mine")
def mine_command(
    scene: Path = typer.Argument(..., help="Capture folder (or a folder of captures with --all)."),
    out: Path = typer.Option(
        None,
        "--out",
        help="objects.json path (default: <scene>/objects.json is NOT "
        "touched; writes ./objects_<scene>.json).",
    ),
    detector: str = typer.Option("gt", "--detector", help="gt or yolo-world."),
    weights: Path | None = typer.Option(None, "--weights", help="Local YOLO-World weights (yolo-world)."),
    vocabulary: str | None = typer.Option(None, "--vocabulary", help="Comma separated classes (yolo-world)."),
) -> None:
    """Mine goal objects of one capture into an object database (paper filters, 3D grounding, merging)."""
    from image2sim.dataengine import mining
    from image2sim.simulator.io.registry import open_capture

    cap = open_capture(scene)
    small: set[str] = set()
    if detector == "gt":
        cats, small = mining.load_categories(scene)
        det = mining.GTDetector(cats)
    elif detector == "yolo-world":
        if weights is None or not vocabulary:
            typer.echo("error: yolo-world needs --weights and --vocabulary", err=True)
            raise typer.Exit(2)
        det = mining.YoloWorldDetector(weights, [v.strip() for v in vocabulary.split(",") if v.strip()])
    else:
        typer.echo(f"error: unknown detector {detector!r}", err=True)
        raise typer.Exit(2)
    objs, stats = mining.mine_capture(cap, det, mining.MiningConfig(), small, progress=True)
    mining.attach_gt_metadata(objs, scene)
    path = out or Path(f"objects_{scene.name}.json")
    mining.save_objects(path, objs, {"detector": det.name, "stats": stats})
    typer.echo(json.dumps({"objects": len(objs), **stats, "file": str(path)}))


def _gaussian_overrides(name_or_file: str) -> dict:
    """The engine's ``gaussians`` field for ``--gaussian-config``: empty for the ``tiny`` preset (the
    default, so earlier runs resume unchanged), else the whole resolved config as plain data."""
    from image2sim.simulator.gaussians.config import config_to_dict, load_gaussian_config

    if name_or_file == "tiny":
        return {}
    return config_to_dict(load_gaussian_config(name_or_file))


@app.command("episodes")
def episodes_command(
    scenes: Path = typer.Option(
        ...,
        "--scenes",
        help="Folder of capture folders (e.g. `data synth` output) or of built scene folders.",
    ),
    out: Path = typer.Option(..., "--out", help="Output folder (episodes, gt, shards, per-scene caches)."),
    per_scene: str = typer.Option("auto", "--per-scene", help="auto (area-based capacity) or N episodes."),
    annotator: str = typer.Option("template", "--annotator", help="template, transformers or openai."),
    annotator_option: list[str] = typer.Option(
        None, "--annotator-option", "-A", help="Backend option key=value (repeatable), e.g. base_url=..."
    ),
    render: str = typer.Option(
        "auto",
        "--render",
        help="auto (= gaussians: the neural simulator, with --renderer its pixel-flow renderer), "
        "procedural (the exact renderer of a procedural capture, chosen explicitly), gaussians or none.",
    ),
    view: str = typer.Option("pinhole", "--view", help="Stored observation: pinhole or ultrawide."),
    renderer: Path | None = typer.Option(
        None,
        "--renderer",
        help="Local pixel-flow renderer weights: Gaussians are splatted, then rendered by the renderer.",
    ),
    device: str = typer.Option(
        "cpu",
        "--device",
        help="Where Gaussian observations render: cpu, or cuda[:N] on a GPU machine (splat and pixel-flow "
        "renderer; the exact renderer stays on the CPU).",
    ),
    obs_height: int = typer.Option(336, "--obs-height", help="Observation height in pixels."),
    frame_stride: int = typer.Option(
        2,
        "--frame-stride",
        min=1,
        help="Store the observation of every n-th step (2, the default: what the policy sees, two "
        "actions per observation; 1: every step, twice the rendering).",
    ),
    split: str = typer.Option("train", "--split", help="Split name of the episode files."),
    episode_format: str = typer.Option(
        "r2r-ce",
        "--format",
        help="Episode files: r2r-ce (<split>/<split>.json.gz with the vocabulary) or rxr-ce "
        "(<split>/<split>_guide.json.gz: instruction_id, language, annotator_id per instruction).",
    ),
    language: str = typer.Option("en-US", "--language", help="rxr-ce: the instructions' language tag."),
    seed: int = typer.Option(0, "--seed", help="Base seed."),
    gaussian_config: str = typer.Option(
        "tiny",
        "--gaussian-config",
        help="gaussians: preset name or YAML of the identity Gaussian scenes built from the captures "
        "(e.g. a coarser fusion.footprint_factor for cheaper frames).",
    ),
    refine_steps: int = typer.Option(
        0,
        "--refine-steps",
        help="gaussians: refine each scene built from a capture this many steps against its frames "
        "(0: feed-forward, the default; -1: as sim build-scene does, two steps per frame, at most 50).",
        min=-1,
    ),
    executor: str = typer.Option(
        "local",
        "--executor",
        help="local (--workers processes on this machine, no network) or ray (a cluster with --address, "
        "or a local Ray).",
    ),
    workers: int = typer.Option(2, "--workers", min=1, help="Parallel scene workers (processes)."),
    address: str | None = typer.Option(None, "--address", help="Join a Ray cluster at this address."),
    min_steps: int | None = typer.Option(None, "--min-steps", help="Drop episodes with fewer actions."),
    face_goal: bool = typer.Option(
        False,
        "--face-goal",
        help="The expert turns towards its goal object before it stops, so its last views show what it "
        "stops beside (RolloutConfig.face_goal).",
    ),
    detector: str = typer.Option(
        "gt",
        "--detector",
        help="Goal objects: gt (a procedural capture's ground truth), yolo-world (local --detector-weights), "
        "annotations (an objects file, see --objects) or none (no objects: landmark-free path instructions "
        "between navigable points; any capture).",
    ),
    detector_weights: Path | None = typer.Option(
        None, "--detector-weights", help="yolo-world: local YOLO-World weights."
    ),
    objects: Path | None = typer.Option(
        None,
        "--objects",
        help="annotations: the objects file (one scene) or a folder of <scene>.json "
        "(default <capture>/objects_annotations.json); format in docs/dataengine.md.",
    ),
    cache: Path | None = typer.Option(
        None,
        "--cache",
        help="Folder of scene assets (navigation maps, Gaussians) shared across runs, keyed by each "
        "capture's content: a second run on the same capture copies them instead of rebuilding.",
    ),
    sampling: list[str] = typer.Option(
        None,
        "--sampling",
        "-S",
        help="Trajectory sampling option key=value (repeatable; SamplingConfig fields), e.g. "
        "min_path_length=1.0 for houses too small for a 3 m path (such episodes start inside the 3 m "
        "success distance of the evaluation).",
    ),
    approach_views: int = typer.Option(
        0,
        "--approach-views",
        min=0,
        help="Per scene: start poses with goal objects in view, each giving up to 2 short approach "
        "episodes (one per visible object) in a second shard, scenes/<name>/approach, listed in "
        "shards.json but never in the episode file: they teach a policy to tell the named object apart.",
    ),
) -> None:
    """Sample, roll out, render and annotate episodes for every scene (resumable; one Ray task per scene)."""
    from image2sim.dataengine.distributed import RunError, run_engine
    from image2sim.dataengine.engine_config import EngineConfig

    try:
        n = None if per_scene == "auto" else int(per_scene)
    except ValueError:
        typer.echo(f"error: --per-scene must be auto or an integer, got {per_scene!r}", err=True)
        raise typer.Exit(2) from None
    try:
        gaussians = _gaussian_overrides(gaussian_config)
    except ValueError as err:  # ConfigError is a ValueError
        typer.echo(f"error: --gaussian-config: {err}", err=True)
        raise typer.Exit(2) from None
    try:
        cfg = EngineConfig(
            per_scene=n,
            annotator=annotator,
            annotator_options=_parse_options(annotator_option),
            render=render,
            view=view,
            obs_height=obs_height,
            frame_stride=frame_stride,
            split=split,
            seed=seed,
            renderer=None if renderer is None else str(renderer),
            device=device,
            gaussians=gaussians,
            refine_steps=refine_steps,
            rollout=({} if min_steps is None else {"min_steps": min_steps})
            | ({"face_goal": True} if face_goal else {}),
            sampling=_parse_options(sampling),
            approach={"views": approach_views} if approach_views else {},
            detector=detector,
            detector_weights=None if detector_weights is None else str(detector_weights),
            objects=None if objects is None else str(objects),
        )
        summary = run_engine(
            scenes,
            out,
            cfg,
            executor=executor,
            workers=workers,
            address=address,
            asset_cache=cache,
            episode_format=episode_format,
            language=language,
        )
    except (RunError, ValueError) as err:
        typer.echo(f"error: {err}", err=True)
        raise typer.Exit(2) from None
    for name, err in summary["failed"].items():
        typer.echo(f"scene {name} failed: {err.splitlines()[0]}", err=True)
    typer.echo(
        json.dumps(
            {k: v for k, v in summary.items() if k != "failed"} | {"failed": sorted(summary["failed"])},
            indent=1,
        )
    )
    if summary["episodes"] == 0:
        for name, outcome in summary.get("per_scene", {}).items():
            typer.echo(f"scene {name}: 0 episodes ({outcome.get('why', '')})", err=True)
        typer.echo(
            "error: no episode was produced (every scene failed or had none); see the per-scene reasons "
            "above. Small houses: --sampling min_path_length=... allows shorter episodes.",
            err=True,
        )
        raise typer.Exit(1)


@app.command("stats")
def stats_command(
    episodes: Path = typer.Argument(
        ..., help="Episode file ({split}.json.gz) or an `episodes` output folder."
    ),
    out: Path | None = typer.Option(
        None, "--out", help="Folder for stats.json / stats.png (default: beside)."
    ),
    split: str = typer.Option("train", "--split", help="Split to read when EPISODES is a folder."),
) -> None:
    """Style mix, instruction length, trajectory length and step histograms (JSON + PNG)."""
    from image2sim.dataengine.stats import write_stats

    path = episodes / split / f"{split}.json.gz" if episodes.is_dir() else episodes
    if not path.is_file():
        typer.echo(f"error: {path}: episode file not found", err=True)
        raise typer.Exit(2)
    gt = path.with_name(path.name.replace(".json.gz", "_gt.json.gz"))
    stats = write_stats(path, out or path.parent / "stats", gt)
    typer.echo(
        json.dumps(
            {k: stats[k] for k in ("episodes", "scenes", "style_mix", "distinct_instructions")}, indent=1
        )
    )
