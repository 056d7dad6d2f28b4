#!/usr/bin/env python3
"""Write the loss curve of training runs as one CSV (``step,run,<loss columns>``) for DVC ``plots:``.

Usage: ``python scripts/loss_curve.py --out plots/train_sim_loss.csv outputs/renderer`` (several run
folders, in training order, are joined: BC then the DAgger rounds). Each run folder holds the
``logs/version_N/metrics.csv`` of ``simulator.tracking.csv_logger``; see
``simulator.tracking.write_loss_curve``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from image2sim.simulator.tracking import write_loss_curve


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, write the curve, print where; exit 2 on a missing or malformed log."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path, help="CSV to write.")
    ap.add_argument("--suffix", default="loss", help="Logged columns to keep: those ending in this.")
    ap.add_argument("runs", nargs="+", type=Path, help="Run folders, in training order.")
    args = ap.parse_args(argv)
    try:
        path = write_loss_curve(args.runs, args.out, args.suffix)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
