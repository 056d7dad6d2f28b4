"""Does a policy read the instruction? A teacher-forced probe on approach episodes (docs/sim2real.md).

Approach episodes (`data episodes --approach-views N`) that start from the same view but lead to
different visible objects form pairs. For each episode of a pair the probe asks the policy for:

- its first two actions from the first view, with the episode's own instruction and with the
  other episode's (only pairs whose experts act differently count: there the instruction decides);
- its first action at the goal (the final view, the agent's streaming context up to there; the
  expert's label is STOP), with the own instruction and with the other goal's.

A policy that grounds the instruction scores higher with its own instruction than with the other
one; equal scores mean it acts on the view alone. Greedy next-token accuracy, as in training.

    python scripts/grounding_probe.py --model <export> --config <policy yaml> \
        --episodes <data episodes --out with approach shards> [--out probe.json]
"""

from __future__ import annotations

import argparse
import collections
import json
import math
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="Exported policy folder.")
    ap.add_argument("--config", required=True, help="The policy's YAML config (sample layout).")
    ap.add_argument("--episodes", required=True, help="A data episodes output folder with approach shards.")
    ap.add_argument("--out", default=None, help="Write the result as JSON here.")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()

    import torch
    from image2sim.eval.nav_summary import wilson_interval
    from image2sim.navpolicy.collate import NavCollator, model_inputs
    from image2sim.navpolicy.config import load_config
    from image2sim.navpolicy.data import NavSample, ShardReader, make_sample, next_actions
    from image2sim.navpolicy.model import build_policy
    from image2sim.navpolicy.prompting import IGNORE_INDEX, PromptBuilder

    torch.set_num_threads(args.threads)
    cfg = load_config(args.config, {"model": {"source": args.model}})
    policy = build_policy(cfg)
    policy.model.eval()
    collate = NavCollator(
        PromptBuilder(policy.tokenizer, policy.codec, cfg.system_prompt), policy.image_processor
    )
    action_ids = policy.codec.all_token_ids()
    shards = sorted(Path(args.episodes).glob("scenes/*/approach"))
    if not shards:
        raise SystemExit(
            f"{args.episodes}: no scenes/*/approach shard (run data episodes --approach-views N)"
        )
    by_view = collections.defaultdict(list)
    for shard in shards:
        reader = ShardReader(shard)
        for i in range(len(reader)):
            t = reader[i]
            by_view[t.frames[0].tobytes()].append(t)
    pairs = [g[:2] for g in by_view.values() if len(g) >= 2]

    def action_hits(sample) -> list[bool]:
        """Greedy hits on the labelled action tokens of ``sample``'s last observation."""
        batch = model_inputs(collate([sample]))
        with torch.no_grad():
            logits = policy.model(**batch).logits[0]
        labels = batch["labels"][0]
        pos = [int(p) for p in (labels != IGNORE_INDEX).nonzero().flatten() if int(labels[p]) in action_ids]
        last = pos[-2:]  # the final observation's two action labels
        return [int(logits[p - 1].argmax()) == int(labels[p]) for p in last]

    first = {"own": [], "other": []}
    stop = {"own": [], "other": []}
    for a, b in pairs:
        for t, other in ((a, b), (b, a)):
            if t.actions[:2] != other.actions[:2]:
                for key, text in (("own", t.instruction), ("other", other.instruction)):
                    s = NavSample(text, t.frames[:1], [0], [()], [next_actions(t.actions, 0)], t.episode_id)
                    first[key] += action_hits(s)
            end = make_sample(
                t,
                max_observations=cfg.data.max_observations,
                max_action_labels=cfg.data.max_action_labels,
                stride=cfg.data.observation_stride,
                context=(cfg.agent.sparse_frames, cfg.agent.dense_frames),
            )  # no rng: cut at the end, where the expert says STOP
            for key, text in (("own", t.instruction), ("other", other.instruction)):
                end.instruction = text
                stop[key].append(action_hits(end)[0])

    def summary(hits: list[bool]) -> dict:
        k, n = sum(hits), len(hits)
        ci = list(wilson_interval(k, n)) if n else [math.nan, math.nan]
        return {"accuracy": k / n if n else math.nan, "ci": ci, "n": n}

    result = {
        "model": args.model,
        "episodes": args.episodes,
        "pairs": len(pairs),
        "first_actions": {k: summary(v) for k, v in first.items()},
        "stop_at_goal": {k: summary(v) for k, v in stop.items()},
    }
    for name in ("first_actions", "stop_at_goal"):
        r = result[name]
        print(
            f"{name}: own instruction {r['own']['accuracy']:.3f} vs other goal's "
            f"{r['other']['accuracy']:.3f} (n = {r['own']['n']})"
        )
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
