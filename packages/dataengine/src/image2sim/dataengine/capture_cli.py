"""``image2sim data inspect|fuse|ingest|lift|train-depth-prior``: look at, fuse, convert and lift captures.

Gathered into the ``data`` Typer app by :mod:`image2sim.dataengine.cli` (this module does not import
it back). Heavy modules (torch, OpenCV, the readers) are imported inside the commands so
``image2sim --help`` stays fast.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer()
"""This module's commands; :mod:`image2sim.dataengine.cli` gathers them into ``image2sim data``."""

_FORMAT_HELP = "Capture format (image2sim, hm3d_360, realsee, pinhole_dir, ...); auto-detected when omitted."


def _fail(message: str) -> None:
    """One error line and exit status 2: every caller reports bad input (an unreadable or unknown
    capture, an existing output), as the CLI's error boundary does (docs/architecture.md)."""
    from rich.console import Console

    Console(stderr=True).print(f"[bold red]error:[/] {message}", markup=True, highlight=False, soft_wrap=True)
    raise typer.Exit(code=2)


_HALF_PIXEL_HELP = (
    "realsee only: pixel convention of the panoramas. 'centres' (default): samples sit on pixel "
    "centres, images used as stored; 'resample': data written at integer pixel indices, resampled by "
    "half a pixel onto our grid."
)


def _open(path: Path, fmt: str | None, strict: bool = True, half_pixel: str | None = None):
    from image2sim.simulator.io import CaptureError, open_capture

    # Only passed when set: the other formats refuse options they do not know.
    options = {} if half_pixel is None else {"half_pixel": half_pixel}
    try:
        return open_capture(path, fmt, strict=strict, **options)
    except CaptureError as err:
        _fail(str(err))


def _progress():
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        transient=False,
    )


def frame_stats(frame) -> dict:
    """Per-frame numbers shown by ``inspect``: size, valid-depth fraction and range, position."""
    import numpy as np

    valid = frame.depth > 0
    d = frame.depth[valid]
    return {
        "id": frame.frame_id,
        "size": f"{frame.width}x{frame.height}",
        "valid": float(valid.mean()) if valid.size else 0.0,
        "dmin": float(d.min()) if d.size else float("nan"),
        "dmax": float(d.max()) if d.size else float("nan"),
        "position": np.asarray(frame.position, dtype=float),
        "notes": list(frame.notes),
    }


@app.command()
def inspect(
    capture: Annotated[Path, typer.Argument(help="Capture folder.")],
    format: Annotated[str | None, typer.Option("--format", "-f", help=_FORMAT_HELP)] = None,
    max_frames: Annotated[
        int | None, typer.Option("--max-frames", min=1, help="Load at most N frames for image statistics.")
    ] = None,
    rows: Annotated[
        int, typer.Option("--rows", min=1, help="Frame rows to print (first and last halves).")
    ] = 12,
    half_pixel: Annotated[str | None, typer.Option("--half-pixel", help=_HALF_PIXEL_HELP)] = None,
) -> None:
    """Print a capture's frames, sizes, depth range and pose bounds.

    Exits 2 (bad input) after the report when a frame was skipped while indexing or could not be
    read: every other command reads captures strictly and would refuse it."""
    import numpy as np
    from image2sim.simulator.io import CaptureError
    from rich.console import Console
    from rich.table import Table

    cap = _open(capture, format, strict=False, half_pixel=half_pixel)
    console = Console()
    n_load = len(cap) if max_frames is None else min(max_frames, len(cap))
    stats, errors = [], []
    with _progress() as bar:
        task = bar.add_task("reading frames", total=n_load)
        for i in range(n_load):
            try:
                stats.append(frame_stats(cap[i]))
            except CaptureError as err:
                errors.append((cap.frame_ids[i], str(err)))
            bar.advance(task)
    positions = cap.poses[:, :3, 3] if cap.poses is not None else np.array([s["position"] for s in stats])

    summary = Table(title=f"capture {cap.root}", show_header=False)
    summary.add_row("format", cap.format)
    summary.add_row("scene", cap.scene_id)
    summary.add_row(
        "frames",
        f"{len(cap)} ({n_load} read, {len(cap.skipped)} skipped while indexing, {len(errors)} unreadable)",
    )
    camera = cap.camera if cap.camera is not None else (cap[0].camera if stats else None)
    summary.add_row("camera", str(camera.to_dict()) if camera is not None else "?")
    if stats:
        dmin = np.nanmin([s["dmin"] for s in stats])
        dmax = np.nanmax([s["dmax"] for s in stats])
        summary.add_row(
            "depth range", f"{dmin:.3f} - {dmax:.3f} m (valid pixels of the {len(stats)} frames read)"
        )
        summary.add_row(
            "valid depth", f"{np.mean([s['valid'] for s in stats]) * 100:.1f}% of pixels (mean over frames)"
        )
    if len(positions):
        lo, hi = positions.min(axis=0), positions.max(axis=0)
        summary.add_row("pose bounds min", "x {:.3f}  y {:.3f}  z {:.3f}".format(*lo))
        summary.add_row("pose bounds max", "x {:.3f}  y {:.3f}  z {:.3f}".format(*hi))
        summary.add_row("pose extent", "{:.3f} x {:.3f} x {:.3f} m".format(*(hi - lo)))
    notes = sorted({n for s in stats for n in s["notes"]})
    for note in notes[:3]:
        summary.add_row("reader note", note)
    console.print(summary)

    table = Table(title="frames (depth in m, camera position in world m)")
    for col in ("#", "id", "size", "d min", "d max", "valid%", "x", "y", "z"):
        table.add_column(col, justify="right" if col not in ("id", "size") else "left", no_wrap=True)
    shown = list(range(len(stats)))
    if len(shown) > rows:
        shown = shown[: rows - rows // 2] + [-1] + shown[len(shown) - rows // 2 :]
    for k in shown:
        if k < 0:
            table.add_row("...", "", "", "", "", "", "", "", "")
            continue
        s = stats[k]
        table.add_row(
            str(k),
            s["id"],
            s["size"],
            f"{s['dmin']:.3f}",
            f"{s['dmax']:.3f}",
            f"{100 * s['valid']:.1f}",
            *(f"{c:.3f}" for c in s["position"]),
        )
    console.print(table)
    bad = list(cap.skipped) + errors
    for fid, reason in bad:
        console.print(f"[yellow]skipped[/] {fid}: {reason}", highlight=False, soft_wrap=True)
    if bad:
        typer.echo(
            f"error: {len(bad)} of {len(cap.skipped) + len(cap)} frames of {cap.root} are unreadable "
            "(listed above); other commands refuse this capture (`sim navmap --skip-bad` leaves them out)",
            err=True,
        )
        raise typer.Exit(2)


@app.command()
def fuse(
    capture: Annotated[Path, typer.Argument(help="Capture folder.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output PLY file.")],
    voxel: Annotated[float, typer.Option("--voxel", min=1e-4, help="Voxel edge in metres.")] = 0.05,
    max_frames: Annotated[
        int | None, typer.Option("--max-frames", min=1, help="Fuse at most N frames.")
    ] = None,
    stride: Annotated[int, typer.Option("--stride", min=1, help="Use every S-th frame.")] = 1,
    format: Annotated[str | None, typer.Option("--format", "-f", help=_FORMAT_HELP)] = None,
    half_pixel: Annotated[str | None, typer.Option("--half-pixel", help=_HALF_PIXEL_HELP)] = None,
) -> None:
    """Back-project frames into the world, voxel-average colours, write a binary PLY (atomically)."""
    from image2sim.simulator.io import CaptureError, write_ply
    from image2sim.simulator.io.fusion import VoxelAccumulator, backproject_frame, select_indices
    from rich.console import Console

    cap = _open(capture, format, half_pixel=half_pixel)
    indices = select_indices(len(cap), stride, max_frames)
    acc = VoxelAccumulator(voxel)
    try:
        with _progress() as bar:
            task = bar.add_task("fusing", total=len(indices))
            for i in indices:
                points, colours = backproject_frame(cap[i])
                acc.add(points, colours)
                bar.advance(task)
    except CaptureError as err:
        _fail(str(err))
    points, colours = acc.result()
    if len(points) == 0:
        _fail(f"{capture}: no valid depth in the selected frames, nothing to write")
    comment = f"image2sim fuse of {cap.root} ({cap.format}), {len(indices)} frames, voxel {voxel} m"
    write_ply(out, points, colours, comment=comment)
    lo, hi = points.min(axis=0), points.max(axis=0)
    Console().print(
        f"fused {len(indices)} frames: {acc.num_points} points -> {len(points)} voxels of {voxel} m\n"
        f"bounds min ({lo[0]:.3f}, {lo[1]:.3f}, {lo[2]:.3f}) max ({hi[0]:.3f}, {hi[1]:.3f}, {hi[2]:.3f})\n"
        f"wrote {out}",
        highlight=False,
        soft_wrap=True,
    )


@app.command()
def ingest(
    src: Annotated[Path, typer.Argument(help="Source capture folder (any readable format).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder for the canonical capture.")],
    format: Annotated[str | None, typer.Option("--format", "-f", help=_FORMAT_HELP)] = None,
    skip_bad: Annotated[
        bool, typer.Option("--skip-bad", help="Skip unusable frames (and report why) instead of failing.")
    ] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace --out if it exists.")] = False,
    scene_id: Annotated[
        str | None, typer.Option("--scene-id", help="Scene id for the manifest (default: the source's).")
    ] = None,
    half_pixel: Annotated[str | None, typer.Option("--half-pixel", help=_HALF_PIXEL_HELP)] = None,
) -> None:
    """Convert a capture to the canonical format; nothing is written unless everything succeeds."""
    from image2sim.simulator.io import CaptureError, write_capture
    from rich.console import Console

    if out.exists() and not overwrite:
        _fail(f"{out}: already exists (pass --overwrite to replace it)")
    cap = _open(src, format, strict=not skip_bad, half_pixel=half_pixel)
    skipped = [(fid, reason) for fid, reason in cap.skipped]
    written_ids: list[str] = []

    def frames():
        with _progress() as bar:
            task = bar.add_task("ingesting", total=len(cap))
            for i in range(len(cap)):
                try:
                    frame = cap[i]
                except CaptureError as err:
                    if not skip_bad:
                        raise
                    skipped.append((cap.frame_ids[i], str(err)))
                else:
                    written_ids.append(frame.frame_id)
                    yield frame
                bar.advance(task)

    def record_skips(tmp: Path) -> None:
        # The manifest is written before `extra` runs; add the final skip list to it here.
        import json

        manifest_path = tmp / "manifest.json"
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
        manifest["metadata"]["skipped"] = [{"frame_id": f, "reason": r} for f, r in skipped]
        manifest_path.write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")

    metadata = {
        "source_format": cap.format,
        "source_path": str(cap.root.resolve()),
        "source_scene_id": cap.scene_id,
    }
    try:
        written = write_capture(
            out,
            frames(),
            scene_id=scene_id or cap.scene_id,
            metadata=metadata,
            extra=record_skips,
            overwrite=overwrite,
        )
    except (CaptureError, FileExistsError) as err:
        _fail(f"{err}" + ("" if skip_bad else "  (nothing was written; --skip-bad ingests the valid frames)"))
    console = Console()
    console.print(
        f"ingested {len(written_ids)} frames from {src} ({cap.format}) into {written}",
        highlight=False,
        soft_wrap=True,
    )
    for fid, reason in skipped:
        console.print(f"[yellow]skipped[/] {fid}: {reason}", highlight=False, soft_wrap=True)


@app.command()
def lift(
    src: Annotated[
        Path, typer.Argument(help="A folder of images (png/jpg; ids = file stems) or a video file.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder for the canonical capture.")],
    camera_height: Annotated[
        float | None,
        typer.Option(
            "--camera-height", min=0.0, help="Camera height above the floor, metres (sets the scale)."
        ),
    ] = None,
    baseline: Annotated[
        float | None,
        typer.Option(
            "--baseline",
            min=0.0,
            help="Distance between --baseline-frames' centres, metres (sets the scale).",
        ),
    ] = None,
    baseline_frames: Annotated[
        tuple[str, str] | None,
        typer.Option("--baseline-frames", help="The two frame ids --baseline is measured between."),
    ] = None,
    object_size: Annotated[
        list[str] | None,
        typer.Option(
            "--object-size",
            help="A known length between two pixels of one input image, FRAME:X0,Y0:X1,Y1=METRES "
            "(pixel column,row; sets the scale; repeat for several, e.g. a door and a table).",
        ),
    ] = None,
    depth: Annotated[
        str,
        typer.Option(
            "--depth",
            help="Depth source: mvs (no weights), model, or mvs+model (the model fills what the stereo "
            "leaves empty).",
        ),
    ] = "mvs",
    depth_model: Annotated[
        Path | None,
        typer.Option(
            "--depth-model", help="Local folder of a transformers depth model (--depth model or mvs+model)."
        ),
    ] = None,
    panorama: Annotated[
        bool | None,
        typer.Option(
            "--panorama/--pinhole",
            help="Force equirect panoramas or pinhole frames (default: 2:1 = panorama).",
        ),
    ] = None,
    camera_model: Annotated[
        str,
        typer.Option(
            "--camera-model",
            help="COLMAP model of pinhole frames: distortion-free SIMPLE_PINHOLE or PINHOLE; with lens "
            "distortion (frames are undistorted) SIMPLE_RADIAL, RADIAL, OPENCV (+ tangential), or a "
            "fisheye SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, OPENCV_FISHEYE.",
        ),
    ] = "SIMPLE_PINHOLE",
    mapper: Annotated[
        str,
        typer.Option(
            "--mapper",
            help="COLMAP reconstruction: incremental (one image at a time) or global (GLOMAP: rotation "
            "averaging and global positioning over all verified pairs at once).",
        ),
    ] = "incremental",
    fps: Annotated[float, typer.Option("--fps", min=0.01, help="Video: frames sampled per second.")] = 2.0,
    max_frames: Annotated[
        int | None, typer.Option("--max-frames", min=1, help="Keep at most N frames (spread evenly).")
    ] = None,
    plane_fill: Annotated[
        bool,
        typer.Option(
            "--plane-fill/--no-plane-fill",
            help="Complete textureless segments whose confident depth lies on one plane (docs/lift.md).",
        ),
    ] = True,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace --out if it exists.")] = False,
) -> None:
    """Lift RGB-only photos, a video or panoramas to a metric posed RGB-D capture (docs/lift.md).

    Poses and intrinsics by structure-from-motion (pycolmap), depth from multi-view stereo or a
    depth model fitted to the sparse points, gravity from the cameras and the floor, metric scale
    from --camera-height, --baseline or --object-size; frames SfM cannot register are dropped and
    listed."""
    from image2sim.simulator.lift.capture import LiftOptions
    from image2sim.simulator.lift.capture import lift as run_lift
    from rich.console import Console

    console = Console(stderr=True)
    if depth not in ("mvs", "model", "mvs+model"):
        _fail(f"--depth must be mvs, model or mvs+model, got {depth!r}")
    if depth != "mvs" and depth_model is None:
        _fail(f"--depth {depth} needs --depth-model DIR (a local transformers depth model folder)")
    from image2sim.simulator.lift.measure import parse_object_size
    from image2sim.simulator.lift.scale import scale_sources
    from image2sim.simulator.lift.sfm import SfmOptions

    try:
        sizes = tuple(parse_object_size(text) for text in object_size or ())
        given = scale_sources(camera_height, baseline, sizes, str(src))
        sfm_options = SfmOptions(camera_model=camera_model, mapper=mapper)
    except ValueError as exc:
        _fail(str(exc))
    if baseline is not None and baseline_frames is None:
        _fail("--baseline needs --baseline-frames A B (the frames it is measured between)")
    if out.exists() and not overwrite:
        _fail(f"{out}: already exists (pass --overwrite to replace it)")
    if not given:
        console.print(
            "[yellow]warning:[/] no --camera-height, --baseline or --object-size: the capture keeps the "
            "reconstruction's arbitrary units, not metres",
            highlight=False,
        )
    options = LiftOptions(
        depth_source=depth,
        depth_model=None if depth_model is None else str(depth_model),
        camera_height=camera_height,
        baseline=baseline,
        baseline_frames=baseline_frames,
        object_sizes=sizes,
        panorama=panorama,
        fps=fps,
        max_frames=max_frames,
        plane_fill=plane_fill,
        sfm=sfm_options,
    )
    stages = ("frames", "sfm", "depth", "scale", "planes", "write")
    with _progress() as bar:
        tasks = {s: bar.add_task(s, total=1, start=False) for s in stages}
        current: dict[str, str] = {}

        def progress(stage: str, message: str) -> None:
            previous = current.get("stage")
            if previous is not None and previous != stage:
                bar.update(tasks[previous], completed=1)
            if previous != stage:
                bar.start_task(tasks[stage])
            current["stage"] = stage
            bar.update(tasks[stage], description=f"{stage}: {message}")

        report = run_lift(src, out, options, overwrite=overwrite, progress=progress, show_depth_progress=True)
        for s in stages:
            bar.update(tasks[s], completed=1)
    rec = report.record
    for item in rec["dropped"]:
        console.print(
            f"[yellow]dropped[/] {item['frame_id']}: {item['reason']}", highlight=False, soft_wrap=True
        )
    reprojection = rec["sfm"].get("mean_reprojection_error_px", 0.0)
    Console().print(
        f"lifted {rec.get('written', rec['registered'])} of {rec['input_frames']} frames into {out} "
        f"(scale {rec['scale_method']}: {rec['scale']:.4g} +- {100 * rec['scale_uncertainty']:.2g} %, "
        f"depth {rec['depth_source']}, SfM reprojection error {reprojection:.3f} px)",
        highlight=False,
        soft_wrap=True,
    )


@app.command("train-depth-prior")
def train_depth_prior(
    captures: Annotated[
        list[Path], typer.Argument(help="RGB-D captures to learn from (any readable format).")
    ],
    out: Annotated[Path, typer.Option("--out", help="New folder for the model (read by --depth-model).")],
    val: Annotated[
        list[Path] | None,
        typer.Option("--val", help="Held-out captures: the loss on 64 of their views, before and after."),
    ] = None,
    steps: Annotated[
        int | None, typer.Option("--steps", min=1, help="Optimiser steps (default 2000).")
    ] = None,
    seed: Annotated[
        int | None, typer.Option("--seed", min=0, help="Seed of weights and views (default 0).")
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set", help="A DepthPriorConfig field, KEY=VALUE (e.g. batch_size=8, hidden_size=96)."
        ),
    ] = None,
) -> None:
    """Train a small monocular depth prior (Depth Anything classes) for `data lift --depth mvs+model`.

    It learns inverse depth up to scale and shift from the captures' views (panoramas: random pinhole
    views; pinhole frames: random crops). It knows the kind of scene it was trained on, nothing more.
    """
    from image2sim.simulator.config import parse_overrides
    from image2sim.simulator.lift.depth_prior import DepthPriorConfig
    from image2sim.simulator.lift.depth_prior import train_depth_prior as run_training
    from rich.console import Console

    try:
        fields_ = parse_overrides(set_ or ())  # its errors name --set and the item
    except ValueError as exc:
        _fail(str(exc))
    if steps is not None:
        fields_["steps"] = steps
    if seed is not None:
        fields_["seed"] = seed
    try:
        config = DepthPriorConfig.from_dict(fields_)
    except (TypeError, ValueError) as exc:
        _fail(f"--set: {exc}")
    if out.exists():
        _fail(f"{out}: already exists (choose a new folder)")
    for path in [*captures, *(val or [])]:
        _open(path, None)  # a clear error for an unreadable capture before any training
    console = Console(stderr=True)
    record = run_training(
        captures,
        out,
        config,
        val_captures=val or (),
        progress=True,
        log=lambda message: console.print(message, highlight=False),
    )
    after = record["val_loss_after"]
    Console().print(
        f"depth prior: {record['parameters']:,} parameters, {record['views_seen']:,} views in "
        f"{record['train_seconds'] / 60:.1f} min, loss {record['loss_first_tenth']:.3f} -> "
        f"{record['loss_last_tenth']:.3f}"
        + ("" if after is None else f", held-out {record['val_loss_before']:.3f} -> {after:.3f}")
        + f"; saved to {out}",
        highlight=False,
        soft_wrap=True,
    )
