"""GPU check (run by hand on a CUDA machine; CI never needs one): parity of the device paths with the
CPU references, and timings of the hot paths at paper scale.

1. ``splat`` on CUDA (``torch`` and ``reference`` backends) against the CPU ``reference``: values and
   gradients, equirect and pinhole;
2. splat forward / forward+backward timings at 100k-1M Gaussians, 512x1024 equirect;
3. best-view selection (``gaussians.views``) on CUDA against CPU: the same kept set;
4. the ``paper`` pixel-flow renderer at 512x1024: one training step (flow JVP + one-step losses, bf16
   autocast) and one-step inference, time and peak memory, batch 1 and 4.

Writes ``$OUT/gpu_check.json`` (or ``reports/gpu_check.json``) and ``gpu_check.md`` next to it
(``--markdown FILE.json`` rewrites the page from a saved report).
Run (from the repository root, no install needed where torch is present)::

    PYTHONPATH=packages/simulator/src:packages/dataengine/src:packages/eval/src \\
        python benchmarks/gpu_check.py
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
import traceback
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))


def sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def timed(fn, repeats: int = 5, warmup: int = 2) -> float:
    """Median milliseconds of ``fn`` after ``warmup`` calls (CUDA synchronised)."""
    for _ in range(warmup):
        fn()
    sync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(1000 * (time.perf_counter() - t0))
    return sorted(times)[len(times) // 2]


def check_splat(report: dict) -> None:
    from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
    from image2sim.simulator.splatting import available_backends, splat
    from splatting import room_scene, upright_pose

    report["backends"] = (
        {str(k): v for k, v in available_backends().items()}
        if isinstance(available_backends(), dict)
        else list(available_backends())
    )
    rows = []
    for cam in (EquirectCamera(64, 128), PinholeCamera.from_fov(90, 90, 64, 64)):
        scene = [t.double() for t in room_scene(3000, seed=1)]
        pose = upright_pose()

        def run(device: str, backend: str, scene=scene, cam=cam, pose=pose):
            inputs = [t.to(device).clone().requires_grad_() for t in scene]
            out = splat(*inputs, cam, pose.to(device), backend=backend)
            loss = (out.rgb**2).sum() + out.depth.sum() + out.alpha.sum() + (out.features**2).sum()
            loss.backward()
            return out, [t.grad.cpu() for t in inputs]

        ref_out, ref_grads = run("cpu", "reference")
        for backend in ("torch", "reference"):
            out, grads = run("cuda", backend)
            err = max(
                float((getattr(out, k).detach().cpu() - getattr(ref_out, k).detach()).abs().max())
                for k in ("rgb", "depth", "alpha")
            )
            gerr = max(
                float((g - r).abs().max() / r.abs().max().clamp_min(1e-12))
                for g, r in zip(grads, ref_grads, strict=True)
            )
            rows.append(
                {"camera": cam.model, "backend": backend, "max_abs_err": err, "max_rel_grad_err": gerr}
            )
    report["splat_parity_float64"] = rows
    timings = []
    cam = EquirectCamera(512, 1024)
    for n in (100_000, 1_000_000):
        scene = [t.cuda() for t in room_scene(n, seed=0)]
        pose = upright_pose().cuda()
        with torch.no_grad():
            fwd = timed(lambda scene=scene, pose=pose: splat(*scene, cam, pose, backend="torch"))
        inputs = [t.clone().requires_grad_() for t in scene]

        def fb(inputs=inputs, pose=pose):
            out = splat(*inputs, cam, pose, backend="torch")
            (out.rgb.sum() + out.depth.sum() + out.features.sum()).backward()
            for t in inputs:
                t.grad = None

        torch.cuda.reset_peak_memory_stats()
        both = timed(fb, repeats=3, warmup=1)
        timings.append(
            {
                "gaussians": n,
                "size": "512x1024",
                "forward_ms": round(fwd, 2),
                "forward_backward_ms": round(both, 2),
                "peak_gib": round(torch.cuda.max_memory_allocated() / 2**30, 2),
            }
        )
        print(timings[-1], flush=True)
    report["splat_cuda_timings"] = timings


def check_views(report: dict) -> None:
    import tempfile

    from image2sim.dataengine.procedural import generate_scene as gen
    from image2sim.dataengine.procedural import preset as pre
    from image2sim.dataengine.procedural import write_scene
    from image2sim.simulator.gaussians import tiny
    from image2sim.simulator.gaussians.encoder import identity_gaussians
    from image2sim.simulator.gaussians.frames import prepare_frame
    from image2sim.simulator.gaussians.views import select_best_views, view_map
    from image2sim.simulator.io.registry import open_capture

    cfg = tiny()
    with tempfile.TemporaryDirectory() as tmp:
        write_scene(gen(pre("tiny"), seed=0), Path(tmp) / "s")
        cap = open_capture(Path(tmp) / "s")
        inputs = [prepare_frame(cap[i], 128, 256, cfg.fusion.edge_tolerance) for i in range(min(8, len(cap)))]
    sets = [identity_gaussians(f, cfg) for f in inputs]
    views = [view_map(f, cfg.fusion) for f in inputs]
    cpu = select_best_views(sets, views, cfg.fusion)
    to = lambda g: type(g)(**{k: v.cuda() for k, v in g.tensors().items()})  # noqa: E731
    import dataclasses

    tensor_fields = [
        f.name for f in dataclasses.fields(views[0]) if isinstance(getattr(views[0], f.name), torch.Tensor)
    ]
    vcuda = [dataclasses.replace(v, **{f: getattr(v, f).cuda() for f in tensor_fields}) for v in views]
    gpu = select_best_views([to(g) for g in sets], vcuda, cfg.fusion)
    report["best_view_cpu_vs_cuda"] = {
        "kept_cpu": [len(g) for g in cpu],
        "kept_cuda": [len(g) for g in gpu],
        "identical": all(torch.equal(a.means, b.means.cpu()) for a, b in zip(cpu, gpu, strict=True)),
    }


def check_renderer(report: dict) -> None:
    import dataclasses

    from image2sim.simulator.renderer.condition import CONDITION_CHANNELS
    from image2sim.simulator.renderer.config import paper
    from image2sim.simulator.renderer.model import PixelFlowRenderer

    cfg = paper()
    # No DINOv3 weights here: the aligner's target tokens are not needed for the flow / pixel terms.
    cfg = dataclasses.replace(cfg, semantic=dataclasses.replace(cfg.semantic, backbone="none"))
    model = PixelFlowRenderer(cfg).cuda()
    params = sum(p.numel() for p in model.parameters())
    rows = []
    for batch in (1, 4):
        h, w = cfg.height, cfg.width
        cond = torch.rand(batch, CONDITION_CHANNELS, h, w, device="cuda")
        rgb = torch.rand(batch, 3, h, w, device="cuda")
        depth = torch.rand(batch, 1, h, w, device="cuda") * 5
        noise = torch.randn(batch, 4, h, w, device="cuda")
        r = torch.rand(batch, device="cuda") * 0.5
        t = r + torch.rand(batch, device="cuda") * 0.5
        opt = torch.optim.AdamW(model.parameters(), lr=1e-5)

        def step(cond=cond, rgb=rgb, depth=depth, noise=noise, r=r, t=t, opt=opt):
            with torch.autocast("cuda", dtype=torch.bfloat16):
                losses = model.losses(cond, rgb, depth, noise, r, t)
            total = sum(v for k, v in losses.items() if k in ("flow", "rec", "pixel") and v.requires_grad)
            total.backward()
            opt.step()
            opt.zero_grad(set_to_none=True)

        torch.cuda.reset_peak_memory_stats()
        try:
            train_ms = timed(step, repeats=3, warmup=1)
            train_mem = torch.cuda.max_memory_allocated() / 2**30
        except Exception as e:  # report, do not hide: e.g. an op without forward-mode AD on CUDA
            train_ms, train_mem = None, None
            report.setdefault("errors", []).append(f"renderer train batch {batch}: {e!r}")
        model.eval()
        with torch.no_grad(), torch.autocast("cuda", dtype=torch.bfloat16):
            infer_ms = timed(
                lambda cond=cond, noise=noise: model.render(cond, steps=1, noise=noise), repeats=5, warmup=2
            )
        model.train()
        rows.append(
            {
                "batch": batch,
                "size": f"{cfg.height}x{cfg.width}",
                "train_step_ms": None if train_ms is None else round(train_ms, 1),
                "train_peak_gib": None if train_mem is None else round(train_mem, 2),
                "one_step_render_ms": round(infer_ms, 2),
            }
        )
        print(rows[-1], flush=True)
    report["renderer_paper"] = {"parameters_m": round(params / 1e6, 2), "rows": rows}


def markdown(report: dict) -> str:
    """The report as a page (``reports/gpu_check.md``)."""
    lines = [
        "# GPU check (`benchmarks/gpu_check.py`, run by hand on a CUDA machine)",
        "",
        f"- Device: {report.get('device')}; torch {report.get('torch')} (CUDA {report.get('cuda')}), "
        f"python {report.get('python')}",
        "- Timings: median of 5 (forward) / 3 (forward+backward, train step) after warm-up, "
        "CUDA synchronised.",
        "",
        "## Splatting on CUDA against the CPU reference (float64, values and gradients)",
        "",
        "| camera | CUDA backend | max abs error | max relative gradient error |",
        "|---|---|---:|---:|",
    ]
    for r in report.get("splat_parity_float64", []):
        lines.append(
            f"| {r['camera']} | {r['backend']} | {r['max_abs_err']:.1e} | {r['max_rel_grad_err']:.1e} |"
        )
    lines += ["", "## Splatting speed (`torch` backend, float32, 16 feature channels)", ""]
    lines += [
        "| Gaussians | size | forward ms | forward+backward ms | peak GiB |",
        "|---:|---|---:|---:|---:|",
    ]
    for r in report.get("splat_cuda_timings", []):
        lines.append(
            f"| {r['gaussians']} | {r['size']} | {r['forward_ms']} | {r['forward_backward_ms']} "
            f"| {r['peak_gib']} |"
        )
    views = report.get("best_view_cpu_vs_cuda")
    if views:
        lines += [
            "",
            f"Best-view selection on CUDA keeps the same Gaussians as on CPU: {views['identical']} "
            f"(kept per frame {views['kept_cuda']}).",
        ]
    rend = report.get("renderer_paper")
    if rend:
        lines += [
            "",
            f"## `paper` pixel-flow renderer ({rend['parameters_m']} M parameters, no DINOv3 weights), "
            "bf16 autocast",
            "",
            "| batch | size | train step ms (flow JVP + one-step terms, AdamW) | train peak GiB "
            "| one-step render ms |",
            "|---:|---|---:|---:|---:|",
        ]
        for r in rend["rows"]:
            train = "out of memory" if r["train_step_ms"] is None else r["train_step_ms"]
            lines.append(
                f"| {r['batch']} | {r['size']} | {train} | {r['train_peak_gib'] or '-'} "
                f"| {r['one_step_render_ms']} |"
            )
    for note in report.get("notes", []):
        lines += ["", f"Note: {note}"]
    for e in report.get("errors", []):
        lines += ["", f"- error: {e.splitlines()[0][:300]}"]
    return "\n".join(lines) + "\n"


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--markdown":
        src = Path(sys.argv[2])
        src.with_suffix(".md").write_text(markdown(json.loads(src.read_text())))
        return
    out = Path(os.environ.get("OUT") or Path(__file__).resolve().parents[1] / "reports")
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "device": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
        "python": platform.python_version(),
    }
    for name, fn in (("splat", check_splat), ("views", check_views), ("renderer", check_renderer)):
        t0 = time.perf_counter()
        try:
            fn(report)
        except Exception:
            report.setdefault("errors", []).append(f"{name}: {traceback.format_exc()[-2000:]}")
            print(traceback.format_exc(), flush=True)
        report.setdefault("seconds", {})[name] = round(time.perf_counter() - t0, 1)
        (out / "gpu_check.json").write_text(json.dumps(report, indent=2, default=str))
        (out / "gpu_check.md").write_text(markdown(report))
    print(json.dumps(report, indent=2, default=str)[:6000])


if __name__ == "__main__":
    main()
