"""Benchmark one per-scene refinement step: eager against compiled projection, same run, same scene.

A refinement step (``gaussians.refine``) splats the scene at one source frame through the
differentiable path, backpropagates RGB L1 + 0.5 x relative depth error, and takes an Adam step.
The projection (``splatting.project.project_gaussians``, float64 torch ops) dominated it eagerly;
``splat(..., compile_projection=True)`` runs it through ``torch.compile``. This script measures:

* ``step``: a whole refinement step (forward, backward, Adam) with the eager and the compiled
  projection, median of ``--repeats`` after one warm-up, wall and CPU seconds, and their ratio;
* ``projection``: forward + backward of the projection alone, the same way;
* ``compile``: the first compiled call, which compiles (wall seconds). By default inductor's cache
  goes to a fresh temporary folder, so this is the cold compile a new machine pays; ``--warm-cache``
  keeps the user's cache (a later process on the same machine).

Scenes: the HM3D sample's default ``best`` scene (tiny config, all 86 panoramas) when
``../shared/data`` is present, and a procedural house (noise tier ``middle``, 16 panoramas).

Run: ``.venv/bin/python benchmarks/refine_step.py [--repeats 5] [--threads 1] [--warm-cache]``.
Writes ``reports/refine_step.json`` and ``reports/refine_step.md``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="timed calls per case (after one warm-up)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--warm-cache", action="store_true", help="keep inductor's cache (default: a fresh one)")
    ap.add_argument("--skip-hm3d", action="store_true", help="the procedural house only")
    args = ap.parse_args()
    cache = None
    if not args.warm_cache:  # before torch is imported: inductor reads it once
        cache = tempfile.TemporaryDirectory(prefix="inductor-cold-")
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = cache.name
    run(args)
    if cache is not None:
        cache.cleanup()


def scenes(skip_hm3d: bool, tmp: Path):
    """(name, scene, capture) pairs: the HM3D sample (if present) and a procedural house."""
    import dataclasses

    from image2sim.dataengine.procedural import generate_scene, preset, write_scene
    from image2sim.simulator.gaussians import tiny
    from image2sim.simulator.gaussians.build import build_scene
    from image2sim.simulator.io.registry import open_capture

    root = Path(__file__).resolve().parents[1]
    hm3d = Path(os.environ.get("IMAGE2SIM_SHARED_DATA", root.parent / "shared" / "data"))
    hm3d = hm3d / "hm3d_360" / "00000-kfPV7w3FaU5"
    if hm3d.is_dir() and not skip_hm3d:
        yield "HM3D 00000-kfPV7w3FaU5 (86 panoramas)", build_scene(hm3d, tiny()), open_capture(hm3d)
    sc = dataclasses.replace(preset("default"), noise="middle")
    sc = dataclasses.replace(sc, capture=dataclasses.replace(sc.capture, views=16))
    cap = tmp / "house"
    write_scene(generate_scene(sc, seed=9000), cap)
    yield "procedural middle, seed 9000 (16 panoramas)", build_scene(cap, tiny()), open_capture(cap)


def measure(name: str, scene, capture, repeats: int) -> list[dict]:
    """Rows ``step`` and ``projection`` of one scene (see the module docstring)."""
    import torch
    import torch.nn.functional as F
    from harness import time_it
    from image2sim.simulator.gaussians.frames import prepare_frame
    from image2sim.simulator.gaussians.refine import RefineConfig, frame_loss, initial_parameters
    from image2sim.simulator.splatting import project as project_mod
    from image2sim.simulator.splatting.project import projector

    enc = scene.info["encoding"]
    view = prepare_frame(capture[3], enc["height"], enc["width"], scene.fusion.edge_tolerance)
    g = scene.gaussians
    depth_weight = RefineConfig().depth_weight
    params = initial_parameters(g)
    opt = torch.optim.Adam(list(params.values()), lr=1e-6, eps=1e-15)  # tiny: the scene barely moves

    def step(compiled: bool) -> None:
        opt.zero_grad(set_to_none=True)
        frame_loss(params, g.features, view, depth_weight, compiled).backward()
        opt.step()

    def projection(compiled: bool) -> None:
        proj = projector(compiled)(
            params["means"],
            params["log_scales"].exp(),
            F.normalize(params["quats"], dim=-1),
            torch.sigmoid(params["opacity_logits"]).detach(),
            view.camera,
            view.cam_to_world.to(params["means"].dtype),
        )
        (proj.means2d.sum() + proj.conics.sum() + proj.depths.sum()).backward()

    t0 = time.perf_counter()
    step(True)  # compiles (and warms) the compiled path
    compile_s = time.perf_counter() - t0
    if project_mod._compile_failed:
        sys.exit(f"compiling failed: {project_mod._compile_failed}")
    rows = []
    for case, fn in (("step", step), ("projection", projection)):
        eager = time_it(lambda f=fn: f(False), repeats=repeats)
        comp = time_it(lambda f=fn: f(True), repeats=repeats)
        rows.append(
            {
                "scene": name,
                "gaussians": len(g),
                "resolution": f"{enc['width']}x{enc['height']}",
                "case": case,
                "eager_s": round(eager.wall, 4),
                "compiled_s": round(comp.wall, 4),
                "speedup": round(eager.wall / comp.wall, 2),
                "eager_cpu_s": round(eager.cpu, 4),
                "compiled_cpu_s": round(comp.cpu, 4),
                "first_compiled_step_s": round(compile_s, 1) if case == "step" else None,
            }
        )
        print(rows[-1], flush=True)
    return rows


def run(args) -> None:
    import torch
    from harness import hardware, load_average, utc_now, write_report

    torch.set_num_threads(args.threads)
    load = load_average()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, scene, capture in scenes(args.skip_hm3d, Path(tmp)):
            rows.extend(measure(name, scene, capture, args.repeats))
    cache_note = (
        "a fresh inductor cache (the cold compile of a new machine)"
        if not args.warm_cache
        else ("inductor's existing cache (a later process on the same machine)")
    )
    lines = [
        "# One refinement step: eager against compiled projection (`benchmarks/refine_step.py`)",
        "",
        f"- Hardware: {hardware()}; load average {load:.1f} at start; {utc_now()}",
        f"- Median of {args.repeats} calls after one warm-up, wall seconds (CPU seconds in the JSON). "
        "`step`: splat one source frame (256x128 panorama, tiny config) through the differentiable "
        "path, RGB L1 + 0.5 x relative depth error, backward, Adam. `projection`: forward + backward "
        "of `project_gaussians` alone.",
        f"- `first compiled step`: the first call of the compiled path, compile included, with {cache_note}.",
        "",
        "| scene | Gaussians | case | eager s | compiled s | speedup | first compiled step s |",
        "|---|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        first = r["first_compiled_step_s"]
        lines.append(
            f"| {r['scene']} | {r['gaussians']} | {r['case']} | {r['eager_s']:.3f} | {r['compiled_s']:.3f} | "
            f"{r['speedup']:.2f}x | {'' if first is None else first} |"
        )
    write_report(
        "refine_step",
        rows,
        {
            "threads": args.threads,
            "repeats": args.repeats,
            "warm_cache": args.warm_cache,
            "load_average": load,
        },
        markdown=lines,
    )


if __name__ == "__main__":
    main()
