"""Shared pieces of the lifting tests: small RGB-only procedural houses and a ground-truth depth stub.

Houses come from ``image2sim data synth`` with a walking camera (bounded turns between views, so
consecutive pinhole views overlap) and fine surface grain (SIFT finds almost nothing on the smooth
procedural textures alone; docs/procedural.md). Only the RGB goes into the lifting pipeline; the
exact poses (``gt/poses.json``) and depth score it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

WALK = {"surface_detail": 0.3, "capture": {"yaw_step_max_deg": 25.0, "spacing_min": 0.25, "spacing_max": 0.5}}
PANO_WALK = {
    "surface_detail": 0.3,
    "capture": {"yaw_step_max_deg": 25.0, "spacing_min": 0.4, "spacing_max": 0.8},
}


def synth_house(
    out: Path, *, camera: str, views: int, height: int, width: int, config: dict, seed: int = 0
) -> Path:
    """One tiny procedural house written by ``image2sim data synth``; returns the scene folder."""
    from image2sim.dataengine.cli import app
    from typer.testing import CliRunner

    cfg = out / "synth.json"
    out.mkdir(parents=True, exist_ok=True)
    cfg.write_text(json.dumps(config), encoding="utf-8")
    args = ["synth", "--preset", "tiny", "--scenes", "1", "--views", str(views), "--camera", camera]
    args += ["--noise", "none", "--height", str(height), "--width", str(width), "--seed", str(seed)]
    args += ["--config", str(cfg), "--out", str(out / "synth")]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    return out / "synth" / "scene_000"


def rgb_folder(scene: Path, dest: Path, ids: list[str] | None = None) -> Path:
    """The scene's colour images alone, as ``dest/<id>.png`` (no depth, no poses)."""
    dest.mkdir(parents=True, exist_ok=True)
    for path in sorted((scene / "frames").glob("*_rgb.png")):
        fid = path.name[: -len("_rgb.png")]
        if ids is None or fid in ids:
            shutil.copy(path, dest / f"{fid}.png")
    return dest


def gt_poses(scene: Path) -> dict[str, np.ndarray]:
    doc = json.loads((scene / "gt" / "poses.json").read_text(encoding="utf-8"))
    return {k: np.asarray(v, dtype=np.float64) for k, v in doc["poses"].items()}


def eye_height(scene: Path) -> float:
    return float(json.loads((scene / "manifest.json").read_text(encoding="utf-8"))["metadata"]["eye_height"])


def truth_depth_fn(scene: Path):
    """A depth source returning the exact depth of each view, in the reconstruction's units.

    Views are matched to the house's frames (and cube faces) by their pixels, the reconstruction is
    aligned to the exact poses by Umeyama on the view centres, and exact metric depth is divided by
    that scale: what a perfect depth estimator fitted to the sparse points would give.
    """
    import torch
    from image2sim.simulator.geometry.reproject import equirect_to_cubemap
    from image2sim.simulator.io import open_capture
    from image2sim.simulator.lift.scale import umeyama
    from image2sim.simulator.lift.sfm import _cube_faces, face_rotations
    from image2sim.simulator.lift.types import DepthEstimate

    cap = open_capture(scene)
    poses = gt_poses(scene)
    truth: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}  # image bytes -> (z-depth, cam_to_world)
    rot = face_rotations()
    for frame in cap:
        pose = poses[frame.frame_id]
        if cap.camera.model == "pinhole":
            truth[frame.rgb.tobytes()] = (frame.depth, pose)
            continue
        from image2sim.simulator.lift.frames import FrameSet

        size = frame.width // 4
        faces = _cube_faces(FrameSet([frame.frame_id], [frame.rgb], scene, True), size)[0]
        rng = torch.from_numpy(frame.depth.astype(np.float64))[None, None]
        face_rng = equirect_to_cubemap(rng, size, mode="nearest")[0, :, 0].numpy()
        u = (np.arange(size) + 0.5 - size / 2) / (size / 2)
        factor = np.sqrt(1 + u[None, :] ** 2 + u[:, None] ** 2)
        for k in range(6):
            face_pose = pose.copy()
            face_pose[:3, :3] = pose[:3, :3] @ rot[k]
            truth[faces[k].tobytes()] = ((face_rng[k] / factor).astype(np.float32), face_pose)

    def estimate(views, *, source="mvs", model_dir=None, sparse=None, progress=True, **kw):
        matched = [truth[v.image.tobytes()] for v in views]
        est_c = np.stack([v.cam_to_world[:3, 3] for v in views])
        true_c = np.stack([m[1][:3, 3] for m in matched])
        s, _, _ = umeyama(est_c, true_c)
        return [
            DepthEstimate(
                depth=(d / s).astype(np.float32), confidence=np.where(d > 0, 0.9, 0.0).astype(np.float32)
            )
            for d, _ in matched
        ]

    return estimate
