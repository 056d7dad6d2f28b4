"""Scale-out and resumability: one task per scene, run in local processes or through Ray.

``run_engine(scene_dirs, out_dir, config, executor="local", workers=2, address=None)``:
  * one run per output folder at a time: ``{out}/.run.lock`` is held (``flock``) for the whole run, so
    two runs on one ``--out`` cannot interleave their scenes and ``run.json``;
  * a run manifest ``{out}/run.json`` records the engine config; restarting with a different config
    in the same folder is refused (it would mix incompatible episodes);
  * a scene is finished when ``{out}/scenes/{name}/done.json`` exists (written last and atomically by
    :func:`~image2sim.dataengine.pipeline.process_scene`), and finished scenes are skipped on restart;
  * per-scene failures are recorded in ``{out}/failures.json`` and do not stop other scenes;
  * the final episode files are rebuilt from the finished scenes' ``episodes.json`` in sorted scene
    order, so a killed-and-restarted run yields the same files with no duplicates and nothing lost;
  * ``{out}/shards.json`` lists the training shards relative to itself (``scenes/<name>/shard``), so
    the output folder can be moved; :func:`read_shard_list` resolves them (older absolute lists too).

``local`` (the default) runs the scenes in this process (``workers=1``) or in a pool of ``workers``
spawned processes that die with the driver: no network, nothing left behind by a killed run.
``ray`` is for clusters (``address``) or an explicit choice: a local Ray (``ray.init(num_cpus=workers)``,
no dashboard, usage statistics off) still opens ports on every interface in Ray 2.60. Each
task runs in a worker whose runtime environment pins the BLAS/OpenMP pools to one thread
(:data:`WORKER_ENV`) and which sets torch to one thread, so ``workers`` tasks use ``workers`` cores
and do not oversubscribe them. At most ``workers`` tasks are in flight at once on a local Ray (so the
same Ray instance can run a 1-worker and a 2-worker pass); on a cluster every task is submitted.
"""

from __future__ import annotations

import json
import os
import time
import traceback
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from pathlib import Path

from image2sim.dataengine.engine_config import EngineConfig
from image2sim.dataengine.episodes import check_episode_layout, write_episode_files
from image2sim.dataengine.pipeline import APPROACH_SHARD, DONE_FILE, EPISODES_FILE, process_scene
from image2sim.simulator.io.atomic import write_bytes_atomic
from image2sim.simulator.io.paths import relative_to_file, resolve_from_file
from image2sim.simulator.lifetime import WORKER_ENV, spawn_pool

__all__ = ["find_scenes", "pending_scenes", "read_shard_list", "run_engine", "merge_outputs", "RunError"]

RUN_FILE = "run.json"
SHARD_LIST = "shards.json"
"""The output folder's list of training shards, ``{"shards": [path relative to this file, ...]}``."""


def read_shard_list(path: str | Path) -> list[Path]:
    """The shard folders a ``shards.json`` lists (or the one in the output folder ``path``), resolved
    relative to the file; absolute entries (files written before the paths were relative) as they are."""
    path = Path(path)
    if path.is_dir():
        path = path / SHARD_LIST
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise FileNotFoundError(f"{path}: no such shard list (run `image2sim data episodes` first)") from exc
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    shards = doc.get("shards") if isinstance(doc, dict) else None
    if not isinstance(shards, list) or not all(isinstance(s, str) for s in shards):
        raise ValueError(f"{path}: expected {{'shards': [path, ...]}}")
    return [resolve_from_file(s, path) for s in shards]


class RunError(RuntimeError):
    """The run cannot start (bad inputs or a conflicting earlier run in the output folder)."""


def _is_scene(path: Path) -> bool:
    """A canonical capture or built scene (``manifest.json``), or a capture of any readable format."""
    if (path / "manifest.json").is_file():
        return True
    from image2sim.simulator.io.records import CaptureError
    from image2sim.simulator.io.registry import detect_format

    try:
        detect_format(path)
    except CaptureError:
        return False
    return True


def find_scenes(root: str | Path) -> list[Path]:
    """Scene folders under ``root``: ``root`` itself when it is a scene, else its sub-folders that are.
    A scene is a canonical capture, a built scene folder, or a capture of any format the readers
    detect (HM3D panoramas, RealSee3D, ScanNet-style exports), read in place."""
    root = Path(root)
    if not root.is_dir():
        raise RunError(f"{root}: scenes folder not found")
    if _is_scene(root):
        return [root]
    found = sorted(p for p in root.iterdir() if p.is_dir() and _is_scene(p))
    if not found:
        from image2sim.simulator.io.registry import available_formats

        raise RunError(
            f"{root}: neither a capture nor a folder of captures (no sub-folder has a manifest.json or "
            f"a layout of a known format: {', '.join(available_formats())}). "
            "`image2sim data inspect <folder>` tells why a capture is not recognised"
        )
    names = [p.name for p in found]
    if len(set(names)) != len(names):
        raise RunError(f"{root}: duplicate scene names")
    return found


def pending_scenes(scenes: Sequence[Path], out_dir: Path) -> list[Path]:
    return [s for s in scenes if not (out_dir / "scenes" / s.name / DONE_FILE).is_file()]


# Fields that change where the work runs, not what it writes: a run may resume on another device.
_PLACEMENT_FIELDS = ("device",)


def _check_run_manifest(out_dir: Path, config: EngineConfig) -> None:
    path = out_dir / RUN_FILE
    cfg = config.to_dict()
    if path.is_file():
        old = json.loads(path.read_text()).get("config")
        # A field added since that run reads as its default (what that run did).
        old = {**EngineConfig().to_dict(), **(old or {})}
        old = {k: v for k, v in old.items() if k not in _PLACEMENT_FIELDS}
        new = {k: v for k, v in cfg.items() if k not in _PLACEMENT_FIELDS}
        if old != new:
            diff = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
            raise RunError(
                f"{path}: an earlier run used a different config (fields {diff}); "
                "use a new --out folder or the same arguments"
            )
    else:
        write_bytes_atomic(path, json.dumps({"config": cfg}, indent=1).encode())


def _run_local(
    todo: Sequence[Path],
    out_dir: Path,
    cfg: dict,
    on_done: Callable,
    workers: int = 1,
    assets: str | None = None,
) -> None:
    """In this process (``workers == 1``), else in a pool of ``workers`` spawned processes that end
    with this one (no network, no daemon: the default executor)."""
    if workers <= 1 or len(todo) <= 1:
        for s in todo:  # one scene at a time; its episodes render over the workers (parallel inside it)
            try:
                on_done(s, process_scene(s, out_dir, cfg, render_workers=workers, asset_cache=assets), None)
            except Exception as err:  # noqa: BLE001 - a scene failure must not stop the run
                on_done(s, None, f"{type(err).__name__}: {err}\n{traceback.format_exc(limit=3)}")
        return
    from concurrent.futures import as_completed

    with spawn_pool(min(workers, len(todo))) as pool:
        futures = {pool.submit(_scene_task, str(s), str(out_dir), cfg, assets): s for s in todo}
        for fut in as_completed(futures):
            try:
                summary, err = fut.result()
            except Exception as exc:  # noqa: BLE001 - e.g. the worker process died: report, go on
                summary, err = None, f"{type(exc).__name__}: {exc}"
            on_done(futures[fut], summary, err)


@contextmanager
def run_lock(out_dir: Path):
    """Hold ``<out>/.run.lock`` (an exclusive ``flock``) for the run: a second run on the same output
    folder fails at once instead of mixing its scenes and ``run.json`` with this one's. The kernel
    drops the lock when the process dies, so a killed run never leaves a stale lock."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock (documented)
        yield
        return
    path = Path(out_dir) / ".run.lock"
    with open(path, "a") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RunError(
                f"{out_dir}: another run is writing to this folder ({path} is locked); wait for it or "
                "use another --out"
            ) from None
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _run_ray(
    todo: Sequence[Path],
    out_dir: Path,
    cfg: dict,
    on_done: Callable,
    workers: int,
    address: str | None,
    assets: str | None = None,
) -> None:
    try:
        import ray
    except ImportError:
        raise RunError(
            "--executor ray needs Ray: pip install 'image2sim-dataengine[ray]' "
            "(the default --executor local needs nothing)"
        ) from None

    started = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage report, no cloud-metadata probe
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        started = True
    try:
        task = ray.remote(num_cpus=1, max_retries=0, runtime_env={"env_vars": dict(WORKER_ENV)})(_scene_task)
        queue = list(todo)
        cap = len(queue) if address else max(1, int(workers))
        refs: dict = {}
        while queue or refs:
            while queue and len(refs) < cap:
                s = queue.pop(0)
                refs[task.remote(str(s), str(out_dir), cfg, assets)] = s
            done, _ = ray.wait(list(refs), num_returns=1)
            for ref in done:
                try:
                    summary, err = ray.get(ref)
                except Exception as exc:  # noqa: BLE001 - e.g. the worker process died: report, go on
                    summary, err = None, f"{type(exc).__name__}: {exc}"
                on_done(refs.pop(ref), summary, err)
    finally:
        if started:
            ray.shutdown()


def _scene_task(scene: str, out_dir: str, cfg: dict, assets: str | None = None):
    """One scene in a Ray worker: torch at one thread; the summary gains the task's wall/CPU seconds."""
    import torch

    torch.set_num_threads(1)
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        summary = process_scene(scene, out_dir, cfg, asset_cache=assets)
        summary["task"] = {
            "pid": os.getpid(),
            "wall_s": time.perf_counter() - t0,
            "cpu_s": time.process_time() - c0,
            "torch_threads": torch.get_num_threads(),
            "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        }
        return summary, None
    except Exception as err:  # noqa: BLE001 - reported, not raised: other scenes go on
        return None, f"{type(err).__name__}: {err}\n{traceback.format_exc(limit=3)}"


def run_engine(
    scenes_root: str | Path,
    out_dir: str | Path,
    config: EngineConfig,
    executor: str = "local",
    workers: int = 2,
    address: str | None = None,
    progress: bool = True,
    limit: int | None = None,
    asset_cache: str | Path | None = None,
    episode_format: str = "r2r-ce",
    language: str = "en-US",
) -> dict:
    """Process every unfinished scene, then rebuild the merged outputs. Returns the run summary.

    ``episode_format`` (r2r-ce or rxr-ce, :func:`~image2sim.dataengine.episodes.write_episode_files`)
    and ``language`` (rxr-ce) only shape the merged episode files, not the scenes' work, so they are
    not part of the run's config: a finished run can be merged again in the other layout.

    ``asset_cache``: scene assets (maps, Gaussians) shared across runs, keyed by each capture's content
    (:mod:`.asset_cache`); not part of the run's config (it changes no output).
    ``limit`` processes at most that many pending scenes (used to simulate interruptions in tests).
    ``tasks`` in the result maps each scene run through Ray to its worker pid, wall and CPU seconds.
    """
    if executor not in ("local", "ray"):
        raise RunError(f"executor must be local or ray, got {executor!r}")
    layout = {"fmt": episode_format, "language": language, "annotator_id": f"image2sim-{config.annotator}"}
    check_episode_layout(episode_format, language)  # fails before any work, not at the merge
    out_dir = Path(out_dir)
    scenes = find_scenes(scenes_root)
    out_dir.mkdir(parents=True, exist_ok=True)
    with run_lock(out_dir):
        assets = None if asset_cache is None else str(Path(asset_cache).resolve())
        return _run_locked(
            scenes, out_dir, config, executor, workers, address, progress, limit, assets, layout
        )


def _run_locked(
    scenes, out_dir: Path, config: EngineConfig, executor, workers, address, progress, limit, assets, layout
) -> dict:
    _check_run_manifest(out_dir, config)
    todo = pending_scenes(scenes, out_dir)
    skipped = len(scenes) - len(todo)
    if limit is not None:
        todo = todo[:limit]
    failures: dict[str, str] = {}
    tasks: dict[str, dict] = {}
    fail_path = out_dir / "failures.json"
    bar = task_id = None
    if progress and todo:
        from rich.progress import Progress

        bar = Progress()
        bar.start()
        task_id = bar.add_task(f"scenes ({skipped} already done)", total=len(todo))

    def on_done(scene: Path, summary, err) -> None:
        if summary is not None and "task" in summary:
            tasks[scene.name] = summary["task"]
        if err is not None:
            failures[scene.name] = err
            write_bytes_atomic(fail_path, json.dumps(failures, indent=1).encode())
        if bar is not None:
            bar.advance(task_id)

    try:
        if executor == "local":
            _run_local(todo, out_dir, config.to_dict(), on_done, workers, assets)
        else:
            _run_ray(todo, out_dir, config.to_dict(), on_done, workers, address, assets)
    finally:
        if bar is not None:
            bar.stop()
    from image2sim.dataengine.trajectories import SamplingConfig
    from image2sim.simulator.config import config_from_dict

    min_geodesic = config_from_dict(SamplingConfig, config.sampling, "sampling").min_path_length
    merged = merge_outputs(out_dir, [s.name for s in scenes], config.split, min_geodesic, **layout)
    return {
        "scenes": len(scenes),
        "skipped": skipped,
        "processed": len(todo) - len(failures),
        "failed": failures,
        "tasks": tasks,
        **merged,
    }


def merge_outputs(
    out_dir: str | Path,
    scene_names: Sequence[str],
    split: str,
    min_geodesic: float = 0.0,
    fmt: str = "r2r-ce",
    language: str = "en-US",
    annotator_id: str = "image2sim",
) -> dict:
    """Rebuild the split's episode files (``{out}/{split}/{split}.json.gz`` + gt, or with ``fmt``
    rxr-ce ``{split}_guide.json.gz`` + gt) and the shard list from finished scenes; every episode is
    checked as it is written (schema, gt, geodesic >= ``min_geodesic``)."""
    out_dir = Path(out_dir)
    episodes, gt, extras, shards, done, per_scene = [], {}, {}, [], [], {}
    for name in sorted(scene_names):
        folder = out_dir / "scenes" / name
        if not (folder / DONE_FILE).is_file():
            continue
        doc = json.loads((folder / EPISODES_FILE).read_text())
        per_scene[name] = _scene_outcome(json.loads((folder / DONE_FILE).read_text()), len(doc["episodes"]))
        episodes += doc["episodes"]
        gt.update(doc["gt"])
        extras.update(doc.get("extras", {}))
        done.append(name)
        for shard in ("shard", APPROACH_SHARD):  # a scene's episodes, then its approach episodes
            if (folder / shard / "manifest.json").is_file():
                shards.append(relative_to_file(folder / shard, out_dir / SHARD_LIST))
    main, gt_path = write_episode_files(
        out_dir, split, episodes, gt, min_geodesic, extras, fmt, language, annotator_id
    )
    write_bytes_atomic(out_dir / SHARD_LIST, json.dumps({"shards": shards}, indent=1).encode())
    return {
        "episodes": len(episodes),
        "scenes_done": len(done),
        "episode_file": str(main),
        "gt_file": str(gt_path),
        "shards": len(shards),
        "per_scene": per_scene,
    }


def _scene_outcome(done: dict, n: int) -> dict:
    """One scene's line of the run summary: its episode count and, when it has none, why (the most
    frequent reasons of its planning and rollout statistics)."""
    out: dict = {"episodes": n}
    if n == 0:
        reasons = {k: v for k, v in {**done.get("plan_stats", {}), **done.get("drops", {})}.items()}
        reasons.pop("planned", None)
        top = sorted(reasons.items(), key=lambda kv: -kv[1])[:3]
        out["why"] = ", ".join(f"{k}: {v}" for k, v in top) or "no objects to navigate to"
        out["navigable_area_m2"] = round(float(done.get("navigable_area", 0.0)), 2)
    return out
