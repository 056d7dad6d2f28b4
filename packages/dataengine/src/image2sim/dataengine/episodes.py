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

RxR-CE layout (``data episodes --format rxr-ce``): the engine's instructions are the *guide* role's
(the annotator walked the path), so it writes ``{split}/{split}_guide.json.gz`` +
``{split}_guide_gt.json.gz`` (+ ``{split}_guide_extras.json``), what VLN-CE's ``RxRVLNCEDatasetV1``
reads for ``ROLES: [guide]``. Records are the same minus the R2R vocabulary: the instruction is
``{"instruction_text", "instruction_id", "language", "annotator_id"}`` (``instruction_id`` a string of
digits, unique in the file, as RxR's; ``annotator_id`` the annotator backend, ``image2sim-template``),
and there is no ``instruction_vocab`` (RxR-CE has none; its models read text features by
``instruction_id``). No follower file is written: nobody followed the instructions.

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
    "EPISODE_FORMATS",
    "FRAME",
    "MAX_TOKENS",
    "QUATERNION_ORDER",
    "tokenize",
    "build_vocab",
    "check_episode_layout",
    "episode_record",
    "gt_record",
    "episode_paths",
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
EPISODE_FORMATS = ("r2r-ce", "rxr-ce")
"""Episode file layouts :func:`write_episode_files` writes (module docstring)."""
RXR_ROLE = "guide"
"""The RxR-CE annotation role of the engine's instructions."""
LANGUAGE_TAG = re.compile(r"^[a-z]{2,3}-[A-Z]{2}$")
"""RxR-style language tags (en-US, en-IN, hi-IN, te-IN)."""
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


def episode_paths(out_dir: str | Path, split: str, fmt: str = "r2r-ce") -> tuple[Path, Path]:
    """The episode file and its gt file of ``split`` in ``fmt``'s layout: ``{split}/{split}.json.gz``
    (R2R-CE) or ``{split}/{split}_guide.json.gz`` (RxR-CE), and the ``_gt.json.gz`` beside it."""
    check_episode_layout(fmt)
    stem = split if fmt == "r2r-ce" else f"{split}_{RXR_ROLE}"
    d = Path(out_dir) / split
    return d / f"{stem}.json.gz", d / f"{stem}_gt.json.gz"


def check_episode_layout(fmt: str, language: str = "en-US") -> None:
    """Raise ``ValueError`` for an unknown episode format or (rxr-ce) a malformed language tag, so a
    run fails before any scene is processed rather than at the merge."""
    if fmt not in EPISODE_FORMATS:
        raise ValueError(f"episode format must be one of {EPISODE_FORMATS}, got {fmt!r}")
    if fmt == "rxr-ce" and not LANGUAGE_TAG.match(language):
        raise ValueError(
            f"language: expected a tag like en-US (RxR: en-US, en-IN, hi-IN, te-IN), got {language!r}"
        )


def _r2r_doc(episodes: Sequence[dict]) -> dict:
    """R2R-CE: tokens padded to :data:`MAX_TOKENS` and the vocabulary block."""
    vocab = build_vocab(e["instruction"]["instruction_text"] for e in episodes)
    index = {w: i for i, w in enumerate(vocab)}
    eps = []
    for e in episodes:
        e = dict(e)
        e["instruction"] = dict(e["instruction"])
        tokens = [index.get(w, 1) for w in tokenize(e["instruction"]["instruction_text"])][:MAX_TOKENS]
        e["instruction"]["instruction_tokens"] = tokens + [0] * (MAX_TOKENS - len(tokens))
        eps.append(e)
    return {
        "frame": FRAME,
        "quaternion_order": QUATERNION_ORDER,
        "episodes": eps,
        "instruction_vocab": vocab_block(vocab),
    }


def _rxr_doc(episodes: Sequence[dict], language: str, annotator_id: str) -> dict:
    """RxR-CE guide file: ``instruction_id`` (file order), ``language`` and ``annotator_id`` per
    instruction, no tokens and no vocabulary."""
    check_episode_layout("rxr-ce", language)
    eps = []
    for i, e in enumerate(episodes):
        ins = {"instruction_text": e["instruction"]["instruction_text"], "instruction_id": str(i)}
        eps.append({**e, "instruction": {**ins, "language": language, "annotator_id": annotator_id}})
    return {"frame": FRAME, "quaternion_order": QUATERNION_ORDER, "episodes": eps}


def write_episode_files(
    out_dir: str | Path,
    split: str,
    episodes: Sequence[dict],
    gt: dict,
    min_geodesic: float = 0.0,
    extras: dict | None = None,
    fmt: str = "r2r-ce",
    language: str = "en-US",
    annotator_id: str = "image2sim",
) -> tuple[Path, Path]:
    """Validate (:func:`validate_episode_doc`) and write the split in ``fmt``'s layout
    (:func:`episode_paths`) with its gt file (+ the ``_extras.json`` sidecar) atomically.

    ``r2r-ce``: tokens padded to :data:`MAX_TOKENS` and the vocabulary block; ``rxr-ce``: the guide
    role's file, each instruction with ``instruction_id``, ``language`` and ``annotator_id``."""
    main, gt_path = episode_paths(out_dir, split, fmt)
    doc = _r2r_doc(episodes) if fmt == "r2r-ce" else _rxr_doc(episodes, language, annotator_id)
    validate_episode_doc(doc, gt, min_geodesic, fmt)
    write_bytes_atomic(gt_path, _gz(gt))
    if extras is not None:
        write_json_atomic(main.with_name(main.name.replace(".json.gz", "_extras.json")), extras, indent=None)
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


def validate_episode_doc(
    doc: dict, gt: dict | None = None, min_geodesic: float = 0.0, fmt: str = "r2r-ce"
) -> None:
    """Check the schema above (``fmt``: r2r-ce or rxr-ce); raises :class:`EpisodeSchemaError` at the
    first problem.

    ``min_geodesic``: no episode may be shorter (the sampling config's ``min_path_length``): a shorter
    one starts inside the evaluation's success radius and is solved by stopping at once."""
    if doc.get("frame") != FRAME or doc.get("quaternion_order") != QUATERNION_ORDER:
        raise EpisodeSchemaError(f"top level: frame/quaternion_order must be {FRAME!r}/{QUATERNION_ORDER!r}")
    if not isinstance(doc.get("episodes"), list):
        raise EpisodeSchemaError("top level: 'episodes' must be a list")
    vocab = _check_vocab(doc, fmt)
    seen, instruction_ids = set(), set()
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
        if fmt == "r2r-ce":
            _check_tokens(ins, vocab, bad)
        else:
            _check_rxr_instruction(ins, instruction_ids, bad)
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


def _check_vocab(doc: dict, fmt: str) -> list[str] | None:
    """R2R-CE's vocabulary word list (required); RxR-CE files have none (None)."""
    if fmt not in EPISODE_FORMATS:
        raise EpisodeSchemaError(f"format must be one of {EPISODE_FORMATS}, got {fmt!r}")
    if fmt == "rxr-ce":
        if "instruction_vocab" in doc:
            raise EpisodeSchemaError("top level: 'instruction_vocab': RxR-CE files have no vocabulary")
        return None
    vocab = doc.get("instruction_vocab", {}).get("word_list")
    if not isinstance(vocab, list) or not all(isinstance(w, str) for w in vocab):
        raise EpisodeSchemaError("top level: instruction_vocab.word_list must be a list of strings")
    return vocab


def _check_tokens(ins: dict, vocab: list[str], bad) -> None:
    """R2R-CE: vocabulary indices padded to :data:`MAX_TOKENS`."""
    toks = ins.get("instruction_tokens")
    if not (isinstance(toks, list) and all(isinstance(t, int) and 0 <= t < len(vocab) for t in toks)):
        raise bad("instruction.instruction_tokens", "must be vocabulary indices")
    if len(toks) != MAX_TOKENS:
        raise bad("instruction.instruction_tokens", f"must be padded to {MAX_TOKENS}, got {len(toks)}")


def _check_rxr_instruction(ins: dict, seen: set, bad) -> None:
    """RxR-CE: a unique ``instruction_id`` (digits), a ``language`` tag and an ``annotator_id``."""
    iid = ins.get("instruction_id")
    if not (isinstance(iid, str) and iid.isdigit()) or iid in seen:
        raise bad("instruction.instruction_id", "must be a unique string of digits (RxR's ids are integers)")
    seen.add(iid)
    if not (isinstance(ins.get("language"), str) and LANGUAGE_TAG.match(ins["language"])):
        raise bad("instruction.language", "must be a tag like en-US")
    if not (isinstance(ins.get("annotator_id"), str) and ins["annotator_id"]):
        raise bad("instruction.annotator_id", "must be a non-empty string")
    if "instruction_tokens" in ins:
        raise bad("instruction.instruction_tokens", "RxR-CE files carry no vocabulary tokens")
