"""Captures of procedural scenes: viewpoint sampling, noise tiers, and writing canonical captures + ``gt/``.

Viewpoints lie on navigable cell centres at one eye height per scene, with random yaw. Consecutive
views are ``spacing_min``..``spacing_max`` apart with a free straight line between them (so they
see the same surfaces), choosing among candidates the one farthest from all earlier views (so the
sequence covers the house). Noise tiers (:data:`~image2sim.dataengine.procedural.config.NOISE_TIERS`)
degrade the *stored* depth, colour and poses; ``gt/poses.json`` keeps the exact poses.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from image2sim.dataengine.procedural.config import NoiseConfig, SynthConfig
from image2sim.dataengine.procedural.gt import write_gt
from image2sim.dataengine.procedural.render import _ray_map, render
from image2sim.dataengine.procedural.scene import ProceduralScene, generate_scene, seed_streams
from image2sim.simulator.conventions import camera_rotation_for_heading
from image2sim.simulator.geometry.cameras import Camera, EquirectCamera, PinholeCamera
from image2sim.simulator.io.records import Frame

__all__ = [
    "Viewpoint",
    "make_camera",
    "sample_viewpoints",
    "geodesic_distance",
    "pose_matrix",
    "jitter_pose",
    "apply_depth_noise",
    "apply_rgb_noise",
    "render_frame",
    "capture_frames",
    "write_scene",
    "scene_seed",
    "synthesize",
]


@dataclass(frozen=True)
class Viewpoint:
    """A camera position (world, metres) and heading (yaw about +Z, radians)."""

    position: tuple[float, float, float]
    yaw: float


def make_camera(cfg: SynthConfig) -> Camera:
    """The capture camera of ``cfg``: an equirectangular panorama or a square-pixel centred pinhole."""
    cap = cfg.capture
    if cap.camera == "equirect":
        return EquirectCamera(cap.height, cap.width)
    f = 0.5 * cap.width / math.tan(math.radians(cap.hfov_deg) / 2)
    return PinholeCamera(f, f, cap.width / 2.0, cap.height / 2.0, cap.height, cap.width)


def pose_matrix(view: Viewpoint) -> np.ndarray:
    """Camera-to-world 4x4 of an upright camera at ``view`` (OpenCV camera, Z-up world)."""
    pose = np.eye(4)
    pose[:3, :3] = camera_rotation_for_heading(view.yaw)
    pose[:3, 3] = view.position
    return pose


def _segment_cells_free(nav: np.ndarray, grid, a: np.ndarray, b: np.ndarray) -> bool:
    """True when every grid cell whose square the segment a-b touches is navigable (exact supercover)."""
    lo = np.minimum(a, b)
    hi = np.maximum(a, b)
    r0, c0 = grid.world_to_cell(lo)
    r1, c1 = grid.world_to_cell(hi)
    if r0 < 0 or c0 < 0 or r1 >= nav.shape[0] or c1 >= nav.shape[1]:
        return False
    rr, cc = np.mgrid[r0 : r1 + 1, c0 : c1 + 1]
    rr, cc = rr.ravel(), cc.ravel()
    res = grid.resolution
    sq_lo = np.stack((grid.origin[0] + cc * res, grid.origin[1] + rr * res), axis=1) - 1e-9
    sq_hi = sq_lo + res + 2e-9
    # Liang-Barsky clip of the segment against every square.
    d = b - a
    t0 = np.zeros(len(rr))
    t1 = np.ones(len(rr))
    for k in range(2):
        if abs(d[k]) < 1e-15:
            inside = (a[k] >= sq_lo[:, k]) & (a[k] <= sq_hi[:, k])
            t1 = np.where(inside, t1, -1.0)
            continue
        ta = (sq_lo[:, k] - a[k]) / d[k]
        tb = (sq_hi[:, k] - a[k]) / d[k]
        t0 = np.maximum(t0, np.minimum(ta, tb))
        t1 = np.minimum(t1, np.maximum(ta, tb))
    touched = t0 <= t1
    return bool(nav[rr[touched], cc[touched]].all())


def _line_of_sight(nav: np.ndarray, grid, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For segments a (2,) -> b (K, 2): True where the segment only crosses navigable cells."""
    return np.array([_segment_cells_free(nav, grid, a, bk) for bk in b], dtype=bool)


def geodesic_distance(nav: np.ndarray, start: tuple[int, int]) -> np.ndarray:
    """Steps (4-connected) from cell ``start`` to every navigable cell (inf where unreachable)."""
    dist = np.full(nav.shape, np.inf)
    if not nav[start]:
        return dist
    frontier = np.zeros(nav.shape, dtype=bool)
    frontier[start] = True
    seen = frontier.copy()
    step = 0
    while frontier.any():
        dist[frontier] = step
        grow = np.zeros_like(frontier)
        grow[1:] |= frontier[:-1]
        grow[:-1] |= frontier[1:]
        grow[:, 1:] |= frontier[:, :-1]
        grow[:, :-1] |= frontier[:, 1:]
        frontier = grow & nav & ~seen
        seen |= frontier
        step += 1
    return dist


def _room_anchor(scene: ProceduralScene, room: int, cells: np.ndarray) -> tuple[int, int]:
    """The navigable cell nearest to a room's centre (inside that room when possible)."""
    r = scene.layout.rooms[room]
    centre = np.array([0.5 * (r.x0 + r.x1), 0.5 * (r.y0 + r.y1)])
    in_room = scene.layout.room_at(cells) == room
    pool = cells[in_room] if in_room.any() else cells
    best = pool[int(np.argmin(np.linalg.norm(pool - centre, axis=1)))]
    iy, ix = scene.grid.world_to_cell(best)
    return int(iy), int(ix)


def sample_viewpoints(scene: ProceduralScene, n: int, rng: np.random.Generator) -> list[Viewpoint]:
    """``n`` viewpoints following the spacing rule of the module docstring, touring the rooms.

    The walk spends about ``n / rooms`` views in a room (each step to the free candidate farthest
    from all earlier views), then heads for the nearest unvisited room (each step to the candidate
    with the smallest geodesic distance to that room's centre), so a capture covers the house while
    consecutive views stay close and mutually visible.
    """
    cap = scene.config.capture
    grid = scene.grid
    iy, ix = np.nonzero(grid.navigable)
    if iy.size == 0:
        raise ValueError(f"scene {scene.scene_id}: no navigable cell to place a camera on")
    cells = grid.cell_centers(iy, ix)
    cell_room = scene.layout.room_at(cells)
    eye = float(rng.uniform(cap.eye_height_min, cap.eye_height_max))
    chosen = [cells[int(rng.integers(0, len(cells)))]]
    n_rooms = len(scene.layout.rooms)
    per_room = max(1, n // n_rooms)
    visited = {int(scene.layout.room_at(chosen[0][None])[0])}
    fields: dict[int, np.ndarray] = {}
    target: int | None = None
    local = 1
    for _ in range(1, n):
        prev = chosen[-1]
        if local >= per_room and target is None and len(visited) < n_rooms:
            here = grid.world_to_cell(prev)
            from_here = geodesic_distance(grid.navigable, (int(here[0]), int(here[1])))
            todo = [r for r in range(n_rooms) if r not in visited]
            anchors = {r: _room_anchor(scene, r, cells) for r in todo}
            target = min(todo, key=lambda r: (from_here[anchors[r]], r))
            if target not in fields:
                fields[target] = geodesic_distance(grid.navigable, anchors[target])
        dist = np.linalg.norm(cells - prev, axis=1)
        pick = None
        for lo in (cap.spacing_min, 0.0):
            pool = np.nonzero((dist >= lo) & (dist <= cap.spacing_max) & (dist > 0))[0]
            if pool.size == 0:
                continue
            cand = pool[rng.permutation(pool.size)[:64]]
            visible = cand[_line_of_sight(grid.navigable, grid, prev, cells[cand])]
            if visible.size == 0:
                continue
            if target is not None:
                geo = fields[target][iy[visible], ix[visible]]
                pick_i = visible[int(np.argmin(geo))]
            else:
                spread = np.min(
                    np.linalg.norm(cells[visible][:, None, :] - np.asarray(chosen)[None], axis=2), axis=1
                )
                pick_i = visible[int(np.argmax(spread))]
            pick = cells[pick_i]
            room = int(cell_room[pick_i])
            if target is not None and room == target:
                target, local = None, 0
            if room not in visited:
                visited.add(room)
            break
        local += 1
        chosen.append(prev if pick is None else pick)
    if cap.yaw_step_max_deg >= 180.0:
        yaws = [float(rng.uniform(-math.pi, math.pi)) for _ in chosen]
    else:  # a walking camera: each heading a bounded random turn from the previous one
        step = math.radians(cap.yaw_step_max_deg)
        yaws = [float(rng.uniform(-math.pi, math.pi))]
        for _ in chosen[1:]:
            yaws.append(float((yaws[-1] + rng.uniform(-step, step) + math.pi) % (2 * math.pi) - math.pi))
    return [Viewpoint((float(p[0]), float(p[1]), eye), yaw) for p, yaw in zip(chosen, yaws, strict=True)]


def _rotation_from_axis_angle(v: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(v))
    if angle < 1e-15:
        return np.eye(3)
    k = v / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


def jitter_pose(pose: np.ndarray, noise: NoiseConfig, rng: np.random.Generator) -> np.ndarray:
    """Pose with Gaussian translation and rotation error (the stored pose of a noisy capture)."""
    out = np.array(pose, dtype=np.float64, copy=True)
    dt = rng.normal(0.0, 1.0, 3) * noise.pose_jitter_translation
    dr = rng.normal(0.0, 1.0, 3) * math.radians(noise.pose_jitter_rotation_deg)
    if noise.pose_jitter_translation == 0 and noise.pose_jitter_rotation_deg == 0:
        return out
    out[:3, :3] = _rotation_from_axis_angle(dr) @ out[:3, :3]
    out[:3, 3] += dt
    return out


def apply_depth_noise(
    depth: np.ndarray, camera: Camera, noise: NoiseConfig, rng: np.random.Generator
) -> np.ndarray:
    """Noisy float32 depth following ``noise`` (0 stays 0 = invalid)."""
    h, w = depth.shape
    d = depth.astype(np.float64)
    valid = d > 0
    rel = rng.normal(0.0, 1.0, d.shape)
    ab = rng.normal(0.0, 1.0, d.shape)
    d = d * (1.0 + noise.depth_noise_relative * rel) + noise.depth_noise_absolute * ab
    valid &= d > 1e-3
    if noise.max_range > 0:
        valid &= depth <= noise.max_range
    if noise.lidar_row_step > 0:
        rays = _ray_map(camera).reshape(h, w, 3)
        elevation = np.degrees(np.arcsin(np.clip(-rays[..., 1], -1.0, 1.0)))
        rows = (np.arange(h) % noise.lidar_row_step == 0)[:, None]
        valid &= (
            rows & (elevation >= noise.lidar_elevation_min_deg) & (elevation <= noise.lidar_elevation_max_deg)
        )
    n_holes = int(rng.integers(noise.holes_min, noise.holes_max + 1)) if noise.holes_max > 0 else 0
    if n_holes:
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
        for _ in range(n_holes):
            cu, cv = rng.uniform(0, w), rng.uniform(0, h)
            a, b = rng.uniform(noise.hole_radius_min, noise.hole_radius_max, 2) * w
            du = np.abs(uu - cu)
            if isinstance(camera, EquirectCamera):
                du = np.minimum(du, w - du)  # holes wrap across the panorama seam
            valid &= (du / a) ** 2 + ((vv - cv) / b) ** 2 > 1.0
    return np.where(valid, d, 0.0).astype(np.float32)


def apply_rgb_noise(rgb: np.ndarray, noise: NoiseConfig, rng: np.random.Generator) -> np.ndarray:
    """Colour with additive Gaussian noise (8-bit levels), rounded and clipped."""
    if noise.rgb_noise_std <= 0:
        return rgb
    noisy = rgb.astype(np.float64) + rng.normal(0.0, noise.rgb_noise_std, rgb.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def render_frame(
    scene: ProceduralScene,
    camera: Camera,
    view: Viewpoint,
    noise: NoiseConfig,
    rng: np.random.Generator,
    frame_id: str,
) -> tuple[Frame, np.ndarray]:
    """Render one view, degrade it by ``noise``; returns the Frame (stored pose) and the exact pose."""
    pose = pose_matrix(view)
    out = render(scene, camera, pose)
    depth = apply_depth_noise(out["depth"], camera, noise, rng)
    rgb = apply_rgb_noise(out["rgb"], noise, rng)
    stored = jitter_pose(pose, noise, rng)
    frame = Frame(
        rgb=rgb,
        depth=depth,
        camera=camera,
        cam_to_world=stored,
        semantics=out["semantics"],
        instances=out["instances"],
        frame_id=frame_id,
    )
    return frame, pose


class _LazyFrames:
    """Sized iterable that renders frames on demand (so write_capture's progress bar tracks rendering)."""

    def __init__(
        self,
        scene: ProceduralScene,
        camera: Camera,
        views: list[Viewpoint],
        noise: NoiseConfig,
        rng: np.random.Generator,
    ):
        self.scene, self.camera, self.views, self.noise, self.rng = scene, camera, views, noise, rng
        self.true_poses: dict[str, list] = {}

    def __len__(self) -> int:
        return len(self.views)

    def __iter__(self) -> Iterator[Frame]:
        for i, view in enumerate(self.views):
            frame_id = f"{i:05d}"
            frame, pose = render_frame(self.scene, self.camera, view, self.noise, self.rng, frame_id)
            self.true_poses[frame_id] = pose.tolist()
            yield frame


def capture_frames(scene: ProceduralScene) -> tuple[list[Frame], list[np.ndarray]]:
    """Render the scene's whole capture in memory: frames (noisy per the config's tier) and exact poses."""
    camera, views, noise, rng = _capture_plan(scene)
    lazy = _LazyFrames(scene, camera, views, noise, rng)
    frames = list(lazy)
    return frames, [np.asarray(lazy.true_poses[f.frame_id]) for f in frames]


def _capture_plan(scene: ProceduralScene):
    cfg = scene.config
    noise = cfg.noise_config()
    streams = seed_streams(scene.seed)
    n = max(1, int(round(cfg.capture.views * noise.view_fraction)))
    views = sample_viewpoints(scene, n, streams["capture"])
    return make_camera(cfg), views, noise, streams["noise"]


def write_scene(
    scene: ProceduralScene, out_dir: str | Path, *, overwrite: bool = False, progress: bool = False
) -> Path:
    """Render and write ``scene`` as a canonical capture with a ``gt/`` folder (atomically)."""
    from image2sim.simulator.io.canonical import write_capture

    camera, views, noise, rng = _capture_plan(scene)
    lazy = _LazyFrames(scene, camera, views, noise, rng)
    cfg = scene.config
    metadata = {
        "generator": "image2sim.dataengine.procedural",
        "seed": int(scene.seed),
        "noise": cfg.noise,
        "noise_parameters": cfg.noise_config().__dict__,
        "config": cfg.to_dict(),
        "eye_height": views[0].position[2],
        "rooms": len(scene.layout.rooms),
        "objects": len(scene.objects),
    }

    def extra(tmp: Path) -> None:
        write_gt(
            scene,
            tmp / "gt",
            extra={
                "poses.json": {
                    "note": "exact camera-to-world poses (OpenCV camera, Z-up world); "
                    "frames/ hold the stored, possibly jittered ones",
                    "poses": lazy.true_poses,
                },
            },
        )

    return write_capture(
        out_dir,
        lazy,
        scene_id=scene.scene_id,
        metadata=metadata,
        extra=extra,
        overwrite=overwrite,
        progress=progress,
    )


def scene_seed(base_seed: int, index: int) -> int:
    """Seed of scene ``index`` of a run with ``base_seed`` (independent streams per scene)."""
    return int(np.random.SeedSequence([int(base_seed), int(index)]).generate_state(1, dtype=np.uint32)[0])


def synthesize(
    config: SynthConfig,
    out_dir: str | Path,
    *,
    scenes: int,
    seed: int,
    overwrite: bool = False,
    progress: bool = True,
    workers: int = 1,
) -> list[Path]:
    """Generate ``scenes`` scenes into ``out_dir/scene_XXX`` (each independent of the others).

    ``workers`` > 1 generates them in that many spawned processes: scene ``i`` depends only on
    ``(config, seed, i)``, so the output is the same as with one worker.
    """
    out_dir = Path(out_dir)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if workers == 1 or scenes == 1:
        return [_synthesize_one(config, out_dir, seed, i, overwrite, progress) for i in range(scenes)]
    from image2sim.simulator.lifetime import spawn_pool

    with spawn_pool(min(workers, scenes)) as pool:
        futures = [
            pool.submit(_synthesize_one, config, out_dir, seed, i, overwrite, False) for i in range(scenes)
        ]
        return [f.result() for f in futures]


def _synthesize_one(
    config: SynthConfig, out_dir: Path, seed: int, index: int, overwrite: bool, progress: bool
) -> Path:
    """Scene ``index`` of the base ``seed`` (a top-level function, so a worker process can run it)."""
    scene = generate_scene(config, scene_seed(seed, index))
    return write_scene(scene, out_dir / f"scene_{index:03d}", overwrite=overwrite, progress=progress)
