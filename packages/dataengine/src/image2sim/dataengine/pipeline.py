"""One scene -> verified, annotated episodes and a training shard (the unit of work of the data engine).

``process_scene(scene_dir, out_dir, config)``:
  1. resolve the scene: a capture folder (``image2sim-capture``) or a built scene folder (Gaussian scene
     ``manifest.json`` whose ``source.capture`` points at the capture); navigation map, graph, object
     database and render function from :mod:`.scene_assets` (the scene folder's when present, else
     built and cached in ``{out}/scenes/{name}/``);
  2. sample plans (:mod:`.trajectories`), roll them out with the oracle follower in the
     :class:`NeuralSimulator` (:mod:`.rollout`), replay every accepted rollout and assert it reaches the
     same final position without collision;
  3. macro-steps, style routing, annotation (template / VLM) with the quality gate;
  4. observations along each kept rollout (render function: the exact procedural renderer, the
     Gaussian scene via ``splat``, or none), a shard, and ``{out}/scenes/{name}/episodes.json``
     written atomically; ``done.json`` last.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from image2sim.dataengine.chunking import ChunkConfig, macro_steps, path_features
from image2sim.dataengine.episodes import episode_record, gt_record
from image2sim.dataengine.rollout import (
    RolloutConfig,
    closest_approach_cut,
    replay,
    rollout_plan,
    truncate_rollout,
)
from image2sim.dataengine.scene_assets import (
    DETECTORS,
    SceneInputs,
    resolve_scene,
    scene_gaussians,
    scene_navigation,
    scene_objects,
    scene_render_fn,
)
from image2sim.dataengine.seeding import named_rng
from image2sim.dataengine.trajectories import (
    ApproachConfig,
    SamplingConfig,
    bucket_of,
    episode_capacity,
    sample_approach_plans,
    sample_path_plans,
    sample_plans,
    switch_plans,
)
from image2sim.simulator.config import config_from_dict, require_render_device
from image2sim.simulator.io.atomic import sweep_stale_temps, write_bytes_atomic
from image2sim.simulator.lifetime import torch_threads

__all__ = [
    "EngineConfig",
    "process_scene",
    "DONE_FILE",
    "EPISODES_FILE",
]

DONE_FILE = "done.json"
EPISODES_FILE = "episodes.json"
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
        if not (math.isfinite(self.goal_view_distance) and self.goal_view_distance > 0):
            raise ValueError(f"EngineConfig.goal_view_distance must be > 0, got {self.goal_view_distance!r}")
        if self.render not in RENDER_MODES:
            raise ValueError(f"EngineConfig.render must be one of {RENDER_MODES}, got {self.render!r}")
        if self.view not in ("pinhole", "ultrawide"):
            raise ValueError(f"EngineConfig.view must be pinhole or ultrawide, got {self.view!r}")
        if self.per_scene is not None and self.per_scene < 1:
            raise ValueError(f"EngineConfig.per_scene must be >= 1 or None, got {self.per_scene!r}")
        if self.frame_stride < 1:
            raise ValueError(f"EngineConfig.frame_stride must be >= 1, got {self.frame_stride}")
        if self.obs_height < 8:
            raise ValueError(f"EngineConfig.obs_height must be >= 8, got {self.obs_height}")
        if self.detector not in DETECTORS:
            raise ValueError(f"EngineConfig.detector must be one of {DETECTORS}, got {self.detector!r}")
        if self.detector == "none" and self.annotator != "template":
            raise ValueError(
                "detector none makes landmark-free path episodes, which only the template annotator "
                "describes (VLM prompts ask about a goal object): use --annotator template"
            )
        require_render_device(self, "device", where="EngineConfig.")
        if self.renderer is not None and self.render not in ("auto", "gaussians"):
            raise ValueError("EngineConfig.renderer needs render=gaussians (it renders splatted Gaussians)")

    @classmethod
    def from_dict(cls, data: dict) -> EngineConfig:
        """Build from a mapping with the shared config mechanism: unknown keys and wrong types raise
        :class:`~image2sim.simulator.config.ConfigError` (a ``ValueError``) naming the field."""
        return config_from_dict(cls, data)

    def to_dict(self) -> dict:
        return asdict(self)


# ---------------------------------------------------------------------------------------- helpers


def _stop_at_the_goal(sim, plan, r, navmap, scfg, rcfg):
    """A rollout that walks past the goal object (its end is more than ``rcfg.overshoot`` farther from
    the object than its closest approach) stops at the closest approach instead; the episode's goal and
    length follow. Dropped (reason ``overshoot_too_short``) when the cut path is no longer a valid
    episode (shorter than the sampling config allows, or than ``rcfg.min_steps``)."""
    if plan.goal_object:
        target = navmap.to_map(np.asarray(plan.goal_object["position"], dtype=np.float64).reshape(1, 3))[0]
    else:  # a path episode: its goal is a point
        target = np.asarray(plan.goal, dtype=np.float64)
    k = closest_approach_cut(r.positions, target, rcfg.overshoot)
    if k is None:
        return r, plan
    cut = truncate_rollout(r, k)
    geo, why = sim.planner.geodesic_distance(plan.start, cut.positions[-1])
    bucket = None if why else bucket_of(float(geo), scfg)
    if bucket is None or len(cut.actions) < rcfg.min_steps:
        cut.reason = "overshoot_too_short"
        return cut, plan
    cut.extra["cut_past_goal_m"] = float(r.path_length - cut.path_length)
    plan = replace(plan, goal=cut.positions[-1].copy(), geodesic_distance=float(geo), bucket=bucket)
    return cut, plan


APPROACH_SHARD = "approach"
"""Sub-folder of ``scenes/<name>`` holding the approach episodes' shard."""


def _approach_rollouts(sim, follower, graph, objects, navmap, occupancy, cfg, scfg, rcfg, name, drops):
    """Rolled-out approach episodes (:class:`ApproachConfig`, ``cfg.approach``) of one scene, from their
    own random stream, so the regular episodes are the same with and without them."""
    from image2sim.dataengine.visibility import VisibilityConfig, visible_mask

    acfg = config_from_dict(ApproachConfig, cfg.approach, "approach")
    if not acfg.views:
        return []
    view = VisibilityConfig(
        max_distance=acfg.max_distance,
        hfov_deg=acfg.hfov_deg,
        vfov_deg=acfg.hfov_deg,
        tolerance=cfg.occlusion_tolerance,
        occlusion=cfg.occlusion,
    )
    eye_up = np.array([0.0, 0.0, float(navmap.embodiment.eye_height)])

    def visible(start, heading, positions):
        return visible_mask(positions, np.asarray(start, float) + eye_up, heading, occupancy, view)

    rng = named_rng(cfg.seed, name + "/approach")
    plans, _ = sample_approach_plans(graph, objects, acfg, scfg, rng, visible, navmap.to_map)

    def roll(plans):
        kept = []
        for plan in plans:
            plan, r = _checked_rollout(sim, follower, plan, rcfg)
            if not r.ok:
                drops[f"{plan.bucket}: {r.reason}"] = drops.get(f"{plan.bucket}: {r.reason}", 0) + 1
                continue
            kept.append((plan, r))
        return kept

    out = roll(plans)
    if acfg.switch:
        ends = [(p, r.positions[-1], float(r.headings[-1])) for p, r in out]
        out += roll(switch_plans(ends, lambda a, b: sim.planner.geodesic_distance(a, b)[0]))
    return out


def _checked_rollout(sim, follower, plan, rcfg, cut=None):
    """(plan, rollout) of the oracle on ``plan``, then ``cut(plan, rollout) -> (rollout, plan)`` when
    given (stopping at the goal), then the replay check: re-executing the actions from the start must
    reach the same end without a collision. A rejected rollout says why in ``reason``."""
    r = rollout_plan(sim, follower, plan, rcfg)
    if r.ok and cut is not None:
        r, plan = cut(plan, r)
    if r.ok:
        pos, _, col = replay(sim, plan.start, plan.heading, r.actions)
        if np.abs(pos[-1] - r.positions[-1]).max() > 1e-6 or any(col):
            r.reason = "replay_mismatch"
    return plan, r


def _room_at(objects, pos_world: np.ndarray) -> str | None:
    best, room = math.inf, None
    for o in objects:
        if o.room_type is None:
            continue
        dist = float(np.linalg.norm(np.asarray(o.position[:2]) - pos_world[:2]))
        if dist < best:
            best, room = dist, o.room_type
    return room


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.asarray(rgb, np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _observation_spec(cfg: EngineConfig):
    """The stored view's spec. Its panorama height is the view's angular resolution
    (:func:`~image2sim.simulator.sim.panorama_height_for`), which panoramic render functions (the
    pixel-flow renderer) render at before cutting the view: without it they rendered at the spec's
    default 256x512, 4x the pixels of a 64 px view and a scale the tiny renderer never trained on."""
    from image2sim.simulator.sim import ObservationSpec, panorama_height_for

    h = int(cfg.obs_height)
    if cfg.view == "pinhole":
        pano_height = panorama_height_for(h, ObservationSpec.pinhole_hfov_deg)  # the spec's default fov
        return ObservationSpec(panorama=False, pinhole=True, pinhole_size=h, pano_height=pano_height)
    width = int(round(h * 512 / 336))
    pano_height = panorama_height_for(width, 180.0)  # the ultra-wide view spans 180 degrees
    return ObservationSpec(
        panorama=False, ultrawide=True, pano_height=pano_height, ultrawide_height=h, ultrawide_width=width
    )


def _field_of_view(spec) -> tuple[float, float]:
    """(horizontal, vertical) degrees of the view an ObservationSpec stores (pinhole views are square)."""
    if spec.pinhole:
        return float(spec.pinhole_hfov_deg), float(spec.pinhole_hfov_deg)
    return float(spec.ultrawide_hfov_deg), float(spec.ultrawide_vfov_deg)


# ---------------------------------------------------------------------------------------- the task


def process_scene(
    scene_dir: str | Path,
    out_dir: str | Path,
    config: EngineConfig | dict,
    render_workers: int = 1,
    asset_cache: str | None = None,
) -> dict:
    """Run the whole engine on one scene; returns the scene summary (also written to ``done.json``).

    ``render_workers`` > 1 renders the episodes' observations in that many spawned processes (the
    local executor passes its ``--workers`` when it runs one scene at a time); the shard is the same
    as with one. ``asset_cache``: a folder of scene assets shared across runs, keyed by the capture's
    content (:mod:`.asset_cache`). With ``render_workers`` > 1 the scene's Gaussians build in a
    process of their own while this one makes the navigation map and the rollouts."""
    cfg = config if isinstance(config, EngineConfig) else EngineConfig.from_dict(config)
    t0 = time.perf_counter()
    inputs = resolve_scene(scene_dir)
    out = Path(out_dir) / "scenes" / inputs.name
    out.mkdir(parents=True, exist_ok=True)
    sweep_stale_temps(out / "shard")  # left by a killed earlier attempt of this scene
    prebuild = _GaussianPrebuild.start(inputs, out, cfg, asset_cache, render_workers)
    # With render workers the cores belong to them and to the Gaussians' build beside this process,
    # so its own torch ops run on one thread: on two threads they oversubscribed the cores (the
    # HM3D sample's command took 159 s instead of 141, byte-identical output).
    try:
        with torch_threads(1 if render_workers > 1 else 0):
            return _run_scene(inputs, out, cfg, render_workers, asset_cache, prebuild, t0)
    finally:
        if prebuild is not None:
            prebuild.cancel()


def _run_scene(inputs, out: Path, cfg: EngineConfig, render_workers: int, asset_cache, prebuild, t0: float):
    """:func:`process_scene`'s work once the output folder exists (``prebuild``: the Gaussians being
    built meanwhile, or None)."""
    from image2sim.dataengine.annotate import AnnotationRequest, build_annotator, route_style
    from image2sim.simulator.navigation.follower import OracleFollower
    from image2sim.simulator.sim import NeuralSimulator

    navmap, graph = scene_navigation(inputs, out, asset_cache)
    objects = scene_objects(inputs, out, cfg)
    scfg = config_from_dict(SamplingConfig, cfg.sampling, "sampling")
    rcfg = config_from_dict(RolloutConfig, cfg.rollout, "rollout")
    area = navmap.navigable_area()
    n = cfg.per_scene if cfg.per_scene is not None else episode_capacity(area, scfg)
    rng = named_rng(cfg.seed, inputs.name)
    sim = NeuralSimulator(navmap, graph)
    follower = OracleFollower(sim.planner)
    n_plans = int(math.ceil(n * scfg.plan_oversample))
    if cfg.detector == "none":
        plans, plan_stats = sample_path_plans(graph, n_plans, scfg, rng)
    else:
        plans, plan_stats = sample_plans(graph, sim.planner, objects, n_plans, scfg, rng, navmap.to_map)
    drops: dict[str, int] = {}
    kept = []
    for plan in plans:
        if len(kept) >= n:
            break
        plan, r = _checked_rollout(
            sim, follower, plan, rcfg, lambda p, r: _stop_at_the_goal(sim, p, r, navmap, scfg, rcfg)
        )
        if not r.ok:
            drops[r.reason] = drops.get(r.reason, 0) + 1
            continue
        kept.append((plan, r))
    n_regular = len(kept)
    from image2sim.dataengine.visibility import (
        Occupancy,
        VisibilityConfig,
        goal_in_view,
        near_categories,
        visible_categories,
    )

    occupancy = Occupancy.from_navmap(navmap) if cfg.occlusion and objects else None
    if objects and cfg.render != "none":  # approach episodes are training frames only
        kept += _approach_rollouts(
            sim, follower, graph, objects, navmap, occupancy, cfg, scfg, rcfg, inputs.name, drops
        )
    # Annotation requests.
    vlm = cfg.annotator != "template"
    if prebuild is not None:
        prebuild.wait()
    render_fn, render_mode = (
        (None, "none")
        if cfg.render == "none"
        else scene_render_fn(inputs, out, cfg.render, cfg.renderer, asset_cache, cfg.device, cfg.gaussians)
    )
    if vlm and render_fn is None:
        raise ValueError(f"{inputs.name}: VLM annotators need rendered views (render={cfg.render!r})")
    vis_cfg = VisibilityConfig(
        max_distance=cfg.visible_distance, tolerance=cfg.occlusion_tolerance, occlusion=cfg.occlusion
    )
    fov = _field_of_view(_observation_spec(cfg))  # the stored observation's
    goal_view = VisibilityConfig(
        max_distance=cfg.goal_view_distance,
        hfov_deg=fov[0],
        vfov_deg=fov[1],
        tolerance=cfg.occlusion_tolerance,
        occlusion=cfg.occlusion,
    )
    obj_map = navmap.to_map(np.array([o.position for o in objects], dtype=np.float64).reshape(-1, 3))
    eye_up = np.array([0.0, 0.0, float(navmap.embodiment.eye_height)])

    def eyes_of(r):
        return np.asarray(r.positions, dtype=np.float64) + eye_up

    index_of = {int(o.object_id): i for i, o in enumerate(objects)}
    near_of: dict[int, list[str]] = {}  # goal object id -> its "near" landmarks (computed once per goal)
    requests, chunks = [], []
    for k, (plan, r) in enumerate(kept):
        eid = f"{inputs.name}-{k:05d}" if k < n_regular else f"{inputs.name}-a{k - n_regular:05d}"
        steps = macro_steps(r.actions, r.positions, r.headings, ChunkConfig())
        world = navmap.to_world(r.positions)
        eyes = eyes_of(r)
        vis = [
            visible_categories(objects, obj_map, eyes[m.start], r.headings[m.start], occupancy, vis_cfg)
            for m in steps
        ]
        rooms = [_room_at(objects, world[m.start]) for m in steps]
        style, structure, tone = route_style(rng)
        near: list[str] = []
        if plan.goal_object:
            gid = int(plan.goal_object["object_id"])
            if gid not in near_of:
                near_of[gid] = near_categories(index_of[gid], objects, obj_map, occupancy)
            near = near_of[gid]
        else:
            style = "r2r"  # a path instruction (no goal object to ask for)
        node, _ = graph.snap(np.asarray(r.positions, dtype=np.float64))
        clearance = np.where(node >= 0, graph.clearance[np.maximum(node, 0)], 0.0)
        images = []
        if vlm:
            images = [_annotation_view(sim, render_fn, plan, r, m.start, cfg) for m in steps]
        requests.append(
            AnnotationRequest(
                eid,
                [m.text for m in steps],
                images,
                plan.goal_object,
                vis,
                rooms,
                style,
                structure,
                tone,
                seed=int(rng.integers(2**31)),
                near=near,
                distances=[float(m.distance) for m in steps],
                turns=[float(m.net_turn_deg) for m in steps],
                features=path_features(steps, r.positions, clearance),
            )
        )
        chunks.append(steps)
    vocab = sorted({o.category for o in objects})
    annotator = build_annotator(cfg.annotator, vocabulary=vocab, **cfg.annotator_options)
    annotations = annotator.annotate(requests) if requests else []
    # Episodes, gt (Habitat frame, VLN-CE's fields only), their extras and the shard.
    episodes, gt, extras = [], {}, {}
    writer = approach_writer = None
    n_approach = 0
    if render_fn is not None:
        from image2sim.dataengine.shards import SceneShardWriter

        spec = {"view": cfg.view, "height": cfg.obs_height, "render": render_mode}
        writer = SceneShardWriter(out / "shard", spec)
        if len(kept) > n_regular:
            approach_writer = SceneShardWriter(out / APPROACH_SHARD, spec)
    accepted = [(plan, r) for (plan, r), ann in zip(kept, annotations, strict=True) if ann.accepted]
    # A generator: nothing renders (and no pool starts) until the first frame is asked for.
    rendered = _rendered_frames(accepted, sim, render_fn, inputs, out, cfg, render_workers)
    try:
        for k, ((plan, r), steps, req, ann) in enumerate(
            zip(kept, chunks, requests, annotations, strict=True)
        ):
            if not ann.accepted:
                drops[f"annotation: {ann.reason}"] = drops.get(f"annotation: {ann.reason}", 0) + 1
                continue
            world = navmap.to_world(r.positions)
            heading_w = _world_heading(navmap, plan.heading)
            approach = k >= n_regular  # training frames only, never the episode file
            if approach:
                n_approach += 1
            else:
                ref_idx = sorted({0, *[m.start for m in steps], len(world) - 1})
                extras[req.episode_id] = {
                    "style": ann.style,
                    "structure": ann.structure,
                    "tone": ann.tone,
                    "goal_object": plan.goal_object,
                    "bucket": plan.bucket,
                    "path_length": r.path_length,
                    "num_steps": len(r.actions),
                    "truncated_stuck": r.truncated_stuck,
                    "macro_steps": [m.text for m in steps],
                }
                episodes.append(
                    episode_record(
                        req.episode_id,
                        inputs.name,  # resolvable as <scenes dir>/<scene_id>
                        world[0],
                        heading_w,
                        navmap.to_world(np.asarray(plan.goal)),
                        plan.goal_radius,
                        world[ref_idx],
                        ann.text,
                        plan.geodesic_distance,
                    )
                )
                gt[req.episode_id] = gt_record(world, r.actions, r.forward_steps)
            shard = approach_writer if approach else writer
            if shard is not None:
                frames, frame_steps = next(rendered)
                extra = {
                    "style": ann.style,
                    "start_world": [float(v) for v in world[0]],  # z up, metres
                    "heading_world": float(heading_w),  # about +z, 0 = +x
                }
                if plan.goal_object:  # path episodes (--detector none) have no goal object
                    goal = navmap.to_map(np.asarray(plan.goal_object["position"], dtype=np.float64))
                    seen = goal_in_view(
                        goal, eyes_of(r)[frame_steps], r.headings[frame_steps], occupancy, goal_view
                    )
                    extra["goal_in_view"] = [int(v) for v in seen]
                    extra["goal_category"] = str(plan.goal_object.get("category", ""))
                shard.add(req.episode_id, inputs.name, ann.text, r.actions, frames, frame_steps, extra)
        for w in (writer, approach_writer):
            if w is not None:
                w.close()
    except BaseException:
        for w in (writer, approach_writer):
            if w is not None:
                w.abort()
        raise
    finally:
        rendered.close()  # ends the render pool, if one started
    summary = {
        "scene": inputs.name,
        "scene_id": inputs.scene_id,
        "navigable_area": area,
        "capacity": n,
        "planned": len(plans),
        "rolled_out_ok": len(kept),
        "stopped_at_goal": sum("cut_past_goal_m" in r.extra for _, r in kept),
        "episodes": len(episodes),
        "approach_episodes": n_approach,
        "drops": drops,
        "plan_stats": plan_stats,
        "objects": len(objects),
        "render": render_mode,
        "seconds": time.perf_counter() - t0,
    }
    doc = {"episodes": episodes, "gt": gt, "extras": extras}
    write_bytes_atomic(out / EPISODES_FILE, json.dumps(doc).encode())
    write_bytes_atomic(out / DONE_FILE, json.dumps(summary, indent=1).encode())
    return summary


class _GaussianPrebuild:
    """The scene's Gaussians built in a spawned process while this one extracts the navigation map
    and rolls the episodes out (on a real capture the two take about as long)."""

    def __init__(self, process, conn) -> None:
        self.process, self.conn = process, conn

    @classmethod
    def start(cls, inputs: SceneInputs, out: Path, cfg: EngineConfig, asset_cache, workers: int):
        """A running build, or None when nothing needs building or no second core is given
        (``workers`` <= 1)."""
        # render auto and gaussians splat Gaussians (a renderer needs one of them: EngineConfig).
        gaussian_render = cfg.render in ("auto", "gaussians")
        built = inputs.gaussian_dir is not None or (out / "gaussians").exists()
        if workers <= 1 or not gaussian_render or built:
            return None
        import multiprocessing as mp
        import os

        ctx = mp.get_context("spawn")
        receiver, sender = ctx.Pipe(duplex=False)
        cache = str(asset_cache) if asset_cache else None
        args = (os.getpid(), sender, inputs, out, cache, cfg.gaussians, workers)
        process = ctx.Process(target=_prebuild_main, args=args, daemon=True)
        process.start()
        sender.close()
        return cls(process, receiver)

    def wait(self) -> None:
        """Block until the Gaussians are stored; their build's error is raised here."""
        try:
            error = self.conn.recv()
        except EOFError:
            error = f"the process building them ended with exit code {self.process.exitcode}"
        self.process.join()
        if error:
            raise RuntimeError(f"building the scene's Gaussians failed: {error}")

    def cancel(self) -> None:
        """Stop the build if it still runs (an error elsewhere in the scene)."""
        if self.process.is_alive():
            self.process.terminate()
        self.process.join()
        self.conn.close()


def _prebuild_main(
    parent_pid: int, conn, inputs: SceneInputs, out: Path, asset_cache, gaussians, workers: int
) -> None:
    from image2sim.simulator.lifetime import worker_init

    worker_init(parent_pid)
    try:
        # Frames on `workers` threads: once this process's parent has its map and rollouts, it
        # waits here, and the cores are this build's.
        scene_gaussians(inputs, out, asset_cache, gaussians, workers)
        conn.send("")
    except BaseException as err:  # reported to the parent, which raises it
        conn.send(f"{type(err).__name__}: {err}")
    finally:
        conn.close()


def _world_heading(navmap, heading: float) -> float:
    d = navmap.to_world(np.array([math.cos(heading), math.sin(heading), 0.0]))
    return math.atan2(d[1], d[0])


def observation_steps(n_actions: int, stride: int) -> list[int]:
    """Steps whose observation a shard stores: every ``stride``-th step from 0 (the policy's streaming
    agent observes every other step, so stride 2 stores what it sees), always including step 0."""
    return list(range(0, max(int(n_actions), 1), max(int(stride), 1)))


def _render_rollout(sim, render_fn, plan, r, cfg: EngineConfig) -> tuple[np.ndarray, list[int]]:
    """Observations of the rollout at :func:`observation_steps` (frames, their steps), by re-executing
    it with rendering on where a frame is stored."""
    sim.render_fn = render_fn
    sim.spec = _observation_spec(cfg)
    key = "pinhole" if cfg.view == "pinhole" else "ultrawide"
    steps = observation_steps(len(r.actions), cfg.frame_stride)
    wanted = set(steps)
    try:
        obs, _ = sim.reset(np.asarray(plan.start, float)[None], np.array([plan.heading]))
        frames = [_to_uint8(obs[0][key]["rgb"])]
        for t, a in enumerate(r.actions[:-1], start=1):
            obs, _ = sim.step([a], observe=t in wanted)
            if t in wanted:
                frames.append(_to_uint8(obs[0][key]["rgb"]))
    finally:
        sim.render_fn = None
    return np.stack(frames), steps


_RENDER_STATE: dict = {}
"""A render worker's simulator and render function (built once per process by :func:`_render_setup`)."""


def _render_setup(scene_dir: str, out: str, cfg: dict) -> None:
    from image2sim.simulator.sim import NeuralSimulator

    config = EngineConfig.from_dict(cfg)
    inputs = resolve_scene(scene_dir)
    navmap, graph = scene_navigation(inputs, Path(out))  # cached by the parent: loaded, not rebuilt
    render_fn, _ = scene_render_fn(
        inputs, Path(out), config.render, config.renderer, device=config.device, gaussians=config.gaussians
    )
    _RENDER_STATE.update(sim=NeuralSimulator(navmap, graph), render_fn=render_fn, cfg=config)


def _render_task(job) -> tuple[np.ndarray, list[int]]:
    plan, r = job
    st = _RENDER_STATE
    return _render_rollout(st["sim"], st["render_fn"], plan, r, st["cfg"])


def _rendered_frames(jobs, sim, render_fn, inputs: SceneInputs, out: Path, cfg: EngineConfig, workers: int):
    """(frames, frame steps) of each (plan, rollout) in order: here, or over ``workers`` spawned
    processes (each loads the scene's cached navigation and Gaussians once). Rendering is deterministic
    per rollout, so the frames do not depend on where they were made."""
    if workers <= 1 or len(jobs) < 2:
        for plan, r in jobs:
            yield _render_rollout(sim, render_fn, plan, r, cfg)
        return
    from image2sim.simulator.lifetime import spawn_pool

    args = (str(inputs.scene_dir), str(out), cfg.to_dict())
    pool = spawn_pool(min(workers, len(jobs)), _render_setup, *args)
    try:
        yield from pool.map(_render_task, jobs, chunksize=1)
    finally:  # on an error here, pending renders are cancelled rather than awaited
        pool.shutdown(wait=True, cancel_futures=True)


def _annotation_view(sim, render_fn, plan, r, state: int, cfg: EngineConfig) -> np.ndarray:
    """180 degree view (equirect crop of the panorama) at rollout state ``state``."""
    from image2sim.simulator.sim import ObservationSpec

    h = int(cfg.annotation_view_height)
    sim.render_fn = render_fn
    sim.spec = ObservationSpec(
        panorama=False,
        ultrawide=True,
        pano_height=max(64, h),
        ultrawide_height=h,
        ultrawide_width=int(round(h * 2 * 180 / 118)),
    )
    try:
        sim.reset(np.asarray(r.positions[state], float)[None], np.array([r.headings[state]]), observe=False)
        return _to_uint8(sim.observe(0)["ultrawide"]["rgb"])
    finally:
        sim.render_fn = None
