"""VLN-CE ``json.gz`` episode files (+ ``{split}_gt.json.gz``) written by the data engine.

Schema (VLN-CE / R2R-CE, extended)::

    {"frame": "image2sim-z-up", "quaternion_order": "wxyz",
     "episodes": [{"episode_id", "trajectory_id", "scene_id", "start_position": [x, y, z],
                   "start_rotation": [w, x, y, z], "goals": [{"position": [x, y, z], "radius": r}],
                   "reference_path": [[x, y, z], ...],
                   "instruction": {"instruction_text": str, "instruction_tokens": [int, ...]},
                   "info": {"geodesic_distance": m},
                   "style", "structure", "tone", "goal_object": {...}, "bucket", "path_length", "num_steps"}],
     "instruction_vocab": {"word_list": [...], "num_vocab": n, "UNK_INDEX": 1, "PAD_INDEX": 0}}

    {split}_gt.json.gz: {episode_id: {"locations": [[x, y, z], ...], "actions": [...], "forward_steps": n}}

Positions are world metres (Z-up) and the quaternion order is stated in the file, so readers never
guess (the evaluation package's loader honours both fields).
"""

from __future__ import annotations

import gzip
import json
import math
import re
from collections.abc import Iterable, Sequence
from pathlib import Path

from image2sim.simulator.io.atomic import write_bytes_atomic

__all__ = [
    "FRAME",
    "QUATERNION_ORDER",
    "tokenize",
    "build_vocab",
    "heading_quaternion",
    "episode_record",
    "write_episode_files",
    "validate_episode_doc",
    "EpisodeSchemaError",
]

FRAME = "image2sim-z-up"
QUATERNION_ORDER = "wxyz"
PAD, UNK = "<PAD>", "<UNK>"


class EpisodeSchemaError(ValueError):
    """An episode document does not follow the schema; the message names the episode and field."""


def tokenize(text: str) -> list[str]:
    """Lower-case words and punctuation marks (R2R-style tokenisation)."""
    return re.findall(r"[a-z0-9']+|[^\sa-z0-9']", text.lower())


def build_vocab(texts: Iterable[str]) -> list[str]:
    """Word list: PAD, UNK, then the words sorted by (descending count, word)."""
    counts: dict[str, int] = {}
    for t in texts:
        for w in tokenize(t):
            counts[w] = counts.get(w, 0) + 1
    return [PAD, UNK] + sorted(counts, key=lambda w: (-counts[w], w))


def heading_quaternion(heading: float) -> list[float]:
    """(w, x, y, z) of a yaw ``heading`` about +Z (0 = facing +X)."""
    return [math.cos(heading / 2), 0.0, 0.0, math.sin(heading / 2)]


def _vec(p) -> list[float]:
    return [float(v) for v in p]


def episode_record(
    episode_id: str,
    scene_id: str,
    start,
    heading: float,
    goal,
    radius: float,
    reference_path,
    text: str,
    geodesic: float,
    extra: dict,
) -> dict:
    """One episode entry (instruction tokens are filled in by :func:`write_episode_files`)."""
    return {
        "episode_id": str(episode_id),
        "trajectory_id": str(episode_id),
        "scene_id": scene_id,
        "start_position": _vec(start),
        "start_rotation": heading_quaternion(heading),
        "goals": [{"position": _vec(goal), "radius": float(radius)}],
        "reference_path": [_vec(p) for p in reference_path],
        "instruction": {"instruction_text": text, "instruction_tokens": []},
        "info": {"geodesic_distance": float(geodesic)},
        **extra,
    }


def _gz(obj) -> bytes:
    # mtime=0: the same episodes give byte-identical files.
    return gzip.compress(json.dumps(obj, separators=(",", ":")).encode("utf-8"), mtime=0)


def write_episode_files(
    out_dir: str | Path, split: str, episodes: Sequence[dict], gt: dict, min_geodesic: float = 0.0
) -> tuple[Path, Path]:
    """Tokenise, validate (see :func:`validate_episode_doc`), write ``{out}/{split}/{split}.json.gz`` +
    ``{split}_gt.json.gz`` atomically."""
    vocab = build_vocab(e["instruction"]["instruction_text"] for e in episodes)
    index = {w: i for i, w in enumerate(vocab)}
    eps = []
    for e in episodes:
        e = dict(e)
        e["instruction"] = dict(e["instruction"])
        e["instruction"]["instruction_tokens"] = [
            index.get(w, 1) for w in tokenize(e["instruction"]["instruction_text"])
        ]
        eps.append(e)
    doc = {
        "frame": FRAME,
        "quaternion_order": QUATERNION_ORDER,
        "episodes": eps,
        "instruction_vocab": {"word_list": vocab, "num_vocab": len(vocab), "PAD_INDEX": 0, "UNK_INDEX": 1},
    }
    validate_episode_doc(doc, gt, min_geodesic)
    d = Path(out_dir) / split
    main, gt_path = d / f"{split}.json.gz", d / f"{split}_gt.json.gz"
    write_bytes_atomic(gt_path, _gz(gt))
    write_bytes_atomic(main, _gz(doc))
    return main, gt_path


def _num_list(v, n: int | None = None) -> bool:
    return (
        isinstance(v, list)
        and (n is None or len(v) == n)
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
    )


def validate_episode_doc(doc: dict, gt: dict | None = None, min_geodesic: float = 0.0) -> None:
    """Check the schema above; raises :class:`EpisodeSchemaError` at the first problem.

    ``min_geodesic``: no episode may be shorter (the sampling config's ``min_path_length``): a shorter
    one starts inside the evaluation's success radius and is solved by stopping at once."""
    if doc.get("frame") != FRAME or doc.get("quaternion_order") != QUATERNION_ORDER:
        raise EpisodeSchemaError(f"top level: frame/quaternion_order must be {FRAME!r}/{QUATERNION_ORDER!r}")
    if not isinstance(doc.get("episodes"), list):
        raise EpisodeSchemaError("top level: 'episodes' must be a list")
    vocab = doc.get("instruction_vocab", {}).get("word_list")
    if not isinstance(vocab, list) or not all(isinstance(w, str) for w in vocab):
        raise EpisodeSchemaError("top level: instruction_vocab.word_list must be a list of strings")
    seen = set()
    for e in doc["episodes"]:
        eid = e.get("episode_id")

        def bad(field: str, why: str, eid=eid) -> EpisodeSchemaError:
            return EpisodeSchemaError(f"episode {eid!r}: field {field!r}: {why}")

        if not isinstance(eid, str) or eid in seen:
            raise bad("episode_id", "must be a unique string")
        seen.add(eid)
        for key in ("trajectory_id", "scene_id"):
            if not isinstance(e.get(key), str):
                raise bad(key, "must be a string")
        if not _num_list(e.get("start_position"), 3):
            raise bad("start_position", "must be 3 finite numbers")
        q = e.get("start_rotation")
        if not _num_list(q, 4) or abs(math.sqrt(sum(v * v for v in q)) - 1) > 1e-6:
            raise bad("start_rotation", "must be a unit quaternion (w, x, y, z)")
        goals = e.get("goals")
        if not (
            isinstance(goals, list)
            and goals
            and all(
                _num_list(g.get("position"), 3)
                and isinstance(g.get("radius"), (int, float))
                and g["radius"] > 0
                for g in goals
            )
        ):
            raise bad("goals", "must be a non-empty list of {position: [x, y, z], radius > 0}")
        ref = e.get("reference_path")
        if not (isinstance(ref, list) and len(ref) >= 2 and all(_num_list(p, 3) for p in ref)):
            raise bad("reference_path", "must hold at least 2 points")
        ins = e.get("instruction", {})
        if not isinstance(ins.get("instruction_text"), str) or not ins["instruction_text"].strip():
            raise bad("instruction.instruction_text", "must be a non-empty string")
        toks = ins.get("instruction_tokens")
        if not (isinstance(toks, list) and all(isinstance(t, int) and 0 <= t < len(vocab) for t in toks)):
            raise bad("instruction.instruction_tokens", "must be vocabulary indices")
        geo = e.get("info", {}).get("geodesic_distance")
        if not (isinstance(geo, (int, float)) and math.isfinite(geo) and geo >= 0):
            raise bad("info.geodesic_distance", "must be a finite non-negative number")
        if geo < min_geodesic - 1e-6:
            raise bad(
                "info.geodesic_distance", f"{geo:.2f} m is below the minimum path length ({min_geodesic} m)"
            )
        if gt is not None:
            g = gt.get(eid)
            if g is None:
                raise bad("episode_id", "missing from the gt file")
            if not (isinstance(g.get("locations"), list) and all(_num_list(p, 3) for p in g["locations"])):
                raise bad("gt.locations", "must be a list of [x, y, z]")
            acts = g.get("actions")
            if not (
                isinstance(acts, list) and acts and all(a in (0, 1, 2, 3) for a in acts) and acts[-1] == 0
            ):
                raise bad("gt.actions", "must be action ids ending with STOP (0)")
            if g.get("forward_steps") != sum(1 for a in acts if a == 1):
                raise bad("gt.forward_steps", "must count the MOVE_FORWARD actions")
