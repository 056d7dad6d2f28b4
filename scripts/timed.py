#!/usr/bin/env python3
"""Run a shell command and record its wall and CPU time (children included) as JSON.

Usage: ``python scripts/timed.py --out budget/bc.json -- <command ...>``. The sim-to-real pipeline
wraps its training stages with it so the report can state the budget it measured; the command's exit
status is passed on, and nothing is written when it fails.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path, help="JSON file to write (wall_s, cpu_s, command).")
    ap.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command")
    args = ap.parse_args(argv)
    cmd = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not cmd:
        ap.error("no command given (put it after --)")
    t0 = time.perf_counter()
    rc = subprocess.call(cmd)
    wall = time.perf_counter() - t0
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    if rc != 0:
        return rc
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(f".{args.out.name}.tmp")
    tmp.write_text(
        json.dumps(
            {
                "wall_s": round(wall, 2),
                "cpu_s": round(ru.ru_utime + ru.ru_stime, 2),
                "command": " ".join(cmd),
            },
            indent=1,
        )
        + "\n"
    )
    os.replace(tmp, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
