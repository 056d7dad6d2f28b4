"""``image2sim sim build-scene`` and ``image2sim sim render``. Imports only typer at module level."""

from __future__ import annotations

import json
from pathlib import Path

import typer

__all__ = ["build_scene_command", "render_command", "train_geometry_command"]


def _parse_frames(text: str | None) -> list[int] | None:
    """``"0,3,5-8"`` -> [0, 3, 5, 6, 7, 8]; None/'' -> all frames."""
    if not text:
        return None
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part:
            a, b = part.split("-", 1)
            out += list(range(int(a), int(b) + 1))
        elif part:
            out.append(int(part))
    return out


def build_scene_command(
    capture: Path = typer.Argument(..., help="Capture folder (any format `image2sim data inspect` reads)."),
    out: Path = typer.Option(
        ..., "--out", help="Scene folder to write (gaussians.safetensors + manifest.json)."
    ),
    encoder: str = typer.Option(
        "identity", help="'identity' (no weights) or a trained encoder .safetensors."
    ),
    config: str = typer.Option(
        "tiny",
        help="Preset (tiny, paper) or YAML/JSON overrides (identity only; a "
        "checkpoint brings its own config). Frames are encoded at its encoder.height x "
        "encoder.width (tiny 256x128, paper 1024x512); the command prints the resolution it used.",
    ),
    frames: str = typer.Option("", help="Frame indices, e.g. '0,3,5-8' (default: all)."),
    voxel_policy: str = typer.Option("", help="Override fusion.policy: footprint or fixed."),
    voxel_size: float = typer.Option(0.0, help="Override fusion.voxel_size (fixed policy), metres."),
    ply: bool = typer.Option(True, help="Also export <out>/gaussians.ply in the 3DGS layout."),
    overwrite: bool = typer.Option(False, help="Replace an existing scene folder."),
    threads: int = typer.Option(0, help="torch threads (0 = torch default)."),
    fuse_every: int = typer.Option(8, help="Frames fused into memory per pass (1 = strictly incremental)."),
    refine_steps: int = typer.Option(
        -1,
        "--refine-steps",
        help="Per-scene refinement: optimise the fused Gaussians this many steps against the "
        "capture's frames, one frame per step (photometric + depth, with pruning; docs/scenes.md). "
        "-1 (default): two steps per frame, at most 50, which brings a scene within 1 dB of each "
        "source frame (under a minute for 600 k Gaussians); 0 = the feed-forward scene alone.",
        min=-1,
    ),
    navigation: bool = typer.Option(
        True,
        "--navigation/--no-navigation",
        help="Also extract navmap.npz + navgraph.npz from the capture (as `sim navmap` does), so "
        "`eval nav` and `data episodes` can use the scene folder.",
    ),
) -> None:
    """Encode a capture's frames into a persistent feature-Gaussian scene (+ its navigation map)."""
    import dataclasses
    import time

    import torch
    from image2sim.simulator.gaussians.build import build_scene
    from image2sim.simulator.gaussians.config import ConfigError, load_gaussian_config
    from image2sim.simulator.gaussians.scene import SceneError
    from image2sim.simulator.io.records import CaptureError

    if threads > 0:
        torch.set_num_threads(threads)
    try:
        cfg = load_gaussian_config(config)
        fusion = cfg.fusion
        if voxel_policy:
            if voxel_policy not in ("footprint", "fixed"):
                raise ConfigError(f"--voxel-policy must be 'footprint' or 'fixed', got {voxel_policy!r}")
            fusion = dataclasses.replace(fusion, policy=voxel_policy)
        if voxel_size > 0:
            fusion = dataclasses.replace(fusion, voxel_size=voxel_size)
        cfg = dataclasses.replace(cfg, fusion=fusion).validate()
        if out.exists() and not overwrite:
            raise SceneError(f"{out}: already exists (pass --overwrite)")
        t0 = time.perf_counter()
        scene = build_scene(
            capture, cfg, encoder=encoder, frames=_parse_frames(frames), progress=True, fuse_every=fuse_every
        )
        elapsed = time.perf_counter() - t0
        if len(scene) == 0:  # e.g. every depth pixel outside fusion.min_range..max_range
            raise SceneError(
                f"{capture}: no Gaussian survived fusion (every pixel invalid or outside the depth range "
                f"{cfg.fusion.min_range:g}..{cfg.fusion.max_range:g} m); nothing written"
            )
        refined = None
        if refine_steps:
            from image2sim.simulator.gaussians.refine import refine_scene_steps
            from image2sim.simulator.io.registry import open_capture

            refined = refine_scene_steps(scene, open_capture(capture), refine_steps, progress=True)
        nav = _navigation(capture) if navigation else None
        scene.save(out, overwrite=overwrite)
        if ply:
            scene.export_ply(out / "gaussians.ply")
        if nav is not None:
            nav[0].save(out / "navmap.npz")
            nav[1].save(out / "navgraph.npz")
    except (ConfigError, SceneError, CaptureError, ValueError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    manifest = scene.manifest()
    counts = manifest["counts"]
    typer.echo(_encoding_statement(manifest, config, encoder))
    if refined is not None:
        typer.echo(
            f"refined {refined.steps} steps in {refined.seconds:.1f} s: {refined.gaussians_before} -> "
            f"{refined.gaussians_after} Gaussians"
        )
    if nav is not None:
        typer.echo(
            f"navigation: {nav[0].navigable_area():.1f} m^2 navigable, {nav[1].num_nodes} graph nodes "
            "(navmap.npz, navgraph.npz)"
        )
    typer.echo(
        f"{out}: {counts['gaussians']} Gaussians from {counts['frames']} frames in {elapsed:.2f} s "
        f"({counts['frames'] / max(elapsed, 1e-9):.2f} frames/s); per voxel size {counts['per_voxel_size']}"
    )


def _navigation(capture: Path):
    """Navigable map and graph of a capture at the default embodiment and configs (``sim navmap``'s)."""
    from image2sim.simulator.io import open_capture
    from image2sim.simulator.navigation.extract import extract_navmap
    from image2sim.simulator.navigation.graph import NavGraph

    navmap = extract_navmap(open_capture(capture), progress=True)
    return navmap, NavGraph.build(navmap, progress=True)


def _encoding_statement(manifest: dict, config: str, encoder: str) -> str:
    """One line: the resolution frames were encoded at, where it came from, and the capture's own."""
    enc = manifest.get("encoding") or {}
    h, w = enc.get("height"), enc.get("width")
    if str(encoder) == "identity":
        origin = f"encoder.width x encoder.height of --config {config}"
        change = "; set encoder.height/encoder.width in a --config YAML to change it"
    else:
        origin = f"encoder.width x encoder.height of the config of the encoder checkpoint {encoder}"
        change = ""
    src = (manifest.get("source") or {}).get("camera") or {}
    native = ""
    if src.get("width"):
        same = (src["width"], src["height"]) == (w, h)
        native = f"; the capture's frames are {src['width']}x{src['height']}" + (
            "" if same else ", area-resized"
        )
    return f"encoded at {w}x{h} (W x H = {origin}){native}{change}"


def _parse_pose(text: str):
    """'tx ty tz qw qx qy qz' (7 numbers, quaternion w-first) or 16 numbers (row-major 4x4)."""
    import numpy as np
    import torch
    from image2sim.simulator.geometry.se3 import quat_to_matrix

    vals = [float(v) for v in text.replace(",", " ").split()]
    if len(vals) == 16:
        return np.asarray(vals, dtype=np.float64).reshape(4, 4)
    if len(vals) == 7:
        pose = np.eye(4)
        pose[:3, :3] = quat_to_matrix(torch.tensor(vals[3:], dtype=torch.float64)).numpy()
        pose[:3, 3] = vals[:3]
        return pose
    raise ValueError(f"--pose needs 7 numbers (tx ty tz qw qx qy qz) or 16 (4x4 row-major), got {len(vals)}")


def render_command(
    scene: Path = typer.Argument(..., help="Scene folder written by build-scene."),
    out: Path = typer.Option(
        ...,
        "--out",
        help="RGB image to write (PNG); <stem>_depth.png (uint16 mm) and "
        "<stem>_alpha.png are written next to it.",
    ),
    frame: int = typer.Option(-1, help="Render at the pose of this frame index of the source capture."),
    pose: str = typer.Option("", help="Camera-to-world pose: 'tx ty tz qw qx qy qz' or 16 numbers."),
    height: int = typer.Option(
        0,
        help="Output height (default: the source capture's camera, recorded in the scene manifest; "
        "with only --height the width keeps the camera's aspect).",
    ),
    width: int = typer.Option(
        0, help="Output width (default: the source capture's camera; alone, the height follows)."
    ),
    backend: str = typer.Option("auto", help="Splatting backend (auto, cpu, torch, reference)."),
    renderer: Path = typer.Option(
        None,
        "--renderer",
        help="Pixel-flow renderer (export folder, .safetensors or .ckpt): RGB-D from the renderer.",
    ),
    steps: int = typer.Option(1, "--steps", help="Pixel-flow network evaluations (with --renderer)."),
    splat_mode: str = typer.Option(
        "normalised",
        "--splat",
        help="Without --renderer, the splat as an image: normalised (expected colour: the composite "
        "divided by alpha, so gaps between Gaussians are not darkened; what the simulator shows), "
        "filled (holes completed from their surroundings, eval render's splat_fill) or raw (the "
        "composite over black).",
    ),
) -> None:
    """Render a saved scene at a frame's pose or a given pose: RGB, depth and alpha images."""
    import numpy as np
    import torch
    from image2sim.simulator.gaussians.frames import resize_camera
    from image2sim.simulator.gaussians.scene import GaussianScene, SceneError
    from image2sim.simulator.geometry.cameras import EquirectCamera
    from image2sim.simulator.io.images import write_rgb_png, write_uint16_png
    from image2sim.simulator.renderer.holefill import SPLAT_MODES, splat_rgbd

    try:
        if splat_mode not in SPLAT_MODES:
            raise ValueError(f"--splat must be one of {', '.join(SPLAT_MODES)}, got {splat_mode!r}")
        sc = GaussianScene.load(scene)
        if (frame >= 0) == bool(pose):
            raise ValueError("give exactly one of --frame or --pose")
        if pose:
            c2w = _parse_pose(pose)
        else:
            c2w = _frame_pose(sc, frame)
        if height < 0 or width < 0:
            raise ValueError(f"--height/--width must be positive, got {height}x{width}")
        camera, origin = _default_camera(sc)
        if height or width:
            h = height or max(1, round(width * camera.height / camera.width))
            w = width or max(1, round(height * camera.width / camera.height))
            camera, origin = resize_camera(camera, h, w), "--height/--width"
        typer.echo(f"rendering at {camera.width}x{camera.height} (W x H, {origin})")
        res = sc.render(camera, torch.as_tensor(c2w, dtype=sc.gaussians.means.dtype), backend=backend)
        flow = None
        if renderer is not None:
            # Splat -> condition C_p -> pixel flow with per-pose noise (the simulator's render path).
            from image2sim.simulator.renderer.model import load_renderer
            from image2sim.simulator.sim import gaussian_render_fn
            from image2sim.simulator.splatting.project import T_MIN

            # Exact condition (as eval render's), not the simulator's early-finished observation splat.
            fn = gaussian_render_fn(
                sc.gaussians, load_renderer(renderer), steps=steps, backend=backend, min_transmittance=T_MIN
            )
            flow = fn(camera, np.asarray(c2w, dtype=np.float64))
    except (SceneError, ValueError, FileNotFoundError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    if flow is None:
        splat_rgb, splat_depth = splat_rgbd(
            res.rgb, res.depth, res.alpha, splat_mode, isinstance(camera, EquirectCamera)
        )
        rgb_f, depth = splat_rgb[0].permute(1, 2, 0).numpy(), splat_depth[0, 0].numpy()
    else:
        rgb_f, depth = flow["rgb"], flow["depth"]
    rgb = (np.clip(rgb_f, 0, 1) * 255 + 0.5).astype(np.uint8)
    alpha = (res.alpha[0, 0].clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_rgb_png(out, rgb)
    write_uint16_png(
        out.with_name(out.stem + "_depth.png"), np.clip(np.rint(depth * 1000), 0, 65535).astype(np.uint16)
    )
    write_rgb_png(out.with_name(out.stem + "_alpha.png"), np.repeat(alpha[..., None], 3, axis=2))
    cover = float((res.alpha > 0.5).float().mean())
    typer.echo(
        f"{out}: {camera.width}x{camera.height}, {len(sc)} Gaussians, alpha>0.5 on {cover:.1%} of pixels "
        f"({res.backend} backend)"
        + (
            f", splat {splat_mode}"
            if flow is None
            else f", pixel-flow renderer {renderer} in {steps} step(s)"
        )
    )


def _default_camera(sc):
    """The camera ``sim render`` uses without --height/--width, and where it came from.

    The source capture's camera (manifest ``source.camera``); for scenes built before that was
    recorded, the source capture's camera read from disk when it is still there; else the scene's
    input (encoded) camera; else a 512x256 panorama.
    """
    from image2sim.simulator.geometry.cameras import EquirectCamera

    cam = sc.source_camera()
    if cam is not None:
        return cam, "the source capture's camera, manifest source.camera"
    source = (sc.info.get("source") or {}).get("capture")
    if source and Path(source).exists():
        from image2sim.simulator.io.records import CaptureError
        from image2sim.simulator.io.registry import open_capture

        try:
            cap = open_capture(source, strict=False)
            cam = cap.camera if cap.camera is not None else cap[0].camera
        except (CaptureError, IndexError):
            cam = None
        if cam is not None:
            return cam, f"the source capture's camera, read from {source}"
    cam = sc.camera()
    if cam is not None:
        return cam, "the scene's input camera, manifest camera: the source capture's is not recorded"
    return EquirectCamera(256, 512), "no camera recorded in the scene: default panorama"


def _frame_pose(sc, frame: int):
    """Pose of capture frame ``frame``: from the scene's frame list, else from the source capture."""
    import numpy as np

    for rec in sc.frames:
        if rec.get("index") == frame and rec.get("cam_to_world") is not None:
            return np.asarray(rec["cam_to_world"], dtype=np.float64)
    source = (sc.info.get("source") or {}).get("capture")
    if not source or not Path(source).exists():
        raise ValueError(
            f"frame {frame} is not in the scene and its source capture {source!r} is unavailable"
        )
    from image2sim.simulator.io.registry import open_capture

    cap = open_capture(source)
    if not 0 <= frame < len(cap):
        raise ValueError(f"--frame {frame} out of range: source capture {source} has {len(cap)} frames")
    if cap.poses is not None:
        return cap.poses[frame]
    return cap[frame].cam_to_world


def train_geometry_command(
    data: list[Path] = typer.Argument(
        None, help="Capture folders to train on (required; `image2sim data synth` makes procedural ones)."
    ),
    out: Path = typer.Option(Path("runs/geometry"), "--out", help="Run folder (checkpoints, logs, encoder)."),
    config: str = typer.Option("tiny", help="Preset (tiny, paper) or YAML/JSON overrides."),
    steps: int = typer.Option(0, help="Override train.steps."),
    resume: bool = typer.Option(True, help="Resume from <out>/checkpoints/last.ckpt when present."),
    accelerator: str = typer.Option("", help="Override trainer.accelerator: cpu, gpu or auto."),
    devices: int = typer.Option(0, help="Override trainer.devices (processes per node; >1 needs ddp)."),
    num_nodes: int = typer.Option(0, help="Override trainer.num_nodes."),
    strategy: str = typer.Option("", help="Override trainer.strategy: auto (one process) or ddp."),
    wandb: str = typer.Option(
        "", help="W&B besides CSV: disabled | offline | online (params: tracking.wandb; '' = train.wandb)."
    ),
    wandb_project: str = typer.Option("image2sim", help="W&B project (params: tracking.project)."),
) -> None:
    """Stage-1 geometry training of the Gaussian encoder (Lightning; DDP by config or flags)."""
    import dataclasses

    from image2sim.simulator.gaussians.config import load_gaussian_config
    from image2sim.simulator.gaussians.train_geometry import train_stage1

    if not data:
        raise typer.BadParameter(
            "give at least one capture folder (e.g. procedural ones from `image2sim data synth --out DIR`)",
            param_hint="DATA",
        )
    from image2sim.simulator.trainer import with_overrides

    cfg = load_gaussian_config(config)
    if steps:
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=steps))
    try:
        cfg = dataclasses.replace(
            cfg, trainer=with_overrides(cfg.trainer, accelerator, devices, num_nodes, strategy)
        )
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    if wandb:
        from image2sim.simulator.tracking import wandb_mode

        try:
            wandb_mode(wandb)
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--wandb") from exc
    result = train_stage1(
        cfg, out, captures=list(data), resume=resume, wandb=wandb, wandb_project=wandb_project
    )
    typer.echo(json.dumps(result, indent=2))
