"""``image2sim eval``: navigation and rendering benchmarks, reports."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(help="Evaluation: navigation metrics, rendering benchmark, reports.", no_args_is_help=True)


@app.command("protocols")
def protocols_cmd(
    name: Annotated[
        str | None, typer.Argument(help="Print one protocol as JSON (image2sim, vlnce, rxr-habitat).")
    ] = None,
) -> None:
    """List the built-in evaluation protocols (or print one in full)."""
    from image2sim.eval.protocols import PROTOCOLS, get_protocol
    from image2sim.eval.report import describe_protocol

    if name:
        typer.echo(json.dumps(get_protocol(name).to_dict(), indent=2))
        return
    for p in PROTOCOLS.values():
        typer.echo(f"{p.name:14s} {describe_protocol(p)}")


@app.command("aggregate")
def aggregate_cmd(
    log: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="Per-episode JSONL log of a run.")],
    out: Annotated[
        Path | None, typer.Option(help="Directory for aggregate.json, metrics.json, table.md.")
    ] = None,
    label: Annotated[str | None, typer.Option(help="Row label (default: the log's stem).")] = None,
) -> None:
    """Aggregate a per-episode log (one protocol) into means with episode counts."""
    from image2sim.eval.metrics.nav import aggregate
    from image2sim.eval.report import nav_table_markdown, write_nav_report
    from image2sim.eval.results import read_episode_log

    _, results = read_episode_log(log)
    report = aggregate(results)
    name = label or log.stem
    typer.echo(nav_table_markdown([(name, report)]))
    if out is not None:
        paths = write_nav_report(out, name, report, {"source": str(log)})
        typer.echo("wrote " + ", ".join(str(p) for p in paths.values()))


@app.command("report")
def report_cmd(
    aggregates: Annotated[
        list[Path] | None,
        typer.Argument(exists=True, dir_okay=False, help="aggregate.json files (optional)."),
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="Write the Markdown table of the aggregates here (atomically).")
    ] = None,
    nav: Annotated[Path | None, typer.Option(help="metrics/nav.json to report (Table 2 layout).")] = None,
    render: Annotated[
        Path | None, typer.Option(help="metrics/render.json to report (Table 1 layout).")
    ] = None,
    out_dir: Annotated[
        Path | None, typer.Option(help="Write nav.md, render.md and render_speed.png here.")
    ] = None,
    figure_scene: Annotated[
        Path | None,
        typer.Option(
            help="Scene folder (navmap.npz): also write demo_figure.png to --out-dir (rendered panorama, "
            "its splat prior, a top-down episode map); needs --figure-capture and --figure-episodes."
        ),
    ] = None,
    figure_capture: Annotated[Path | None, typer.Option(help="figure: the scene's capture folder.")] = None,
    figure_episodes: Annotated[
        Path | None, typer.Option(help="figure: episode file or `episodes` output folder (train split).")
    ] = None,
    figure_checkpoint: Annotated[
        Path | None, typer.Option(help="figure: renderer checkpoint (omit: untrained model).")
    ] = None,
    renderer_config: Annotated[str, typer.Option(help="figure: renderer preset or YAML.")] = "tiny",
    gaussian_config: Annotated[str, typer.Option(help="figure: Gaussian scene preset or file.")] = "tiny",
    holdout_every: Annotated[int, typer.Option(help="figure: every n-th frame is held out.")] = 8,
) -> None:
    """Tables laid out like the paper's Table 2 (navigation) and Table 1 (rendering), the speed plot,
    and optionally the demo figure."""
    from image2sim.eval.report import nav_table_markdown, read_aggregate
    from image2sim.eval.results import read_metrics_file
    from image2sim.simulator.io.atomic import write_text_atomic

    if not aggregates and nav is None and render is None and figure_scene is None:
        raise typer.BadParameter("give aggregate.json files, --nav, --render and/or --figure-scene")
    if figure_scene is not None and (out_dir is None or figure_capture is None or figure_episodes is None):
        raise typer.BadParameter("--figure-scene needs --out-dir, --figure-capture and --figure-episodes")
    if aggregates:
        table = nav_table_markdown([read_aggregate(p) for p in aggregates])
        typer.echo(table)
        if out is not None:
            write_text_atomic(out, table)
    if nav is not None:
        from image2sim.eval.runner import nav_markdown

        text = nav_markdown(read_metrics_file(nav))
        typer.echo("## Navigation\n\n" + text)
        if out_dir is not None:
            written = write_text_atomic(out_dir / "nav.md", "# Navigation (Table 2 layout)\n\n" + text)
            typer.echo(f"wrote {written}")
    if render is not None:
        from image2sim.eval.plots import plot_speed_vs_error
        from image2sim.eval.render_bench import render_markdown

        doc = read_metrics_file(render)
        text = render_markdown(doc)
        typer.echo("## Rendering\n\n" + text)
        if out_dir is not None:
            written = write_text_atomic(out_dir / "render.md", "# Rendering (Table 1 layout)\n\n" + text)
            typer.echo(f"wrote {written}")
            typer.echo(f"wrote {plot_speed_vs_error(doc, out_dir / 'render_speed.png')}")
    if figure_scene is not None:
        from image2sim.eval.figure import demo_figure_from_outputs

        shown = demo_figure_from_outputs(
            figure_scene,
            figure_capture,
            figure_episodes,
            out_dir / "demo_figure.png",
            renderer_config=renderer_config,
            checkpoint=figure_checkpoint,
            gaussian_config=gaussian_config,
            holdout_every=holdout_every,
        )
        typer.echo(f"wrote {out_dir / 'demo_figure.png'} ({json.dumps(shown)})")


def _protocol(name_or_file: str):
    """A built-in protocol name or a JSON file holding a protocol record."""
    from image2sim.eval.protocols import ProtocolError, load_protocol

    try:
        return load_protocol(name_or_file)
    except ProtocolError as exc:
        raise typer.BadParameter(str(exc), param_hint="--protocol") from exc


@app.command("nav")
def nav_cmd(
    scenes: Annotated[Path, typer.Option(help="Folder of scene folders (navmap.npz + navgraph.npz each).")],
    episodes: Annotated[
        Path | None, typer.Option(help="VLN-CE schema episode file (.json.gz); scenes by scene_id stem.")
    ] = None,
    gt: Annotated[Path | None, typer.Option(help="Matching *_gt.json.gz (dense nDTW references).")] = None,
    dataset: Annotated[
        str,
        typer.Option(
            help="Published benchmark to read from --dataset-root: r2r-ce, rxr-ce or reverie-ce "
            "(their layout, schema and checks: R2R-CE needs its vocabulary, RxR-CE has roles and "
            "languages); 'none' reads --episodes or samples --point-goal."
        ),
    ] = "none",
    dataset_root: Annotated[
        Path | None, typer.Option(help="With --dataset: the folder holding <split>/<split>*.json.gz.")
    ] = None,
    split: Annotated[str, typer.Option(help="With --dataset: the split, e.g. val_unseen.")] = "val_unseen",
    rxr_role: Annotated[
        list[str], typer.Option(help="rxr-ce: roles to load, guide and/or follower (repeatable).")
    ] = ["guide"],  # noqa: B006
    language: Annotated[
        list[str], typer.Option(help="rxr-ce: keep only these languages, e.g. en-US (repeatable).")
    ] = [],  # noqa: B006
    point_goal: Annotated[
        int, typer.Option(help="Without --episodes: sample this many point-goal episodes per scene.")
    ] = 0,
    min_distance: Annotated[float, typer.Option(help="Point-goal start-goal geodesic minimum (m).")] = 1.5,
    agent: Annotated[
        list[str], typer.Option(help="Agent(s): random, forward, oracle, image2nav (repeatable).")
    ] = ["oracle"],  # noqa: B006
    protocol: Annotated[
        str, typer.Option(help="Protocol name or JSON file with a protocol record.")
    ] = "image2sim",
    forward_steps: Annotated[int, typer.Option(help="Forward steps of the 'forward' baseline.")] = 37,
    model: Annotated[str, typer.Option(help="image2nav: exported policy folder or 'tiny'.")] = "tiny",
    policy_config: Annotated[str, typer.Option(help="image2nav: navpolicy config preset or YAML.")] = "tiny",
    seed: Annotated[int, typer.Option(help="Run seed (episode seeds derive from it).")] = 0,
    workers: Annotated[int, typer.Option(help="Scene-level processes.")] = 1,
    max_episodes: Annotated[int, typer.Option(help="At most this many episodes per scene (0: all).")] = 0,
    backend: Annotated[
        str,
        typer.Option(
            help="neural (scene folders with navmap/navgraph), exact (procedural captures from "
            "`data synth`, rendered exactly: the sim-to-real 'real world') or habitat (habitat-sim on "
            "<scenes>/<episode scene_id>; needs habitat-sim and --episodes)."
        ),
    ] = "neural",
    out: Annotated[Path, typer.Option(help="Run folder (per-scene JSONL logs; resumable).")] = Path(
        "runs/eval_nav"
    ),
    metrics: Annotated[Path, typer.Option(help="Headline metrics file to update.")] = Path(
        "metrics/nav.json"
    ),
    wandb: Annotated[
        bool, typer.Option(help="Also log the headline metrics to W&B (offline by default).")
    ] = False,
    submission: Annotated[
        Path | None,
        typer.Option(help="Also write a leaderboard predictions file of the (single) agent's run."),
    ] = None,
    submission_format: Annotated[
        str,
        typer.Option(help="r2r-ce (EvalAI predictions JSON) or rxr-ce (RxR-Habitat jsonl)."),
    ] = "r2r-ce",
) -> None:
    """Run agents on navigation episodes (resumes an interrupted run) and update metrics/nav.json."""
    from image2sim.eval.metrics.nav import aggregate
    from image2sim.eval.report import nav_table_markdown, write_nav_report
    from image2sim.eval.runner import (
        RunConfig,
        load_exact_backend,
        load_scene_backend,
        nav_summary,
        run_nav_results,
        sample_point_goal_episodes,
        update_nav_metrics,
    )

    proto = _protocol(protocol)
    if submission is not None:
        from image2sim.eval.submission import SUBMISSION_FORMATS

        if len(agent) != 1:
            raise typer.BadParameter(
                "a submission is one agent's run: give one --agent", param_hint="--submission"
            )
        if submission_format not in SUBMISSION_FORMATS:
            raise typer.BadParameter(
                f"expected one of {SUBMISSION_FORMATS}", param_hint="--submission-format"
            )
    if backend == "habitat" and episodes is None and dataset == "none":
        raise typer.BadParameter(
            "--backend habitat needs --episodes or --dataset (point goals are sampled on our graphs)"
        )
    if dataset != "none":
        from image2sim.eval import datasets as ds

        loaders = {
            "r2r-ce": lambda: ds.load_r2r_ce(dataset_root, split),
            "reverie-ce": lambda: ds.load_reverie_ce(dataset_root, split),
            "rxr-ce": lambda: ds.load_rxr_ce(dataset_root, split, roles=rxr_role, languages=language or None),
        }
        if dataset not in loaders:
            raise typer.BadParameter(f"--dataset must be none or one of {sorted(loaders)}, got {dataset!r}")
        if dataset_root is None or episodes is not None:
            raise typer.BadParameter("--dataset needs --dataset-root (and no --episodes)")
        try:
            eps = list(loaders[dataset]().episodes)
        except (ds.EpisodeFileError, ValueError) as err:
            raise typer.BadParameter(str(err)) from err
        if not eps:
            raise typer.BadParameter(
                f"{dataset} {split} at {dataset_root}: no episodes (after role/language filters)"
            )
    elif episodes is not None:
        from image2sim.eval.datasets import load_image2sim_episodes

        eps = list(load_image2sim_episodes(episodes, gt).episodes)
    elif point_goal > 0:
        eps = []
        marker = "manifest.json" if backend == "exact" else "navmap.npz"
        for d in sorted(p for p in scenes.iterdir() if (p / marker).is_file()):
            load = load_exact_backend if backend == "exact" else load_scene_backend
            sim = load(d, proto).sim
            eps += sample_point_goal_episodes(
                sim, point_goal, seed=seed, min_distance=min_distance, scene_id=d.name
            )
        if not eps:
            raise typer.BadParameter(f"{scenes}: no scene folder with {marker}")
    else:
        raise typer.BadParameter("give --episodes or --point-goal N")
    rows = []
    for name in agent:
        options: dict = {}
        if name == "forward":
            options = {"forward_steps": forward_steps}
        elif name == "image2nav":
            options = {"model": model, "config": policy_config}
        cfg = RunConfig(
            agent=name,
            agent_options=options,
            seed=seed,
            workers=workers,
            max_episodes_per_scene=max_episodes or None,
            backend=backend,
        )
        results = run_nav_results(eps, scenes, proto, cfg, out)
        report = aggregate(results)
        update_nav_metrics(metrics, proto, name, nav_summary(results, ci_seed=seed))
        write_nav_report(out / name / "report", name, report, {"source": str(out / name)})
        rows.append((name, report))
    typer.echo(nav_table_markdown(rows))
    goalless = sum(not e.has_goal for e in eps)
    if goalless:
        typer.echo(
            f"{goalless} of {len(eps)} episodes have no goal (a test split): NE, OSR, SR, SPL and sDTW "
            "are n/a there (null in the metrics file); the leaderboard scores the submission"
        )
    typer.echo(f"updated {metrics}")
    if submission is not None:
        from image2sim.eval.submission import read_run_trajectories, write_submission

        ids = {e.episode_id: getattr(e.instruction, "instruction_id", None) for e in eps}
        path = write_submission(
            submission, submission_format, read_run_trajectories(out / agent[0]), list(ids), ids
        )
        typer.echo(f"wrote {submission_format} predictions of {len(ids)} episodes to {path}")
    if wandb:
        from image2sim.eval.results import read_metrics_file
        from image2sim.eval.tracking import log_metrics_wandb

        command = {
            "agents": list(agent),
            "protocol": proto.name,
            "episodes": str(episodes) if episodes else None,
            "point_goal": point_goal,
            "min_distance": min_distance,
            "forward_steps": forward_steps,
            "model": model,
            "policy_config": policy_config,
            "seed": seed,
            "max_episodes": max_episodes,
            "scenes": str(scenes),
            "backend": backend,
        }
        run_dir = log_metrics_wandb(read_metrics_file(metrics), "nav", stage="eval_nav", config=command)
        typer.echo(f"W&B run: {run_dir}")


def _split_spec(spec: str, option: str) -> tuple[str, str]:
    name, sep, rest = spec.partition("=")
    if not sep or not name or not rest:
        raise typer.BadParameter(f"expected NAME=VALUE, got {spec!r}", param_hint=option)
    return name, rest


def _nav_source(value: str, option: str, successes: bool = True) -> dict:
    """``AGENT@FILE`` -> {"doc", "agent", "where", "successes"}: per-episode successes from the run's
    logs beside FILE (None where there are none, or not asked for: the scaling points are never
    paired)."""
    from image2sim.eval.sim2real import episode_successes, load_json

    agent, sep, path = value.partition("@")
    if not sep:
        raise typer.BadParameter(f"expected AGENT@nav.json, got {value!r}", param_hint=option)
    try:
        return {
            "doc": load_json(path),
            "agent": agent,
            "where": path,
            "successes": episode_successes(path, agent) if successes else None,
        }
    except (FileNotFoundError, ValueError) as exc:
        raise typer.BadParameter(str(exc), param_hint=option) from exc


@app.command("sim2real")
def sim2real_cmd(
    row: Annotated[
        list[str],
        typer.Option(
            help="NAME=AGENT@nav.json: a transfer row (neural, splat_only, exact, random, forward)."
        ),
    ],
    scaling: Annotated[
        list[str],
        typer.Option(
            help="HOUSES:EPISODES=AGENT@nav.json: one point of the data-scaling curve (repeatable)."
        ),
    ] = [],  # noqa: B006
    check: Annotated[
        list[str],
        typer.Option(
            help="CHECK/NAME=AGENT@nav.json: a row of another held-out evaluation (e.g. fresh seeds)."
        ),
    ] = [],  # noqa: B006
    policy: Annotated[
        list[str], typer.Option(help="NAME=FOLDER: the exported policy of a row (path relative to the repo).")
    ] = [],  # noqa: B006
    episode_logs: Annotated[
        list[str],
        typer.Option(
            help="NAME=FOLDER: a row's per-episode logs when they are not in <metrics folder>/<agent>/ "
            "(for the paired comparisons)."
        ),
    ] = [],  # noqa: B006
    seed_run: Annotated[
        list[str],
        typer.Option(
            help="ROW/SEED=AGENT@nav.json: the row's policy retrained with another training seed, "
            "evaluated on the same episodes (repeatable; the row itself is seed 0)."
        ),
    ] = [],  # noqa: B006
    budget: Annotated[
        list[str],
        typer.Option(help="NAME=FILE: a timing record of scripts/timed.py (wall_s, cpu_s) to report."),
    ] = [],  # noqa: B006
    heldout_episodes: Annotated[
        Path | None,
        typer.Option(
            "--episodes",
            help="The held-out episode file (json.gz) the rows were evaluated on: splits each row's SR "
            "by the start's geodesic distance to the goal (rows with per-episode logs).",
        ),
    ] = None,
    header: Annotated[Path | None, typer.Option(help="Markdown put above the generated tables.")] = None,
    out: Annotated[Path, typer.Option(help="Metrics JSON.")] = Path("metrics/sim2real.json"),
    report: Annotated[Path, typer.Option(help="Markdown report.")] = Path("reports/sim2real.md"),
    plot: Annotated[Path, typer.Option(help="Scaling plot (PNG).")] = Path("plots/sim2real_scaling.png"),
) -> None:
    """Gather the sim-to-real experiment's evaluations into metrics/sim2real.json, a report and a plot."""
    from image2sim.eval.sim2real import episode_successes, gather, load_json, policy_parameters
    from image2sim.eval.sim2real_report import write_outputs

    rows = {}
    for spec in row:
        name, value = _split_spec(spec, "--row")
        rows[name] = _nav_source(value, "--row")
    for spec in episode_logs:
        name, folder = _split_spec(spec, "--episode-logs")
        if name not in rows:
            raise typer.BadParameter(f"no row {name!r} (rows: {sorted(rows)})", param_hint="--episode-logs")
        try:
            rows[name]["successes"] = episode_successes(rows[name]["where"], rows[name]["agent"], folder)
        except (FileNotFoundError, ValueError) as exc:
            raise typer.BadParameter(str(exc), param_hint="--episode-logs") from exc
    points = []
    for spec in scaling:
        key, value = _split_spec(spec, "--scaling")
        houses, sep, episodes = key.partition(":")
        if not sep or not houses.isdigit() or not episodes.isdigit():
            raise typer.BadParameter(f"expected HOUSES:EPISODES=..., got {spec!r}", param_hint="--scaling")
        points.append(
            {
                "houses": int(houses),
                "episodes": int(episodes),
                **_nav_source(value, "--scaling", successes=False),
            }
        )
    checks: dict = {}
    for spec in check:
        key, value = _split_spec(spec, "--check")
        group, sep, name = key.partition("/")
        if not sep:
            raise typer.BadParameter(f"expected CHECK/NAME=AGENT@file, got {spec!r}", param_hint="--check")
        checks.setdefault(group, {"rows": {}})["rows"][name] = _nav_source(value, "--check")
    seed_runs: dict = {}
    for spec in seed_run:
        key, value = _split_spec(spec, "--seed-run")
        name, sep, label = key.partition("/")
        if not sep or not name or not label:
            raise typer.BadParameter(f"expected ROW/SEED=AGENT@file, got {spec!r}", param_hint="--seed-run")
        seed_runs.setdefault(name, {})[label] = _nav_source(value, "--seed-run")
    policies = dict(_split_spec(p, "--policy") for p in policy)
    budgets: dict = {}
    for spec in budget:
        name, path = _split_spec(spec, "--budget")
        try:
            budgets[name] = load_json(path)
        except (FileNotFoundError, ValueError) as exc:
            raise typer.BadParameter(str(exc), param_hint="--budget") from exc
    for name, folder in policies.items():
        budgets.setdefault(f"policy_{name}", {})["parameters"] = policy_parameters(folder)
    start_distances = None
    if heldout_episodes is not None:
        from image2sim.eval.datasets import load_episode_file

        try:
            eps, _ = load_episode_file(heldout_episodes)
        except (FileNotFoundError, ValueError) as exc:
            raise typer.BadParameter(str(exc), param_hint="--episodes") from exc
        start_distances = {e.episode_id: e.geodesic_distance for e in eps if e.geodesic_distance is not None}
    try:
        doc = gather(
            rows, points, policies, budgets, checks, start_distances=start_distances, seed_runs=seed_runs
        )
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    if header is not None:
        doc["header"] = header.read_text()
    write_outputs(doc, out, report, plot)
    typer.echo(f"wrote {out}, {report}" + (f", {plot}" if doc.get("scaling") else ""))
    for name, chk in doc["checks"].items():
        if chk.get("met") is not None:
            typer.echo(f"{name}: neural SR {chk['sr_ratio']:.2f}x best baseline; target met: {chk['met']}")


@app.command("render")
def render_cmd(
    checkpoint: Annotated[
        Path | None, typer.Option(help="Renderer checkpoint of `sim train` (omit: untrained model).")
    ] = None,
    config: Annotated[
        str, typer.Option(help="Renderer preset or YAML the checkpoint was trained with.")
    ] = "tiny",
    data: Annotated[list[Path], typer.Option(help="Capture folders (held-out frames are scored).")] = [],  # noqa: B006
    holdout_every: Annotated[int, typer.Option(help="Every n-th frame is held out (as in sim train).")] = 8,
    max_frames: Annotated[int, typer.Option(help="At most this many frames per capture (0: all).")] = 0,
    max_views: Annotated[int, typer.Option(help="At most this many held-out views per tier (0: all).")] = 0,
    steps: Annotated[list[int], typer.Option(help="Pixel-flow step counts.")] = [1, 2, 4, 8],  # noqa: B006
    tier: Annotated[list[str], typer.Option(help="Noise tiers: none, middle, high.")] = [  # noqa: B006
        "none",
        "middle",
        "high",
    ],  # noqa: B006
    ablation: Annotated[
        list[str],
        typer.Option(help="SWITCH=CHECKPOINT of an ablation model (no_semantic, no_alpha_gate, no_distill)."),
    ] = [],  # noqa: B006
    condition_source: Annotated[
        str, typer.Option(help="degraded (renderer's degradations) or gaussians (splat identity Gaussians).")
    ] = "degraded",
    tier_data: Annotated[
        list[str], typer.Option(help="gaussians: TIER=CAPTURE (repeatable), captures at that noise tier.")
    ] = [],  # noqa: B006
    gaussian_config: Annotated[str, typer.Option(help="gaussians: Gaussian scene preset or file.")] = "tiny",
    encoder: Annotated[
        str,
        typer.Option(
            help="gaussians: identity, or a stage-1 encoder checkpoint (file or folder) building the scenes."
        ),
    ] = "identity",
    source_every: Annotated[
        int,
        typer.Option(help="gaussians: only every n-th training frame builds the Gaussians (see sim train)."),
    ] = 1,
    input_views: Annotated[
        str,
        typer.Option(
            help="gaussians: build the Gaussians from the training panoramas (pano) or from six 90° "
            "pinhole views cut from each (pinhole6, the paper's pinhole-input variant)."
        ),
    ] = "pano",
    target: Annotated[
        str,
        typer.Option(
            help="gaussians: score against 'exact' (noise-free procedural GT at the pose), 'capture' "
            "(the held-out frame) or 'auto' (exact for procedural captures)."
        ),
    ] = "auto",
    lpips_weights: Annotated[Path | None, typer.Option(help="LPIPS weights (safetensors).")] = None,
    warmup: Annotated[int, typer.Option(help="Untimed warm-up calls before FPS timing.")] = 2,
    runs: Annotated[int, typer.Option(help="Timed calls (FPS = 1 / median).")] = 5,
    threads: Annotated[int, typer.Option(help="torch threads.")] = 1,
    out: Annotated[Path, typer.Option(help="Headline metrics file.")] = Path("metrics/render.json"),
    plot: Annotated[
        Path | None,
        typer.Option(help="Speed-vs-PSNR PNG (default: beside --out, <out stem>_speed.png)."),
    ] = None,
    wandb: Annotated[
        bool, typer.Option(help="Also log the headline metrics to W&B (offline by default).")
    ] = False,
) -> None:
    """The paper's Table-1 protocol: splat-only vs 1/2/4/8-step pixel flow on held-out panoramas."""
    from image2sim.eval.plots import plot_speed_vs_error
    from image2sim.eval.render_bench import RenderBenchConfig, render_markdown, run_render_bench

    abl = {}
    for item in ablation:
        if "=" not in item:
            raise typer.BadParameter(f"--ablation {item!r}: expected SWITCH=CHECKPOINT")
        k, v = item.split("=", 1)
        abl[k] = v
    tiers_data: dict[str, list[str]] = {}
    for item in tier_data:
        if "=" not in item:
            raise typer.BadParameter(f"--tier-data {item!r}: expected TIER=CAPTURE")
        k, v = item.split("=", 1)
        tiers_data.setdefault(k, []).append(v)
    bench = RenderBenchConfig(
        condition_source=condition_source,
        tier_data=tiers_data,
        gaussian_config=gaussian_config,
        encoder=encoder,
        source_every=source_every,
        input_views=input_views,
        target=target,
        renderer_config=config,
        checkpoint=str(checkpoint) if checkpoint else None,
        data=[str(d) for d in data],
        holdout_every=holdout_every,
        max_frames=max_frames or None,
        max_views=max_views or None,
        steps=list(steps),
        tiers=list(tier),
        ablations=abl,
        lpips_weights=str(lpips_weights) if lpips_weights else None,
        warmup=warmup,
        runs=runs,
        threads=threads,
    )
    doc = run_render_bench(bench, out)
    typer.echo(render_markdown(doc))
    typer.echo(f"wrote {out}")
    # Nothing lands outside --out unless asked: the pipeline names plots/render_speed.png itself.
    plot = plot if plot is not None else out.with_name(f"{out.stem}_speed.png")
    typer.echo(f"wrote {plot_speed_vs_error(doc, plot)}")
    if wandb:
        from dataclasses import asdict

        from image2sim.eval.tracking import log_metrics_wandb

        run_dir = log_metrics_wandb(doc, "render", stage="eval_render", config=asdict(bench))
        typer.echo(f"W&B run: {run_dir}")
