"""``image2sim sim navmap`` and ``image2sim sim plan`` (heavy imports happen inside the commands)."""

from __future__ import annotations

import json
from pathlib import Path

import typer


def _parse_point(text: str, name: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise typer.BadParameter(f"{name} must be 'x,y,z' numbers, got {text!r}") from None
    if len(values) != 3:
        raise typer.BadParameter(f"{name} must have three comma-separated numbers, got {text!r}")
    return values


def _load_source(path: Path, config: dict, stride: int | None, skip_bad: bool = False):
    """A capture folder (any registered format), a Gaussian scene folder, or a point-cloud .npz."""
    import numpy as np
    from image2sim.simulator.navigation.embodiment import Embodiment, NavMapConfig
    from image2sim.simulator.navigation.extract import extract_navmap, extract_navmap_from_points

    emb = Embodiment.from_dict(config.get("embodiment"), where="--config embodiment")
    nav_cfg = dict(config.get("navmap") or {})
    if stride is not None:
        nav_cfg["pixel_stride"] = stride
    cfg = NavMapConfig.from_dict(nav_cfg, where="--config navmap")
    if path.is_file() and path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            if "points" not in data:
                raise typer.BadParameter(f"{path}: point-cloud .npz needs a 'points' array")
            return extract_navmap_from_points(
                data["points"],
                data["normals"] if "normals" in data else None,
                data["labels"] if "labels" in data else None,
                data["cameras"] if "cameras" in data else None,
                emb,
                cfg,
            )
    if path.is_dir() and (path / "gaussians.safetensors").is_file():
        from image2sim.simulator.gaussians.scene import GaussianScene
        from image2sim.simulator.navigation.extract import extract_navmap_from_gaussians

        scene = GaussianScene.load(path)
        g = scene.gaussians
        cams = [f["cam_to_world"] for f in scene.frames if f.get("cam_to_world") is not None]
        cam_pos = np.array([np.asarray(c)[:3, 3] for c in cams]) if cams else None
        return extract_navmap_from_gaussians(
            g.means.numpy(), g.quats.numpy(), g.scales.numpy(), g.opacities.numpy(), cam_pos, emb, cfg
        )
    from image2sim.simulator.io import open_capture

    capture = open_capture(path, strict=not skip_bad)
    navmap = extract_navmap(capture, emb, cfg, progress=True)
    for fid, why in getattr(capture, "skipped", []) or []:
        typer.echo(f"skipped frame {fid}: {why}", err=True)
    return navmap


def navmap_command(
    source: Path = typer.Argument(  # noqa: B008 (typer's declaration style)
        ...,
        help="Capture folder, scene folder (gaussians.safetensors) or point cloud .npz (points, normals?).",
    ),
    out: Path = typer.Option(  # noqa: B008 (typer's declaration style)
        Path("navmap.npz"), "--out", help="Output navmap .npz (a PNG is written beside it)."
    ),
    config: Path | None = typer.Option(  # noqa: B008 (typer's declaration style)
        None, "--config", help="YAML/JSON with 'embodiment' and 'navmap' sections."
    ),
    stride: int | None = typer.Option(  # noqa: B008 (typer's declaration style)
        None, "--stride", help="Pixel stride for back-projection (overrides config)."
    ),
    graph: bool = typer.Option(  # noqa: B008 (typer's declaration style)
        True, "--graph/--no-graph", help="Also build and save navgraph.npz beside the map."
    ),
    skip_bad: bool = typer.Option(  # noqa: B008 (typer's declaration style)
        False,
        "--skip-bad",
        help="Skip unreadable frames (bad pose, missing or corrupt image) and list them on stderr. "
        "Default: the first bad frame is an error (a map silently built from fewer frames is smaller).",
    ),
) -> None:
    """Extract the navigable map (+ top-down PNG of navigable cells, clearance and levels)."""
    from image2sim.simulator.io.records import CaptureError
    from image2sim.simulator.navigation.topdown import render_topdown, write_png

    cfg = _read_config(config)
    try:
        navmap = _load_source(source, cfg, stride, skip_bad)
    except (CaptureError, FileNotFoundError, ValueError) as err:
        typer.echo(f"error: {err}", err=True)
        typer.echo("(--skip-bad skips unreadable frames and lists them)", err=True)
        raise typer.Exit(2) from None
    navmap.save(out)
    png = write_png(out.with_suffix(".png"), render_topdown(navmap))
    summary = navmap.summary()
    if graph:
        from image2sim.simulator.navigation.embodiment import GraphConfig
        from image2sim.simulator.navigation.graph import NavGraph, joined_storeys

        g = NavGraph.build(
            navmap, GraphConfig.from_dict(cfg.get("graph"), where="--config graph"), progress=True
        )
        g.save(out.with_name("navgraph.npz"))
        joined = joined_storeys(g, navmap.level_heights, navmap.config.level_tolerance)
        summary["graph"] = {"nodes": g.num_nodes, "edges": g.num_edges, "storeys_joined": joined}
        if navmap.num_levels > 1 and not joined:
            # Say why and what to do: a new user otherwise sees two storeys and no path between them.
            summary["notes"].append(
                f"no path joins the storeys: their stairs have steps taller than max_step_height "
                f"{navmap.embodiment.max_step_height} m (or none were captured); a body that climbs "
                "them: --config configs/navigation/climb_0.25.yaml"
            )
    typer.echo(json.dumps({"navmap": str(out), "png": str(png), **summary}, indent=2))


def plan_command(
    scene: Path = typer.Argument(  # noqa: B008 (typer's declaration style)
        ..., help="A navmap .npz or a folder holding navmap.npz (and navgraph.npz)."
    ),
    start: str = typer.Option(..., "--start", help="Start feet position x,y,z (map frame)."),  # noqa: B008 (typer's declaration style)
    goal: str = typer.Option(..., "--goal", help="Goal feet position x,y,z (map frame)."),  # noqa: B008 (typer's declaration style)
    out: Path = typer.Option(  # noqa: B008 (typer's declaration style)
        Path("path.png"), "--out", help="PNG of the path over the map (JSON beside it)."
    ),
) -> None:
    """Plan a collision-aware path between two points and draw it."""
    import numpy as np
    from image2sim.simulator.navigation.graph import NavGraph
    from image2sim.simulator.navigation.navmap import NavMap
    from image2sim.simulator.navigation.planner import Planner
    from image2sim.simulator.navigation.topdown import render_topdown, write_png

    map_path = scene / "navmap.npz" if scene.is_dir() else scene
    navmap = NavMap.load(map_path)
    graph_path = map_path.with_name("navgraph.npz")
    graph = NavGraph.load(graph_path) if graph_path.is_file() else NavGraph.build(navmap, progress=True)
    planner = Planner(graph)
    s, g = np.array(_parse_point(start, "--start")), np.array(_parse_point(goal, "--goal"))
    result = planner.shortest_path(s, g)
    geo, why = planner.geodesic_distance(s, g)
    write_png(out, render_topdown(navmap, path=result.waypoints if result.reachable else None))
    report = {
        "reachable": result.reachable,
        "reason": result.reason or why,
        "length_m": result.length,
        "cost": result.cost,
        "geodesic_m": geo,
        "euclidean_m": float(np.linalg.norm(g - s)),
        "waypoints": result.waypoints.round(4).tolist(),
        "png": str(out),
    }
    out.with_suffix(".json").write_text(json.dumps(report, indent=2))
    typer.echo(json.dumps({k: v for k, v in report.items() if k != "waypoints"}, indent=2))
    if not result.reachable:
        raise typer.Exit(code=1)


def _read_config(path: Path | None) -> dict:
    if path is None:
        return {}
    if not path.is_file():
        raise typer.BadParameter(f"{path}: config file not found")
    text = path.read_text()
    if path.suffix in (".yaml", ".yml"):
        import yaml

        data = yaml.safe_load(text) or {}
    else:
        data = json.loads(text)
    unknown = sorted(set(data) - {"embodiment", "navmap", "graph"})
    if unknown:
        raise typer.BadParameter(f"{path}: unknown section(s) {unknown}; expected embodiment, navmap, graph")
    return data
