"""NeuralSimulator: one reconstructed scene, a batch of kinematic agents, optional rendered observations.

Motion comes from :mod:`image2sim.simulator.navigation` (navigable map, collision world, graph).
Observations are produced by a *render function* ``render_fn(camera, cam_to_world) -> {"rgb": (H, W,
3) float32 in [0, 1], "depth": (H, W) float32}``; :class:`GaussianRenderFn` builds one from a Gaussian
scene through :func:`image2sim.simulator.splatting.splat`; :class:`PixelFlowRenderFn` renders
panoramas as splat -> condition C_p -> one-step (or N-step) pixel flow with deterministic per-pose
noise, and the simulator cuts pinhole / ultra-wide views out of that panorama (the renderer is
panoramic). Any callable with the render-function signature can be injected (tests use analytic
renderers). Positions are map-frame feet positions (see :class:`NavMap`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from image2sim.simulator.conventions import Action, camera_rotation_for_heading
from image2sim.simulator.geometry.cameras import Camera, EquirectCamera, PinholeCamera
from image2sim.simulator.navigation.agent import Agent, CollisionWorld
from image2sim.simulator.navigation.embodiment import ConfigError, _DictMixin
from image2sim.simulator.navigation.graph import NavGraph
from image2sim.simulator.navigation.navmap import NavMap
from image2sim.simulator.navigation.planner import DistanceField, Planner

__all__ = [
    "OBSERVATION_MIN_TRANSMITTANCE",
    "ObservationSpec",
    "GaussianRenderFn",
    "PixelFlowRenderFn",
    "NeuralSimulator",
    "NavEnv",
    "RenderFn",
    "views_from_panorama",
    "load_pixel_flow",
    "gaussian_tensors",
    "gaussian_render_fn",
    "panorama_height_for",
]

RenderFn = Callable[[Camera, np.ndarray], dict]

_GAUSSIAN_FIELDS = ("means", "scales", "quats", "opacities", "colors")
_SPLAT_FIELDS = (*_GAUSSIAN_FIELDS, "features")  # what a render function passes to splat


def _render_device(device):
    """``device`` as a ``torch.device``; a clear error for a device this machine does not have."""
    import torch

    dev = torch.device(device if device is not None else "cpu")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"render device {str(dev)!r}: torch sees no CUDA device on this machine")
    return dev


def _on_device(gaussians: dict, device, owner: str) -> dict:
    missing = [k for k in _GAUSSIAN_FIELDS if k not in gaussians]
    if missing:
        raise ValueError(f"{owner}: gaussians are missing {missing}")
    return {k: v.to(device) for k, v in gaussians.items() if v is not None}


@dataclass(frozen=True)
class ObservationSpec(_DictMixin):
    """Which observations each step returns, and their sizes."""

    panorama: bool = True
    """Return the equirectangular RGB-D panorama."""
    pano_height: int = 256
    """Panorama height in pixels (width = 2 x height)."""
    pinhole: bool = False
    """Return a pinhole crop rendered directly with a pinhole camera."""
    pinhole_size: int = 336
    """Pinhole crop size (square) in pixels."""
    pinhole_hfov_deg: float = 90.0
    """Pinhole horizontal (= vertical) field of view in degrees."""
    ultrawide: bool = False
    """Return the ultra-wide crop: the central part of the panorama resampled to a fixed size."""
    ultrawide_width: int = 512
    """Ultra-wide crop width in pixels."""
    ultrawide_height: int = 336
    """Ultra-wide crop height in pixels."""
    ultrawide_hfov_deg: float = 180.0
    """Ultra-wide horizontal field of view in degrees (centred on the heading)."""
    ultrawide_vfov_deg: float = 118.0
    """Ultra-wide vertical field of view in degrees (centred on the horizon)."""

    def __post_init__(self) -> None:
        for name in ("pano_height", "pinhole_size", "ultrawide_width", "ultrawide_height"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"ObservationSpec.{name} must be >= 1, got {getattr(self, name)!r}")
        if not 0 < self.pinhole_hfov_deg < 180:
            raise ConfigError(
                f"ObservationSpec.pinhole_hfov_deg must lie in (0, 180), got {self.pinhole_hfov_deg}"
            )
        if not (0 < self.ultrawide_hfov_deg <= 360 and 0 < self.ultrawide_vfov_deg <= 180):
            raise ConfigError("ObservationSpec ultra-wide FOV must lie in (0, 360] x (0, 180] degrees")

    @property
    def any(self) -> bool:
        return self.panorama or self.pinhole or self.ultrawide


OBSERVATION_MIN_TRANSMITTANCE = 2e-3
"""``splat``'s ``min_transmittance`` for simulator observations (images for an agent, stored as 8-bit
frames): a pixel is finished once its transmittance is below this. What it leaves out moves a colour
by at most 0.002, half an 8-bit level, and nearly opaque scenes splat faster than at 3DGS's 1e-4
(``benchmarks/splat_early_finish.py``). Metrics (``eval render``) splat at 1e-4."""


class GaussianRenderFn:
    """Render function over a Gaussian scene via ``splat`` (+ optional pixel-flow renderer).

    ``gaussians`` maps names to tensors: means (N, 3), scales (N, 3), quats (N, 4) (w, x, y, z),
    opacities (N,), colors (N, 3) and optionally features (N, C). ``renderer`` (optional) is a
    callable ``renderer(splat_output) -> rgb (1, 3, H, W)`` applied after splatting. ``device``: where
    the Gaussians live and the splat runs (``cuda`` on a GPU machine); observations come back as
    CPU numpy arrays either way. ``mode``: how the splat becomes an image without a renderer,
    :func:`~image2sim.simulator.renderer.holefill.splat_rgbd`'s ``raw``, ``normalised`` (default:
    the expected colour, as ``eval render``'s ``splat_only``) or ``filled`` (holes completed, as
    its ``splat_fill``). ``min_transmittance``: ``splat``'s early finish
    (:data:`OBSERVATION_MIN_TRANSMITTANCE`). Pinhole views on the CPU skip the spatial blocks of
    Gaussians that cannot reach the image (:class:`~image2sim.simulator.splatting.culling.FrustumBlocks`,
    built at the first pinhole view): the same image, bit for bit, without projecting the rest.
    The Gaussians are checked for NaN/inf when the function is made and indexed once: make a new
    render function for changed Gaussians rather than editing its tensors.
    """

    def __init__(
        self,
        gaussians: dict,
        renderer: Callable | None = None,
        backend: str = "auto",
        device=None,
        mode: str = "normalised",
        min_transmittance: float = OBSERVATION_MIN_TRANSMITTANCE,
    ) -> None:
        from image2sim.simulator.renderer.holefill import SPLAT_MODES
        from image2sim.simulator.splatting.api import check_finite

        if mode not in SPLAT_MODES:
            raise ValueError(f"GaussianRenderFn: mode must be one of {SPLAT_MODES}, got {mode!r}")
        self.device = _render_device(device)
        self.gaussians = _on_device(gaussians, self.device, "GaussianRenderFn")
        # Checked once here, not scanned again at every view (5 ms a view for 630 k Gaussians).
        check_finite("GaussianRenderFn", {k: v for k, v in self.gaussians.items() if k in _SPLAT_FIELDS})
        self.renderer = renderer
        self.backend = backend
        self.mode = mode
        self.min_transmittance = float(min_transmittance)
        self._blocks = None  # FrustumBlocks, built at the first pinhole view

    def _cull(self, camera: Camera):
        """The scene's spatial blocks for a pinhole view on the CPU (None otherwise)."""
        if not isinstance(camera, PinholeCamera) or self.device.type != "cpu":
            return None
        if self._blocks is None:
            from image2sim.simulator.splatting.culling import FrustumBlocks

            self._blocks = FrustumBlocks(self.gaussians["means"], self.gaussians["scales"])
        return self._blocks

    def __call__(self, camera: Camera, cam_to_world: np.ndarray) -> dict:
        import torch
        from image2sim.simulator.renderer.holefill import splat_rgbd
        from image2sim.simulator.splatting import splat

        g = self.gaussians
        pose = torch.as_tensor(np.asarray(cam_to_world), dtype=g["means"].dtype, device=self.device)
        with torch.no_grad():
            out = splat(
                g["means"],
                g["scales"],
                g["quats"],
                g["opacities"],
                g["colors"],
                g.get("features"),
                camera,
                pose,
                backend=self.backend,
                min_transmittance=self.min_transmittance,
                nonfinite="checked",
                cull=self._cull(camera),
            )
            if self.renderer is not None:  # the renderer makes the colour; depth as the splat has it
                rgb, depth = self.renderer(out), out.normalized_depth()
            else:
                panoramic = isinstance(camera, EquirectCamera)
                rgb, depth = splat_rgbd(out.rgb, out.depth, out.alpha, self.mode, panoramic)
        return {
            "rgb": rgb[0].permute(1, 2, 0).clamp(0, 1).float().cpu().numpy(),
            "depth": depth[0, 0].float().cpu().numpy(),
        }


class PixelFlowRenderFn:
    """Panoramic render function: splat -> condition C_p -> pixel-flow renderer in ``steps`` steps.

    The splat is unpremultiplied into expected colour / range (background 0), the 24-channel
    condition is built with :func:`~image2sim.simulator.renderer.condition.build_condition` (the
    scene's features when it carries the renderer's 16 channels, zeros otherwise) and the model's
    :meth:`~image2sim.simulator.renderer.model.PixelFlowRenderer.render` runs with noise seeded by
    the pose (:func:`~image2sim.simulator.renderer.meanflow.pose_noise`), so revisiting a pose renders
    the same image. Only equirectangular cameras with W = 2H are accepted: :class:`NeuralSimulator`
    cuts pinhole and ultra-wide views from the panorama (``panoramic = True``). ``device``: where the
    Gaussians and the network live (``cuda`` on a GPU machine); the per-pose noise is drawn on the
    CPU, so a pose renders the same noise on every device. ``min_transmittance``: ``splat``'s early
    finish for the condition (:data:`OBSERVATION_MIN_TRANSMITTANCE`).
    """

    panoramic = True

    def __init__(
        self,
        gaussians: dict,
        model,
        steps: int = 1,
        seed: int = 0,
        backend: str = "auto",
        device=None,
        min_transmittance: float = OBSERVATION_MIN_TRANSMITTANCE,
    ) -> None:
        if int(steps) < 1:
            raise ValueError(f"PixelFlowRenderFn: steps must be >= 1, got {steps}")
        self.device = _render_device(device)
        self.gaussians = _on_device(gaussians, self.device, "PixelFlowRenderFn")
        self.model = model.to(self.device).eval()
        self.steps = int(steps)
        self.seed = int(seed)
        self.backend = backend
        self.min_transmittance = float(min_transmittance)

    def condition(self, camera: EquirectCamera, cam_to_world: np.ndarray):
        """The (1, 24, H, W) condition C_p of the Gaussians splatted at ``cam_to_world``."""
        import torch
        from image2sim.simulator.renderer.condition import build_condition, unpremultiply
        from image2sim.simulator.renderer.config import CONDITION_FEATURES
        from image2sim.simulator.splatting import splat

        g = self.gaussians
        feats = g.get("features")
        if feats is not None and (feats.dim() != 2 or feats.shape[-1] != CONDITION_FEATURES):
            feats = None  # features of another encoder width carry no meaning for this renderer
        pose = torch.as_tensor(np.asarray(cam_to_world), dtype=g["means"].dtype, device=self.device)
        with torch.no_grad():
            out = splat(
                g["means"],
                g["scales"],
                g["quats"],
                g["opacities"],
                g["colors"],
                feats,
                camera,
                pose,
                background=0.0,
                backend=self.backend,
                min_transmittance=self.min_transmittance,
            )
            rgb, depth = unpremultiply(out.rgb, out.depth, out.alpha, background=0.0)
            f = out.features if feats is not None else rgb.new_zeros(1, CONDITION_FEATURES, *rgb.shape[-2:])
            return build_condition(
                f.float(),
                rgb.float(),
                depth.float(),
                out.alpha.float(),
                camera.ray_map(torch.float32).to(self.device),
            )

    def __call__(self, camera: Camera, cam_to_world: np.ndarray) -> dict:
        import torch

        if not isinstance(camera, EquirectCamera) or camera.width != 2 * camera.height:
            raise ValueError(
                f"PixelFlowRenderFn renders panoramas only (EquirectCamera with W = 2H), got {camera!r}"
            )
        cond = self.condition(camera, cam_to_world)
        pose = torch.as_tensor(np.asarray(cam_to_world, dtype=np.float64))
        with torch.no_grad():
            res = self.model.render(cond, steps=self.steps, poses=[pose], seed=self.seed)
        return {
            "rgb": res.rgb[0].permute(1, 2, 0).clamp(0, 1).float().cpu().numpy(),
            "depth": res.depth[0, 0].float().cpu().numpy(),
        }


MIN_PANORAMA_HEIGHT = 32
"""The smallest panorama a panoramic render function is asked for (tiny views still get 32x64)."""


def panorama_height_for(view_pixels: int, view_fov_deg: float) -> int:
    """Height of the panorama at a view's angular resolution: ``view_pixels`` across ``view_fov_deg``
    degrees is ``view_pixels * 360 / fov`` columns over the full circle, and the panorama's height is
    half its width. A panoramic renderer (the pixel-flow renderer) renders at this height, so the view
    is cut from it without up- or downsampling: 64 px over 90 degrees gives 128x256, the tiny
    renderer's training size. The data engine and DAgger both ask for panoramas through this."""
    if not (view_pixels >= 1 and 0 < view_fov_deg <= 360):
        raise ValueError(
            f"panorama_height_for: need view_pixels >= 1 and 0 < fov <= 360, got "
            f"{view_pixels}, {view_fov_deg}"
        )
    return max(MIN_PANORAMA_HEIGHT, int(round(view_pixels * 180.0 / view_fov_deg)))


def views_from_panorama(pano: dict, spec: ObservationSpec) -> dict:
    """Pinhole and ultra-wide views (as selected by ``spec``) cut from an RGB-D panorama centred on
    the heading with :func:`~image2sim.simulator.geometry.reproject.perspective_from_equirect`.

    RGB is sampled bilinearly, depth with nearest neighbour (no blending across depth edges); the
    pinhole depth is converted from range to z (pinhole convention), the ultra-wide crop keeps range.
    """
    import torch
    from image2sim.simulator.geometry.reproject import perspective_from_equirect

    rgb = torch.from_numpy(np.ascontiguousarray(pano["rgb"], dtype=np.float32)).permute(2, 0, 1)[None]
    depth = torch.from_numpy(np.ascontiguousarray(pano["depth"], dtype=np.float32))[None, None]
    out: dict = {}

    def cut(hfov: float, vfov: float, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        c = perspective_from_equirect(rgb, 0.0, 0.0, hfov, vfov, h, w, mode="bilinear")
        d = perspective_from_equirect(depth, 0.0, 0.0, hfov, vfov, h, w, mode="nearest")
        return c[0].permute(1, 2, 0).clamp(0, 1).numpy(), d[0, 0].numpy()

    if spec.pinhole:
        s = spec.pinhole_size
        c, d = cut(spec.pinhole_hfov_deg, spec.pinhole_hfov_deg, s, s)
        cam = PinholeCamera.from_fov(spec.pinhole_hfov_deg, spec.pinhole_hfov_deg, s, s)
        z_over_range = cam.ray_map(torch.float32)[2].numpy()  # unit rays: z component = cos(off-axis)
        out["pinhole"] = {"rgb": c, "depth": (d * z_over_range).astype(np.float32)}
    if spec.ultrawide:
        c, d = cut(
            spec.ultrawide_hfov_deg, spec.ultrawide_vfov_deg, spec.ultrawide_height, spec.ultrawide_width
        )
        out["ultrawide"] = {"rgb": c, "depth": d}
    return out


def _ultrawide_from_pano(pano: dict, spec: ObservationSpec) -> dict:
    """Crop lon in +-hfov/2, lat in +-vfov/2 out of an equirect panorama and resample it (cv2)."""
    import cv2

    rgb, depth = pano["rgb"], pano["depth"]
    h, w = depth.shape
    u0 = w / 2 - w * spec.ultrawide_hfov_deg / 720.0
    u1 = w / 2 + w * spec.ultrawide_hfov_deg / 720.0
    v0 = h / 2 - h * spec.ultrawide_vfov_deg / 360.0
    v1 = h / 2 + h * spec.ultrawide_vfov_deg / 360.0
    # Map each output pixel centre to continuous panorama coordinates (pixel centres at +0.5).
    xs = u0 + (np.arange(spec.ultrawide_width) + 0.5) * (u1 - u0) / spec.ultrawide_width - 0.5
    ys = v0 + (np.arange(spec.ultrawide_height) + 0.5) * (v1 - v0) / spec.ultrawide_height - 0.5
    mx, my = np.meshgrid(xs.astype(np.float32), ys.astype(np.float32))
    out_rgb = cv2.remap(rgb.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    out_depth = cv2.remap(depth.astype(np.float32), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_WRAP)
    return {"rgb": out_rgb, "depth": out_depth}


def load_pixel_flow(renderer):
    """A ``PixelFlowRenderer`` from a weights path or module; None for None / other callables."""
    import os

    if renderer is None:
        return None
    if isinstance(renderer, (str, os.PathLike)):
        from image2sim.simulator.renderer.model import load_renderer

        return load_renderer(renderer)
    from image2sim.simulator.renderer.model import PixelFlowRenderer

    return renderer if isinstance(renderer, PixelFlowRenderer) else None


def gaussian_tensors(gaussians) -> dict:
    """The render functions' tensor dict of a :class:`~image2sim.simulator.gaussians.scene.Gaussians`
    (``features`` only when the scene carries them)."""
    names = (*_GAUSSIAN_FIELDS, "features")
    return {k: getattr(gaussians, k) for k in names if getattr(gaussians, k) is not None}


def gaussian_render_fn(
    gaussians,
    renderer=None,
    *,
    steps: int = 1,
    seed: int = 0,
    backend: str = "auto",
    device=None,
    mode: str = "normalised",
    min_transmittance: float = OBSERVATION_MIN_TRANSMITTANCE,
) -> RenderFn:
    """The render function of a Gaussian scene: :class:`PixelFlowRenderFn` when ``renderer`` is
    pixel-flow weights (a path or a ``PixelFlowRenderer``), else :class:`GaussianRenderFn` (splat
    only, with ``renderer`` applied after splatting when it is another callable). ``gaussians``: a
    scene's ``Gaussians`` or a tensor dict; ``device``: cpu (default) or cuda; ``mode``: the splat-only
    image (:class:`GaussianRenderFn`); ``min_transmittance``: ``splat``'s early finish (1e-4 for
    exact images, as ``sim render`` uses)."""
    tensors = gaussians if isinstance(gaussians, dict) else gaussian_tensors(gaussians)
    model = load_pixel_flow(renderer)
    if model is not None:
        return PixelFlowRenderFn(
            tensors,
            model,
            steps=steps,
            seed=seed,
            backend=backend,
            device=device,
            min_transmittance=min_transmittance,
        )
    return GaussianRenderFn(
        tensors, renderer, backend, device=device, mode=mode, min_transmittance=min_transmittance
    )


class NeuralSimulator:
    """A scene (navigation map + graph + optional renderer) and a batch of agents.

    ``reset(positions, headings)`` places B agents; ``step(actions)`` applies one action per agent
    and returns ``(observations, info)`` with info arrays ``position`` (B, 3), ``heading`` (B,),
    ``collided`` (B,), ``stuck`` (B,). Observations are a list of per-agent dicts (``None`` when no
    render function is set or ``observe=False``).
    """

    def __init__(
        self,
        navmap: NavMap,
        graph: NavGraph | None = None,
        render_fn: RenderFn | None = None,
        observations: ObservationSpec | None = None,
    ) -> None:
        self.navmap = navmap
        self.embodiment = navmap.embodiment
        self.world = CollisionWorld(navmap)
        self._graph = graph
        self._planner: Planner | None = None
        self.render_fn = render_fn
        self.spec = observations or ObservationSpec()
        self.agents: list[Agent] = []

    @classmethod
    def from_scene(
        cls,
        folder,
        observations: ObservationSpec | None = None,
        renderer=None,
        backend: str = "auto",
        steps: int = 1,
        seed: int = 0,
        device=None,
    ) -> NeuralSimulator:
        """Open a scene folder: ``gaussians.safetensors`` (+ ``navmap.npz`` / ``navgraph.npz`` when
        present; otherwise the map is extracted from the Gaussians).

        ``renderer``: None = splat-only observations; a path to pixel-flow renderer weights (a
        ``sim export-renderer`` folder, ``.safetensors`` from ``save_renderer`` or a Lightning
        ``.ckpt``, read by :func:`~image2sim.simulator.renderer.model.load_renderer`) or a
        ``PixelFlowRenderer`` module = panoramas rendered by :class:`PixelFlowRenderFn` in ``steps``
        network evaluations with noise seeded by the pose and ``seed``; any other callable
        ``renderer(splat_output) -> rgb`` is applied after splatting (:class:`GaussianRenderFn`).
        ``device``: where the Gaussians (and the renderer) render: cpu (default) or cuda.
        """
        from pathlib import Path

        from image2sim.simulator.gaussians.scene import GaussianScene
        from image2sim.simulator.navigation.extract import extract_navmap_from_gaussians

        folder = Path(folder)
        scene = GaussianScene.load(folder)
        g = scene.gaussians
        if g is None:
            raise ValueError(f"{folder}: the Gaussian scene is empty")
        model = load_pixel_flow(renderer)  # fail early on a bad path, before the map extraction
        if (folder / "navmap.npz").is_file():
            navmap = NavMap.load(folder / "navmap.npz")
        else:
            cams = [
                np.asarray(f["cam_to_world"])[:3, 3]
                for f in scene.frames
                if f.get("cam_to_world") is not None
            ]
            navmap = extract_navmap_from_gaussians(
                g.means.numpy(),
                g.quats.numpy(),
                g.scales.numpy(),
                g.opacities.numpy(),
                np.array(cams) if cams else None,
            )
        graph = NavGraph.load(folder / "navgraph.npz") if (folder / "navgraph.npz").is_file() else None
        chosen = model if model is not None else renderer  # loaded once, above
        render_fn = gaussian_render_fn(g, chosen, steps=steps, seed=seed, backend=backend, device=device)
        return cls(navmap, graph, render_fn, observations)

    @property
    def graph(self) -> NavGraph:
        """Navigation graph, built lazily on first use."""
        if self._graph is None:
            self._graph = NavGraph.build(self.navmap)
        return self._graph

    @property
    def planner(self) -> Planner:
        if self._planner is None:
            self._planner = Planner(self.graph)
        return self._planner

    def set_goal(self, goal_world: np.ndarray | None) -> None:
        """Tell a goal-aware render function (one with ``set_goal``, e.g.
        :class:`~image2sim.simulator.markers.MarkedRenderFn`) the episode's world-frame goal; a no-op
        for other render functions, so task code can always call it."""
        setter = getattr(self.render_fn, "set_goal", None)
        if setter is not None:
            setter(goal_world)

    # --- agents ---------------------------------------------------------------------------
    def reset(self, positions: np.ndarray, headings: np.ndarray | None = None, observe: bool = True):
        """Place one agent per row of ``positions`` (B, 3); returns ``(observations, info)``."""
        pos = np.atleast_2d(np.asarray(positions, dtype=np.float64))
        heads = np.zeros(len(pos)) if headings is None else np.asarray(headings, dtype=np.float64).reshape(-1)
        if len(heads) != len(pos):
            raise ValueError(f"reset: {len(pos)} positions but {len(heads)} headings")
        self.agents = [Agent(self.world, self.embodiment) for _ in range(len(pos))]
        for agent, p, h in zip(self.agents, pos, heads, strict=False):
            agent.reset(p, float(h))
        info = self._info(np.zeros(len(pos), bool), np.zeros(len(pos), bool))
        return (self.observe_all() if observe else None), info

    def step(self, actions, observe: bool = True):
        """Apply one action per agent; returns ``(observations, info)``."""
        acts = np.asarray(actions, dtype=np.int64).reshape(-1)
        if len(acts) != len(self.agents):
            raise ValueError(
                f"step: got {len(acts)} actions for {len(self.agents)} agents (call reset first)"
            )
        collided = np.zeros(len(acts), bool)
        stuck = np.zeros(len(acts), bool)
        for i, (agent, a) in enumerate(zip(self.agents, acts, strict=False)):
            if int(a) not in {int(x) for x in Action}:
                raise ValueError(
                    f"step: action {int(a)} of agent {i} is not one of {[int(x) for x in Action]}"
                )
            res = agent.step(int(a))
            collided[i], stuck[i] = res.collided, res.stuck
        return (self.observe_all() if observe else None), self._info(collided, stuck)

    def _info(self, collided: np.ndarray, stuck: np.ndarray) -> dict:
        return {
            "position": np.array([a.state.position for a in self.agents]).reshape(-1, 3),
            "heading": np.array([a.state.heading for a in self.agents]),
            "collided": collided,
            "stuck": stuck,
        }

    # --- observations ---------------------------------------------------------------------
    def camera_pose(self, index: int) -> np.ndarray:
        """World-frame camera-to-world (4, 4) of agent ``index`` (eye height, upright, heading yaw)."""
        agent = self.agents[index]
        pose = np.eye(4)
        pose[:3, :3] = camera_rotation_for_heading(agent.state.heading)
        pose[:3, 3] = agent.camera_position
        # Map frame -> world frame (identity unless gravity was corrected).
        r_wm = self.navmap.rotation.T
        pose[:3, :3] = r_wm @ pose[:3, :3]
        pose[:3, 3] = r_wm @ pose[:3, 3]
        return pose

    def observe(self, index: int) -> dict | None:
        """Selected observations of one agent (``None`` without a render function).

        A panoramic render function (``render_fn.panoramic``, e.g. :class:`PixelFlowRenderFn`) renders
        the panorama once and the pinhole / ultra-wide views are cut from it; other render functions
        render the pinhole view directly with a pinhole camera.
        """
        if self.render_fn is None or not self.spec.any:
            return None
        pose = self.camera_pose(index)
        out: dict = {}
        panoramic = bool(getattr(self.render_fn, "panoramic", False))
        if self.spec.panorama or self.spec.ultrawide or (panoramic and self.spec.pinhole):
            pano = self.render_fn(EquirectCamera(self.spec.pano_height, 2 * self.spec.pano_height), pose)
            if self.spec.panorama:
                out["panorama"] = pano
            if panoramic:
                out.update(views_from_panorama(pano, self.spec))
            elif self.spec.ultrawide:
                out["ultrawide"] = _ultrawide_from_pano(pano, self.spec)
        if self.spec.pinhole and not panoramic:
            s = self.spec.pinhole_size
            cam = PinholeCamera.from_fov(self.spec.pinhole_hfov_deg, self.spec.pinhole_hfov_deg, s, s)
            out["pinhole"] = self.render_fn(cam, pose)
        return out

    def observe_all(self) -> list:
        return [self.observe(i) for i in range(len(self.agents))]


class NavEnv:
    """Gymnasium-style single-agent point-goal environment on a :class:`NeuralSimulator`.

    ``reset(start, heading, goal) -> (obs, info)``; ``step(action) -> (obs, reward, terminated,
    truncated, info)``. Reward: decrease of the geodesic distance to the goal minus a 0.01 slack per
    step, + ``success_reward`` on STOP within ``success_distance``. ``info`` adds
    ``distance_to_goal`` (geodesic, via a distance field computed once per episode) and ``success``.
    """

    def __init__(
        self,
        sim: NeuralSimulator,
        max_steps: int = 500,
        success_distance: float = 0.25,
        success_reward: float = 2.5,
        slack_reward: float = -0.01,
    ) -> None:
        self.sim = sim
        self.max_steps = int(max_steps)
        self.success_distance = float(success_distance)
        self.success_reward = float(success_reward)
        self.slack_reward = float(slack_reward)
        self.field: DistanceField | None = None
        self._steps = 0
        self._last = math.inf

    def reset(self, start: np.ndarray, heading: float, goal: np.ndarray):
        self.field = self.sim.planner.distance_field(np.asarray(goal, float))
        obs, info = self.sim.reset(np.asarray(start, float)[None], np.array([heading]))
        self._steps = 0
        self._last = self.field(info["position"][0])
        return (obs[0] if obs else None), self._single(info, self._last, False)

    def step(self, action: int):
        if self.field is None:
            raise RuntimeError("NavEnv.step called before reset")
        obs, info = self.sim.step([action])
        self._steps += 1
        d = self.field(info["position"][0])
        terminated = int(action) == int(Action.STOP)
        success = terminated and d <= self.success_distance
        reward = (
            self._last - d if math.isfinite(d) and math.isfinite(self._last) else 0.0
        ) + self.slack_reward
        if success:
            reward += self.success_reward
        self._last = d
        truncated = not terminated and self._steps >= self.max_steps
        return (obs[0] if obs else None), float(reward), terminated, truncated, self._single(info, d, success)

    @staticmethod
    def _single(info: dict, d: float, success: bool) -> dict:
        return {
            "position": info["position"][0],
            "heading": float(info["heading"][0]),
            "collided": bool(info["collided"][0]),
            "stuck": bool(info["stuck"][0]),
            "distance_to_goal": float(d),
            "success": bool(success),
        }
