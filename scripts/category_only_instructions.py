"""Category-only instructions, the control of docs/sim2real.md "Pilot 2026-12-07 (session 46)": every
instruction is replaced by "Find the <goal category>." so that a policy has one word to read instead
of a template. Works on training shards (frames hard-linked, records rewritten) and on episode files.

    python scripts/category_only_instructions.py shards <out dir> <shard> [<shard> ...]
    python scripts/category_only_instructions.py episodes <split.json.gz> <out.json.gz>

Shards name the goal in ``extra.goal_category`` (data engine shards since 2026-11-28); episode
files in the extras file beside them (``<split>_extras.json``: ``goal_object.category``). A record
without a category is an error naming it. Each output shard lands in ``<out dir>/<scene>/shard``.
The gt and extras files are copied beside an output episode file, so that ``eval nav --episodes
<out.json.gz>`` reads it.
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import shutil
import sys
from pathlib import Path


def instruction_for(category: str) -> str:
    return f"Find the {category.replace('_', ' ')}."


def rewrite_shard(src: Path, dst: Path) -> int:
    """Copy shard ``src`` to ``dst`` with category-only instructions; returns the trajectory count."""
    from image2sim.navpolicy.data import ShardReader
    from image2sim.simulator.io.atomic import write_bytes_atomic

    reader = ShardReader(src)  # validates the manifest and the records
    lines = []
    for k, rec in enumerate(reader.records):
        category = str((rec.get("extra") or {}).get("goal_category", ""))
        if not category:
            raise SystemExit(f"{src}/trajectories.jsonl line {k + 1}: no extra.goal_category")
        lines.append(json.dumps(rec | {"instruction": instruction_for(category)}))
    (dst / "frames").mkdir(parents=True, exist_ok=True)
    for f in sorted((src / "frames").iterdir()):
        target = dst / "frames" / f.name
        if not target.exists():
            os.link(f, target)  # same bytes: the frames are never rewritten
    write_bytes_atomic(dst / "trajectories.jsonl", ("\n".join(lines) + "\n").encode())
    write_bytes_atomic(dst / "manifest.json", (src / "manifest.json").read_bytes())  # last: marks it whole
    return len(lines)


def rewrite_episodes(src: Path, out: Path) -> int:
    """Write ``src`` (an episode file of ``data episodes``) to ``out`` with category-only instructions."""
    from image2sim.simulator.io.atomic import write_bytes_atomic

    stem = src.name.removesuffix(".json.gz")
    extras_path = src.with_name(f"{stem}_extras.json")
    if not extras_path.is_file():
        raise SystemExit(f"{extras_path}: missing (it names each episode's goal category)")
    extras = json.loads(extras_path.read_text())
    doc = json.loads(gzip.open(src, "rt").read())
    for e in doc["episodes"]:
        category = str(((extras.get(e["episode_id"]) or {}).get("goal_object") or {}).get("category", ""))
        if not category:
            raise SystemExit(f"{extras_path}: episode {e['episode_id']} has no goal_object.category")
        e["instruction"] = {"instruction_text": instruction_for(category)}
    out.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(out, gzip.compress(json.dumps(doc).encode()))
    out_stem = out.name.removesuffix(".json.gz")
    for suffix in ("_gt.json.gz", "_extras.json"):
        side = src.with_name(stem + suffix)
        if side.is_file():
            shutil.copyfile(side, out.with_name(out_stem + suffix))
    return len(doc["episodes"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="kind", required=True)
    sh = sub.add_parser("shards", help="training shards")
    sh.add_argument("out", type=Path, help="folder for the rewritten shards (<out>/<scene>/shard)")
    sh.add_argument("shards", type=Path, nargs="+", help="shard folders (<scene>/shard)")
    ep = sub.add_parser("episodes", help="an episode file")
    ep.add_argument("episodes", type=Path, help="<split>.json.gz of data episodes")
    ep.add_argument("out", type=Path, help="the episode file to write (<name>.json.gz)")
    args = ap.parse_args()
    if args.kind == "shards":
        for shard in args.shards:
            dst = args.out / shard.parent.name / "shard"
            if (dst / "manifest.json").exists():
                sys.exit(f"{dst}: a shard already exists here")
            print(f"{dst}: {rewrite_shard(shard, dst)} trajectories")
    else:
        print(f"{args.out}: {rewrite_episodes(args.episodes, args.out)} episodes")


if __name__ == "__main__":
    main()
