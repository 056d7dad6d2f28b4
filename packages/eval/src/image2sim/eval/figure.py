"""The README's demo picture: a rendered panorama beside its splat prior, and a top-down episode map.

:func:`demo_figure` draws, for one held-out view of one scene (the split of ``eval render``):

* the **splat prior**: the scene's Gaussians (built from the other frames) splatted at the held-out
  pose, as the ``splat_only`` method shows it;
* the **rendered panorama**: the pixel-flow renderer's one-step output on that condition;
* the **held-out panorama** the two are scored against (PSNR printed on each);
* a **top-down map** of the scene's navigation map (navigable cells, obstacles) with one episode's
  reference path, start and goal.

The view and its condition come from :func:`~image2sim.eval.render_samples.splat_samples` and the
methods from the benchmark's own method table, so the picture shows exactly what ``eval render``
scores. :func:`demo_figure_from_outputs` finds the inputs in the pipeline's output folders.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from image2sim.eval.datasets import NavEpisode

__all__ = ["FigureError", "demo_figure", "demo_figure_from_outputs", "pick_episode", "topdown_image"]


class FigureError(ValueError):
    """The figure's inputs are missing or inconsistent (message names the file)."""


def topdown_image(navmap: Any) -> np.ndarray:
    """(nx, ny, 3) float RGB of a navigation map's columns: navigable floor light, other floor
    darker, obstacles grey, unknown white. Index ``[i, j]`` is the cell at map x = i, y = j."""
    nx, ny = navmap.shape2d
    img = np.ones((nx, ny, 3))
    obs = np.asarray(navmap.obstacle_ij, dtype=np.int64).reshape(-1, 2)
    img[obs[:, 0], obs[:, 1]] = 0.55
    floor = np.asarray(navmap.floor_ij, dtype=np.int64).reshape(-1, 2)
    nav = np.asarray(navmap.navigable, dtype=bool)
    img[floor[~nav, 0], floor[~nav, 1]] = (0.80, 0.80, 0.80)
    img[floor[nav, 0], floor[nav, 1]] = (0.80, 0.90, 1.00)
    return img


def pick_episode(episodes: Sequence[NavEpisode], scene_names: str | Sequence[str]) -> NavEpisode:
    """The scene's episode with the longest reference path (ties: first in file order).

    An episode belongs to the scene when its ``scene_id`` or its stem is one of ``scene_names``
    (the data engine writes the capture's manifest ``scene_id``; VLN-CE files write scene paths).
    """
    names = {scene_names} if isinstance(scene_names, str) else set(scene_names)
    mine = [e for e in episodes if e.scene_id in names or e.scene_name in names]
    if not mine:
        raise FigureError(f"no episode of scene {sorted(names)} among {len(episodes)} episodes")

    def length(e: NavEpisode) -> float:
        p = e.ndtw_reference
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0

    return max(mine, key=length)


def _image(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().clamp(0, 1).permute(1, 2, 0).numpy()


def demo_figure(
    capture: str | Path,
    navmap: Any,
    episode: NavEpisode,
    out_png: str | Path,
    *,
    renderer_config: str = "tiny",
    checkpoint: str | Path | None = None,
    gaussian_config: str = "tiny",
    holdout_every: int = 8,
) -> dict[str, Any]:
    """Draw the picture to ``out_png`` (atomic); returns what it shows (view index, PSNRs, episode).

    ``navmap`` is the scene's :class:`~image2sim.simulator.navigation.NavMap` (the episode is in the
    world frame and drawn in the map's frame); ``checkpoint`` None renders with an untrained model
    (the title says so).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from image2sim.eval.metrics.render import psnr
    from image2sim.eval.plots import save_figure_atomic
    from image2sim.eval.render_bench import RenderBenchConfig, _methods
    from image2sim.eval.render_samples import splat_samples
    from image2sim.simulator.renderer.config import load_renderer_config

    cfg = load_renderer_config(renderer_config)
    samples = splat_samples([capture], cfg.height, cfg.width, holdout_every, gaussian_config, max_views=1)
    if not samples:
        raise FigureError(f"{capture}: no held-out view (holdout_every={holdout_every})")
    s = samples[0]
    bench = RenderBenchConfig(
        renderer_config=renderer_config, checkpoint=None if checkpoint is None else str(checkpoint), steps=[1]
    )
    methods = _methods(cfg, bench)
    pose = torch.eye(4, dtype=torch.float64)
    pose[0, 3] = float(s["index"])  # as benchmark_methods: the renderer seeds its noise by pose
    target = s["target_rgb"].float()
    shown: dict[str, Any] = {"view_index": int(s["index"]), "target_kind": s["target_kind"]}
    panels = []
    for name, label in (("splat_only", "splat prior"), ("flow_1step", "rendered (pixel flow, 1 step)")):
        with torch.no_grad():
            rgb, _ = methods[name](s["condition"][None], pose[None])
        value = float(psnr(rgb[0].float().clamp(0, 1), target))
        shown[f"psnr_{name}"] = value
        panels.append((f"{label}: PSNR {value:.1f} dB", _image(rgb[0])))
    panels.append((f"held-out panorama ({s['target_kind']} ground truth)", _image(target)))

    path_world = np.asarray(episode.ndtw_reference, dtype=np.float64).reshape(-1, 3)
    path = np.asarray(navmap.to_map(path_world), dtype=np.float64).reshape(-1, 3)
    start = np.asarray(navmap.to_map(episode.start_position), dtype=np.float64).reshape(3)
    goal = np.asarray(navmap.to_map(episode.goal_position), dtype=np.float64).reshape(3)
    origin, voxel = np.asarray(navmap.origin, dtype=np.float64), float(navmap.voxel_size)
    shown.update(episode_id=episode.episode_id, path_points=len(path))

    def cells(p: np.ndarray) -> np.ndarray:
        return (np.atleast_2d(p)[:, :2] - origin[:2]) / voxel - 0.5  # image coords of cell centres

    fig = plt.figure(figsize=(10.0, 6.4), dpi=110)
    grid = fig.add_gridspec(3, 2, width_ratios=(1.4, 1.0))
    for row, (title, img) in enumerate(panels):
        ax = fig.add_subplot(grid[row, 0])
        ax.imshow(img, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    ax = fig.add_subplot(grid[:, 1])
    # Rows of the image are map x, columns map y: transpose so x runs right and y up.
    ax.imshow(topdown_image(navmap).transpose(1, 0, 2), origin="lower", interpolation="nearest")
    c = cells(path)
    ax.plot(c[:, 0], c[:, 1], "-", color="tab:red", lw=2, label="reference path")
    (sx, sy), (gx, gy) = cells(start)[0], cells(goal)[0]
    ax.plot([sx], [sy], "o", color="tab:green", ms=8, label="start")
    ax.plot([gx], [gy], "*", color="tab:orange", ms=13, label="goal")
    # Frame the floor (stray obstacle points far outside the rooms would shrink the map).
    fl = np.asarray(navmap.floor_ij, dtype=np.float64).reshape(-1, 2)
    lo = np.minimum(fl.min(axis=0), np.minimum(c.min(axis=0), cells(goal)[0])) - 8
    hi = np.maximum(fl.max(axis=0), np.maximum(c.max(axis=0), cells(goal)[0])) + 8
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_title(f"episode {episode.episode_id}: top-down navigation map", fontsize=9)
    ax.legend(fontsize=8, loc="upper right")
    ax.set_xticks([])
    ax.set_yticks([])
    trained = "trained renderer" if checkpoint is not None else "UNTRAINED renderer (plumbing run)"
    fig.suptitle(f"{Path(capture).name}, held-out view {s['index']} ({trained})", fontsize=10)
    fig.tight_layout()
    try:
        save_figure_atomic(fig, out_png)
    finally:
        plt.close(fig)
    return shown


def demo_figure_from_outputs(
    scene_dir: str | Path,
    capture: str | Path,
    episodes: str | Path,
    out_png: str | Path,
    *,
    split: str = "train",
    **kwargs: Any,
) -> dict[str, Any]:
    """:func:`demo_figure` on the pipeline's outputs: a scene folder (``navmap.npz``), its capture,
    and an episode file or an ``episodes`` output folder (``{split}/{split}.json.gz``)."""
    from image2sim.eval.datasets import load_image2sim_episodes
    from image2sim.simulator.io.registry import open_capture
    from image2sim.simulator.navigation import NavMap

    scene_dir, episodes = Path(scene_dir), Path(episodes)
    if not (scene_dir / "navmap.npz").is_file():
        raise FigureError(f"{scene_dir}: no navmap.npz")
    path = episodes / split / f"{split}.json.gz" if episodes.is_dir() else episodes
    if not path.is_file():
        raise FigureError(f"{path}: episode file not found")
    gt = path.with_name(path.name.replace(".json.gz", "_gt.json.gz"))
    eps = load_image2sim_episodes(path, gt if gt.is_file() else None).episodes
    episode = pick_episode(eps, [scene_dir.name, open_capture(capture).scene_id])
    return demo_figure(capture, NavMap.load(scene_dir / "navmap.npz"), episode, out_png, **kwargs)
