"""``image2sim nav``: Image2Nav training and inference."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from image2sim.navpolicy.train_cli import check_source
from image2sim.navpolicy.train_cli import nav_config as _config

app = typer.Typer(help="Navigation policy (Image2Nav): train, DAgger, run.", no_args_is_help=True)


def _gather_commands() -> None:
    # Command modules keep their own registries and never import this one (no cycle).
    from image2sim.navpolicy import train_cli, vision_cli

    app.registered_commands[:0] = train_cli.app.registered_commands  # train first in --help
    app.registered_commands.extend(vision_cli.app.registered_commands)


@app.command("tokenizer")
def tokenizer_cmd(
    config: Annotated[
        str, typer.Option(help="Preset (tiny|paper) or YAML; its model.source picks the tokenizer.")
    ] = "tiny",
) -> None:
    """Show the special-token ids and how each action tokenizes (single token or not)."""
    from image2sim.navpolicy.actions import ActionCodec
    from image2sim.navpolicy.model import policy_tokenizer, tokenizer_corpus
    from image2sim.navpolicy.tokenizer import check_special_tokens

    cfg = _config(config)
    tok = policy_tokenizer(cfg, tokenizer_corpus(cfg))  # instructions: the config's data.shards too
    codec = ActionCodec.from_tokenizer(tok)
    typer.echo(
        json.dumps(
            {
                "vocab_size": len(tok),
                "special_tokens": check_special_tokens(tok),
                "actions_first": {a.name: list(v) for a, v in codec.first.items()},
                "actions_following": {a.name: list(v) for a, v in codec.following.items()},
                "single_token": codec.single_token,
            },
            indent=2,
        )
    )


@app.command("synth-shard")
def synth_shard(
    out: Annotated[Path, typer.Argument(help="Shard folder to create.")],
    n: Annotated[int, typer.Option(help="Number of trajectories.")] = 32,
    size: Annotated[int, typer.Option(help="Square frame size in pixels.")] = 64,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
) -> None:
    """Write a toy shard (colour-coded frames) to smoke-test training without the data engine."""
    from image2sim.navpolicy.data import synthetic_trajectories, write_shard

    write_shard(
        out,
        synthetic_trajectories(n, height=size, width=size, seed=seed),
        observation={"camera": "synthetic", "height": size, "width": size},
    )
    typer.echo(f"wrote {n} trajectories to {out}")


@app.command("inspect")
def inspect_cmd(
    shard: Annotated[Path, typer.Argument(help="Shard folder.")],
    index: Annotated[int, typer.Option(help="Trajectory index.")] = 0,
    config: Annotated[str, typer.Option(help="Preset or YAML.")] = "tiny",
) -> None:
    """Print the training prompt of one sample, marking the labelled (action) tokens with [[...]]."""
    from image2sim.navpolicy.collate import NavCollator
    from image2sim.navpolicy.data import NavShardDataset, sample_options
    from image2sim.navpolicy.model import build_policy
    from image2sim.navpolicy.prompting import IGNORE_INDEX, PromptBuilder

    cfg = _config(config)
    pol = build_policy(cfg, seed=0)
    opts = sample_options(cfg) | {"jitter": False}  # deterministic: the last cut, bin centres
    sample = NavShardDataset([shard], **opts)[index]
    batch = NavCollator(PromptBuilder(pol.tokenizer, pol.codec, cfg.system_prompt), pol.image_processor)(
        [sample]
    )
    pieces = []
    for t, lab in zip(batch["input_ids"][0].tolist(), batch["labels"][0].tolist(), strict=True):
        s = pol.tokenizer.decode([t])
        pieces.append(f"[[{s}]]" if lab != IGNORE_INDEX else s)
    text = "".join(pieces)
    pad = "<|image_pad|>"
    while pad * 2 in text:
        text = text.replace(pad * 2, pad)
    typer.echo(text.replace(pad, "<image>"))
    typer.echo(
        f"tokens={batch['input_ids'].shape[1]} labels={int((batch['labels'] != IGNORE_INDEX).sum())} "
        f"images={batch['image_grid_thw'].shape[0]}"
    )


@app.command("from-episodes")
def from_episodes_cmd(
    out: Annotated[
        Path, typer.Option(help="Shard folder to write (published atomically; refused if it exists).")
    ],
    sim_scenes: Annotated[
        Path, typer.Option(help="Folder of scene folders named by the episodes' scene_id stem.")
    ],
    episodes: Annotated[
        Path | None,
        typer.Option(
            help="A VLN-CE-schema episode file (.json.gz; Habitat frame unless it states its frame). "
            "Its <name>_gt.json.gz beside it is used when --gt is not given."
        ),
    ] = None,
    gt: Annotated[
        Path | None, typer.Option(help="With --episodes: the matching *_gt.json.gz (dense routes).")
    ] = None,
    dataset: Annotated[
        str,
        typer.Option(
            help="Instead of --episodes: a published benchmark in --dataset-root, r2r-ce or rxr-ce."
        ),
    ] = "none",
    dataset_root: Annotated[
        Path | None, typer.Option(help="With --dataset: the folder holding <split>/<split>*.json.gz.")
    ] = None,
    split: Annotated[str, typer.Option(help="With --dataset: the split, e.g. train.")] = "train",
    rxr_role: Annotated[
        list[str], typer.Option(help="rxr-ce: roles to load, guide and/or follower (repeatable).")
    ] = ["guide"],  # noqa: B006
    language: Annotated[
        list[str], typer.Option(help="rxr-ce: keep only these languages, e.g. en-US (repeatable).")
    ] = [],  # noqa: B006
    source: Annotated[
        str,
        typer.Option(
            help="Observations from 'neural' (built scenes + --renderer), 'splat_only' (built scenes, "
            "no learned renderer) or 'exact' (procedural captures rendered exactly)."
        ),
    ] = "neural",
    renderer: Annotated[
        Path | None,
        typer.Option(help="source neural: pixel-flow renderer (export folder, .safetensors or .ckpt)."),
    ] = None,
    config: Annotated[
        str, typer.Option(help="Policy preset or YAML: its observation section sets the frames.")
    ] = "tiny",
    frame_stride: Annotated[
        int, typer.Option(help="Store the observation of every n-th step (2 = what the agent sees).")
    ] = 2,
    max_steps: Annotated[int, typer.Option(help="Step cap per episode (reached: skipped).")] = 500,
    end_tolerance: Annotated[
        float, typer.Option(help="Skip an episode whose follower stops farther (m) from the route's end.")
    ] = 0.5,
    skip_missing_scenes: Annotated[
        bool, typer.Option(help="Count episodes of absent scene folders as skipped instead of failing.")
    ] = False,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing --out shard.")] = False,
) -> None:
    """Human-annotated instruction episodes (R2R-CE / RxR-CE) -> an Image2Nav training shard.

    Each episode is rolled out in its scene's simulator by the reference-path oracle along its dense
    ground-truth route (else its reference path), and stored with its human instruction; episodes
    whose route the oracle cannot finish are skipped and counted by reason. Mix the shard with
    generated data by sample ratio: ``nav train --shard OUT --shard-weight W ...``.
    """
    from image2sim.eval import datasets as ds
    from image2sim.navpolicy.human import shard_from_episodes

    check_source(source, renderer)
    if renderer is not None and not renderer.exists():
        raise typer.BadParameter(f"{renderer}: no such file or folder", param_hint="--renderer")
    if not sim_scenes.is_dir():
        raise typer.BadParameter(f"{sim_scenes}: no such folder", param_hint="--sim-scenes")
    if (episodes is None) == (dataset == "none"):
        raise typer.BadParameter("give either --episodes FILE or --dataset r2r-ce|rxr-ce (one of them)")
    if out.exists() and not overwrite:
        raise typer.BadParameter(f"{out} exists (pass --overwrite to replace it)", param_hint="--out")
    cfg = _config(config)
    try:
        if episodes is not None:
            if gt is None:
                beside = episodes.with_name(episodes.name.replace(".json.gz", "_gt.json.gz"))
                gt = beside if beside != episodes and beside.is_file() else None
            data = ds.load_image2sim_episodes(episodes, gt)
        else:
            if dataset not in ("r2r-ce", "rxr-ce"):
                raise typer.BadParameter(f"must be r2r-ce or rxr-ce, got {dataset!r}", param_hint="--dataset")
            if dataset_root is None:
                raise typer.BadParameter("--dataset needs --dataset-root", param_hint="--dataset-root")
            if dataset == "r2r-ce":
                data = ds.load_r2r_ce(dataset_root, split)
            else:
                data = ds.load_rxr_ce(dataset_root, split, roles=rxr_role, languages=language or None)
    except (ds.EpisodeFileError, ValueError) as exc:  # names the file, the episode and the field
        raise typer.BadParameter(str(exc), param_hint="--episodes" if episodes else "--dataset") from exc
    if not data.episodes:
        raise typer.BadParameter(f"{episodes or dataset_root}: no episodes (after role/language filters)")
    try:
        summary = shard_from_episodes(
            data,
            sim_scenes,
            out,
            source,
            renderer,
            cfg.observation,
            frame_stride,
            max_steps,
            dataset=episodes.name if episodes is not None else data.name,
            end_tolerance=end_tolerance,
            missing_scenes="skip" if skip_missing_scenes else "error",
            overwrite=overwrite,
        )
    except FileNotFoundError as exc:
        raise typer.BadParameter(str(exc), param_hint="--sim-scenes") from exc
    except (ValueError, FileExistsError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    shown = {k: v for k, v in summary.items() if k != "skipped_episodes"}
    shown["summary_file"] = str(out / "summary.json")  # lists every skipped episode and why
    typer.echo(json.dumps(shown, indent=2))


@app.command("card")
def card_cmd(
    export: Annotated[Path, typer.Argument(help="A policy export folder (nav train's <out>/export).")],
    metrics: Annotated[
        Path | None, typer.Option(help="Metrics JSON to put in the card (e.g. metrics/nav.json).")
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            help="Write the card to this file instead of <export>/README.md (a DVC stage's own output)."
        ),
    ] = None,
    threads: Annotated[int, typer.Option(help="torch threads.")] = 1,
) -> None:
    """Rewrite an export's model card (README.md), e.g. with the metrics of a later evaluation."""
    import torch
    from image2sim.navpolicy.card import update_model_card

    torch.set_num_threads(threads)
    typer.echo(f"wrote {update_model_card(export, metrics, out)}")


@app.command("act")
def act_cmd(
    agent: Annotated[
        str, typer.Option(help="image2nav, random, forward, forward_turn or oracle.")
    ] = "image2nav",
    model: Annotated[str, typer.Option(help="image2nav: exported policy folder or 'tiny'.")] = "tiny",
    config: Annotated[str, typer.Option(help="Preset or YAML (observation and agent settings).")] = "tiny",
    scene_seed: Annotated[int, typer.Option(help="Procedural scene seed.")] = 1000,
    episode: Annotated[int, typer.Option(help="Episode index on that scene.")] = 0,
    max_steps: Annotated[int, typer.Option(help="Step limit.")] = 200,
    success_distance: Annotated[float, typer.Option(help="Success radius (metres).")] = 0.5,
    seed: Annotated[int, typer.Option(help="Episode seed (random baselines, model).")] = 0,
    out: Annotated[Path, typer.Option(help="Output folder (topdown.png, frames/, episode.json).")] = Path(
        "outputs/nav-act"
    ),
) -> None:
    """Run one agent on one episode of a procedural scene; write a top-down trajectory PNG, the
    observed frames and the episode's metrics (through the evaluation runner)."""
    from image2sim.navpolicy.act import run_act

    cfg = _config(config, {"model": {"source": model}} if model != "tiny" else None)
    try:
        rec = run_act(cfg, agent, out, scene_seed, episode, max_steps, success_distance, seed)
    except (ValueError, FileNotFoundError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    typer.echo(json.dumps(rec, indent=2))


@app.command("compare")
def compare_cmd(
    model: Annotated[str, typer.Option(help="Exported policy folder for image2nav, or 'tiny'.")] = "tiny",
    config: Annotated[str, typer.Option(help="Preset or YAML.")] = "tiny",
    agents: Annotated[
        str, typer.Option(help="Comma-separated agents.")
    ] = "image2nav,random,forward,forward_turn,oracle",
    scene_seeds: Annotated[
        str, typer.Option(help="Held-out procedural scene seeds, comma-separated.")
    ] = "1000,1001",
    episodes_per_scene: Annotated[int, typer.Option(help="Episodes per scene.")] = 10,
    max_steps: Annotated[int, typer.Option(help="Step limit.")] = 150,
    success_distance: Annotated[float, typer.Option(help="Success radius (metres).")] = 0.5,
    out: Annotated[Path, typer.Option(help="JSON report (a .md table is written beside it).")] = Path(
        "outputs/nav-compare.json"
    ),
) -> None:
    """Image2Nav vs the baselines on held-out procedural episodes (SR/SPL with 95% intervals)."""
    from image2sim.navpolicy.act import compare_agents, comparison_markdown

    cfg = _config(config, {"model": {"source": model}} if model != "tiny" else None)
    seeds = [int(x) for x in scene_seeds.split(",") if x.strip()]
    names = [x.strip() for x in agents.split(",") if x.strip()]
    try:
        summary = compare_agents(cfg, names, seeds, episodes_per_scene, max_steps, success_distance)
    except (ValueError, FileNotFoundError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    rec = {"model": model, "scene_seeds": seeds, "success_distance": success_distance, "agents": summary}
    from image2sim.simulator.io.atomic import write_json_atomic, write_text_atomic

    write_json_atomic(out, rec)
    md = comparison_markdown(summary)
    write_text_atomic(out.with_suffix(".md"), md)
    typer.echo(md)


@app.command("replay")
def replay_cmd(
    shard: Annotated[Path, typer.Argument(help="Shard folder with recorded trajectories.")],
    model: Annotated[
        str, typer.Option(help="Exported policy folder, or 'tiny' for an untrained model.")
    ] = "tiny",
    config: Annotated[str, typer.Option(help="Preset or YAML (agent and observation settings).")] = "tiny",
    episodes: Annotated[int, typer.Option(help="How many trajectories to replay.")] = 4,
    out: Annotated[Path, typer.Option(help="JSON report.")] = Path("outputs/nav-replay.json"),
) -> None:
    """Open-loop check: stream each recorded episode's frames through the agent (expert actions are
    what gets executed) and compare its two predicted actions with the expert's next two."""
    import numpy as np
    from image2sim.navpolicy.agent import Image2NavAgent
    from image2sim.navpolicy.data import ShardReader, next_actions
    from image2sim.navpolicy.model import build_policy

    cfg = _config(config, {"model": {"source": model}} if model != "tiny" else None)
    pol = build_policy(cfg, seed=0)
    agent = Image2NavAgent(pol, cfg.agent, cfg.system_prompt)
    reader = ShardReader(shard)
    report = []
    for e in range(min(episodes, len(reader))):
        traj = reader[e]
        agent.reset(traj.instruction)
        hits, prev = [], None
        for frame, step in zip(traj.frames, traj.frame_steps, strict=True):
            executed = None if prev is None else list(traj.actions[prev:step])
            pred = [int(a) for a in agent.act(frame, executed=executed)]
            hits.append([p == t for p, t in zip(pred, next_actions(traj.actions, step), strict=True)])
            prev = step
        h = np.asarray(hits, dtype=float)
        report.append(
            {
                "episode_id": traj.episode_id,
                "steps": len(hits),
                "first_action_acc": float(h[:, 0].mean()),
                "pair_acc": float(h.all(1).mean()),
                "fallbacks": sum(s.fallback for s in agent.history),
            }
        )
    from image2sim.simulator.io.atomic import write_json_atomic

    write_json_atomic(out, report)
    typer.echo(json.dumps(report, indent=2))


@app.command("serve")
def serve_cmd(
    model: Annotated[str, typer.Option(help="Exported policy folder, or 'tiny' (untrained).")] = "tiny",
    config: Annotated[str, typer.Option(help="Preset or YAML (agent and observation settings).")] = "tiny",
    host: Annotated[
        str, typer.Option(help="Address to bind; anything but loopback needs --token-env.")
    ] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port (0: any free port; the URL is printed).")] = 8000,
    token_env: Annotated[
        str,
        typer.Option(help="Name of the environment variable holding the bearer token clients must send."),
    ] = "",
    max_sessions: Annotated[int, typer.Option(help="Open sessions at most (one more: 429).")] = 8,
    session_ttl: Annotated[float, typer.Option(help="Seconds an idle session lives.")] = 600.0,
    max_body_mb: Annotated[float, typer.Option(help="Largest request body in MiB (larger: 413).")] = 8.0,
    max_image_pixels: Annotated[
        int, typer.Option(help="Largest image (width x height), checked from its header.")
    ] = 4096 * 4096,
    threads: Annotated[int, typer.Option(help="torch threads (0 = torch default; tiny prefers 1).")] = 0,
) -> None:
    """Serve the policy over HTTP: a session per robot episode, streaming context with KV-cache reuse
    (the in-process agent's actions for the same observations). API: docs/navpolicy.md."""
    import dataclasses
    import os

    from image2sim.navpolicy.serve import ServeSettings, bind_error, create_app, policy_agent_factory, serve

    problem = bind_error(host, token_env or None, dict(os.environ))
    if problem:
        typer.echo(f"error: {problem}", err=True)
        raise typer.Exit(2)
    try:
        settings = ServeSettings(
            max_sessions=max_sessions,
            session_ttl_s=session_ttl,
            max_body_bytes=int(max_body_mb * 1024 * 1024),
            max_image_pixels=max_image_pixels,
            token=os.environ[token_env] if token_env else None,
            model_name=model,
        )
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    cfg = _config(config, {"model": {"source": model}} if model != "tiny" else None)
    if threads:
        import torch

        torch.set_num_threads(threads)
    o = cfg.observation
    try:
        factory = policy_agent_factory(cfg)
    except FileNotFoundError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    settings = dataclasses.replace(
        settings, observation={"camera": o.camera, "height": o.height, "width": o.width}
    )
    auth = f"bearer token from ${token_env}" if token_env else "no token (loopback only)"
    serve(
        create_app(factory, settings),
        host,
        port,
        on_ready=lambda url: typer.echo(f"Image2Nav policy server on {url} (model {model}; {auth})"),
    )


@app.command("drive")
def drive_cmd(
    server: Annotated[str, typer.Option(help="Policy server URL (image2sim nav serve).")],
    scene: Annotated[
        Path,
        typer.Option(help="Scene folder (navmap.npz, navgraph.npz, Gaussians) named as the episodes' scene."),
    ],
    episodes: Annotated[
        Path, typer.Option(help="Episode file (.json.gz, VLN-CE schema); its _gt beside it.")
    ],
    token_env: Annotated[
        str, typer.Option(help="Name of the environment variable holding the server's bearer token.")
    ] = "",
    protocol: Annotated[
        str, typer.Option(help="Protocol name or JSON file with a protocol record.")
    ] = "image2sim",
    backend: Annotated[
        str, typer.Option(help="neural (built scene folder) or exact (procedural capture rendered exactly).")
    ] = "neural",
    max_episodes: Annotated[int, typer.Option(help="At most this many episodes (0: all).")] = 0,
    seed: Annotated[int, typer.Option(help="Run seed (episode seeds derive from it).")] = 0,
    out: Annotated[Path, typer.Option(help="Run folder (per-scene JSONL logs; resumable).")] = Path(
        "runs/nav_drive"
    ),
    metrics: Annotated[Path, typer.Option(help="Headline metrics file to update.")] = Path(
        "metrics/nav_drive.json"
    ),
) -> None:
    """Drive a simulated robot through a policy server: the episodes run in the scene's NeuralSimulator
    through the evaluation runner (agent ``image2nav_http``), with ``eval nav``'s metrics and reports."""
    from image2sim.eval.datasets import EpisodeFileError, load_image2sim_episodes
    from image2sim.eval.metrics.nav import aggregate
    from image2sim.eval.protocols import ProtocolError, load_protocol
    from image2sim.eval.report import nav_table_markdown, write_nav_report
    from image2sim.eval.runner import RunConfig, nav_summary, run_nav_results, update_nav_metrics

    if backend not in ("neural", "exact"):
        raise typer.BadParameter(f"must be neural or exact, got {backend!r}", param_hint="--backend")
    if not scene.is_dir():
        raise typer.BadParameter(f"{scene}: no such folder", param_hint="--scene")
    scene = scene.resolve()  # its name is the episodes' scene name, also for `--scene .`
    try:
        proto = load_protocol(protocol)
    except ProtocolError as exc:
        raise typer.BadParameter(str(exc), param_hint="--protocol") from exc
    gt = episodes.with_name(episodes.name.replace(".json.gz", "_gt.json.gz"))
    try:
        eps = list(
            load_image2sim_episodes(episodes, gt if gt != episodes and gt.is_file() else None).episodes
        )
    except (EpisodeFileError, FileNotFoundError, ValueError) as exc:
        raise typer.BadParameter(str(exc), param_hint="--episodes") from exc
    mine = [e for e in eps if e.scene_name == scene.name]
    if not mine:
        names = sorted({e.scene_name for e in eps})
        raise typer.BadParameter(
            f"{episodes}: no episode of scene {scene.name!r} (its episodes name {names})",
            param_hint="--scene",
        )
    if len(mine) < len(eps):
        typer.echo(f"{len(eps) - len(mine)} episode(s) of other scenes skipped", err=True)
    import httpx
    from image2sim.navpolicy.client import PolicyClient, ServerError, token_from_env

    try:
        with PolicyClient(server, token=token_from_env(token_env or None), timeout_s=30) as client:
            client.info()  # fail fast: unreachable server, wrong token
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--token-env") from exc
    except ServerError as exc:
        typer.echo(f"error: policy server {server}: {exc}", err=True)
        raise typer.Exit(2 if exc.status in (401, 403, 404) else 1) from exc
    except httpx.HTTPError as exc:  # connection refused, timeout
        typer.echo(f"error: cannot reach the policy server at {server} ({exc})", err=True)
        raise typer.Exit(1) from exc
    name = "image2nav_http"
    cfg = RunConfig(
        agent=name,
        agent_options={"server": server, "token_env": token_env},
        seed=seed,
        max_episodes_per_scene=max_episodes or None,
        backend=backend,
    )
    results = run_nav_results(mine, scene.parent, proto, cfg, out)
    report = aggregate(results)
    update_nav_metrics(metrics, proto, name, nav_summary(results, ci_seed=seed))
    write_nav_report(out / name / "report", name, report, {"source": str(out / name), "server": server})
    typer.echo(nav_table_markdown([(name, report)]))
    typer.echo(f"updated {metrics}")


_gather_commands()
