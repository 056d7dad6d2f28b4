"""Metric scale and gravity for a reconstruction, and the scores that check them.

Gravity: the capture's up direction is the mean camera up vector (``-y`` of OpenCV cameras: people
hold cameras roughly level), refined by the floor: RANSAC finds the dominant planes of the points
whose normals lie within ``max_tilt_deg`` of that guess, and the lowest one holding at least
``floor_min_share`` of the largest one's inliers and lying below the cameras is the floor.

Scale, one of:

* ``camera_height``: a stated height of the camera above the floor (metres); the scale is that over
  the median of the cameras' heights above the floor plane. Uncertainty: the relative standard
  deviation of the scale over bootstrap resamples of the cameras and of the floor's inliers.
* ``baseline``: a stated distance between the centres of two named frames. Uncertainty: the
  triangulation precision of that distance (reprojection error over focal length, times the median
  scene depth) relative to it.
* ``object_size``: stated lengths between two pixels of an input image, measured on the dense depth
  (:mod:`~image2sim.simulator.lift.measure`, ``--object-size``). Uncertainty: the ends' depth spread
  and one pixel of localisation, combined over the lengths.
* ``none``: reconstruction units, uncertainty 0 and a warning from the caller.

The result is a similarity ``x -> s R x + t`` into the canonical world: Z up, metres, floor at
z = 0, the first frame's centre above the origin, its viewing direction along +X.

Scoring helpers (pure functions): :func:`umeyama` (Sim(3) / SE(3) least squares), :func:`ate`,
:func:`rotation_errors_deg`, :func:`scale_error`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from image2sim.simulator.lift.measure import ObjectLength, scale_from_lengths

__all__ = [
    "ScaleError",
    "Similarity",
    "ScaleResult",
    "Plane",
    "umeyama",
    "ate",
    "rotation_errors_deg",
    "scale_error",
    "camera_up_mean",
    "fit_planes",
    "find_floor",
    "rotation_taking",
    "estimate_metric_frame",
    "scale_sources",
]


class ScaleError(ValueError):
    """Metric scale or gravity cannot be estimated; the message names the input and the problem."""


@dataclass
class Similarity:
    """``x -> scale * rotation @ x + translation``."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation

    def apply_pose(self, cam_to_world: np.ndarray) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = self.rotation @ cam_to_world[:3, :3]
        out[:3, 3] = self.apply(cam_to_world[:3, 3])
        return out

    def to_dict(self) -> dict:
        return {
            "scale": float(self.scale),
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
        }


@dataclass
class Plane:
    """Points ``x`` with ``normal . x = offset``; ``inliers`` indexes the points that support it."""

    normal: np.ndarray
    offset: float
    inliers: np.ndarray


@dataclass
class ScaleResult:
    """Where the reconstruction goes: the similarity, how its scale was found, how sure it is."""

    transform: Similarity
    method: str
    scale: float
    uncertainty: float
    """Relative (1-sigma) uncertainty of ``scale``."""
    up: np.ndarray
    """Unit up direction in reconstruction coordinates."""
    floor: Plane | None
    details: dict = field(default_factory=dict)

    def record(self) -> dict:
        """JSON-ready record for the capture's manifest."""
        return {
            "scale_method": self.method,
            "scale": float(self.scale),
            "scale_uncertainty": float(self.uncertainty),
            "up_in_reconstruction": [float(x) for x in self.up],
            "floor_found": self.floor is not None,
            **self.details,
        }


# --- scoring --------------------------------------------------------------------------------------


def umeyama(
    src: np.ndarray, dst: np.ndarray, *, with_scale: bool = True
) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares ``(s, R, t)`` with ``dst ~ s R src + t`` (Umeyama 1991); points (N, 3), N >= 3."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(
            f"umeyama needs two (N >= 3, 3) point sets of one shape, got {src.shape} and {dst.shape}"
        )
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, d, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = float((xs**2).sum() / len(src))
    if with_scale:
        if var_s <= 0:
            raise ValueError("umeyama: the source points are all identical (no scale can be fitted)")
        s = float(np.trace(np.diag(d) @ S) / var_s)
    else:
        s = 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def ate(est: np.ndarray, true: np.ndarray, *, with_scale: bool = True) -> float:
    """Absolute trajectory error: RMSE of positions (N, 3) after the best Sim(3) (or SE(3)) alignment."""
    s, R, t = umeyama(est, true, with_scale=with_scale)
    aligned = s * np.asarray(est, dtype=np.float64) @ R.T + t
    return float(np.sqrt(np.mean(np.sum((aligned - true) ** 2, axis=1))))


def rotation_errors_deg(
    R_est: np.ndarray, R_true: np.ndarray, R_align: np.ndarray | None = None
) -> np.ndarray:
    """Angles (degrees) between ``R_align @ R_est[i]`` and ``R_true[i]``, rotations (N, 3, 3)."""
    import torch
    from image2sim.simulator.geometry.se3 import rotation_angle

    R_est = np.asarray(R_est, dtype=np.float64)
    R_true = np.asarray(R_true, dtype=np.float64)
    if R_align is not None:
        R_est = np.einsum("ij,njk->nik", R_align, R_est)
    rel = np.einsum("nji,njk->nik", R_est, R_true)
    return np.degrees(rotation_angle(torch.from_numpy(rel)).numpy())


def scale_error(est: np.ndarray, true: np.ndarray) -> float:
    """Relative scale error of metric positions ``est`` against ``true`` (N, 3): ``|1/s - 1|`` with
    ``s`` the scale of the best Sim(3) alignment (0 when the estimate has the true scale)."""
    s, _, _ = umeyama(est, true, with_scale=True)
    return float(abs(1.0 / s - 1.0))


# --- gravity and floor ----------------------------------------------------------------------------


def camera_up_mean(cam_to_world: np.ndarray) -> np.ndarray:
    """Unit mean of the cameras' up vectors (``-y`` of OpenCV cameras) in world coordinates."""
    up = -np.asarray(cam_to_world, dtype=np.float64)[:, :3, 1].sum(axis=0)
    norm = np.linalg.norm(up)
    if norm < 1e-9:
        raise ScaleError("the cameras' up vectors cancel out: no up direction can be estimated from them")
    return up / norm


def fit_planes(
    points: np.ndarray,
    up: np.ndarray,
    threshold: float,
    *,
    max_tilt_deg: float = 25.0,
    max_planes: int = 4,
    iterations: int = 400,
    min_inliers: int = 20,
    seed: int = 0,
) -> list[Plane]:
    """Dominant planes with normals within ``max_tilt_deg`` of ``up`` (normals oriented along it),
    found by sequential RANSAC (each plane's inliers removed before the next) and refined by least
    squares on their inliers."""
    rng = np.random.default_rng(seed)
    pts = np.asarray(points, dtype=np.float64)
    remaining = np.arange(len(pts))
    cos_tilt = np.cos(np.radians(max_tilt_deg))
    planes: list[Plane] = []
    for _ in range(max_planes):
        if len(remaining) < max(3, min_inliers):
            break
        P = pts[remaining]
        best, best_count = None, 0
        for _ in range(iterations):
            a, b, c = P[rng.choice(len(P), 3, replace=False)]
            n = np.cross(b - a, c - a)
            norm = np.linalg.norm(n)
            if norm < 1e-12:
                continue
            n /= norm
            if n @ up < 0:
                n = -n
            if n @ up < cos_tilt:
                continue
            count = int((np.abs(P @ n - n @ a) < threshold).sum())
            if count > best_count:
                best, best_count = (n, float(n @ a)), count
        if best is None or best_count < min_inliers:
            break
        n, d = best
        inl = np.abs(P @ n - d) < threshold
        for _ in range(2):  # least-squares refinement on the inliers
            Q = P[inl]
            centroid = Q.mean(axis=0)
            _, _, Vt = np.linalg.svd(Q - centroid, full_matrices=False)
            n = Vt[2] if Vt[2] @ up >= 0 else -Vt[2]
            d = float(n @ centroid)
            inl = np.abs(P @ n - d) < threshold
        if n @ up < cos_tilt or inl.sum() < min_inliers:
            break
        planes.append(Plane(normal=n, offset=d, inliers=remaining[inl]))
        remaining = remaining[~inl]
    return planes


def find_floor(
    points: np.ndarray,
    cam_to_world: np.ndarray,
    up: np.ndarray,
    *,
    threshold: float | None = None,
    floor_min_share: float = 0.05,
    max_tilt_deg: float = 8.0,
    min_inliers: int = 20,
    min_contrast: float = 2.0,
    seed: int = 0,
    candidates: list[dict] | None = None,
) -> Plane | None:
    """The floor: the lowest well-supported near-horizontal plane below every camera (None when none is).

    A floor is a small share of the points of a room (walls and furniture hold most), so random
    triplets rarely land on it: candidate heights are the peaks of the points' height histogram
    along ``up`` (a horizontal plane is a peak), a plane is fitted by RANSAC to the points near each
    peak (tilt up to ``max_tilt_deg``, so a rough ``up`` suffices) and refitted to all its inliers.

    Any horizontal slab through the walls also holds points (the walls crossing it), so a plane's
    inlier count says little: its *support* is its inliers minus the background, the larger count
    of the two parallel slabs ``4 * threshold`` above and below it (the walls cross those as much;
    the larger, so the bottom edge of the visible walls is no plane). A plane is well supported
    when its support is at least ``min_inliers`` and its inliers at least ``min_contrast`` times the
    background (a surface, not a slice of the walls; measured on a pinhole house that sees the floor
    only at grazing angles: floor 51 inliers over a background of 17, wall slices 50-316 inliers over
    0.8-1.4 times as many). The floor is the lowest well-supported plane with at least
    ``floor_min_share`` of the best one's support (a guard against stray clusters below the floor;
    small, as a textured table can hold ten times the points of a floor seen at grazing angles),
    and it must lie below every camera.
    ``candidates``, when given, receives one record per plane tried (height below the cameras'
    median in reconstruction units, inliers, background, tilt, accepted).
    """
    pts = np.asarray(points, dtype=np.float64)
    centres = np.asarray(cam_to_world)[:, :3, 3]
    cam_h = centres @ up
    cam_height = float(np.median(cam_h))
    below = np.nonzero(pts @ up < cam_height)[0]  # the floor lies below the cameras; this drops the ceiling
    pts = pts[below]
    if len(pts) < min_inliers:
        return None
    if threshold is None:
        # 0.5 % of the median camera-to-point distance: a plane's thickness at reconstruction scale.
        sample = pts[:: max(1, len(pts) // 2000)]
        dist = np.linalg.norm(sample[:, None, :] - centres[None, :: max(1, len(centres) // 16)], axis=2)
        threshold = 0.005 * float(np.median(dist))
    h = pts @ up
    edges = np.arange(h.min(), h.max() + 2 * threshold, threshold)
    counts = np.histogram(h, bins=edges)[0].astype(np.float64)
    window = np.convolve(counts, np.ones(3), mode="same")  # points within ~1.5 thresholds
    peaks = [
        i
        for i in range(len(window))
        if window[i] >= min_inliers
        and window[i] >= window[max(i - 1, 0)]
        and window[i] >= window[min(i + 1, len(window) - 1)]
    ]
    cos_tilt = np.cos(np.radians(max_tilt_deg))
    planes: list[tuple[Plane, float]] = []
    for i in sorted(peaks, key=lambda i: edges[i])[:40]:  # lowest first
        centre_h = 0.5 * (edges[i] + edges[i + 1])
        # A narrow slab: with a tilted ``up`` guess it holds part of the floor, still a plane, and
        # few points of the walls crossing it; the plane is then refitted to all its inliers.
        near = np.nonzero(np.abs(h - centre_h) < 2 * threshold)[0]
        found = fit_planes(
            pts[near],
            up,
            threshold,
            max_tilt_deg=max_tilt_deg,
            max_planes=1,
            min_inliers=min_inliers,
            seed=seed,
        )
        if not found:
            continue
        n, d = found[0].normal, found[0].offset
        for _ in range(2):
            inl = np.nonzero(np.abs(pts @ n - d) < threshold)[0]
            c = pts[inl].mean(axis=0)
            _, _, Vt = np.linalg.svd(pts[inl] - c, full_matrices=False)
            n = Vt[2] if Vt[2] @ up >= 0 else -Vt[2]
            d = float(n @ c)
        signed = pts @ n - d
        inl = np.nonzero(np.abs(signed) < threshold)[0]
        background = float(max(int((np.abs(signed - k * threshold) < threshold).sum()) for k in (-4, 4)))
        support = len(inl) - background
        below_all = bool(d < float((centres @ n).min()) - 3 * threshold)
        ok = (
            below_all
            and n @ up >= cos_tilt
            and support >= min_inliers
            and len(inl) >= min_contrast * background
        )
        if candidates is not None:
            candidates.append(
                {
                    "depth_below_cameras": round(cam_height - d, 6),
                    "inliers": int(len(inl)),
                    "background": float(background),
                    "tilt_deg": round(float(np.degrees(np.arccos(np.clip(n @ up, -1, 1)))), 3),
                    "below_all_cameras": below_all,
                    "well_supported": bool(ok),
                }
            )
        if ok:
            planes.append((Plane(n, d, inl), support))
    if not planes:
        return None
    best = max(s for _, s in planes)
    floor = min((p for p, s in planes if s >= floor_min_share * best), key=lambda p: p.offset)
    # Inlier indices refer to ``points`` as given, not to the below-camera subset.
    return Plane(floor.normal, floor.offset, below[floor.inliers])


def rotation_taking(up: np.ndarray, forward: np.ndarray | None = None) -> np.ndarray:
    """Rotation taking ``up`` to +Z and (the horizontal part of) ``forward`` to +X."""
    z = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    f = np.array([1.0, 0.0, 0.0]) if forward is None else np.asarray(forward, dtype=np.float64)
    x = f - (f @ z) * z
    if np.linalg.norm(x) < 1e-6:  # forward along up: any horizontal axis
        x = np.cross(z, [0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])  # rows: world axes expressed in reconstruction coordinates


def scale_sources(camera_height, baseline, object_sizes, source: str = "lift") -> list[str]:
    """The scale options given (``--camera-height``, ``--baseline``, ``--object-size``); ``ScaleError``
    naming them when more than one is."""
    given = [n for n, v in (("--camera-height", camera_height), ("--baseline", baseline)) if v is not None]
    given += ["--object-size"] if len(object_sizes) else []
    if len(given) > 1:
        raise ScaleError(f"{source}: give one scale source, not both {' and '.join(given)}")
    return given


def estimate_metric_frame(
    cam_to_world: np.ndarray,
    points: np.ndarray,
    *,
    frame_ids: list[str] | None = None,
    camera_height: float | None = None,
    baseline: float | None = None,
    baseline_frames: tuple[str, str] | None = None,
    reprojection_error_px: float = 0.5,
    focal_px: float = 500.0,
    bootstrap: int = 200,
    seed: int = 0,
    source: str = "reconstruction",
    dense_points: np.ndarray | None = None,
    object_lengths: Sequence[ObjectLength] = (),
) -> ScaleResult:
    """Gravity, floor and scale of a reconstruction (poses (N, 4, 4), points (P, 3)); see the module
    docstring. At most one of ``camera_height``, ``baseline`` and ``object_lengths`` is given.

    ``points`` are the sparse SfM points; ``dense_points`` (confident dense depth), when given, join
    them only when the sparse points alone show no floor: triangulated feature points hold floor
    texture even where the floor is seen at grazing angles, while dense depth there is scarce and
    its errors blur the wall slices the floor must stand out from (on the benchmark's pinhole house
    the floor stood out 8x from the sparse points' background, 3x with dense depth added; scale
    error 0.13 % against 0.64 %)."""
    poses = np.asarray(cam_to_world, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    scale_sources(camera_height, baseline, object_lengths, source)
    cam_up = camera_up_mean(poses)
    tried: list[dict] = []
    floor = find_floor(pts, poses, cam_up, seed=seed, candidates=tried)
    details: dict = {"up_source": "cameras", "floor_points": "sparse"}
    if floor is None and dense_points is not None and len(dense_points):
        pts = np.concatenate([pts, np.asarray(dense_points, dtype=np.float64).reshape(-1, 3)])
        tried_dense: list[dict] = []
        floor = find_floor(pts, poses, cam_up, seed=seed, candidates=tried_dense)
        tried += tried_dense
        details["floor_points"] = "sparse+dense"
    up = cam_up
    if floor is not None:
        tilt = float(np.degrees(np.arccos(np.clip(floor.normal @ cam_up, -1, 1))))
        details["floor_tilt_to_camera_up_deg"] = tilt
        details["floor_inliers"] = int(len(floor.inliers))
        details["floor_candidates"] = len(tried)
        up = floor.normal
        details["up_source"] = "floor plane"
    centres = poses[:, :3, 3]
    heights_rel = None
    if floor is not None:
        heights_rel = centres @ floor.normal - floor.offset
    if camera_height is not None:
        if camera_height <= 0:
            raise ScaleError(f"{source}: --camera-height must be positive, got {camera_height}")
        if floor is None:
            raise ScaleError(
                f"{source}: --camera-height needs the floor, and no well-supported horizontal plane below "
                f"every camera was found among the reconstructed points ({len(tried)} candidate planes, "
                "none standing out from the walls: is the floor visible and textured?); give the scale "
                "by --baseline M --baseline-frames A B instead"
            )
        med = float(np.median(heights_rel))
        if med <= 0:
            raise ScaleError(f"{source}: the floor plane lies above the cameras' median height")
        scale = camera_height / med
        rng = np.random.default_rng(seed)
        inl = pts[floor.inliers]
        boots = []
        for _ in range(bootstrap):
            cams = centres[rng.integers(0, len(centres), len(centres))]
            sub = inl[rng.integers(0, len(inl), len(inl))]
            c = sub.mean(axis=0)
            _, _, Vt = np.linalg.svd(sub - c, full_matrices=False)
            n = Vt[2] if Vt[2] @ floor.normal >= 0 else -Vt[2]
            h = float(np.median(cams @ n - n @ c))
            if h > 0:
                boots.append(camera_height / h)
        uncertainty = float(np.std(boots) / scale) if boots else float("inf")
        spread = 1.4826 * float(np.median(np.abs(heights_rel - med))) / med
        method = "camera_height"
        details.update(
            {
                "camera_height_m": float(camera_height),
                "camera_height_spread": spread,
                "camera_heights_m": [float(h * scale) for h in heights_rel],
            }
        )
    elif baseline is not None:
        if baseline <= 0:
            raise ScaleError(f"{source}: --baseline must be positive, got {baseline}")
        if baseline_frames is None or frame_ids is None:
            raise ScaleError(
                f"{source}: --baseline needs the two frames it is measured between (--baseline-frames A B)"
            )
        a, b = baseline_frames
        missing = [f for f in (a, b) if f not in frame_ids]
        if missing:
            raise ScaleError(
                f"{source}: --baseline-frames {missing} not among the registered frames "
                f"({len(frame_ids)}: {frame_ids[:6]}...)"
            )
        dist = float(np.linalg.norm(centres[frame_ids.index(a)] - centres[frame_ids.index(b)]))
        if dist <= 0:
            raise ScaleError(f"{source}: frames {a} and {b} have the same centre: no baseline between them")
        scale = baseline / dist
        depth = float(np.median(np.linalg.norm(pts - centres.mean(axis=0), axis=1))) if len(pts) else dist
        uncertainty = float(np.sqrt(2.0) * reprojection_error_px / focal_px * depth / dist)
        method = "baseline"
        details.update({"baseline_m": float(baseline), "baseline_frames": [a, b]})
    elif len(object_lengths):
        scale, uncertainty = scale_from_lengths(object_lengths)
        method = "object_size"
        details["object_sizes"] = [x.record() for x in object_lengths]
    else:
        scale, uncertainty, method = 1.0, 0.0, "none"
    # Canonical frame: up -> +Z, the first camera's forward -> +X, floor at z = 0, first camera at x = y = 0.
    R = rotation_taking(up, poses[0, :3, 2])
    rotated_first = scale * R @ centres[0]
    if floor is not None:
        z0 = scale * floor.offset
    else:
        z0 = float(np.min(scale * (pts @ up))) if len(pts) else float(rotated_first[2])
        details["floor_note"] = "no floor plane found: z = 0 at the lowest reconstructed point"
    t = np.array([-rotated_first[0], -rotated_first[1], -z0])
    return ScaleResult(
        transform=Similarity(float(scale), R, t),
        method=method,
        scale=float(scale),
        uncertainty=uncertainty,
        up=up,
        floor=floor,
        details=details,
    )
