"""Leaderboard prediction files from an ``eval nav`` run: R2R-CE (EvalAI) and RxR-Habitat.

Both are built from the run's trajectory logs (``<run>/<agent>/<scene>.jsonl.traj.jsonl``), which
hold each episode's pose at the start and after every action, in our world frame. Poses are
converted to the Habitat frame with :mod:`image2sim.simulator.geometry.habitat`.

* **R2R-CE** (what VLN-CE's ``inference.py`` writes and EvalAI scores): one JSON object
  ``{episode_id: [{"position": [x, y, z], "heading": h, "stop": bool}, ...]}`` with one entry per
  state, the first at the start. ``heading`` is VLN-CE's ``get_info`` heading: the yaw of the agent
  rotation about Habitat's +Y, which for our heading ``h_world`` (about +Z, 0 = +X) is
  ``h_world - pi/2`` wrapped to ``(-pi, pi]``. Only the final entry has ``"stop": true``, and only
  when the episode ended with STOP.
* **RxR-Habitat**: JSON lines ``{"instruction_id": int, "path": [[x, y, z], ...]}`` sorted by
  instruction id, consecutive duplicate positions (turns) removed, as VLN-CE writes them.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from image2sim.simulator.geometry.habitat import world_to_habitat
from image2sim.simulator.io.atomic import write_text_atomic

__all__ = [
    "SUBMISSION_FORMATS",
    "SubmissionError",
    "r2r_ce_predictions",
    "read_run_trajectories",
    "rxr_habitat_predictions",
    "write_submission",
]

SUBMISSION_FORMATS = ("r2r-ce", "rxr-ce")


class SubmissionError(ValueError):
    """A submission cannot be written from this run (the message says which episode or field)."""

    cli_exit_code = 2


def _vlnce_heading(world_heading: float) -> float:
    return math.remainder(float(world_heading) - math.pi / 2.0, 2.0 * math.pi)


def read_run_trajectories(agent_dir: str | Path) -> dict[str, dict]:
    """``episode_id -> {"positions", "headings", "actions"}`` from every trajectory log of one agent's
    run folder. Logs written before poses were recorded are refused (rerun into a new folder)."""
    out: dict[str, dict] = {}
    for path in sorted(Path(agent_dir).glob("*.jsonl.traj.jsonl")):
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
            rec = json.loads(line)
            if "positions" not in rec:
                raise SubmissionError(
                    f"{path}:{n}: episode {rec.get('episode_id')!r} has no recorded poses (a run from an "
                    "older version): evaluate again into a new --out"
                )
            out[str(rec["episode_id"])] = rec
    if not out:
        raise SubmissionError(f"{agent_dir}: no trajectory logs (*.jsonl.traj.jsonl)")
    return out


def r2r_ce_predictions(trajectories: Mapping[str, Mapping[str, Any]]) -> dict[str, list[dict]]:
    """The R2R-CE predictions object (see the module docstring)."""
    out: dict[str, list[dict]] = {}
    for eid, rec in trajectories.items():
        positions, headings, actions = rec["positions"], rec["headings"], rec["actions"]
        if len(positions) != len(headings) or not positions:
            raise SubmissionError(f"episode {eid}: {len(positions)} positions but {len(headings)} headings")
        stopped = bool(actions) and int(actions[-1]) == 0
        steps = []
        for k, (p, h) in enumerate(zip(positions, headings, strict=True)):
            steps.append(
                {
                    "position": [float(v) for v in world_to_habitat(p)],
                    "heading": _vlnce_heading(h),
                    "stop": stopped and k == len(positions) - 1,
                }
            )
        out[str(eid)] = steps
    return out


def rxr_habitat_predictions(
    trajectories: Mapping[str, Mapping[str, Any]], instruction_ids: Mapping[str, Any]
) -> list[dict]:
    """The RxR-Habitat prediction lines (see the module docstring); ``instruction_ids`` maps each
    episode id to its RxR ``instruction_id``."""
    lines = []
    for eid, rec in trajectories.items():
        if eid not in instruction_ids or instruction_ids[eid] is None:
            raise SubmissionError(f"episode {eid}: no instruction_id (RxR-CE episodes carry one)")
        path: list[list[float]] = []
        for p in rec["positions"]:
            q = [float(v) for v in world_to_habitat(p)]
            if not path or q != path[-1]:
                path.append(q)
        lines.append({"instruction_id": int(instruction_ids[eid]), "path": path})
    return sorted(lines, key=lambda d: d["instruction_id"])


def write_submission(
    path: str | Path,
    fmt: str,
    trajectories: Mapping[str, Mapping[str, Any]],
    episode_ids: Sequence[str],
    instruction_ids: Mapping[str, Any] | None = None,
) -> Path:
    """Write the predictions of ``episode_ids`` (every episode of the split: a missing one is an
    error, not a silently partial submission) atomically."""
    if fmt not in SUBMISSION_FORMATS:
        raise SubmissionError(f"submission format must be one of {SUBMISSION_FORMATS}, got {fmt!r}")
    missing = [e for e in episode_ids if str(e) not in trajectories]
    if missing:
        raise SubmissionError(f"{len(missing)} episodes have no trajectory in the run, e.g. {missing[:3]}")
    chosen = {str(e): trajectories[str(e)] for e in episode_ids}
    if fmt == "r2r-ce":
        text = json.dumps(r2r_ce_predictions(chosen), indent=1)
    else:
        lines = rxr_habitat_predictions(chosen, instruction_ids or {})
        text = "".join(json.dumps(d, separators=(",", ":")) + "\n" for d in lines)
    return write_text_atomic(path, text)
