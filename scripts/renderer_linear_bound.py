"""How much can the renderer's prior path alone add on held-out views? (issue 20, docs/renderer.md)

A reference between `splat_fill` and a network: the renderer's own linear path alone
(`decoder.prior_filter` with `prior_fill: interpolate`, one K x K filter of the hole-filled prior's
logits and alpha added to the logits), fitted by `renderer.prior_filter`'s least squares on the
training conditions (leave-target-out splats of the training frames, as `sim train` builds them)
and applied to the held-out views' conditions (as `eval render --condition-source gaussians`
builds them). Also the "oracle" filter fitted on each held-out view itself: an upper bound for any
linear sharpening of that view. With ``--hidden H --fit-steps N`` also the nonlinear path
(`decoder.prior_hidden`: the filter plus a per-pixel MLP, fitted for N Adam steps on random
training pixels as `sim train` does before its first flow step). Scores are PSNR against the exact
noise-free panorama.

    python scripts/renderer_linear_bound.py data/synthetic/scene_* --holdout-every 4 \
        [--cache outputs/cache/splat_conditions] [--kernel 7] [--hidden 64 --fit-steps 3000] \
        [--out result.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch


def _prior_path(pairs, args, hidden: int = 0, fit_steps: int = 0):
    """The `tiny` renderer, untrained, with its prior filter fitted by `sim train`'s least-squares
    start on ``pairs`` (all pixels) and, with ``hidden``, its MLP path fitted for ``fit_steps``:
    its one-step output is the prior path alone (the heads start at zero)."""
    import dataclasses

    from image2sim.simulator.renderer.config import tiny
    from image2sim.simulator.renderer.model import PixelFlowRenderer
    from image2sim.simulator.renderer.module import init_prior_filter, init_prior_path

    cfg = tiny()
    decoder = dataclasses.replace(
        cfg.decoder,
        prior_filter=args.kernel,
        prior_fill="interpolate",
        prior_hidden=hidden,
        prior_fit_steps=fit_steps,
    )
    cfg = dataclasses.replace(cfg, height=args.height, width=args.width, decoder=decoder)
    model = PixelFlowRenderer(cfg).eval()
    init_prior_filter(model, pairs, pixels_per_image=None)
    fitted = init_prior_path(model, pairs, seed=args.seed)
    if fitted is not None:
        print(f"prior path fitted: training PSNR {fitted['psnr_start']:.2f} -> {fitted['psnr_end']:.2f} dB")
    return model


def _one_step(model, cond: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return model.render(cond, steps=1, noise=torch.zeros(cond.shape[0], 4, *cond.shape[-2:])).rgb


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("captures", nargs="+", help="procedural capture folders (exact targets)")
    p.add_argument("--holdout-every", type=int, default=4)
    p.add_argument("--height", type=int, default=128)
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--gaussian-config", default="tiny")
    p.add_argument("--kernel", type=int, default=7, help="odd filter size")
    p.add_argument("--hidden", type=int, default=0, help="also score the MLP path of this width (0: no)")
    p.add_argument("--fit-steps", type=int, default=3000, help="Adam steps fitting the MLP path")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cache", default=None, help="sim train's --splat-cache folder (reused when it matches)")
    p.add_argument("--max-views", type=int, default=12)
    p.add_argument("--out", type=Path, default=None, help="write the per-view numbers as JSON")
    args = p.parse_args()
    if args.kernel < 1 or args.kernel % 2 == 0:
        p.error(f"--kernel must be odd and positive, got {args.kernel}")
    torch.set_num_threads(1)
    from image2sim.eval.render_samples import splat_samples
    from image2sim.simulator.metrics.image import psnr
    from image2sim.simulator.renderer.holefill import fill_condition
    from image2sim.simulator.renderer.splat_data import SplatConditionDataset, SplatDataConfig

    cfg = SplatDataConfig(
        gaussian_config=args.gaussian_config, holdout_every=args.holdout_every, cache_dir=args.cache
    )
    train = SplatConditionDataset(args.captures, args.height, args.width, cfg)
    trained = _prior_path(train, args)
    nonlinear = _prior_path(train, args, args.hidden, args.fit_steps) if args.hidden else None
    held = splat_samples(
        args.captures,
        args.height,
        args.width,
        args.holdout_every,
        gaussian_config=args.gaussian_config,
        max_views=args.max_views,
        target="exact",
    )
    views = []
    for s in held:
        cond = s["condition"].reshape(1, -1, args.height, args.width)
        target = s["target_rgb"].reshape(1, 3, args.height, args.width)
        oracle = _prior_path([{"condition": cond[0], "target_rgb": target[0]}], args)
        views.append(
            {
                "view": int(s["index"]),
                "splat_fill": float(psnr(fill_condition(cond)[0], target)),
                "linear_filter": float(psnr(_one_step(trained, cond), target)),
                "oracle_filter": float(psnr(_one_step(oracle, cond), target)),
            }
        )
        if nonlinear is not None:
            views[-1]["mlp_path"] = float(psnr(_one_step(nonlinear, cond), target))
        print(" ".join(f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in views[-1].items()))
    mean = {k: sum(v[k] for v in views) / len(views) for k in views[0] if k != "view"}
    print(
        f"{len(views)} held-out views, {train.num_splat} training pairs, {args.kernel}x{args.kernel} filter: "
        + ", ".join(f"{k} {v:.2f} dB" for k, v in mean.items())
    )
    if args.out is not None:
        record = {
            "kernel": args.kernel,
            "hidden": args.hidden,
            "fit_steps": args.fit_steps,
            "seed": args.seed,
        }
        args.out.write_text(json.dumps({**record, "mean": mean, "views": views}, indent=2) + "\n")


if __name__ == "__main__":
    main()
