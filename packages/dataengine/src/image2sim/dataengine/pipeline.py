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
  4. observations along each kept rollout (:mod:`.frames`; render function: the exact procedural
     renderer, the Gaussian scene via ``splat``, or none), a shard, and
     ``{out}/scenes/{name}/episodes.json`` written atomically; ``done.json`` last.

The config is :class:`~image2sim.dataengine.engine_config.EngineConfig` (re-exported here).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from image2sim.dataengine.chunking import ChunkConfig, macro_steps, path_features
from image2sim.dataengine.engine_config import EngineConfig
from image2sim.dataengine.episodes import episode_record, gt_record
from image2sim.dataengine.frames import (
    GaussianPrebuild,
    annotation_view,
    field_of_view,
    observation_spec,
    rendered_frames,
)
from image2sim.dataengine.rollout import (
    RolloutConfig,
    closest_approach_cut,
    face_target,
    replay,
    rollout_plan,
    truncate_rollout,
)
from image2sim.dataengine.scene_assets import (
    SceneInputs,
    resolve_scene,
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
from image2sim.simulator.config import config_from_dict
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
# ---------------------------------------------------------------------------------------- helpers


def _stop_at_the_goal(sim, plan, r, navmap, scfg, rcfg):
    """A rollout that walks past the goal object (its end is more than ``rcfg.overshoot`` farther from
    the object than its closest approach) stops at the closest approach instead; the episode's goal and
    length follow. Dropped (reason ``overshoot_too_short``) when the cut path is no longer a valid
    episode (shorter than the sampling config allows, or than ``rcfg.min_steps``). With
    ``rcfg.face_goal`` the expert then turns towards the goal object before it stops."""
    if plan.goal_object:
        target = navmap.to_map(np.asarray(plan.goal_object["position"], dtype=np.float64).reshape(1, 3))[0]
    else:  # a path episode: its goal is a point
        target = np.asarray(plan.goal, dtype=np.float64)
    r, plan = _cut_at_closest_approach(sim, plan, r, target, scfg, rcfg)
    if r.ok and rcfg.face_goal and plan.goal_object:
        r = face_target(r, target, sim.embodiment.turn_angle)
    return r, plan


def _cut_at_closest_approach(sim, plan, r, target, scfg, rcfg):
    """The overshoot cut of :func:`_stop_at_the_goal` (see there)."""
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
    reach the same end, facing the same way, without a collision. A rejected rollout says why in
    ``reason``."""
    from image2sim.simulator.navigation.agent import wrap_angle

    r = rollout_plan(sim, follower, plan, rcfg)
    if r.ok and cut is not None:
        r, plan = cut(plan, r)
    if r.ok:
        pos, head, col = replay(sim, plan.start, plan.heading, r.actions)
        turned = abs(wrap_angle(float(head[-1]) - float(r.headings[-1])))
        if np.abs(pos[-1] - r.positions[-1]).max() > 1e-6 or turned > 1e-6 or any(col):
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
    prebuild = GaussianPrebuild.start(inputs, out, cfg, asset_cache, render_workers)
    # With render workers the cores belong to them and to the Gaussians' build beside this process,
    # so its own torch ops run on one thread: on two threads they oversubscribed the cores (the
    # HM3D sample's command took 159 s instead of 141, byte-identical output).
    try:
        with torch_threads(1 if render_workers > 1 else 0):
            return _run_scene(inputs, out, cfg, render_workers, asset_cache, prebuild, t0)
    finally:
        if prebuild is not None:
            prebuild.cancel()


@dataclass
class _Scene:
    """What the stages of one scene share: its inputs and config, navigation, objects and simulator."""

    inputs: SceneInputs
    out: Path
    cfg: EngineConfig
    navmap: object
    graph: object
    objects: list
    sim: object
    rng: np.random.Generator
    occupancy: object  # obstacle voxels for visibility (None: no occlusion test or no objects)

    def eyes(self, r) -> np.ndarray:
        """The agent's eye positions along rollout ``r`` (map frame)."""
        up = np.array([0.0, 0.0, float(self.navmap.embodiment.eye_height)])
        return np.asarray(r.positions, dtype=np.float64) + up


@dataclass
class _Rollouts:
    """The scene's verified rollouts: the episodes' first (``n_regular``), then approach episodes."""

    capacity: int
    plans: list
    plan_stats: dict
    kept: list  # (plan, rollout)
    n_regular: int
    drops: dict


def _run_scene(inputs, out: Path, cfg: EngineConfig, render_workers: int, asset_cache, prebuild, t0: float):
    """:func:`process_scene`'s work once the output folder exists (``prebuild``: the Gaussians being
    built meanwhile, or None): rollouts, annotation, then the episodes and shards."""
    from image2sim.dataengine.visibility import Occupancy
    from image2sim.simulator.sim import NeuralSimulator

    navmap, graph = scene_navigation(inputs, out, asset_cache)
    objects = scene_objects(inputs, out, cfg)
    scene = _Scene(
        inputs,
        out,
        cfg,
        navmap,
        graph,
        objects,
        NeuralSimulator(navmap, graph),
        named_rng(cfg.seed, inputs.name),
        Occupancy.from_navmap(navmap) if cfg.occlusion and objects else None,
    )
    ro = _roll_out(scene)
    if prebuild is not None:
        prebuild.wait()
    render_fn, render_mode = (
        (None, "none")
        if cfg.render == "none"
        else scene_render_fn(
            inputs, out, cfg.render, cfg.renderer, asset_cache, cfg.device, cfg.gaussians, cfg.refine_steps
        )
    )
    if cfg.annotator != "template" and render_fn is None:
        raise ValueError(f"{inputs.name}: VLM annotators need rendered views (render={cfg.render!r})")
    requests, chunks = _annotation_requests(scene, ro, render_fn)
    from image2sim.dataengine.annotate import build_annotator

    vocab = sorted({o.category for o in scene.objects})
    annotator = build_annotator(cfg.annotator, vocabulary=vocab, **cfg.annotator_options)
    annotations = annotator.annotate(requests) if requests else []
    episodes, gt, extras, n_approach = _write_episodes_and_shards(
        scene, ro, chunks, requests, annotations, render_fn, render_mode, render_workers
    )
    summary = {
        "scene": inputs.name,
        "scene_id": inputs.scene_id,
        "navigable_area": navmap.navigable_area(),
        "capacity": ro.capacity,
        "planned": len(ro.plans),
        "rolled_out_ok": len(ro.kept),
        "stopped_at_goal": sum("cut_past_goal_m" in r.extra for _, r in ro.kept),
        "episodes": len(episodes),
        "approach_episodes": n_approach,
        "drops": ro.drops,
        "plan_stats": ro.plan_stats,
        "objects": len(scene.objects),
        "render": render_mode,
        "seconds": time.perf_counter() - t0,
    }
    doc = {"episodes": episodes, "gt": gt, "extras": extras}
    write_bytes_atomic(out / EPISODES_FILE, json.dumps(doc).encode())
    write_bytes_atomic(out / DONE_FILE, json.dumps(summary, indent=1).encode())
    return summary


def _roll_out(scene: _Scene) -> _Rollouts:
    """Plans (object goals, or paths for ``detector none``) rolled out by the oracle and replayed,
    up to the scene's capacity, then the approach episodes (training frames only)."""
    from image2sim.simulator.navigation.follower import OracleFollower

    cfg, sim, navmap, graph = scene.cfg, scene.sim, scene.navmap, scene.graph
    scfg = config_from_dict(SamplingConfig, cfg.sampling, "sampling")
    rcfg = config_from_dict(RolloutConfig, cfg.rollout, "rollout")
    n = cfg.per_scene if cfg.per_scene is not None else episode_capacity(navmap.navigable_area(), scfg)
    follower = OracleFollower(sim.planner)
    n_plans = int(math.ceil(n * scfg.plan_oversample))
    if cfg.detector == "none":
        plans, plan_stats = sample_path_plans(graph, n_plans, scfg, scene.rng)
    else:
        plans, plan_stats = sample_plans(
            graph, sim.planner, scene.objects, n_plans, scfg, scene.rng, navmap.to_map
        )
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
    if scene.objects and cfg.render != "none":  # approach episodes are training frames only
        kept += _approach_rollouts(
            sim,
            follower,
            graph,
            scene.objects,
            navmap,
            scene.occupancy,
            cfg,
            scfg,
            rcfg,
            scene.inputs.name,
            drops,
        )
    return _Rollouts(n, plans, plan_stats, kept, n_regular, drops)


def _annotation_requests(scene: _Scene, ro: _Rollouts, render_fn) -> tuple[list, list]:
    """One annotation request per kept rollout (its macro-steps, the objects visible at each, rooms,
    route style, "near" landmarks, path features; VLM annotators also get 180-degree views), and
    the macro-steps themselves."""
    from image2sim.dataengine.annotate import AnnotationRequest, route_style
    from image2sim.dataengine.visibility import VisibilityConfig, near_categories, visible_categories

    cfg, navmap, objects, rng = scene.cfg, scene.navmap, scene.objects, scene.rng
    name = scene.inputs.name
    vlm = cfg.annotator != "template"
    vis_cfg = VisibilityConfig(
        max_distance=cfg.visible_distance, tolerance=cfg.occlusion_tolerance, occlusion=cfg.occlusion
    )
    obj_map = navmap.to_map(np.array([o.position for o in objects], dtype=np.float64).reshape(-1, 3))
    index_of = {int(o.object_id): i for i, o in enumerate(objects)}
    near_of: dict[int, list[str]] = {}  # goal object id -> its "near" landmarks (computed once per goal)
    requests, chunks = [], []
    for k, (plan, r) in enumerate(ro.kept):
        eid = f"{name}-{k:05d}" if k < ro.n_regular else f"{name}-a{k - ro.n_regular:05d}"
        steps = macro_steps(r.actions, r.positions, r.headings, ChunkConfig())
        world = navmap.to_world(r.positions)
        eyes = scene.eyes(r)
        vis = [
            visible_categories(objects, obj_map, eyes[m.start], r.headings[m.start], scene.occupancy, vis_cfg)
            for m in steps
        ]
        rooms = [_room_at(objects, world[m.start]) for m in steps]
        style, structure, tone = route_style(rng)
        near: list[str] = []
        if plan.goal_object:
            gid = int(plan.goal_object["object_id"])
            if gid not in near_of:
                near_of[gid] = near_categories(index_of[gid], objects, obj_map, scene.occupancy)
            near = near_of[gid]
        else:
            style = "r2r"  # a path instruction (no goal object to ask for)
        node, _ = scene.graph.snap(np.asarray(r.positions, dtype=np.float64))
        clearance = np.where(node >= 0, scene.graph.clearance[np.maximum(node, 0)], 0.0)
        images = []
        if vlm:
            images = [annotation_view(scene.sim, render_fn, plan, r, m.start, cfg) for m in steps]
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
    return requests, chunks


def _write_episodes_and_shards(
    scene: _Scene, ro: _Rollouts, chunks, requests, annotations, render_fn, render_mode, render_workers
):
    """Episodes, gt (Habitat frame, VLN-CE's fields only) and their extras of the accepted rollouts,
    and their frames in the shard (approach episodes: in their own shard only). Returns
    (episodes, gt, extras, approach episode count); rejected annotations are counted in ``ro.drops``."""
    from image2sim.dataengine.visibility import VisibilityConfig, goal_in_view

    inputs, out, cfg, navmap, drops = scene.inputs, scene.out, scene.cfg, scene.navmap, ro.drops
    fov = field_of_view(observation_spec(cfg))  # the stored observation's
    goal_view = VisibilityConfig(
        max_distance=cfg.goal_view_distance,
        hfov_deg=fov[0],
        vfov_deg=fov[1],
        tolerance=cfg.occlusion_tolerance,
        occlusion=cfg.occlusion,
    )
    episodes, gt, extras = [], {}, {}
    writer = approach_writer = None
    n_approach = 0
    if render_fn is not None:
        from image2sim.dataengine.shards import SceneShardWriter

        spec = {"view": cfg.view, "height": cfg.obs_height, "render": render_mode}
        writer = SceneShardWriter(out / "shard", spec)
        if len(ro.kept) > ro.n_regular:
            approach_writer = SceneShardWriter(out / APPROACH_SHARD, spec)
    accepted = [(plan, r) for (plan, r), ann in zip(ro.kept, annotations, strict=True) if ann.accepted]
    # A generator: nothing renders (and no pool starts) until the first frame is asked for.
    rendered = rendered_frames(accepted, scene.sim, render_fn, inputs, out, cfg, render_workers)
    try:
        for k, ((plan, r), steps, req, ann) in enumerate(
            zip(ro.kept, chunks, requests, annotations, strict=True)
        ):
            if not ann.accepted:
                drops[f"annotation: {ann.reason}"] = drops.get(f"annotation: {ann.reason}", 0) + 1
                continue
            world = navmap.to_world(r.positions)
            heading_w = _world_heading(navmap, plan.heading)
            approach = k >= ro.n_regular  # training frames only, never the episode file
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
                        goal, scene.eyes(r)[frame_steps], r.headings[frame_steps], scene.occupancy, goal_view
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
    return episodes, gt, extras, n_approach


def _world_heading(navmap, heading: float) -> float:
    d = navmap.to_world(np.array([math.cos(heading), math.sin(heading), 0.0]))
    return math.atan2(d[1], d[0])
