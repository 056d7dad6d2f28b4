"""Does a policy's STOP depend on its instruction? (docs/sim2real.md, "Wrong-goal end samples")

For every trajectory of the given shards whose record names its goal's category
(``extra.goal_category``, data engine shards since 2026-11-28), the end of the trajectory (where the
expert stops beside its goal) is shown to the policy teacher-forced, as the streaming agent would see
it, twice: under its own instruction and under the instruction of a trajectory of the same scene
whose goal is another category. The policy's probability of STOP there is read both times (the
product of the STOP piece's token probabilities, ``navpolicy.train.stop_unlikelihood``). A policy
that reads its instruction stops more under its own; one that acts on the view alone scores the same.

    .venv/bin/python scripts/stop_probe.py --model <export> --config <policy yaml> \\
        --shard <episodes>/scenes/scene_000/shard [--shard ...] [--out probe.json]

Prints and writes: mean P(STOP) own / other, the share of ends where own > other, and n. For a
policy exported with its goal head (``agent.stop_gate``), also the head's probability that the named
goal is in view at the end's last image, own / other (``goal_p_own``, ``goal_p_other``, and the share
where own > other): what the STOP gate reads there.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="exported policy folder")
    ap.add_argument("--config", required=True, help="policy config the model trained with")
    ap.add_argument("--shard", action="append", required=True, help="shard folder (repeatable)")
    ap.add_argument("--out", default="", help="JSON file to write")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0, help="seed of the other-goal instruction draw")
    args = ap.parse_args()

    import numpy as np
    import torch
    from image2sim.navpolicy.collate import NavCollator, image_end_positions, model_inputs
    from image2sim.navpolicy.config import load_config
    from image2sim.navpolicy.data import NavShardDataset, sample_options
    from image2sim.navpolicy.model import build_policy
    from image2sim.navpolicy.prompting import PromptBuilder
    from image2sim.navpolicy.train import stop_unlikelihood

    cfg = load_config(args.config, {"model": {"source": args.model}})
    policy = build_policy(cfg)
    policy.model.eval()
    opts = sample_options(cfg) | {"jitter": False, "wrong_goal_stop_probability": 0.0}
    ds = NavShardDataset(args.shard, **opts)
    col = NavCollator(
        PromptBuilder(policy.tokenizer, policy.codec, cfg.system_prompt), policy.image_processor
    )
    rng = np.random.default_rng(args.seed)

    pairs = []  # (own-instruction end sample, other-instruction end sample)
    for i in range(len(ds)):
        other = ds.wrong_goal_source(i, rng)
        if other is None:
            continue
        end = ds.wrong_goal_sample(ds.trajectory(i), ds.instruction_of(i), None)  # marks its STOP
        pairs.append((end, dataclasses.replace(end, instruction=ds.instruction_of(other))))

    head = policy.goal_head

    def p_stop(samples) -> tuple[list[float], list[float]]:
        """P(STOP) at each sample's end, and the goal head's probability at its last image (nan
        without a head)."""
        out, goal = [], []
        for k in range(0, len(samples), args.batch):
            chunk = samples[k : k + args.batch]
            batch = col(chunk)
            with torch.no_grad():
                res = policy.model(**model_inputs(batch), output_hidden_states=head is not None)
                if head is not None:
                    ends = image_end_positions(batch["mm_token_type_ids"])
                    last = [ends[ends[:, 0] == b][-1] for b in range(len(chunk))]
                    rows = torch.tensor([int(e[0]) for e in last])
                    cols = torch.tensor([int(e[1]) for e in last])
                    goal += head.probability(res.hidden_states, rows, cols).tolist()
                else:
                    goal += [float("nan")] * len(chunk)
            mask = batch["stop_negative_mask"]
            for b in range(len(chunk)):
                r = stop_unlikelihood(res.logits[b : b + 1], batch["input_ids"][b : b + 1], mask[b : b + 1])
                out.append(float("nan") if r is None else float(r[1]))  # no STOP in view: skipped
        return out, goal

    own, goal_own = map(np.array, p_stop([a for a, _ in pairs]))
    oth, goal_oth = map(np.array, p_stop([b for _, b in pairs]))
    keep = np.isfinite(own) & np.isfinite(oth)
    own, oth, goal_own, goal_oth = own[keep], oth[keep], goal_own[keep], goal_oth[keep]
    result = {
        "model": args.model,
        "n": int(keep.sum()),
        "p_stop_own": round(float(own.mean()), 4) if len(own) else None,
        "p_stop_other": round(float(oth.mean()), 4) if len(oth) else None,
        "own_greater_share": round(float((own > oth).mean()), 4) if len(own) else None,
        "mean_difference": round(float((own - oth).mean()), 4) if len(own) else None,
    }
    if head is not None and len(own):
        result |= {
            "goal_p_own": round(float(goal_own.mean()), 4),
            "goal_p_other": round(float(goal_oth.mean()), 4),
            "goal_own_greater_share": round(float((goal_own > goal_oth).mean()), 4),
        }
    print(json.dumps(result))
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
