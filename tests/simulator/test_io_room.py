"""An analytic box room and writers that render it in each source capture format's OWN conventions.

The readers are then checked against ground truth: every back-projected pixel of every format
must land on the room's surface, with the colour of the face it hit. The writers here follow each
format's documentation literally (pixel mapping, pose convention, depth units), independently of
the reader code. The tests in this file check the room renderer itself.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from image2sim.simulator.conventions import Y_DOWN_TO_Z_UP_WORLD
from scipy.spatial.transform import Rotation

ROOM_LO = np.array([-2.0, -1.5, 0.0])
ROOM_HI = np.array([3.0, 2.5, 2.7])
# One colour per face: -x, +x, -y, +y, floor, ceiling.
FACE_COLOURS = np.array(
    [[220, 40, 40], [40, 200, 40], [40, 40, 220], [230, 200, 30], [150, 150, 150], [250, 250, 250]], np.uint8
)


def box_range(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance along unit ``dirs`` from ``origins`` (inside the room) to the first wall."""
    d = np.where(np.abs(dirs) < 1e-12, 1e-12, dirs)
    t_hi = (ROOM_HI - origins) / d
    t_lo = (ROOM_LO - origins) / d
    return np.min(np.where(d > 0, t_hi, t_lo), axis=-1)


def face_of(points: np.ndarray) -> np.ndarray:
    """Index (0..5) of the room face nearest to each point."""
    gaps = np.stack(
        [
            points[..., 0] - ROOM_LO[0],
            ROOM_HI[0] - points[..., 0],
            points[..., 1] - ROOM_LO[1],
            ROOM_HI[1] - points[..., 1],
            points[..., 2] - ROOM_LO[2],
            ROOM_HI[2] - points[..., 2],
        ],
        axis=-1,
    )
    return np.argmin(np.abs(gaps), axis=-1)


def surface_distance(points: np.ndarray) -> np.ndarray:
    """Distance of each point (inside or near the room) to the room's boundary surface."""
    gaps = np.concatenate([points - ROOM_LO, ROOM_HI - points], axis=-1)
    inside = np.all(gaps >= 0, axis=-1)
    inner = np.min(np.abs(gaps), axis=-1)
    outer = np.linalg.norm(np.maximum(0, np.maximum(ROOM_LO - points, points - ROOM_HI)), axis=-1)
    return np.where(inside, inner, outer)


def render(origin: np.ndarray, world_dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(range, colour) of unit world rays (..., 3) from ``origin`` (our Z-up world)."""
    rng = box_range(origin, world_dirs)
    colour = FACE_COLOURS[face_of(origin + rng[..., None] * world_dirs)]
    return rng, colour


def camera_positions(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.uniform(ROOM_LO + 0.6, ROOM_HI - 0.6) for _ in range(n)]


def _write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image[:, :, ::-1] if image.ndim == 3 else image)


# --- hm3d_360: OpenGL camera, theta = 2 pi (u + 0.5)/W, phi = pi (v + 0.5)/H, range mm, quat xyzw --


def write_hm3d_fixture(root: Path, n: int = 3, height: int = 32, width: int = 64, seed: int = 0) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    vv, uu = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    theta = 2 * np.pi * (uu + 0.5) / width
    phi = np.pi * (vv + 0.5) / height
    d_gl = np.stack((-np.sin(phi) * np.sin(theta), np.cos(phi), np.sin(phi) * np.cos(theta)), axis=-1)
    for i, pos in enumerate(camera_positions(n, seed)):
        rot = Rotation.random(random_state=seed + i)  # arbitrary orientations catch axis mix-ups
        rng, colour = render(pos, d_gl @ rot.as_matrix().T)
        _write_png(root / f"{i:05d}_rgb.png", colour)
        _write_png(root / f"{i:05d}_depth.png", np.rint(rng * 1000).astype(np.uint16))
        q = rot.as_quat()  # x, y, z, w
        (root / f"{i:05d}_pose.txt").write_text(" ".join(f"{x:.9f}" for x in [*pos, *q]) + "\n")
    return root


# --- realsee: Y-down world, camera x right y down z forward, samples on pixel centres:
#     lon = ((u + .5)/W - .5) 2pi, lat = ((v + .5)/H - .5) pi (u, v = pixel indices; what real RealSee3D
#     data measures, see docs/data-formats.md). convention="index" writes the other mapping,
#     lon = (u/W - .5) 2pi, lat = (v/H - .5) pi, for the reader's half_pixel="resample" mode.

REALSEE_CONVENTIONS = ("centres", "index")


def realsee_directions(height: int, width: int, convention: str = "centres") -> np.ndarray:
    """Unit camera-frame directions (H, W, 3) of every Realsee pixel, written from the format's
    description (independently of the reader)."""
    if convention not in REALSEE_CONVENTIONS:
        raise ValueError(f"convention must be one of {REALSEE_CONVENTIONS}, got {convention!r}")
    offset = 0.5 if convention == "centres" else 0.0
    vv, uu = np.meshgrid(np.arange(height) + offset, np.arange(width) + offset, indexing="ij")
    lon = (uu / width - 0.5) * 2 * np.pi
    lat = (vv / height - 0.5) * np.pi
    return np.stack((np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)), axis=-1)


def realsee_viewpoint(pos: np.ndarray, rot_r: np.ndarray) -> np.ndarray:
    """Realsee extrinsics (camera-to-world in its Y-down world) of a camera at ``pos`` (our world)
    with rotation ``rot_r`` (its world)."""
    ext = np.eye(4)
    ext[:3, :3] = rot_r
    ext[:3, 3] = Y_DOWN_TO_Z_UP_WORLD.T @ pos  # camera centre in their world
    return ext


def write_realsee_fixture(
    root: Path,
    n: int = 3,
    height: int = 32,
    width: int = 64,
    rgb_scale: float = 1,
    seed: int = 0,
    scale: float = 4000.0,
    convention: str = "centres",
    viewpoints: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> Path:
    """``n`` viewpoints of the box room (or the given ``(position in our world, rotation in the
    Realsee world)`` pairs). Colour is rendered at ``rgb_scale`` times the depth size (rounded)."""
    root.mkdir(parents=True, exist_ok=True)
    M = Y_DOWN_TO_Z_UP_WORLD  # ours = M @ theirs
    if viewpoints is None:
        viewpoints = [
            (pos, Rotation.random(random_state=100 + seed + i).as_matrix())  # rotation in the Y-down world
            for i, pos in enumerate(camera_positions(n, seed))
        ]
    ch, cw = int(round(height * rgb_scale)), int(round(width * rgb_scale))
    ids = []
    for i, (pos, rot_r) in enumerate(viewpoints):
        vid = f"vp{i:02d}"
        ids.append(vid)
        rng, _ = render(pos, realsee_directions(height, width, convention) @ (M @ rot_r).T)
        _, colour = render(pos, realsee_directions(ch, cw, convention) @ (M @ rot_r).T)
        vp = root / "viewpoints" / vid
        _write_png(vp / "depth_image.png", np.rint(rng * scale).astype(np.uint16))
        vp.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(vp / "panoImage_1600.jpg"), colour[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 98])
        np.savetxt(vp / "extrinsics.txt", realsee_viewpoint(pos, rot_r))
        (vp / "depth_scale.txt").write_text(f"{scale}\n")
    (root / "viewpoints.txt").write_text("\n".join(ids) + "\n")
    return root


# --- pinhole_dir (ScanNet export): OpenCV K with integer pixel centres, z-depth mm, 4x4 poses -------


def write_pinhole_fixture(
    root: Path,
    n: int = 3,
    depth_hw: tuple[int, int] = (24, 32),
    colour_hw: tuple[int, int] = (48, 64),
    seed: int = 0,
    write_colour_intrinsics: bool = True,
) -> Path:
    dh, dw = depth_hw
    ch, cw = colour_hw
    k_d = np.array([[22.0, 0, 15.2, 0], [0, 21.0, 11.7, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    if write_colour_intrinsics:
        k_c = np.array([[47.0, 0, 31.0, 0], [0, 45.0, 22.8, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    else:
        sx, sy = cw / dw, ch / dh  # exporter resized colour: scale about pixel corners, not centres
        k_c = k_d.copy()
        k_c[0, 0], k_c[1, 1] = k_d[0, 0] * sx, k_d[1, 1] * sy
        k_c[0, 2], k_c[1, 2] = (k_d[0, 2] + 0.5) * sx - 0.5, (k_d[1, 2] + 0.5) * sy - 0.5
    (root / "intrinsic").mkdir(parents=True, exist_ok=True)
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", k_d)
    if write_colour_intrinsics:
        np.savetxt(root / "intrinsic" / "intrinsic_color.txt", k_c)

    def rays(k: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        vv, uu = np.meshgrid(np.arange(h, dtype=float), np.arange(w, dtype=float), indexing="ij")
        d = np.stack(((uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1], np.ones_like(uu)), axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True), d

    for i, pos in enumerate(camera_positions(n, seed)):
        rot = Rotation.random(random_state=200 + seed + i).as_matrix()
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rot, pos
        unit, _ = rays(k_d, dh, dw)
        rng, _ = render(pos, unit @ rot.T)
        z = rng * unit[..., 2]
        unit_c, _ = rays(k_c, ch, cw)
        _, colour = render(pos, unit_c @ rot.T)
        _write_png(root / "depth" / f"{i}.png", np.rint(z * 1000).astype(np.uint16))
        (root / "color").mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(
            str(root / "color" / f"{i}.jpg"), colour[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 98]
        )
        (root / "pose").mkdir(parents=True, exist_ok=True)
        np.savetxt(root / "pose" / f"{i}.txt", pose)
    return root


# --- checks of the room itself ---------------------------------------------------------------


def test_box_range_hits_the_surface() -> None:
    rng = np.random.default_rng(1)
    origin = np.array([0.3, 0.2, 1.1])
    dirs = rng.normal(size=(1000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hits = origin + box_range(origin, dirs)[:, None] * dirs
    assert np.max(surface_distance(hits)) < 1e-9
    # Axis rays have closed-form ranges.
    axes = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0], [0, 0, -1.0]])
    np.testing.assert_allclose(box_range(origin, axes), [2.7, 2.3, 1.6, 1.1])
    assert face_of(origin + box_range(origin, axes)[:, None] * axes).tolist() == [1, 0, 5, 4]


def test_surface_distance_inside_and_outside() -> None:
    pts = np.array([[0.0, 0.0, 1.0], [3.5, 0.0, 1.0], [0.0, 0.0, 2.6]])
    np.testing.assert_allclose(surface_distance(pts), [1.0, 0.5, 0.1])
