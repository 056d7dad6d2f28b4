"""VLN-CE ``json.gz`` episode files (+ ``{split}_gt.json.gz``) written by the data engine.

The files are what VLN-CE's ``VLNCEDatasetV1`` (and Habitat) read unmodified: the Habitat frame (Y up,
metres, quaternions ``[x, y, z, w]``; conversions in :mod:`image2sim.simulator.geometry.habitat`),
episode records holding only VLN-CE's fields, instruction tokens padded to 200 with PAD (0), and the
vocabulary block of R2R-CE::

    {"frame": "habitat-y-up", "quaternion_order": "xyzw",
     "episodes": [{"episode_id", "trajectory_id", "scene_id", "start_position": [x, y, z],
                   "start_rotation": [x, y, z, w], "goals": [{"position": [x, y, z], "radius": r}],
                   "reference_path": [[x, y, z], ...],
                   "instruction": {"instruction_text": str, "instruction_tokens": [int] * 200},
                   "info": {"geodesic_distance": m}}],
     "instruction_vocab": {"word_list", "word2idx_dict", "itos", "stoi", "num_vocab", "UNK_INDEX",
                           "PAD_INDEX"}}

    {split}_gt.json.gz: {episode_id: {"locations": [[x, y, z], ...], "actions": [...], "forward_steps": n}}
    {split}_extras.json: {episode_id: {"style", "structure", "tone", "goal_object", "bucket",
                                       "path_length", "num_steps", "macro_steps", ...}}

The engine's own fields live in the sidecar ``{split}_extras.json`` (plain JSON, so tools that glob the
split folder's ``*.json.gz`` never take it for an episode file). The two top-level ``frame`` and
``quaternion_order`` keys are ignored by VLN-CE and let our loader check the frame instead of guessing.
``scene_id`` is the scene's folder name: ``<scenes dir>/<scene_id>`` is the scene for
``eval nav --scenes <scenes dir>`` (the engine's own ``<out>/scenes`` holds the map and Gaussians).
"""

from __future__ import annotations

import gzip
import json
import math
import re
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from image2sim.simulator.geometry.habitat import habitat_rotation_for_heading, world_to_habitat
from image2sim.simulator.io.atomic import write_bytes_atomic, write_json_atomic

__all__ = [
    "EPISODE_FIELDS",
    "FRAME",
    "MAX_TOKENS",
    "QUATERNION_ORDER",
    "tokenize",
    "build_vocab",
    "episode_record",
    "gt_record",
    "read_extras",
    "vocab_block",
    "write_episode_files",
    "validate_episode_doc",
    "EpisodeSchemaError",
]

FRAME = "habitat-y-up"
QUATERNION_ORDER = "xyzw"
PAD, UNK = "<PAD>", "<UNK>"
MAX_TOKENS = 200
"""R2R-CE pads (and truncates) instruction tokens to this length."""
EPISODE_FIELDS = {
    "episode_id",
    "scene_id",
    "scene_dataset_config",
    "additional_obj_config_paths",
    "start_position",
    "start_rotation",
    "info",
    "goals",
    "start_room",
    "shortest_paths",
    "reference_path",
    "instruction",
    "trajectory_id",
}
"""The keyword arguments of VLN-CE's episode class (habitat's ``Episode`` + ``NavigationEpisode`` +
``VLNExtendedEpisode``): any other key in a record is a ``TypeError`` in its loader."""
INSTRUCTION_FIELDS = {
    "instruction_text",
    "instruction_tokens",
    "instruction_id",
    "language",
    "annotator_id",
    "edit_distance",
    "timed_instruction",
    "split",
}


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
) -> dict:
    """One VLN-CE episode from world-frame inputs (Z up; ``heading`` about +Z, 0 = +X), converted to the
    Habitat frame. Instruction tokens are filled in by :func:`write_episode_files`."""
    return {
        "episode_id": str(episode_id),
        "trajectory_id": str(episode_id),
        "scene_id": scene_id,
        "start_position": _vec(world_to_habitat(start)),
        "start_rotation": _vec(habitat_rotation_for_heading(heading)),
        "goals": [{"position": _vec(world_to_habitat(goal)), "radius": float(radius)}],
        "reference_path": [_vec(p) for p in world_to_habitat(np.asarray(reference_path, dtype=np.float64))],
        "instruction": {"instruction_text": text, "instruction_tokens": []},
        "info": {"geodesic_distance": float(geodesic)},
    }


def gt_record(locations, actions, forward_steps: int) -> dict:
    """The ground truth of one episode (world-frame ``locations`` converted to the Habitat frame)."""
    return {
        "locations": [_vec(p) for p in world_to_habitat(np.asarray(locations, dtype=np.float64))],
        "actions": [int(a) for a in actions],
        "forward_steps": int(forward_steps),
    }


def vocab_block(words: Sequence[str]) -> dict:
    """R2R-CE's ``instruction_vocab`` (VLN-CE's ``VocabDict`` reads ``word_list``)."""
    words = list(words)
    index = {w: i for i, w in enumerate(words)}
    return {
        "word_list": words,
        "word2idx_dict": index,
        "itos": words,
        "stoi": index,
        "num_vocab": len(words),
        "UNK_INDEX": 1,
        "PAD_INDEX": 0,
    }


def _gz(obj) -> bytes:
    # mtime=0: the same episodes give byte-identical files.
    return gzip.compress(json.dumps(obj, separators=(",", ":")).encode("utf-8"), mtime=0)


def write_episode_files(
    out_dir: str | Path,
    split: str,
    episodes: Sequence[dict],
    gt: dict,
    min_geodesic: float = 0.0,
    extras: dict | None = None,
) -> tuple[Path, Path]:
    """Tokenise (padded to :data:`MAX_TOKENS`), validate (:func:`validate_episode_doc`), write
    ``{out}/{split}/{split}.json.gz`` + ``{split}_gt.json.gz`` (+ ``{split}_extras.json``) atomically."""
    vocab = build_vocab(e["instruction"]["instruction_text"] for e in episodes)
    index = {w: i for i, w in enumerate(vocab)}
    eps = []
    for e in episodes:
        e = dict(e)
        e["instruction"] = dict(e["instruction"])
        tokens = [index.get(w, 1) for w in tokenize(e["instruction"]["instruction_text"])][:MAX_TOKENS]
        e["instruction"]["instruction_tokens"] = tokens + [0] * (MAX_TOKENS - len(tokens))
        eps.append(e)
    doc = {
        "frame": FRAME,
        "quaternion_order": QUATERNION_ORDER,
        "episodes": eps,
        "instruction_vocab": vocab_block(vocab),
    }
    validate_episode_doc(doc, gt, min_geodesic)
    d = Path(out_dir) / split
    main, gt_path = d / f"{split}.json.gz", d / f"{split}_gt.json.gz"
    write_bytes_atomic(gt_path, _gz(gt))
    if extras is not None:
        write_json_atomic(d / f"{split}_extras.json", extras, indent=None)
    write_bytes_atomic(main, _gz(doc))
    return main, gt_path


def read_extras(episode_file: str | Path) -> dict:
    """The sidecar ``{split}_extras.json`` beside an episode file ({} when absent)."""
    path = Path(episode_file)
    side = path.with_name(path.name.replace(".json.gz", "_extras.json"))
    return json.loads(side.read_text()) if side.is_file() else {}


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
        unknown = sorted(set(e) - EPISODE_FIELDS)
        if unknown:
            raise bad(
                unknown[0], f"not a VLN-CE episode field (extras belong in the sidecar); all: {unknown}"
            )
        unknown = sorted(set(e.get("instruction") or {}) - INSTRUCTION_FIELDS)
        if unknown:
            raise bad(f"instruction.{unknown[0]}", "not a VLN-CE instruction field")
        q = e.get("start_rotation")
        if not _num_list(q, 4) or abs(math.sqrt(sum(v * v for v in q)) - 1) > 1e-6:
            raise bad("start_rotation", "must be a unit quaternion [x, y, z, w]")
        if abs(q[0]) > 1e-6 or abs(q[2]) > 1e-6:
            raise bad("start_rotation", "must be a yaw about Habitat's +Y (x = z = 0: the agent upright)")
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
        if len(toks) != MAX_TOKENS:
            raise bad("instruction.instruction_tokens", f"must be padded to {MAX_TOKENS}, got {len(toks)}")
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
