"""The lifting pipeline: frames -> structure-from-motion -> depth -> metric scale -> canonical capture.

:func:`lift` runs every stage and writes a canonical capture (atomically, through
:func:`~image2sim.simulator.io.canonical.write_capture`) with per-frame depth confidence and a
manifest record ``metadata.lift``: ``sfm`` (matcher, timings, reprojection error, points,
intrinsics or rig residuals), ``depth_source``, ``scale_method``, ``scale``, ``scale_uncertainty``,
``registered``, ``written``, ``dropped`` (frames left out, with the reason: rejected video frames,
frames SfM did not register, and frames left with no valid depth pixel, which the canonical reader
would refuse), ``floor_fill`` and ``timings_s`` per stage.

After the scale stage, pixels without depth that the floor plane explains get its depth
(:func:`fill_floor`, confidence :data:`FLOOR_FILL_CONFIDENCE`), and textureless colour segments whose
confident depth lies on one plane get that plane's depth (:mod:`.planes`, stage ``planes``,
confidence :data:`~image2sim.simulator.lift.planes.PLANE_FILL_CONFIDENCE`).

Pinhole frames keep their images and get the shared SfM intrinsics (z-depth). Panoramas get depth
per cube face, converted to range and assembled into the equirectangular frame (each panorama pixel
reads the face whose axis is nearest its direction, nearest-neighbour so no depth is blended across
edges); colour is the input panorama.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from image2sim.simulator.lift.distortion import undistort_pixels
from image2sim.simulator.lift.frames import FrameSet, load_frames
from image2sim.simulator.lift.measure import ObjectLength, ObjectSize, measure_object
from image2sim.simulator.lift.scale import ScaleError, ScaleResult, estimate_metric_frame, scale_sources
from image2sim.simulator.lift.sfm import SfmOptions, SfmResult, run_sfm
from image2sim.simulator.lift.types import DepthEstimate, PinholeView, SparseDepth

__all__ = ["LiftOptions", "LiftReport", "lift", "dense_points", "assemble_equirect"]

DepthFn = Callable[..., list[DepthEstimate]]


@dataclass
class LiftOptions:
    """Settings of :func:`lift` (the ``image2sim data lift`` options)."""

    depth_source: str = "mvs"
    """"mvs" (plane-sweep multi-view stereo, no weights), "model" (a depth model from ``depth_model``)
    or "mvs+model" (the stereo, with the model filling the pixels it leaves empty)."""
    depth_model: str | None = None
    """Local folder of a transformers depth model (``depth_source`` "model" or "mvs+model")."""
    camera_height: float | None = None
    """Camera height above the floor in metres: sets the metric scale."""
    baseline: float | None = None
    """Distance in metres between the centres of ``baseline_frames``: sets the metric scale."""
    baseline_frames: tuple[str, str] | None = None
    """The two frame ids ``baseline`` is measured between."""
    object_sizes: tuple[ObjectSize, ...] = ()
    """Known lengths between two pixels of an input image: set the metric scale
    (:mod:`~image2sim.simulator.lift.measure`)."""
    panorama: bool | None = None
    """True/False forces equirect/pinhole; None detects 2:1 images as panoramas."""
    fps: float = 2.0
    """Frames sampled per second of video."""
    max_frames: int | None = None
    """Keep at most this many frames (spread evenly)."""
    min_confidence_floor: float = 0.5
    """Dense depth at or above this confidence joins the sparse points for finding the floor (when
    the sparse points alone show none)."""
    floor_fill: bool = True
    """Give pixels without depth that see the floor the floor plane's depth (:func:`fill_floor`)."""
    plane_fill: bool = True
    """Then complete textureless segments whose confident depth (the view's own and its neighbours')
    lies on one plane (:func:`~image2sim.simulator.lift.planes.fill_planes`)."""
    sfm: SfmOptions = field(default_factory=SfmOptions)
    """Structure-from-motion settings."""


@dataclass
class LiftReport:
    """What :func:`lift` did: the capture path, the stages' results and the manifest record."""

    out: Path
    frames: FrameSet
    sfm: SfmResult
    scale: ScaleResult
    record: dict
    metric_poses: dict[str, np.ndarray]


def dense_points(views: list[PinholeView], estimates: list[DepthEstimate], min_conf: float, stride: int = 4):
    """World points (M, 3) of confident depth pixels (every ``stride``-th row and column)."""
    out = []
    for view, est in zip(views, estimates, strict=True):
        d = est.depth[::stride, ::stride]
        c = est.confidence[::stride, ::stride]
        v, u = np.nonzero((d > 0) & (c >= min_conf))
        if not len(v):
            continue
        uu, vv = u * stride + 0.5, v * stride + 0.5
        K = view.K
        z = d[v, u].astype(np.float64)
        cam = np.stack([(uu - K[0, 2]) / K[0, 0] * z, (vv - K[1, 2]) / K[1, 1] * z, z], axis=1)
        T = view.cam_to_world
        out.append(cam @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(out) if out else np.zeros((0, 3))


FLOOR_FILL_CONFIDENCE = 0.02
"""Confidence of depth filled from the floor plane (:func:`fill_floor`): below every confidence the
plane sweep keeps (it zeroes < 0.05), so filled pixels are told apart by ``0 < confidence < 0.05``."""


def fill_floor(
    views: list[PinholeView],
    estimates: list[DepthEstimate],
    normal: np.ndarray,
    offset: float,
    *,
    min_ncc: float = 0.8,
    min_margin: float = 0.1,
    shift: float = 0.1,
    min_texture: float = 0.01,
    confidence: float = FLOOR_FILL_CONFIDENCE,
) -> tuple[list[DepthEstimate], int]:
    """Depth of the floor plane ``normal . x = offset`` at pixels without depth whose colour the plane
    explains; returns the new estimates and the number of pixels filled.

    Level views see the floor at grazing angles, where the plane sweep's fronto-parallel planes do
    not fit a 9 x 9 window and it is rarely confident, though the plane is known (the floor of the
    scale stage). The plane's own homography warps each view onto its source views
    (:func:`~image2sim.simulator.lift.mvs.plane_ncc`); a pixel without depth whose ray meets the
    plane in front of the camera gets the plane's depth when its patch is textured (grey std >=
    ``min_texture``) and matches the sources under the plane (mean ZNCC of the best two >=
    ``min_ncc``) clearly better than under the parallel planes ``shift`` times the cameras' height
    above and below it (by ``min_margin``: near the horizon, or with little parallax, every plane
    warps alike and the match proves nothing). A wall or an object standing on the floor does not
    match under the floor's homography, and a plain patch proves nothing. Filled pixels get
    ``confidence``, distinctly low.
    """
    from image2sim.simulator.lift.mvs import plane_ncc

    centres = np.stack([v.cam_to_world[:3, 3] for v in views])
    delta = shift * float(np.median(centres @ normal - offset))  # 15 cm for cameras 1.5 m up
    out, filled = [], 0
    for i, est in enumerate(estimates):
        plane, ncc, std = plane_ncc(views, i, normal, offset)
        rival = np.maximum(
            plane_ncc(views, i, normal, offset + delta)[1], plane_ncc(views, i, normal, offset - delta)[1]
        )
        fill = (
            (est.depth <= 0)
            & (plane > 0)
            & (std >= min_texture)
            & (ncc >= min_ncc)
            & (ncc - rival >= min_margin)
        )
        k = int(fill.sum())
        if k:
            est = DepthEstimate(
                depth=np.where(fill, plane, est.depth).astype(np.float32),
                confidence=np.where(fill, np.float32(confidence), est.confidence).astype(np.float32),
            )
        out.append(est)
        filled += k
    return out, filled


def _range_factor(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """|K^-1 [u, v, 1]| at pixel centres: z-depth times this is the range along the ray."""
    u = np.arange(width) + 0.5
    v = np.arange(height) + 0.5
    x = (u[None, :] - K[0, 2]) / K[0, 0]
    y = (v[:, None] - K[1, 2]) / K[1, 1]
    return np.sqrt(1.0 + x * x + y * y)


def assemble_equirect(
    faces_depth: list[np.ndarray], faces_conf: list[np.ndarray], face_K: np.ndarray, height: int, width: int
) -> tuple[np.ndarray, np.ndarray]:
    """Six cube faces of z-depth and confidence (``CUBEMAP_FACES`` order) -> equirect range, confidence."""
    import torch
    from image2sim.simulator.geometry.reproject import cubemap_to_equirect

    F = faces_depth[0].shape[0]
    factor = _range_factor(face_K, F, F)
    rng = np.stack([d * factor for d in faces_depth])  # (6, F, F)
    cube = torch.from_numpy(np.stack([rng, np.stack(faces_conf)], axis=1)).double()[None]  # (1, 6, 2, F, F)
    pano = cubemap_to_equirect(cube, height, width, mode="nearest")[0].numpy()
    return pano[0].astype(np.float32), np.clip(pano[1], 0.0, 1.0).astype(np.float32)


def _default_depth_fn() -> DepthFn:
    from image2sim.simulator.lift.depth import estimate_depth

    return estimate_depth


def check_object_sizes(sizes, frames: FrameSet) -> None:
    """Refuse, before any work, an object size whose image does not exist or whose pixels lie outside
    it (``ScaleError`` naming the size)."""
    h, w = frames.size
    for size in sizes:
        if size.frame_id not in frames.ids:
            raise ScaleError(
                f"--object-size {size.label()}: no input image {size.frame_id!r} (ids: {frames.ids[:6]}...)"
            )
        for x, y in (size.a, size.b):
            if not (0 <= x < w and 0 <= y < h):
                raise ScaleError(
                    f"--object-size {size.label()}: pixel ({x:g}, {y:g}) lies outside the {w}x{h} image"
                )


def measure_objects(sizes, frames: FrameSet, sfm: SfmResult, views, estimates) -> list[ObjectLength]:
    """Each known object size measured on the dense depth of its frame (``ScaleError`` naming the
    size when its frame was not registered or no confident depth lies near an end)."""
    out = []
    for size in sizes:
        if size.frame_id not in sfm.frame_ids:
            raise ScaleError(
                f"--object-size {size.label()}: frame {size.frame_id!r} was not registered by "
                "structure-from-motion; measure in another image"
            )
        own = [
            (v, e)
            for sv, v, e in zip(sfm.views, views, estimates, strict=True)
            if sv.frame_id == size.frame_id
        ]
        if not sfm.distortion.is_pinhole:  # the user's pixels are in the distorted input image
            K = own[0][0].K
            a, b = (
                tuple(undistort_pixels(np.add(xy, 0.5), K, sfm.distortion) - 0.5) for xy in (size.a, size.b)
            )
            size = dataclasses.replace(size, a=a, b=b)
        pose = sfm.cam_to_world[sfm.frame_ids.index(size.frame_id)]
        camera = frames.size if frames.panorama else own[0][0].K
        try:
            out.append(measure_object(size, camera, pose, own, float(own[0][0].K[0, 0])))
        except ValueError as exc:
            raise ScaleError(str(exc)) from exc
    return out


def lift(
    source: str | Path,
    out: str | Path,
    options: LiftOptions | None = None,
    *,
    overwrite: bool = False,
    progress: Callable[[str, str], None] | None = None,
    depth_fn: DepthFn | None = None,
    show_depth_progress: bool = False,
) -> LiftReport:
    """Lift RGB-only images or a video at ``source`` to a metric canonical capture at ``out``.

    ``progress(stage, message)`` is told when each stage starts and ends; ``depth_fn`` replaces
    :func:`image2sim.simulator.lift.depth.estimate_depth` (same signature).
    """
    from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
    from image2sim.simulator.io.canonical import MAX_DEPTH_M, encode_depth_mm, write_capture
    from image2sim.simulator.io.records import Frame
    from image2sim.simulator.lift.frames import LiftInputError

    opts = options or LiftOptions()
    out = Path(out)
    say = progress or (lambda stage, message: None)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: already exists (pass --overwrite to replace it)")
    timings: dict[str, float] = {}

    t = time.perf_counter()
    say("frames", f"reading {source}")
    scale_sources(opts.camera_height, opts.baseline, opts.object_sizes, str(source))
    frames = load_frames(source, panorama=opts.panorama, fps=opts.fps, max_frames=opts.max_frames)
    check_object_sizes(opts.object_sizes, frames)
    timings["frames"] = time.perf_counter() - t
    say("frames", f"{len(frames)} frames ({'panoramas' if frames.panorama else 'pinhole'})")

    t = time.perf_counter()
    say("sfm", "structure-from-motion")
    sfm = run_sfm(frames, opts.sfm, progress=lambda stage, fraction: say("sfm", stage))
    timings["sfm"] = time.perf_counter() - t
    say("sfm", f"registered {len(sfm.frame_ids)} of {len(frames)}")

    t = time.perf_counter()
    say("depth", f"depth ({opts.depth_source}) for {len(sfm.views)} views")
    views = [v.pinhole_view() for v in sfm.views]
    sparse: list[SparseDepth] = [v.sparse_depth(sfm.points) for v in sfm.views]
    estimate = depth_fn or _default_depth_fn()
    estimates = estimate(
        views,
        source=opts.depth_source,
        model_dir=opts.depth_model,
        sparse=sparse,
        progress=show_depth_progress,
    )
    if len(estimates) != len(views):
        raise RuntimeError(
            f"depth source {opts.depth_source!r} returned {len(estimates)} maps for {len(views)} views"
        )
    timings["depth"] = time.perf_counter() - t

    t = time.perf_counter()
    say("scale", "gravity, floor and metric scale")
    K0 = sfm.K if sfm.K is not None else sfm.views[0].K
    lengths = measure_objects(opts.object_sizes, frames, sfm, views, estimates)
    scale = estimate_metric_frame(
        sfm.cam_to_world,
        sfm.points,
        dense_points=dense_points(views, estimates, opts.min_confidence_floor),
        frame_ids=sfm.frame_ids,
        camera_height=opts.camera_height,
        baseline=opts.baseline,
        baseline_frames=opts.baseline_frames,
        reprojection_error_px=float(sfm.stats.get("mean_reprojection_error_px", 0.5)),
        focal_px=float(K0[0, 0]),
        source=str(source),
        object_lengths=lengths,
    )
    if opts.floor_fill and scale.floor is not None:
        estimates, filled = fill_floor(views, estimates, scale.floor.normal, scale.floor.offset)
        floor_fill = {"pixels": filled, "confidence": FLOOR_FILL_CONFIDENCE}
    else:
        floor_fill = {"pixels": 0, "confidence": None}
    timings["scale"] = time.perf_counter() - t
    sim = scale.transform

    plane_fill: dict = {"pixels": 0, "confidence": None}
    if opts.plane_fill:
        from image2sim.simulator.lift.planes import PLANE_FILL_CONFIDENCE, fill_planes

        t = time.perf_counter()
        say("planes", "completing textureless segments from their planes")
        estimates, plane_stats = fill_planes(views, estimates)
        plane_fill = {**plane_stats, "confidence": PLANE_FILL_CONFIDENCE}
        timings["planes"] = time.perf_counter() - t
        say("planes", f"{plane_stats['pixels']} pixels in {plane_stats['segments']} segments")

    t = time.perf_counter()
    notes_of: dict[str, list[str]] = {}
    out_frames: list[Frame] = []
    clipped = 0
    image_of = dict(zip(frames.ids, frames.images, strict=True))
    if frames.panorama:
        h, w = frames.size
        camera = EquirectCamera(h, w)
        by_frame: dict[str, dict[int, DepthEstimate]] = {}
        face_K = sfm.views[0].K
        for view, est in zip(sfm.views, estimates, strict=True):
            by_frame.setdefault(view.frame_id, {})[int(view.face)] = est
        for fid, pose in zip(sfm.frame_ids, sfm.cam_to_world, strict=True):
            faces = by_frame[fid]
            depth, conf = assemble_equirect(
                [faces[k].depth for k in range(6)], [faces[k].confidence for k in range(6)], face_K, h, w
            )
            out_frames.append((fid, image_of[fid], depth * np.float32(sim.scale), conf, sim.apply_pose(pose)))
    else:
        h, w = frames.size
        K = sfm.K
        camera = PinholeCamera(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), h, w)
        for view, est in zip(sfm.views, estimates, strict=True):
            out_frames.append(
                (
                    view.frame_id,
                    view.image,
                    est.depth.astype(np.float32) * np.float32(sim.scale),
                    est.confidence.astype(np.float32),
                    sim.apply_pose(view.cam_to_world),
                )
            )
    frames_to_write = []
    metric_poses = {}
    no_depth: list[tuple[str, str]] = []
    for fid, rgb, depth, conf, pose in out_frames:
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
        too_far = depth > MAX_DEPTH_M
        if too_far.any():
            clipped += int(too_far.sum())
            depth[too_far] = 0.0
        if not encode_depth_mm(depth, f"{fid} depth").any():
            # Every pixel invalid (e.g. a plain wall the stereo cannot match): the canonical reader
            # refuses such a depth image, so the frame is left out and named, like an unregistered one.
            no_depth.append(
                (
                    fid,
                    f"no valid depth: the {opts.depth_source} depth left every pixel invalid or unconfident",
                )
            )
            continue
        conf = np.where(depth > 0, np.clip(np.nan_to_num(conf), 0.0, 1.0), 0.0).astype(np.float32)
        notes = [
            f"lifted from {frames.source.name}: SfM pose, {opts.depth_source} depth, scale {scale.method}"
        ]
        notes_of[fid] = notes
        metric_poses[fid] = pose
        frames_to_write.append(
            Frame(
                rgb=rgb,
                depth=depth,
                camera=camera,
                cam_to_world=pose,
                frame_id=fid,
                notes=notes,
                confidence=conf,
            )
        )
    if not frames_to_write:
        raise LiftInputError(
            f"{source}: no registered frame got any valid depth from the {opts.depth_source} depth source "
            f"({len(out_frames)} frames): nothing to write"
        )
    record = {
        "source": str(Path(source).resolve()),
        "sfm": _jsonable(sfm.stats),
        "depth_source": opts.depth_source,
        "depth_model": opts.depth_model,
        **scale.record(),
        "transform": sim.to_dict(),
        "registered": len(sfm.frame_ids),
        "written": len(frames_to_write),
        "input_frames": len(frames),
        "dropped": [
            {"frame_id": f, "reason": r} for f, r in list(frames.rejected) + list(sfm.dropped) + no_depth
        ],
        "depth_beyond_range_px": clipped,
        "floor_fill": floor_fill,
        "plane_fill": plane_fill,
        "panorama": frames.panorama,
    }
    record.pop("camera_heights_m", None)
    say("write", f"writing {out}")

    def add_timings(tmp: Path) -> None:
        # The manifest is written before ``extra`` runs; the write stage's time is known only now.
        import json

        timings["write"] = time.perf_counter() - t
        record["timings_s"] = {k: round(float(v), 3) for k, v in timings.items()}
        path = tmp / "manifest.json"
        manifest = json.loads(path.read_text(encoding="utf-8"))
        manifest["metadata"]["lift"]["timings_s"] = record["timings_s"]
        path.write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")

    write_capture(
        out,
        frames_to_write,
        scene_id=Path(source).stem,
        metadata={"lift": record},
        extra=add_timings,
        overwrite=overwrite,
    )
    return LiftReport(out=out, frames=frames, sfm=sfm, scale=scale, record=record, metric_poses=metric_poses)


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if np.isfinite(v) else None
    if isinstance(value, (np.integer, int)) and not isinstance(value, bool):
        return int(value)
    return value
