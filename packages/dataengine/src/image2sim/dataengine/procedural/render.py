"""``render(scene, camera, cam_to_world) -> dict(rgb, depth, semantics, instances)`` by ray casting.

Rays come from the camera models of :mod:`image2sim.simulator.geometry.cameras` (unit directions
at pixel centres). Depth is the Euclidean range for panoramas and the z-depth for pinhole cameras,
0 where a ray hits nothing. Shading is view-independent (ambient + the hit point's room light,
Lambertian, + a weak directional fill, no shadows), so a surface point has the same colour in every
view and multi-view photometry is consistent.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from image2sim.dataengine.procedural.scene import WALL_MATERIAL, ProceduralScene
from image2sim.dataengine.procedural.textures import detail_factor, evaluate_albedo
from image2sim.simulator.geometry.cameras import Camera, EquirectCamera

__all__ = ["render", "camera_rays", "AMBIENT", "FILL_DIRECTION", "FILL_STRENGTH"]

AMBIENT = 0.45
"""Ambient light level (fraction of albedo)."""
FILL_DIRECTION = np.array([0.35, 0.55, 0.76]) / np.linalg.norm([0.35, 0.55, 0.76])
"""Direction *towards* the weak directional fill light (world)."""
FILL_STRENGTH = 0.18
"""Strength of the directional fill."""
LIGHT_FALLOFF = 3.5
"""Point-light distance (metres) at which intensity halves: I / (1 + (r / falloff)^2)."""
_ROOM_PROBE = 0.02
"""Offset along the face normal used to find the room a surface point faces (metres)."""


@functools.lru_cache(maxsize=8)
def _ray_map(camera: Camera) -> np.ndarray:
    """Camera-frame unit rays (H*W, 3) float64, cached per camera (cameras are frozen dataclasses)."""
    rays = camera.ray_map(torch.float64).permute(1, 2, 0).reshape(-1, 3).numpy().copy()
    rays.setflags(write=False)
    return rays


def camera_rays(camera: Camera, cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World origin (3,), unit world directions (H*W, 3) and camera-frame directions (H*W, 3)."""
    pose = np.asarray(cam_to_world, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"cam_to_world must be a finite 4x4 matrix, got shape {pose.shape}")
    rays_cam = _ray_map(camera)
    rot = pose[:3, :3]
    # Elementwise (no BLAS): faster for (N, 3) x (3, 3) and bit-identical on every machine.
    dirs = rays_cam[:, 0:1] * rot[:, 0] + rays_cam[:, 1:2] * rot[:, 1] + rays_cam[:, 2:3] * rot[:, 2]
    return pose[:3, 3].copy(), dirs, rays_cam


def shade(scene: ProceduralScene, points: np.ndarray, box: np.ndarray, face: np.ndarray) -> np.ndarray:
    """Linear colour (N, 3) in [0, 1] of hit ``points`` on ``box`` faces ``face``."""
    axis = face // 2
    sign = np.where(face % 2 == 1, 1.0, -1.0)
    normal = np.zeros_like(points)
    normal[np.arange(points.shape[0]), axis] = sign
    probe = points + _ROOM_PROBE * normal
    room = scene.layout.room_at(probe[:, :2])
    room_c = np.clip(room, 0, None)
    material = scene.box_material[box].copy()
    walls = material == WALL_MATERIAL
    material[walls] = scene.room_wall_material[room_c[walls]]
    table = scene.materials.arrays()
    albedo = evaluate_albedo(points, axis, material, table)
    amount = scene.config.surface_detail
    if amount > 0:
        albedo = albedo * detail_factor(points, axis, table["seed"][material], amount)[:, None]
    to_light = scene.light_position[room_c] - points
    dist2 = (to_light * to_light).sum(axis=1)
    # The normal is an axis vector: n . l is the signed component of l along that axis.
    n_dot_l = sign * to_light[np.arange(points.shape[0]), axis]
    lam = np.clip(n_dot_l / np.sqrt(np.maximum(dist2, 1e-12)), 0.0, None)
    point = lam / (1.0 + dist2 / LIGHT_FALLOFF**2)
    fill = FILL_STRENGTH * np.clip(sign * FILL_DIRECTION[axis], 0.0, None)
    light = AMBIENT + point[:, None] * scene.light_color[room_c] + fill[:, None]
    light[room < 0] = AMBIENT
    return np.clip(albedo * light, 0.0, 1.0)


def render(
    scene: ProceduralScene, camera: Camera, cam_to_world: np.ndarray, *, caster: str | None = None
) -> dict:
    """Render RGB (H, W, 3) uint8, depth (H, W) float32, semantics and instances (H, W) int32.

    Also returns ``box`` (index of the box each ray hit, -1 for none) and ``face``.
    """
    h, w = int(camera.height), int(camera.width)
    origin, dirs, rays_cam = camera_rays(camera, cam_to_world)
    t, box, face = scene.caster(caster).cast(origin, dirs, (h, w))
    hit = box >= 0
    depth = np.zeros(h * w, dtype=np.float64)
    if isinstance(camera, EquirectCamera):
        depth[hit] = t[hit]
    else:
        depth[hit] = t[hit] * rays_cam[hit, 2]
    rgb = np.zeros((h * w, 3), dtype=np.float64)
    points = origin + t[hit, None] * dirs[hit]
    rgb[hit] = shade(scene, points, box[hit], face[hit])
    semantics = np.zeros(h * w, dtype=np.int32)
    instances = np.zeros(h * w, dtype=np.int32)
    semantics[hit] = scene.box_category[box[hit]]
    instances[hit] = scene.box_instance[box[hit]]
    return {
        "rgb": np.rint(rgb * 255.0).astype(np.uint8).reshape(h, w, 3),
        "depth": depth.astype(np.float32).reshape(h, w),
        "semantics": semantics.reshape(h, w),
        "instances": instances.reshape(h, w),
        "box": box.reshape(h, w),
        "face": face.reshape(h, w),
    }
