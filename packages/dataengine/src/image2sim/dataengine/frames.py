"""A scene's observation frames: the stored view of every kept rollout, rendered here or over worker
processes, the 180-degree views VLM annotators see, and the scene's Gaussians built in a process of
their own while :func:`~image2sim.dataengine.pipeline.process_scene` makes the map and the rollouts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from image2sim.dataengine.engine_config import EngineConfig
from image2sim.dataengine.scene_assets import (
    SceneInputs,
    resolve_scene,
    scene_gaussians,
    scene_navigation,
    scene_render_fn,
)

__all__ = [
    "GaussianPrebuild",
    "annotation_view",
    "field_of_view",
    "observation_spec",
    "observation_steps",
    "rendered_frames",
]


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.asarray(rgb, np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)


def observation_spec(cfg: EngineConfig):
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


def field_of_view(spec) -> tuple[float, float]:
    """(horizontal, vertical) degrees of the view an ObservationSpec stores (pinhole views are square)."""
    if spec.pinhole:
        return float(spec.pinhole_hfov_deg), float(spec.pinhole_hfov_deg)
    return float(spec.ultrawide_hfov_deg), float(spec.ultrawide_vfov_deg)


class GaussianPrebuild:
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
        args = (os.getpid(), sender, inputs, out, cache, cfg.gaussians, workers, cfg.refine_steps)
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
    parent_pid: int,
    conn,
    inputs: SceneInputs,
    out: Path,
    asset_cache,
    gaussians,
    workers: int,
    refine_steps: int,
) -> None:
    from image2sim.simulator.lifetime import worker_init

    worker_init(parent_pid)
    try:
        # Frames on `workers` threads: once this process's parent has its map and rollouts, it
        # waits here, and the cores are this build's.
        scene_gaussians(inputs, out, asset_cache, gaussians, workers, refine_steps)
        conn.send("")
    except BaseException as err:  # reported to the parent, which raises it
        conn.send(f"{type(err).__name__}: {err}")
    finally:
        conn.close()


def observation_steps(n_actions: int, stride: int) -> list[int]:
    """Steps whose observation a shard stores: every ``stride``-th step from 0 (the policy's streaming
    agent observes every other step, so stride 2 stores what it sees), always including step 0."""
    return list(range(0, max(int(n_actions), 1), max(int(stride), 1)))


def _render_rollout(sim, render_fn, plan, r, cfg: EngineConfig) -> tuple[np.ndarray, list[int]]:
    """Observations of the rollout at :func:`observation_steps` (frames, their steps), by re-executing
    it with rendering on where a frame is stored."""
    sim.render_fn = render_fn
    sim.spec = observation_spec(cfg)
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
        inputs,
        Path(out),
        config.render,
        config.renderer,
        device=config.device,
        gaussians=config.gaussians,
        refine_steps=config.refine_steps,
    )
    _RENDER_STATE.update(sim=NeuralSimulator(navmap, graph), render_fn=render_fn, cfg=config)


def _render_task(job) -> tuple[np.ndarray, list[int]]:
    plan, r = job
    st = _RENDER_STATE
    return _render_rollout(st["sim"], st["render_fn"], plan, r, st["cfg"])


def rendered_frames(jobs, sim, render_fn, inputs: SceneInputs, out: Path, cfg: EngineConfig, workers: int):
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


def annotation_view(sim, render_fn, plan, r, state: int, cfg: EngineConfig) -> np.ndarray:
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
