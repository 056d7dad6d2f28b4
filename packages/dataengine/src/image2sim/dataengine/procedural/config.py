"""Configuration of the procedural scene generator: layout, objects, capture and noise tiers.

Every field has a docstring (the attribute docstring below it). Configs are plain frozen
dataclasses; :func:`synth_config_from_dict` builds one from nested dicts (YAML/JSON) with the shared
:mod:`image2sim.simulator.config` mechanism (unknown keys and wrong types rejected), and
:meth:`SynthConfig.validate` rejects impossible values with a message that names the field.
Presets: :func:`preset` (``"default"``, ``"tiny"``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

from image2sim.simulator.config import ConfigError as SharedConfigError
from image2sim.simulator.config import (
    config_to_dict,
    merge_config,
    require_at_least,
    require_in_range,
    require_one_of,
)

__all__ = [
    "LayoutConfig",
    "ObjectConfig",
    "CaptureConfig",
    "NoiseConfig",
    "SynthConfig",
    "ConfigError",
    "NOISE_TIERS",
    "noise_tier",
    "preset",
    "PRESETS",
    "synth_config_from_dict",
]


ConfigError = SharedConfigError
"""An invalid generator configuration (the repository's one config error class)."""


@dataclass(frozen=True)
class LayoutConfig:
    """Floor plan: rooms, corridor, walls, doors."""

    rooms_min: int = 3
    """Fewest rooms in a floor plan (a corridor counts as a room); >= 1."""
    rooms_max: int = 8
    """Most rooms in a floor plan; <= 8."""
    room_size_min: float = 2.6
    """Smallest side of a room (wall centreline to centreline), metres."""
    room_size_max: float = 6.0
    """Largest side of a room, metres."""
    corridor_probability: float = 0.5
    """Probability that a plan with >= 3 rooms is built around a hallway corridor."""
    corridor_width: float = 1.4
    """Corridor width (centreline to centreline), metres."""
    wall_thickness: float = 0.1
    """Wall thickness, metres (walls are centred on the room boundaries)."""
    ceiling_height_min: float = 2.5
    """Lowest ceiling height of a plan (one height per plan), metres."""
    ceiling_height_max: float = 2.9
    """Highest ceiling height, metres."""
    door_width_min: float = 0.85
    """Narrowest door opening, metres."""
    door_width_max: float = 1.1
    """Widest door opening, metres."""
    door_height: float = 2.1
    """Door opening height, metres (a lintel fills the wall above it)."""
    extra_door_probability: float = 0.3
    """Probability of a door on an adjacent room pair beyond the spanning tree (loops in the plan)."""


@dataclass(frozen=True)
class ObjectConfig:
    """Furniture and small-object placement."""

    furniture_scale: float = 1.0
    """Multiplier on the per-room-type furniture counts (0 gives empty rooms)."""
    small_per_surface_max: int = 3
    """Most small objects placed on one support surface (table top, shelf board, counter)."""
    small_probability: float = 0.7
    """Probability that a support surface receives small objects at all."""
    placement_attempts: int = 30
    """Random placement attempts per object before it is skipped."""
    wall_gap: float = 0.01
    """Gap between a wall and furniture backed against it, metres (avoids coplanar faces)."""
    door_clearance: float = 0.9
    """Depth of the keep-out zone in front of each door (both sides), metres."""
    category_colours: bool = True
    """Each object category's main material has its own saturated hue
    (:func:`~image2sim.dataengine.procedural.textures.category_hue`), as real object classes have
    typical looks, so a category named in an instruction is recognisable in a small image; patterns,
    brightness and the secondary materials still vary per instance. False: every instance's colour
    is drawn freely from its material family."""


@dataclass(frozen=True)
class NoiseConfig:
    """Sensor/pose degradation of one noise tier (see :data:`NOISE_TIERS`)."""

    depth_noise_relative: float = 0.0
    """Std of multiplicative Gaussian depth noise (range-proportional), e.g. 0.01 = 1 % of depth."""
    depth_noise_absolute: float = 0.0
    """Std of additive Gaussian depth noise, metres."""
    pose_jitter_translation: float = 0.0
    """Std of the Gaussian position error of stored poses, metres per axis."""
    pose_jitter_rotation_deg: float = 0.0
    """Std of the rotation error of stored poses, degrees (axis-angle, isotropic)."""
    holes_min: int = 0
    """Fewest elliptical missing-depth holes per frame."""
    holes_max: int = 0
    """Most elliptical missing-depth holes per frame."""
    hole_radius_min: float = 0.02
    """Smallest hole semi-axis as a fraction of the image width."""
    hole_radius_max: float = 0.06
    """Largest hole semi-axis as a fraction of the image width."""
    lidar_row_step: int = 0
    """If > 0, keep depth only on every n-th image row (LiDAR-like scan lines); 0 keeps all rows."""
    lidar_elevation_min_deg: float = -90.0
    """Lowest elevation (ray angle above the horizon, degrees) with depth when lidar_row_step > 0."""
    lidar_elevation_max_deg: float = 90.0
    """Highest elevation with depth when lidar_row_step > 0."""
    max_range: float = 0.0
    """Depth beyond this range (metres) becomes invalid; 0 = no limit."""
    view_fraction: float = 1.0
    """Fraction of the requested views that are kept (fewer views in harder tiers)."""
    rgb_noise_std: float = 0.0
    """Std of additive Gaussian colour noise, in 8-bit levels."""


NOISE_TIERS: dict[str, NoiseConfig] = {
    # Clean: exact poses and depth (the paper's synthetic, no-noise regime).
    "none": NoiseConfig(),
    # Mirrors consumer RGB-D panoramas: small range-proportional noise, slight pose error, a few holes.
    "middle": NoiseConfig(
        depth_noise_relative=0.005,
        depth_noise_absolute=0.002,
        pose_jitter_translation=0.01,
        pose_jitter_rotation_deg=0.3,
        holes_min=2,
        holes_max=5,
        hole_radius_min=0.02,
        hole_radius_max=0.06,
        max_range=12.0,
        rgb_noise_std=2.0,
    ),
    # Mirrors sparse real LiDAR captures: scan lines in an elevation band, big holes, more pose error.
    "high": NoiseConfig(
        depth_noise_relative=0.015,
        depth_noise_absolute=0.01,
        pose_jitter_translation=0.04,
        pose_jitter_rotation_deg=1.0,
        holes_min=4,
        holes_max=8,
        hole_radius_min=0.05,
        hole_radius_max=0.12,
        lidar_row_step=2,
        lidar_elevation_min_deg=-35.0,
        lidar_elevation_max_deg=25.0,
        max_range=8.0,
        view_fraction=0.5,
        rgb_noise_std=4.0,
    ),
}
"""The three benchmark regimes of the paper (no / middle / high noise) as concrete parameters."""


def noise_tier(name: str) -> NoiseConfig:
    """The :class:`NoiseConfig` of a named tier; unknown names are a :class:`ConfigError`."""
    try:
        return NOISE_TIERS[name]
    except KeyError:
        raise ConfigError(f"noise tier {name!r} is unknown (expected one of {sorted(NOISE_TIERS)})") from None


@dataclass(frozen=True)
class CaptureConfig:
    """Camera placement and image size of the generated captures."""

    views: int = 24
    """Views per scene before the noise tier's ``view_fraction``."""
    camera: str = "equirect"
    """Camera model: "equirect" (panorama, depth = range) or "pinhole" (depth = z)."""
    height: int = 512
    """Image height in pixels."""
    width: int = 1024
    """Image width in pixels."""
    hfov_deg: float = 90.0
    """Horizontal field of view of the pinhole camera, degrees (ignored for panoramas)."""
    eye_height_min: float = 1.25
    """Lowest camera height above the floor, metres (one height per scene)."""
    eye_height_max: float = 1.6
    """Highest camera height above the floor, metres."""
    spacing_min: float = 0.4
    """Shortest distance between consecutive views, metres."""
    spacing_max: float = 1.2
    """Longest distance between consecutive views (with a free straight line between them), metres."""
    yaw_step_max_deg: float = 180.0
    """Largest heading change between consecutive views, degrees. 180 (default): every view draws an
    independent random yaw; smaller values make a walking camera whose consecutive views overlap, as
    a phone video or a photo walk does (what structure-from-motion needs; ``image2sim data lift``)."""
    agent_radius: float = 0.15
    """Agent radius: navigable cells keep at least this distance from walls and objects, metres."""
    grid_resolution: float = 0.05
    """Cell size of the ground-truth navigable grid, metres."""


@dataclass(frozen=True)
class SynthConfig:
    """Everything the generator needs; one object per run."""

    layout: LayoutConfig = field(default_factory=LayoutConfig)
    """Floor plan parameters."""
    objects: ObjectConfig = field(default_factory=ObjectConfig)
    """Furniture and small-object parameters."""
    capture: CaptureConfig = field(default_factory=CaptureConfig)
    """Camera and image parameters."""
    noise: str = "none"
    """Noise tier name: "none", "middle" or "high" (parameters in :data:`NOISE_TIERS`)."""
    caster: str = "auto"
    """Ray caster: "auto" (embree when importable, else numpy), "embree" or "numpy" (tile-culled slabs)."""
    surface_detail: float = 0.0
    """Contrast of fine albedo grain (periods of a few centimetres) on every surface, in [0, 1): real
    paint, wood and fabric carry such detail and feature-based structure-from-motion needs it
    (``image2sim data lift``); 0 keeps the smooth patterns, and the images, exactly as before."""

    def noise_config(self) -> NoiseConfig:
        """The parameters of :attr:`noise`."""
        return noise_tier(self.noise)

    def validate(self) -> SynthConfig:
        """Raise :class:`ConfigError` naming the first invalid field; return ``self`` when valid."""
        lay, cap = self.layout, self.capture
        _check_finite(self)
        if lay.rooms_min < 1:
            raise ConfigError(f"layout.rooms_min must be >= 1 (a plan needs a room), got {lay.rooms_min}")
        if lay.rooms_max > 8:
            raise ConfigError(f"layout.rooms_max must be <= 8, got {lay.rooms_max}")
        if lay.rooms_max < lay.rooms_min:
            raise ConfigError(
                f"layout.rooms_max ({lay.rooms_max}) is below layout.rooms_min ({lay.rooms_min})"
            )
        for name in (
            "room_size_min",
            "room_size_max",
            "corridor_width",
            "wall_thickness",
            "ceiling_height_min",
            "ceiling_height_max",
            "door_width_min",
            "door_width_max",
            "door_height",
        ):
            if getattr(lay, name) <= 0:
                raise ConfigError(f"layout.{name} must be positive, got {getattr(lay, name)}")
        if lay.room_size_max < lay.room_size_min:
            raise ConfigError(
                f"layout.room_size_max ({lay.room_size_max}) is below room_size_min ({lay.room_size_min})"
            )
        if lay.ceiling_height_max < lay.ceiling_height_min:
            raise ConfigError("layout.ceiling_height_max is below layout.ceiling_height_min")
        if lay.door_width_max < lay.door_width_min:
            raise ConfigError("layout.door_width_max is below layout.door_width_min")
        if lay.door_height >= lay.ceiling_height_min:
            raise ConfigError(
                f"layout.door_height ({lay.door_height} m) must be below the ceiling (ceiling_height_min "
                f"{lay.ceiling_height_min} m)"
            )
        narrowest = min(lay.room_size_min, lay.corridor_width)
        if lay.door_width_min + lay.wall_thickness + 0.2 > narrowest:
            raise ConfigError(
                f"layout: a door of {lay.door_width_min} m with walls of {lay.wall_thickness} m "
                "(and 10 cm margins) "
                f"does not fit in a room/corridor side of {narrowest} m"
            )
        if lay.corridor_width - lay.wall_thickness <= 2 * cap.agent_radius + 2 * cap.grid_resolution:
            raise ConfigError(
                f"layout.corridor_width ({lay.corridor_width} m) leaves no navigable floor "
                "for an agent of radius "
                f"{cap.agent_radius} m"
            )
        if lay.door_width_min <= 2 * cap.agent_radius + 2 * cap.grid_resolution:
            raise ConfigError(
                f"layout.door_width_min ({lay.door_width_min} m) must exceed "
                "the agent diameter plus two grid cells "
                f"(2 * capture.agent_radius + 2 * capture.grid_resolution = "
                f"{2 * cap.agent_radius + 2 * cap.grid_resolution:g} m) or rooms cannot connect"
            )
        unit = ("layout.corridor_probability", "layout.extra_door_probability", "objects.small_probability")
        require_in_range(self, unit, 0.0, 1.0)
        require_at_least(
            self,
            (
                "objects.furniture_scale",
                "objects.small_per_surface_max",
                "objects.wall_gap",
                "objects.door_clearance",
            ),
            0,
        )
        require_at_least(self, ("objects.placement_attempts", "capture.views"), 1)
        require_one_of(self, "capture.camera", ("equirect", "pinhole"))
        if cap.height < 2 or cap.width < 2:
            raise ConfigError(f"capture image size must be at least 2x2, got {cap.width}x{cap.height}")
        require_in_range(self, "capture.hfov_deg", 0, 180, low_open=True, high_open=True)
        if cap.eye_height_min <= 0 or cap.eye_height_max < cap.eye_height_min:
            raise ConfigError(
                f"capture eye heights must satisfy 0 < eye_height_min <= eye_height_max, got "
                f"{cap.eye_height_min}..{cap.eye_height_max}"
            )
        if cap.eye_height_max >= lay.ceiling_height_min - 0.05:
            raise ConfigError(
                f"capture.eye_height_max ({cap.eye_height_max} m) must stay below the ceiling "
                f"(layout.ceiling_height_min = {lay.ceiling_height_min} m, minus 5 cm)"
            )
        if cap.spacing_min < 0 or cap.spacing_max <= 0 or cap.spacing_max < cap.spacing_min:
            raise ConfigError(
                f"capture spacing must satisfy 0 <= spacing_min <= spacing_max, 0 < spacing_max; got "
                f"{cap.spacing_min}..{cap.spacing_max}"
            )
        require_in_range(self, "capture.yaw_step_max_deg", 0.0, 180.0)
        require_at_least(self, "capture.agent_radius", 0)
        require_in_range(self, "capture.grid_resolution", 0, 0.5, low_open=True)  # metres
        require_one_of(self, "caster", ("auto", "embree", "numpy", "numpy-brute"))
        require_in_range(self, "surface_detail", 0.0, 1.0, high_open=True)
        noise = self.noise_config()
        if not 0 < noise.view_fraction <= 1:
            raise ConfigError(f"noise tier {self.noise!r}: view_fraction must lie in (0, 1]")
        return self

    def to_dict(self) -> dict:
        """Plain nested dict (JSON-serialisable), the inverse of :func:`synth_config_from_dict`."""
        return config_to_dict(self)


def _check_finite(cfg: SynthConfig) -> None:
    for section in ("layout", "objects", "capture"):
        sub = getattr(cfg, section)
        for f in fields(sub):
            value = getattr(sub, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ConfigError(f"{section}.{f.name} must be finite, got {value}")


def synth_config_from_dict(data: dict, base: SynthConfig | None = None) -> SynthConfig:
    """Build and validate a :class:`SynthConfig` from nested dicts, overriding ``base`` (default preset).

    A thin wrapper over the shared :func:`image2sim.simulator.config.merge_config`: unknown keys
    anywhere and wrong types are a :class:`ConfigError` naming the dotted field path.
    """
    return merge_config(base or SynthConfig(), data).validate()


PRESETS: dict[str, SynthConfig] = {
    "default": SynthConfig(),
    # Small, fast scenes for tests: 1-2 small rooms, a few objects, 64x128 panoramas.
    "tiny": SynthConfig(
        layout=LayoutConfig(
            rooms_min=1, rooms_max=2, room_size_min=2.6, room_size_max=3.6, corridor_probability=0.0
        ),
        objects=ObjectConfig(furniture_scale=0.6, small_per_surface_max=2, placement_attempts=15),
        capture=CaptureConfig(views=4, height=64, width=128, spacing_min=0.3, spacing_max=0.8),
    ),
}
"""Named starting points; override fields with :func:`synth_config_from_dict` or ``dataclasses.replace``."""


def preset(name: str) -> SynthConfig:
    """A validated copy of a named preset; unknown names are a :class:`ConfigError`."""
    try:
        return PRESETS[name].validate()
    except KeyError:
        raise ConfigError(f"preset {name!r} is unknown (expected one of {sorted(PRESETS)})") from None
