"""A visible goal marker: an upright cylinder ("pillar") composited into any render function's output.

Point-goal tasks give the goal as metres relative to the start pose, which a policy must then track by
path integration of its own actions. A marker standing on the goal turns the task into visual homing
(the goal-image / beacon variants of point-goal navigation): the policy can see where to go. The
marker is purely visual (agents walk through it) and is exact: each pixel's ray is intersected with
the cylinder analytically and the result is depth-tested against the scene's depth, so the marker is
occluded by walls and furniture like a real object.

:func:`composite_marker` is the pure function; :class:`MarkedRenderFn` wraps a render function and
holds the current goal (set through :meth:`image2sim.simulator.sim.NeuralSimulator.set_goal`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from image2sim.simulator.config import ConfigError
from image2sim.simulator.geometry.cameras import Camera, PinholeCamera

__all__ = ["GoalMarker", "MarkedRenderFn", "composite_marker", "ray_cylinder_distance"]


@dataclass
class GoalMarker:
    """Shape and colour of the goal pillar."""

    radius: float = 0.15
    """Cylinder radius in metres."""
    height: float = 1.6
    """Height above the goal's floor point in metres (above a typical eye height, so its top cap is
    never seen from a standing agent and is not drawn)."""
    colour: list[float] = field(default_factory=lambda: [1.0, 0.0, 1.0])
    """Linear RGB in [0, 1] (magenta: a colour the procedural scenes do not use)."""
    name: str = "magenta pillar"
    """How instructions refer to the marker."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise ConfigError(f"goal marker radius must be a positive number, got {self.radius!r}")
        if not (math.isfinite(self.height) and self.height > 0):
            raise ConfigError(f"goal marker height must be a positive number, got {self.height!r}")
        c = list(self.colour)
        if len(c) != 3 or not all(isinstance(v, (int, float)) and 0.0 <= v <= 1.0 for v in c):
            raise ConfigError(f"goal marker colour must be three numbers in [0, 1], got {self.colour!r}")
        self.colour = [float(v) for v in c]


def ray_cylinder_distance(
    origin: np.ndarray, dirs: np.ndarray, base: np.ndarray, radius: float, height: float
) -> tuple[np.ndarray, np.ndarray]:
    """Distance along unit rays to an upright (world +Z) cylinder's side surface, and the surface normal.

    ``origin`` (3,), ``dirs`` (..., 3) unit world directions, ``base`` (3,) the centre of the cylinder's
    bottom. Returns ``(s, normal)``: ``s`` (...) the nearest positive hit distance whose height lies in
    ``[base_z, base_z + height]`` (``inf`` where there is none; a ray starting inside the cylinder hits
    the far wall), ``normal`` (..., 3) the outward horizontal unit normal at the hit (zero on misses).
    """
    o = np.asarray(origin, np.float64)
    d = np.asarray(dirs, np.float64)
    b = np.asarray(base, np.float64)
    ox, oy = o[0] - b[0], o[1] - b[1]
    dx, dy = d[..., 0], d[..., 1]
    a = dx * dx + dy * dy
    half_b = ox * dx + oy * dy
    c = ox * ox + oy * oy - radius * radius
    disc = half_b * half_b - a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        root = np.sqrt(np.maximum(disc, 0.0))
        # Vertical rays (a == 0) never hit the side surface.
        ok = (disc >= 0) & (a > 1e-12)
        s_near = np.where(ok, (-half_b - root) / a, np.inf)
        s_far = np.where(ok, (-half_b + root) / a, np.inf)
    s = np.full(d.shape[:-1], np.inf)
    for cand in (s_far, s_near):  # the near root overrides the far one where both are valid
        z = o[2] + cand * d[..., 2]
        valid = np.isfinite(cand) & (cand > 1e-6) & (z >= b[2]) & (z <= b[2] + height)
        s = np.where(valid, cand, s)
    hit = np.isfinite(s)
    normal = np.zeros(d.shape)
    s_hit = np.where(hit, s, 0.0)
    nx, ny = ox + s_hit * dx, oy + s_hit * dy
    norm = np.maximum(np.hypot(nx, ny), 1e-12)
    normal[..., 0] = np.where(hit, nx / norm, 0.0)
    normal[..., 1] = np.where(hit, ny / norm, 0.0)
    return s, normal


def composite_marker(
    out: dict, camera: Camera, cam_to_world: np.ndarray, base: np.ndarray, marker: GoalMarker
) -> dict:
    """``out`` (a render function's ``{"rgb": (H, W, 3) [0, 1], "depth": (H, W)}``) with the marker
    drawn where it is nearer than the scene (depth 0 = no scene surface, so the marker wins there).

    Depth follows the camera's convention (pinhole: z; panorama: range). Shading is Lambertian
    against the viewing ray (0.55 + 0.45·|n·d|) so the pillar reads as round. Returns a new dict;
    other keys are passed through.
    """
    pose = np.asarray(cam_to_world, np.float64)
    rays = camera.ray_map().double().permute(1, 2, 0).numpy()  # (H, W, 3) unit, camera frame
    world_dirs = rays @ pose[:3, :3].T
    s, normal = ray_cylinder_distance(pose[:3, 3], world_dirs, base, marker.radius, marker.height)
    depth_marker = s * rays[..., 2] if isinstance(camera, PinholeCamera) else s
    rgb = np.asarray(out["rgb"], np.float32)
    depth = np.asarray(out["depth"], np.float32)
    if rgb.shape[:2] != s.shape or depth.shape != s.shape:
        raise ValueError(
            f"composite_marker: render output rgb {rgb.shape} / depth {depth.shape} does not match the "
            f"camera's {s.shape}"
        )
    scene = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf)
    mask = np.isfinite(depth_marker) & (depth_marker < scene)
    shade = 0.55 + 0.45 * np.abs(np.sum(normal * world_dirs, axis=-1))
    colour = np.clip(shade[..., None] * np.asarray(marker.colour, np.float64), 0.0, 1.0)
    res = dict(out)
    res["rgb"] = np.where(mask[..., None], colour, rgb).astype(np.float32)
    res["depth"] = np.where(mask, depth_marker, depth).astype(np.float32)
    return res


class MarkedRenderFn:
    """A render function that draws :class:`GoalMarker` at the current goal on top of ``render_fn``.

    With no goal set it renders exactly what ``render_fn`` does. ``panoramic`` is passed through.
    """

    def __init__(self, render_fn, marker: GoalMarker) -> None:
        self.render_fn = render_fn
        self.marker = marker
        self.goal: np.ndarray | None = None
        self.panoramic = bool(getattr(render_fn, "panoramic", False))

    def set_goal(self, goal_world: np.ndarray | None) -> None:
        """The world-frame floor point (3,) the marker stands on, or ``None`` to hide it."""
        if goal_world is None:
            self.goal = None
            return
        g = np.asarray(goal_world, np.float64).reshape(-1)
        if g.shape != (3,) or not np.all(np.isfinite(g)):
            raise ValueError(f"goal marker position must be a finite world point (3,), got {goal_world!r}")
        self.goal = g

    def __call__(self, camera: Camera, cam_to_world: np.ndarray) -> dict:
        out = self.render_fn(camera, cam_to_world)
        if self.goal is None:
            return out
        return composite_marker(out, camera, cam_to_world, self.goal, self.marker)
