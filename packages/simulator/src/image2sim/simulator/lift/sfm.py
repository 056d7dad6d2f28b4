"""Camera poses and intrinsics by structure-from-motion (pycolmap, CPU).

Pinhole frames: SIFT features, exhaustive (few frames) or sequential (video) matching, incremental
mapping with one shared camera whose intrinsics bundle adjustment refines. With a camera model that
has lens distortion (``SfmOptions.camera_model``: radial, OpenCV or fisheye) the registered frames and
their observations are undistorted to the pinhole camera of the same focal length afterwards.

Panoramas: each equirectangular frame is split into the six 90-degree cube faces of
:data:`~image2sim.simulator.geometry.reproject.CUBEMAP_FACES`, which share the panorama's centre.
The faces are reconstructed as a rig (COLMAP's rig support: the face-from-panorama rotations are
known and held fixed, so a panorama has one pose), and the panorama pose is recovered from the rig
pose. The residual reported for panoramas is the spread of the face centres around the panorama
centre and the angle between the face rotations and the known ones (both 0 up to round-off when the
rig held).

Everything comes out in our conventions: OpenCV camera, camera-to-world, pixel centres at +0.5
(COLMAP's convention too), reconstruction units (arbitrary scale, arbitrary gravity).
"""

from __future__ import annotations

import logging
import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from image2sim.simulator.lift.distortion import (
    FISHEYE_MODELS,
    LENS_MODELS,
    NEGLIGIBLE_PX,
    PINHOLE_LENS,
    Lens,
    initial_camera_params,
    lens_of_camera,
    max_displacement_px,
    undistort_image,
    undistort_pixels,
)
from image2sim.simulator.lift.frames import FrameSet, LiftInputError
from image2sim.simulator.lift.types import PinholeView, SparseDepth

__all__ = ["SfmError", "SfmOptions", "SfmView", "SfmResult", "run_sfm", "face_rotations"]

log = logging.getLogger(__name__)


class SfmError(LiftInputError):
    """Structure-from-motion could not reconstruct the input; the message names it and why."""


ROTATION_CONFIGURATIONS = ("PANORAMIC", "PLANAR_OR_PANORAMIC")
"""Two-view geometries COLMAP labels as explained by a rotation (or a plane) alone."""
ROTATION_SPREAD_SURE = 0.02
"""Camera-centre spread (x the median scene depth) below which a capture only rotates."""
ROTATION_SPREAD_MAX, ROTATION_PAIR_SHARE = 0.1, 0.95
"""Below this spread, a pinhole capture whose verified pairs are at least this share rotation-like
only rotates too (a free lens model can fake a small baseline)."""
MAPPERS = ("incremental", "global")
"""COLMAP reconstruction pipelines :class:`SfmOptions` can use."""
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", *LENS_MODELS)
"""COLMAP camera models the lift accepts for pinhole frames."""


@dataclass
class SfmOptions:
    """Settings of :func:`run_sfm`."""

    matcher: str = "auto"
    """"exhaustive", "sequential" (video: each frame with its ``overlap`` successors), "retrieval"
    (unordered frames: each with its ``retrieval_neighbours`` most alike in SIFT words,
    :mod:`~image2sim.simulator.lift.pairs`) or "auto" (exhaustive up to ``exhaustive_max`` frames,
    beyond it sequential for video and retrieval for a folder)."""
    exhaustive_max: int = 80
    """Largest number of frames (panorama faces count once per panorama) matched exhaustively."""
    overlap: int = 10
    """Successors each frame is matched with by the sequential matcher."""
    retrieval_neighbours: int = 20
    """Most alike frames each frame is matched with by the retrieval matcher."""
    vocabulary: int = 512
    """Visual words of the retrieval matcher's vocabulary (k-means over the capture's descriptors)."""
    mapper: str = "incremental"
    """"incremental" (COLMAP's incremental mapper: registers one image at a time from a seed pair) or
    "global" (COLMAP's global mapper, GLOMAP: rotation averaging and global positioning over every
    verified pair at once, then bundle adjustment)."""
    camera_model: str = "SIMPLE_PINHOLE"
    """COLMAP camera model of pinhole frames: distortion-free SIMPLE_PINHOLE (f, cx, cy) or PINHOLE
    (fx, fy, cx, cy); or with lens distortion: radial SIMPLE_RADIAL (f, cx, cy, k) or RADIAL (f, cx,
    cy, k1, k2), OPENCV (fx, fy, cx, cy, k1, k2, p1, p2: tangential terms too), or the equidistant
    fisheye SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, OPENCV_FISHEYE (k1..k4 on the ray angle). Their
    frames are undistorted to the pinhole camera after mapping when the lens moves a pixel by more
    than ``NEGLIGIBLE_PX`` (:mod:`~image2sim.simulator.lift.distortion`; a fisheye always does). On a
    procedural house through a barrel lens (k1 = -0.12) SIMPLE_RADIAL gave pose ATE 2.0 mm where
    SIMPLE_PINHOLE gave 21 cm. The default stays SIMPLE_PINHOLE: on a small distortion-free capture
    (10 views) the free coefficient bent the sparse points enough to hide the floor plane."""
    focal_prior: float | None = None
    """Initial focal length in pixels (default: COLMAP's 1.2 x the larger image side; fisheye models:
    half the larger side)."""
    max_features: int = 8192
    """SIFT features per image at most."""
    min_registered: int = 3
    """Fewest registered frames (panoramas) a usable reconstruction has."""
    face_size: int | None = None
    """Cube-face size of panoramas in pixels (default: width / 4, the panorama's resolution)."""
    num_threads: int = 2
    """CPU threads for extraction, matching and mapping."""
    seed: int = 0
    """COLMAP's random seed (RANSAC, mapping order)."""

    def __post_init__(self) -> None:
        if self.camera_model not in CAMERA_MODELS:
            raise SfmError(
                f"--camera-model must be one of {', '.join(CAMERA_MODELS)}, got {self.camera_model!r}"
            )
        if self.mapper not in MAPPERS:
            raise SfmError(f"--mapper must be one of {', '.join(MAPPERS)}, got {self.mapper!r}")
        if self.retrieval_neighbours < 1 or self.vocabulary < 2:
            raise SfmError(
                f"SfmOptions: retrieval_neighbours must be >= 1 and vocabulary >= 2, got "
                f"{self.retrieval_neighbours} and {self.vocabulary}"
            )


@dataclass
class SfmView:
    """One registered pinhole view (a frame, or a cube face of a panorama) and what it observes.

    Attributes:
        frame_id: the frame it belongs to.
        face: cube-face index into ``CUBEMAP_FACES`` (None for pinhole frames).
        K: (3, 3) intrinsics, pixel centres at +0.5.
        cam_to_world: (4, 4) camera-to-world (OpenCV camera, reconstruction units).
        uv: (k, 2) pixel coordinates of the view's observations of 3D points.
        point_index: (k,) index of each observation's point in :attr:`SfmResult.points`.
        image: (H, W, 3) uint8 RGB of the view.
    """

    frame_id: str
    face: int | None
    K: np.ndarray
    cam_to_world: np.ndarray
    uv: np.ndarray
    point_index: np.ndarray
    image: np.ndarray

    def pinhole_view(self) -> PinholeView:
        return PinholeView(image=self.image, K=self.K.copy(), cam_to_world=self.cam_to_world.copy())

    def sparse_depth(self, points: np.ndarray) -> SparseDepth:
        """The z-depth of this view's observed points (for fitting dense depth to them)."""
        world_to_cam = np.linalg.inv(self.cam_to_world)
        p = points[self.point_index] @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
        return SparseDepth(uv=self.uv.astype(np.float64), depth=p[:, 2].astype(np.float64))


@dataclass
class SfmResult:
    """A reconstruction: registered frames, their views, the sparse points.

    Attributes:
        frame_ids: registered frames, in input order.
        cam_to_world: (N, 4, 4) frame poses (the panorama centre for panoramas).
        K: (3, 3) shared intrinsics of pinhole frames (None for panoramas).
        views: registered views (one per pinhole frame; the registered faces of panoramas).
        points: (P, 3) sparse 3D points; ``colors`` (P, 3) uint8.
        dropped: ``(frame_id, reason)`` for frames SfM could not register.
        panorama: True when the frames are equirectangular panoramas.
        stats: numbers for the record (timings, reprojection error, matcher, residuals).
        distortion: the lens removed from the views (see the field).
    """

    frame_ids: list[str]
    cam_to_world: np.ndarray
    K: np.ndarray | None
    views: list[SfmView]
    points: np.ndarray
    colors: np.ndarray
    dropped: list[tuple[str, str]] = field(default_factory=list)
    panorama: bool = False
    stats: dict = field(default_factory=dict)
    distortion: Lens = PINHOLE_LENS
    """The lens removed from the input frames: the views are undistorted to :attr:`K`, the input
    images are not (the pinhole lens: nothing was removed)."""

    def frame_pose(self, frame_id: str) -> np.ndarray:
        return self.cam_to_world[self.frame_ids.index(frame_id)]

    def transformed(self, scale: float, rotation: np.ndarray, translation: np.ndarray) -> SfmResult:
        """The same reconstruction after ``x -> scale * R x + t`` (poses keep unit rotations)."""
        R = np.asarray(rotation, dtype=np.float64)
        t = np.asarray(translation, dtype=np.float64)

        def pose(T: np.ndarray) -> np.ndarray:
            out = np.eye(4)
            out[:3, :3] = R @ T[:3, :3]
            out[:3, 3] = scale * R @ T[:3, 3] + t
            return out

        views = [
            SfmView(v.frame_id, v.face, v.K, pose(v.cam_to_world), v.uv, v.point_index, v.image)
            for v in self.views
        ]
        return SfmResult(
            frame_ids=list(self.frame_ids),
            cam_to_world=np.stack([pose(T) for T in self.cam_to_world]),
            K=self.K,
            views=views,
            points=scale * self.points @ R.T + t,
            colors=self.colors,
            dropped=list(self.dropped),
            panorama=self.panorama,
            stats=dict(self.stats),
            distortion=self.distortion,
        )


def face_rotations() -> np.ndarray:
    """(6, 3, 3) rotations taking cube-face camera directions to the panorama camera frame."""
    import torch
    from image2sim.simulator.geometry.reproject import CUBEMAP_FACES, view_rotation

    yaw = torch.tensor([math.radians(f[1]) for f in CUBEMAP_FACES], dtype=torch.float64)
    pitch = torch.tensor([math.radians(f[2]) for f in CUBEMAP_FACES], dtype=torch.float64)
    return view_rotation(yaw, pitch).numpy()


def _rigid_to_matrix(rigid) -> np.ndarray:
    T = np.eye(4)
    T[:3, :4] = np.asarray(rigid.matrix(), dtype=np.float64)
    return T


def _quiet_colmap() -> None:
    import pycolmap

    pycolmap.logging.minloglevel = 2  # warnings and errors only; progress is ours


def _cube_faces(frames: FrameSet, face_size: int) -> list[np.ndarray]:
    """(6, F, F, 3) uint8 cube faces per panorama."""
    import torch
    from image2sim.simulator.geometry.reproject import equirect_to_cubemap

    out = []
    for img in frames.images:
        pano = torch.from_numpy(img).permute(2, 0, 1)[None].double() / 255.0
        cube = equirect_to_cubemap(pano, face_size)[0]  # (6, 3, F, F)
        out.append((cube.permute(0, 2, 3, 1).clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).numpy())
    return out


def _write_png(path: Path, rgb: np.ndarray) -> None:
    from image2sim.simulator.io.images import write_rgb_png

    path.parent.mkdir(parents=True, exist_ok=True)
    write_rgb_png(path, rgb)


def _pick_largest(recs: dict):
    if not recs:
        return None
    return max(recs.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))


def run_sfm(
    frames: FrameSet,
    options: SfmOptions | None = None,
    *,
    progress: Callable[[str, float], None] | None = None,
) -> SfmResult:
    """Reconstruct ``frames``; see the module docstring. ``progress(stage, fraction)`` is called
    as stages finish. Raises :class:`SfmError` naming the input when no usable reconstruction exists.
    """
    import pycolmap

    opts = options or SfmOptions()
    n = len(frames)
    if n < opts.min_registered:
        raise SfmError(
            f"{frames.source}: too few frames for structure-from-motion: {n} "
            f"(need at least {opts.min_registered})"
        )
    _quiet_colmap()
    pycolmap.set_random_seed(opts.seed)
    report = progress or (lambda stage, fraction: None)
    stats: dict = {"frames": n, "panorama": frames.panorama}
    with tempfile.TemporaryDirectory(prefix="image2sim-sfm-") as tmp_name:
        tmp = Path(tmp_name)
        image_dir, db_path = tmp / "images", tmp / "database.db"
        t0 = time.perf_counter()
        rot = face_rotations()
        faces_of: dict[str, np.ndarray] = {}
        if frames.panorama:
            h, w = frames.size
            face_size = int(opts.face_size or max(16, w // 4))
            for fid, cube in zip(frames.ids, _cube_faces(frames, face_size), strict=True):
                faces_of[fid] = cube
                for k in range(6):
                    _write_png(image_dir / f"face{k}" / f"{fid}.png", cube[k])
            f = face_size / 2.0  # 90-degree faces
            face_K = np.array([[f, 0, face_size / 2.0], [0, f, face_size / 2.0], [0, 0, 1.0]])
            reader = pycolmap.ImageReaderOptions(
                camera_model="SIMPLE_PINHOLE", camera_params=f"{f},{face_size / 2.0},{face_size / 2.0}"
            )
            camera_mode = pycolmap.CameraMode.PER_FOLDER
        else:
            for fid, img in zip(frames.ids, frames.images, strict=True):
                _write_png(image_dir / f"{fid}.png", img)
            params = ""
            h, w = frames.size
            if opts.focal_prior is not None:
                params = initial_camera_params(opts.camera_model, float(opts.focal_prior), w, h)
            elif opts.camera_model in FISHEYE_MODELS:
                # COLMAP's guess (1.2 x the larger side, a 45-degree view) found no model at all on a
                # fisheye house whose f was 220 px for 320 px; half the larger side (a 115-degree view)
                # and 280 px both recovered it.
                params = initial_camera_params(opts.camera_model, max(w, h) / 2.0, w, h)
            reader = pycolmap.ImageReaderOptions(camera_model=opts.camera_model, camera_params=params)
            camera_mode = pycolmap.CameraMode.SINGLE
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.use_gpu = False
        extraction.num_threads = opts.num_threads
        extraction.sift.max_num_features = opts.max_features
        pycolmap.extract_features(
            db_path, image_dir, camera_mode=camera_mode, reader_options=reader, extraction_options=extraction
        )
        if frames.panorama:
            _apply_face_rig(db_path, rot)
        stats["extract_s"] = time.perf_counter() - t0
        report("features", 1.0)

        t1 = time.perf_counter()
        matching = pycolmap.FeatureMatchingOptions()
        matching.use_gpu = False
        matching.num_threads = opts.num_threads
        if frames.panorama:
            matching.rig_verification = True
            matching.skip_image_pairs_in_same_frame = True
        matcher = opts.matcher
        if matcher == "auto":
            unordered = "sequential" if frames.fps is not None else "retrieval"
            matcher = "exhaustive" if n <= opts.exhaustive_max else unordered
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(db_path, matching_options=matching)
        elif matcher == "retrieval":
            stats["retrieval_pairs"] = _match_retrieval(db_path, tmp / "pairs.txt", matching, opts)
        elif matcher == "sequential":
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = opts.overlap * (6 if frames.panorama else 1)
            pycolmap.match_sequential(db_path, matching_options=matching, pairing_options=pairing)
        else:
            raise SfmError(f"matcher must be auto, exhaustive, sequential or retrieval, got {opts.matcher!r}")
        stats["matcher"] = matcher
        stats["match_s"] = time.perf_counter() - t1
        stats["pair_geometry"] = _pair_configurations(db_path)
        report("matching", 1.0)

        t2 = time.perf_counter()
        (tmp / "sparse").mkdir()
        recs = _map(db_path, image_dir, tmp / "sparse", opts, frames.panorama)
        stats["mapper"] = opts.mapper
        stats["map_s"] = time.perf_counter() - t2
        report("mapping", 1.0)
        rec = _pick_largest(recs)
        if rec is None:
            raise SfmError(
                f"{frames.source}: structure-from-motion found no reconstruction from {n} frames "
                "(no image pair with enough matched features and baseline: too little texture, too "
                "little overlap, or a camera that only rotates)"
            )
        stats["models"] = len(recs)
        if frames.panorama:
            result = _panorama_result(rec, frames, faces_of, face_K, rot)
        else:
            result = _pinhole_result(rec, frames)
    registered = len(result.frame_ids)
    result.stats.update(stats)
    result.stats["registered"] = registered
    result.stats["mean_reprojection_error_px"] = float(rec.compute_mean_reprojection_error())
    result.stats["points"] = int(len(result.points))
    if registered < opts.min_registered:
        raise SfmError(
            f"{frames.source}: too few registered frames: {registered} of {n} "
            f"(need {opts.min_registered}; unregistered: {[d for d, _ in result.dropped][:8]})"
        )
    baseline = _baseline_ratio(result)
    result.stats["baseline_ratio"] = baseline
    pairs = stats["pair_geometry"]
    rotation_share = sum(pairs.get(c, 0) for c in ROTATION_CONFIGURATIONS) / max(1, sum(pairs.values()))
    result.stats["rotation_pair_share"] = rotation_share
    # Two signals, because a free lens model can fake a baseline: with SIMPLE_RADIAL a capture that
    # only rotates was reconstructed with spread 0.049 (focal and k wrong), but every one of its
    # verified pairs was homography-like; a walking capture had spread 0.54 and 19 % general pairs.
    small = baseline < ROTATION_SPREAD_SURE or (
        not frames.panorama and baseline < ROTATION_SPREAD_MAX and rotation_share >= ROTATION_PAIR_SHARE
    )
    if small:
        raise SfmError(
            f"{frames.source}: the cameras barely move (camera-centre spread {baseline:.3f} x the median "
            f"scene depth; {100 * rotation_share:.0f} % of matched pairs related by a rotation or a plane "
            "alone): a capture that only rotates has no baseline to triangulate depth or poses from"
        )
    for fid, reason in result.dropped:
        log.warning("%s: frame %s dropped: %s", frames.source, fid, reason)
    return result


def _map(db_path: Path, image_dir: Path, out: Path, opts: SfmOptions, panorama: bool) -> dict:
    """Reconstructions (id -> ``pycolmap.Reconstruction``) of the matched database by
    ``opts.mapper``. A panorama's cube faces are a rig whose face rotations and intrinsics are
    known: neither mapper refines them."""
    import pycolmap

    if opts.mapper == "global":
        mapping = pycolmap.GlobalPipelineOptions()
        mapping.num_threads = opts.num_threads
        mapping.random_seed = opts.seed
        mapping.multiple_models = True
        mapper = mapping.mapper
        mapper.num_threads = opts.num_threads
        mapper.random_seed = opts.seed
        mapper.global_positioning.use_gpu = False
        mapper.bundle_adjustment.ceres.use_gpu = False
        if panorama:
            mapper.refine_sensor_from_rig = False
            mapper.rotation_averaging.refine_sensor_from_rig = False
            mapper.global_positioning.refine_sensor_from_rig = False
            ba = mapper.bundle_adjustment
            ba.refine_sensor_from_rig = False
            ba.refine_focal_length = False
            ba.refine_principal_point = False
            ba.refine_extra_params = False
        return pycolmap.global_mapping(db_path, image_dir, out, mapping)
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = opts.num_threads
    mapping.random_seed = opts.seed
    mapping.multiple_models = True
    if panorama:
        mapping.ba_refine_sensor_from_rig = False
        mapping.ba_refine_focal_length = False
        mapping.ba_refine_principal_point = False
        mapping.ba_refine_extra_params = False
    return pycolmap.incremental_mapping(db_path, image_dir, out, mapping)


def _match_retrieval(db_path: Path, pairs_file: Path, matching, opts: SfmOptions) -> int:
    """Match each frame's images with those of its ``opts.retrieval_neighbours`` most alike frames
    (a panorama's six faces pooled into one frame); returns the number of frame pairs."""
    import pycolmap
    from image2sim.simulator.lift.pairs import assign_words, content_sample, kmeans, retrieval_pairs, tfidf

    with pycolmap.Database.open(db_path) as db:
        images = db.read_all_images()
        desc = {im.image_id: np.asarray(db.read_descriptors(im.image_id).data) for im in images}
    frame_of = {im.image_id: im.name.rsplit("/", 1)[-1] for im in images}  # faces share the file name
    names = sorted(set(frame_of.values()))
    images_of: dict[str, list[str]] = {name: [] for name in names}
    for im in images:
        images_of[frame_of[im.image_id]].append(im.name)
    found = [d for d in desc.values() if len(d)]
    if not found:
        raise SfmError("retrieval matching: no image has a SIFT feature")
    sample = content_sample(found, 50_000, seed=opts.seed)
    centres = kmeans(sample, opts.vocabulary, seed=opts.seed)
    words: dict[str, list[np.ndarray]] = {name: [] for name in names}
    for iid, d in desc.items():
        if len(d):
            words[frame_of[iid]].append(assign_words(d, centres))
    vectors = tfidf([np.concatenate(w) if w else np.zeros(0, np.int64) for w in words.values()], len(centres))
    frame_pairs = retrieval_pairs(vectors, opts.retrieval_neighbours)
    lines = [f"{a} {b}" for i, j in frame_pairs for a in images_of[names[i]] for b in images_of[names[j]]]
    pairs_file.write_text("\n".join(lines) + "\n")
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(pairs_file)
    pycolmap.match_image_pairs(db_path, matching_options=matching, pairing_options=pairing)
    return len(frame_pairs)


def _pair_configurations(db_path: Path) -> dict[str, int]:
    """How many verified image pairs COLMAP's two-view geometry labelled with each configuration
    (``CALIBRATED``, ``UNCALIBRATED``, ``PLANAR``, ``PANORAMIC``, ...; 5 or more inliers)."""
    import pycolmap

    counts: dict[str, int] = {}
    with pycolmap.Database.open(db_path) as db:
        _, geometries = db.read_two_view_geometries()
        for g in geometries:
            if len(g.inlier_matches) < 5:
                continue
            name = pycolmap.TwoViewGeometryConfiguration(g.config).name
            counts[name] = counts.get(name, 0) + 1
    return counts


def _apply_face_rig(db_path: Path, rot: np.ndarray) -> None:
    """Declare the six faces of each panorama one rig frame: faces k share the centre of face 0,
    rotated by the known face rotations (``cam_k_from_cam_0 = R_k^T R_0``)."""
    import pycolmap

    cams = []
    for k in range(6):
        if k == 0:
            cam_from_rig = None
        else:
            cam_from_rig = pycolmap.Rigid3d(
                pycolmap.Rotation3d(rot[k].T @ rot[0]), np.zeros((3, 1), dtype=np.float64)
            )
        cams.append(
            pycolmap.RigConfigCamera(ref_sensor=k == 0, image_prefix=f"face{k}/", cam_from_rig=cam_from_rig)
        )
    with pycolmap.Database.open(db_path) as db:
        pycolmap.apply_rig_config([pycolmap.RigConfig(cameras=cams)], db)


def _observations(image) -> tuple[np.ndarray, np.ndarray]:
    uv, ids = [], []
    for p in image.points2D:
        if p.has_point3D():
            uv.append(np.asarray(p.xy, dtype=np.float64))
            ids.append(int(p.point3D_id))
    return np.asarray(uv, dtype=np.float64).reshape(-1, 2), np.asarray(ids, dtype=np.int64)


def _points(rec) -> tuple[np.ndarray, np.ndarray, dict[int, int]]:
    ids = sorted(rec.points3D.keys())
    index = {pid: i for i, pid in enumerate(ids)}
    xyz = np.array([rec.points3D[pid].xyz for pid in ids], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([rec.points3D[pid].color for pid in ids], dtype=np.uint8).reshape(-1, 3)
    return xyz, rgb, index


def _pinhole_result(rec, frames: FrameSet) -> SfmResult:
    points, colors, index = _points(rec)
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    cams = {im.camera_id for im in by_name.values()}
    if len(cams) != 1:
        raise SfmError(f"{frames.source}: expected one shared camera, the reconstruction has {len(cams)}")
    camera = rec.cameras[cams.pop()]
    K = np.asarray(camera.calibration_matrix(), dtype=np.float64)
    # A lens with distortion: the views become the undistorted pinhole frames of K.
    lens = lens_of_camera(camera.model.name, camera.params)
    h, w = frames.size
    displacement = max_displacement_px(K, lens, h, w)
    distorted = displacement > NEGLIGIBLE_PX
    ids, poses, views, dropped = [], [], [], []
    for fid, img in zip(frames.ids, frames.images, strict=True):
        im = by_name.get(f"{fid}.png")
        if im is None:
            dropped.append((fid, "not registered by structure-from-motion"))
            continue
        T = np.linalg.inv(_rigid_to_matrix(im.cam_from_world()))
        uv, pid = _observations(im)
        if distorted:
            img, uv = undistort_image(img, K, lens), undistort_pixels(uv, K, lens)
            seen = np.isfinite(uv).all(axis=1)  # a fisheye's rays past 90 degrees have no pinhole image
            uv, pid = uv[seen], np.asarray(pid)[seen]
        ids.append(fid)
        poses.append(T)
        views.append(SfmView(fid, None, K, T, uv, np.array([index[p] for p in pid], dtype=np.int64), img))
    return SfmResult(
        frame_ids=ids,
        cam_to_world=np.stack(poses) if poses else np.zeros((0, 4, 4)),
        K=K,
        views=views,
        points=points,
        colors=colors,
        dropped=dropped,
        panorama=False,
        stats={
            "camera": {"model": camera.model.name, "params": [float(x) for x in camera.params]},
            "undistorted": distorted,
            "max_distortion_px": displacement,
        },
        distortion=lens if distorted else PINHOLE_LENS,
    )


def _panorama_result(
    rec, frames: FrameSet, faces_of: dict[str, np.ndarray], face_K: np.ndarray, rot: np.ndarray
) -> SfmResult:
    points, colors, index = _points(rec)
    per_frame: dict[str, dict[int, object]] = {}
    for im in rec.images.values():
        if not im.has_pose:
            continue
        folder, name = im.name.split("/", 1)
        per_frame.setdefault(Path(name).stem, {})[int(folder[4:])] = im
    ids, poses, views, dropped = [], [], [], []
    centre_spread, angle_err = [], []
    for fid in frames.ids:
        faces = per_frame.get(fid)
        if not faces:
            dropped.append((fid, "no cube face registered by structure-from-motion"))
            continue
        # Each registered face k gives a panorama pose: R_pano = R_face R_k^T, same centre.
        pano_R, centres = [], []
        for k, im in faces.items():
            T = np.linalg.inv(_rigid_to_matrix(im.cam_from_world()))
            pano_R.append(T[:3, :3] @ rot[k].T)
            centres.append(T[:3, 3])
        R = _average_rotations(np.stack(pano_R))
        c = np.mean(centres, axis=0)
        centre_spread.append(float(np.max(np.linalg.norm(np.asarray(centres) - c, axis=1))))
        angle_err.append(max(_angle_deg(R.T @ Rk) for Rk in pano_R))
        pano = np.eye(4)
        pano[:3, :3], pano[:3, 3] = R, c
        ids.append(fid)
        poses.append(pano)
        for k in range(6):
            face_pose = np.eye(4)
            face_pose[:3, :3], face_pose[:3, 3] = R @ rot[k], c
            im = faces.get(k)
            if im is not None:
                uv, pid = _observations(im)
                pidx = np.array([index[p] for p in pid], dtype=np.int64)
            else:
                uv, pidx = np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
            views.append(SfmView(fid, k, face_K, face_pose, uv, pidx, faces_of[fid][k]))
    return SfmResult(
        frame_ids=ids,
        cam_to_world=np.stack(poses) if poses else np.zeros((0, 4, 4)),
        K=None,
        views=views,
        points=points,
        colors=colors,
        dropped=dropped,
        panorama=True,
        stats={
            "rig_centre_spread_max": max(centre_spread, default=0.0),
            "rig_rotation_residual_deg_max": max(angle_err, default=0.0),
        },
    )


def _angle_deg(R: np.ndarray) -> float:
    import torch
    from image2sim.simulator.geometry.se3 import rotation_angle

    return math.degrees(float(rotation_angle(torch.from_numpy(np.asarray(R, dtype=np.float64)))))


def _average_rotations(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations (projection of their sum onto SO(3))."""
    U, _, Vt = np.linalg.svd(Rs.sum(axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _baseline_ratio(result: SfmResult) -> float:
    """Spread of camera centres (largest distance from their mean) over the median point depth."""
    centres = result.cam_to_world[:, :3, 3]
    spread = float(np.max(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))
    if len(result.points) == 0:
        return 0.0
    dist = np.linalg.norm(result.points[:, None, :] - centres[None, : min(len(centres), 32)], axis=2)
    return spread / max(float(np.median(dist)), 1e-12)
