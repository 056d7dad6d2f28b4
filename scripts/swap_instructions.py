"""The instruction-swap control of docs/sim2real.md: every episode keeps its start, goal and reference
path, but its instruction is replaced by one of another episode of the same scene whose goal object
has another category. A policy that follows instructions loses success; one that ignores them
scores the same.

    python scripts/swap_instructions.py <split.json.gz> <out.json.gz> [--seed 0]

The extras file beside the input (``<split>_extras.json``, written by ``data episodes``; older runs
kept the same fields in each episode record) names each episode's goal category.
The gt file is copied beside the output under the matching name, so that ``eval nav --episodes
<out.json.gz>`` reads it. Episodes with no other category in their scene keep their own
instruction (counted in the printed summary).
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import shutil
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("episodes", type=Path, help="An episode file of data episodes (<split>.json.gz).")
    ap.add_argument("out", type=Path, help="The swapped episode file to write (<name>.json.gz).")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    import numpy as np

    src = args.episodes
    stem = src.name.removesuffix(".json.gz")
    extras_path = src.with_name(f"{stem}_extras.json")
    doc = json.loads(gzip.open(src, "rt").read())
    # The engine's extras file; older runs kept the same fields inside each episode record.
    extras = json.loads(extras_path.read_text()) if extras_path.is_file() else {}
    category = {
        e["episode_id"]: (extras.get(e["episode_id"], e).get("goal_object") or {}).get("category")
        for e in doc["episodes"]
    }
    if not any(category.values()):
        raise SystemExit(
            f"{src}: no episode names a goal category (no {extras_path.name}, no goal_object fields)"
        )
    by_scene = collections.defaultdict(list)
    for e in doc["episodes"]:
        by_scene[e["scene_id"]].append(e)
    rng = np.random.default_rng(args.seed)
    originals = {e["episode_id"]: e["instruction"] for e in doc["episodes"]}
    kept = 0
    for e in doc["episodes"]:
        mine = category.get(e["episode_id"])
        others = [o for o in by_scene[e["scene_id"]] if category.get(o["episode_id"]) not in (None, mine)]
        if not others:
            kept += 1
            continue
        e["instruction"] = dict(originals[others[int(rng.integers(len(others)))]["episode_id"]])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(args.out, "wt") as fh:
        json.dump(doc, fh)
    out_stem = args.out.name.removesuffix(".json.gz")
    shutil.copyfile(src.with_name(f"{stem}_gt.json.gz"), args.out.with_name(f"{out_stem}_gt.json.gz"))
    print(
        json.dumps({"episodes": len(doc["episodes"]), "swapped": len(doc["episodes"]) - kept, "kept": kept})
    )


if __name__ == "__main__":
    main()
