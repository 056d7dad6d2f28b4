"""The data engine's configuration (:class:`EngineConfig`): everything a scene task needs, as plain
data, so it travels to worker processes and Ray tasks and is saved with every run (``run.json``)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from image2sim.dataengine.scene_assets import DETECTORS
from image2sim.simulator.config import (
    ConfigError,
    config_from_dict,
    require_at_least,
    require_in_range,
    require_one_of,
    require_render_device,
)

__all__ = ["EngineConfig", "RENDER_MODES"]

RENDER_MODES = ("auto", "procedural", "gaussians", "none")


@dataclass
class EngineConfig:
    """Everything a scene task needs (plain data, so it travels to Ray workers)."""

    per_scene: int | None = None
    """Episodes planned per scene; None = area-based capacity (paper: clamped to [50, 1000])."""
    annotator: str = "template"
    """template, transformers or openai."""
    annotator_options: dict = field(default_factory=dict)
    """Backend options (openai: base_url, model, timeout, ...; transformers: path)."""
    render: str = "auto"
    """Observation renderer: auto (= gaussians: the neural simulator over Gaussians built from the
    capture, through ``renderer`` when given), procedural (the exact renderer of a procedural capture:
    an upper bound, chosen explicitly), gaussians or none (no frames, no shard)."""
    view: str = "pinhole"
    """Observation stored in the shard: pinhole (90 degrees, square) or ultrawide (180 x 118 degrees)."""
    obs_height: int = 336
    """Pinhole size / ultra-wide height in pixels (ultra-wide width = height x 512 / 336)."""
    frame_stride: int = 2
    """Store the observation of every n-th step only (1 = every step). Image2Nav predicts two actions
    per observation (the paper: 32 observations paired with 64 action labels; the streaming agent
    observes every other step), so 2 stores every view a policy is trained on or shown, at half the
    rendering cost of 1."""
    annotation_view_height: int = 168
    """Height of the 180 degree views given to VLM annotators (width = 2 x height x 180 / 118)."""
    renderer: str | None = None
    """Local pixel-flow renderer weights (an ``export-renderer`` folder, ``save_renderer`` safetensors
    or a Lightning checkpoint) applied after splatting (the simulator's ``PixelFlowRenderFn``); needs
    render=gaussians (or auto)."""
    gaussians: dict = field(default_factory=dict)
    """Gaussian config of the identity scenes built from captures for ``render=gaussians``, as plain
    data over a preset (``gaussian_config_from_dict``; ``data episodes --gaussian-config`` reads a
    preset name or YAML into it). Empty: the ``tiny`` preset. A coarser fusion
    (``fusion.footprint_factor``) makes fewer Gaussians and cheaper frames
    (``reports/scene_density.md``)."""
    refine_steps: int = 0
    """Per-scene refinement of the Gaussian scenes built from captures (``gaussians.refine``): 0 keeps
    them feed-forward (the default: the engine builds many scenes, and refining the HM3D sample takes
    ~45 s more); N refines N steps; -1 as ``sim build-scene`` does (two steps per frame, at most 50),
    which brings a scene within ~0.5 dB of each source frame (docs/scenes.md)."""
    device: str = "cpu"
    """Torch device the Gaussian observations render on: cpu, or cuda / cuda:N on a GPU machine (the
    splat and the pixel-flow renderer; the exact procedural renderer, the navigation and the files stay
    on the CPU). The frames match the CPU's up to float rounding."""
    detector: str = "gt"
    """Where goal objects come from: gt (a procedural capture's ground truth), yolo-world (mined with
    local weights), annotations (a person's objects file, :mod:`.objects_file`) or none (no objects:
    landmark-free path episodes between navigable points, so any capture yields episodes)."""
    detector_weights: str | None = None
    """Local YOLO-World weights (yolo-world only)."""
    objects: str | None = None
    """annotations: the objects file (one scene) or a folder of ``<scene name>.json``; default
    ``<capture>/objects_annotations.json``."""
    seed: int = 0
    """Base seed; each scene uses a stream derived from (seed, scene name)."""
    split: str = "train"
    """Split name of the written episode files."""
    sampling: dict = field(default_factory=dict)
    """Overrides of :class:`SamplingConfig` fields."""
    rollout: dict = field(default_factory=dict)
    """Overrides of :class:`RolloutConfig` fields."""
    mining: dict = field(default_factory=dict)
    """Overrides of :class:`MiningConfig` fields."""
    approach: dict = field(default_factory=dict)
    """Overrides of :class:`~image2sim.dataengine.trajectories.ApproachConfig` fields: short training
    episodes that start with their goal in view, written to ``scenes/<name>/approach`` (a second shard,
    never the episode file). ``{"views": 0}`` (the default): none."""
    visible_distance: float = 3.5
    """Objects within this distance and inside the 180 x 118 degree view count as visible at a macro-step
    (and may be named by the annotator) when nothing occludes them (see :mod:`.visibility`)."""
    occlusion: bool = True
    """Occlusion test of the visibility: a ray march through the navigation map's obstacle voxels."""
    occlusion_tolerance: float = 0.3
    """Obstacle voxels within this distance (metres) of an object do not occlude it (its own surface)."""
    goal_view_distance: float = 5.0
    """Each stored frame of an object-goal episode is labelled ``goal_in_view`` (shard record
    ``extra``): 1 when the goal object lies within this distance, inside the stored view's field of
    view and unoccluded. Image2Nav's ``train.goal_aux_weight`` learns from it."""

    def __post_init__(self) -> None:
        where = "EngineConfig."
        require_in_range(
            self, "goal_view_distance", 0.0, math.inf, low_open=True, high_open=True, where=where
        )
        require_one_of(self, "render", RENDER_MODES, where)
        require_one_of(self, "view", ("pinhole", "ultrawide"), where)
        require_one_of(self, "detector", DETECTORS, where)
        if self.per_scene is not None:
            require_at_least(self, "per_scene", 1, where)
        require_at_least(self, "frame_stride", 1, where)
        require_at_least(self, "refine_steps", -1, where)
        require_at_least(self, "obs_height", 8, where)
        if self.detector == "none" and self.annotator != "template":
            raise ConfigError(
                "detector none makes landmark-free path episodes, which only the template annotator "
                "describes (VLM prompts ask about a goal object): use --annotator template"
            )
        require_render_device(self, "device", where)
        if self.renderer is not None and self.render not in ("auto", "gaussians"):
            raise ConfigError("EngineConfig.renderer needs render=gaussians (it renders splatted Gaussians)")

    @classmethod
    def from_dict(cls, data: dict) -> EngineConfig:
        """Build from a mapping with the shared config mechanism: unknown keys and wrong types raise
        :class:`~image2sim.simulator.config.ConfigError` (a ``ValueError``) naming the field."""
        return config_from_dict(cls, data)

    def to_dict(self) -> dict:
        return asdict(self)
