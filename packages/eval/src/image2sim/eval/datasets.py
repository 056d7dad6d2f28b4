"""Episode datasets: R2R-CE, RxR-CE, REVERIE-CE (VLN-CE ``json.gz`` schema) and our own episodes.

Layouts (``root`` is the dataset directory, e.g. ``R2R_VLNCE_v1-3_preprocessed``)
    R2R-CE      ``{root}/{split}/{split}.json.gz`` (``episodes`` + ``instruction_vocab``) and optional
                ``{root}/{split}/{split}_gt.json.gz`` (``{episode_id: {locations, actions, forward_steps}}``)
    RxR-CE      ``{root}/{split}/{split}_{role}.json.gz`` and ``{split}_{role}_gt.json.gz``, role in
                ``guide`` / ``follower``; instructions add ``instruction_id``, ``language``,
                ``annotator_id``, ``edit_distance`` and ``timed_instruction``
    REVERIE-CE  the R2R-CE layout without a required vocabulary

Frames. VLN-CE files are in Habitat's world (Y-up, metres) with quaternions ``[x, y, z, w]``;
everything returned here is in our world (Z-up, see :mod:`image2sim.simulator.conventions`), via
:func:`habitat_to_world` ``(x, y, z) -> (x, -z, y)``, a +90° rotation about X. Our own episode files
(written by the data engine) may state ``"frame": "image2sim-z-up"`` and
``"quaternion_order": "wxyz"`` at the top level; a file without these keys is read as Habitat's.

Test splits list ``"goals": []`` (or ``null``) and have no ``_gt`` file: their episodes load with
``goal_position=None`` (:attr:`NavEpisode.has_goal` is False) and an empty reference path, and the
runner reports the goal's metrics as n/a (the leaderboard scores the submission).

Malformed files fail with :class:`EpisodeFileError` naming the file, the episode id and the field.
"""

from __future__ import annotations

import gzip
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from image2sim.eval.metrics.nav import EpisodeSpec
from image2sim.simulator.geometry.habitat import (
    habitat_heading,
    habitat_quaternion_to_world,
    habitat_to_world,
    unit_quaternion,
    world_heading,
)

Frame = Literal["habitat-y-up", "image2sim-z-up"]
HABITAT_FRAME: Frame = "habitat-y-up"
"""Frame name of VLN-CE / Habitat files (Y-up, agent looks along -Z)."""
WORLD_FRAME: Frame = "image2sim-z-up"
"""Frame name of our world (Z-up, heading 0 = +X)."""
RXR_ROLES = ("guide", "follower")
"""Annotation roles of RxR-CE."""


class EpisodeFileError(ValueError):
    """An episode or ground-truth file is missing or malformed."""


# ------------------------------------------------------------------------------------- records


@dataclass(frozen=True)
class TimedWord:
    """One word of an RxR timed instruction."""

    word: str
    """The word as spoken/written."""
    start_time: float | None
    """Start time in seconds (RxR uses NaN/absent for untimed words; mapped to None)."""
    end_time: float | None
    """End time in seconds, or None."""


@dataclass(frozen=True)
class Instruction:
    """A navigation instruction (R2R fields, plus RxR's when present)."""

    text: str
    """Instruction text."""
    tokens: tuple[int, ...] | None = None
    """Vocabulary token ids (R2R-CE), if given."""
    instruction_id: str | None = None
    """RxR instruction id."""
    language: str | None = None
    """RxR language tag (en-US, en-IN, hi-IN, te-IN)."""
    annotator_id: str | None = None
    """RxR annotator id."""
    edit_distance: float | None = None
    """RxR edit distance between guide and follower paths."""
    timed_instruction: tuple[TimedWord, ...] | None = None
    """RxR word timings."""


@dataclass(frozen=True, eq=False)
class NavEpisode:
    """One instruction-following episode in our world frame."""

    episode_id: str
    """Episode id as a string (VLN-CE uses ints; ground-truth files key them as strings)."""
    scene_id: str
    """Scene path as written in the file (e.g. ``mp3d/<scan>/<scan>.glb``)."""
    start_position: np.ndarray
    """(3,) start position, world metres (Z-up)."""
    start_rotation: np.ndarray
    """(4,) start rotation (w, x, y, z) in our world."""
    start_heading: float
    """Start heading in radians (yaw about +Z, 0 = +X)."""
    goal_position: np.ndarray | None
    """(3,) position of the first goal, world metres; ``None`` when the goal is unknown (the test
    splits of R2R-CE / RxR-CE list ``"goals": []``: the leaderboard scores them)."""
    goal_radius: float | None
    """Goal radius from the file (VLN-CE writes 3.0), if given. Success uses the protocol's radius."""
    geodesic_distance: float | None
    """``info.geodesic_distance`` (start to goal) if given."""
    reference_path: np.ndarray
    """(K, 3) sparse reference path (the R2R viewpoints), world metres; (0, 3) on a test split."""
    instruction: Instruction
    """The instruction."""
    trajectory_id: str | None = None
    """Trajectory id (several instructions share a path)."""
    gt_locations: np.ndarray | None = None
    """(T, 3) dense ground-truth positions from the ``_gt`` file; VLN-CE scores nDTW against these."""
    gt_actions: tuple[int, ...] | None = None
    """Ground-truth action ids from the ``_gt`` file."""
    role: str | None = None
    """RxR annotation role (guide / follower)."""

    @property
    def scene_name(self) -> str:
        """``mp3d/17DRP5sb8fy/17DRP5sb8fy.glb`` -> ``17DRP5sb8fy``."""
        return Path(self.scene_id).stem

    @property
    def has_goal(self) -> bool:
        """Whether the goal is known (False on test splits without goals)."""
        return self.goal_position is not None

    @property
    def ndtw_reference(self) -> np.ndarray | None:
        """The path nDTW should use: the dense ground truth if loaded, else the reference path;
        ``None`` when there is neither (a test split)."""
        if self.gt_locations is not None:
            return self.gt_locations
        return self.reference_path if len(self.reference_path) else None

    def metric_spec(self) -> EpisodeSpec:
        """The :class:`~image2sim.eval.metrics.nav.EpisodeSpec` the navigation measures need."""
        return EpisodeSpec(self.episode_id, self.ndtw_reference)


@dataclass(frozen=True)
class EpisodeDataset:
    """Episodes of one split plus the instruction vocabulary, if the dataset has one."""

    name: str
    """``r2r-ce``, ``rxr-ce``, ``reverie-ce`` or ``image2sim``."""
    split: str
    """Split name (``val_unseen``...)."""
    episodes: tuple[NavEpisode, ...]
    """Episodes in file order."""
    vocab: tuple[str, ...] | None = None
    """``instruction_vocab.word_list`` (R2R-CE)."""
    by_id: Mapping[str, NavEpisode] = field(default_factory=dict, compare=False, repr=False)
    """Episode id -> episode."""

    def __len__(self) -> int:
        return len(self.episodes)

    def scenes(self) -> list[str]:
        """Sorted scene names referenced by the episodes."""
        return sorted({e.scene_name for e in self.episodes})


# ------------------------------------------------------------------------------------- parsing


def _read_json_gz(path: Path) -> Any:
    if not path.is_file():
        raise EpisodeFileError(f"{path}: file not found")
    try:
        with gzip.open(path, "rt", encoding="utf-8") as f:
            return json.load(f)
    except (OSError, EOFError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise EpisodeFileError(f"{path}: cannot read gzipped JSON ({type(exc).__name__}: {exc})") from exc


class _Ctx:
    """Error context: file and episode id."""

    def __init__(self, path: Path, episode_id: Any = None) -> None:
        self.path = path
        self.episode_id = episode_id

    def fail(self, field_name: str, problem: str) -> EpisodeFileError:
        who = f"episode {self.episode_id}" if self.episode_id is not None else "top level"
        return EpisodeFileError(f"{self.path}: {who}: field {field_name!r}: {problem}")

    def get(self, obj: Mapping[str, Any], key: str, types: type | tuple[type, ...], prefix: str = "") -> Any:
        name = f"{prefix}{key}"
        if not isinstance(obj, Mapping):
            raise self.fail(prefix.rstrip(".") or key, f"expected an object, got {type(obj).__name__}")
        if key not in obj:
            raise self.fail(name, "missing")
        value = obj[key]
        if isinstance(value, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
            raise self.fail(name, "expected a number, got a bool")
        if not isinstance(value, types):
            raise self.fail(name, f"expected {_type_names(types)}, got {type(value).__name__}")
        return value

    def vec(self, value: Any, name: str, n: int) -> np.ndarray:
        if not (isinstance(value, list) and len(value) == n and all(_is_num(v) for v in value)):
            raise self.fail(name, f"expected a list of {n} numbers, got {value!r:.80}")
        arr = np.asarray(value, dtype=np.float64)
        if not np.all(np.isfinite(arr)):
            raise self.fail(name, "contains NaN or inf")
        return arr

    def path_points(self, value: Any, name: str) -> np.ndarray:
        if not isinstance(value, list) or not value:
            raise self.fail(name, "expected a non-empty list of [x, y, z] points")
        return np.stack([self.vec(p, f"{name}[{i}]", 3) for i, p in enumerate(value)])


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _type_names(types: type | tuple[type, ...]) -> str:
    ts = types if isinstance(types, tuple) else (types,)
    return " or ".join(t.__name__ for t in ts)


def _frame_of(doc: Mapping[str, Any], ctx: _Ctx) -> tuple[Frame, str]:
    frame = doc.get("frame", HABITAT_FRAME)
    order = doc.get("quaternion_order", "xyzw" if frame == HABITAT_FRAME else "wxyz")
    if frame not in (HABITAT_FRAME, WORLD_FRAME):
        raise ctx.fail("frame", f"expected {HABITAT_FRAME!r} or {WORLD_FRAME!r}, got {frame!r}")
    if order not in ("xyzw", "wxyz"):
        raise ctx.fail("quaternion_order", f"expected 'xyzw' or 'wxyz', got {order!r}")
    return frame, order


def _to_world_points(p: np.ndarray, frame: Frame) -> np.ndarray:
    return habitat_to_world(p) if frame == HABITAT_FRAME else p


def _parse_instruction(raw: Any, ctx: _Ctx) -> Instruction:
    text = ctx.get(raw, "instruction_text", str, "instruction.")
    tokens = raw.get("instruction_tokens")
    if tokens is not None:
        if not isinstance(tokens, list):
            raise ctx.fail("instruction.instruction_tokens", "expected a list")
        if all(isinstance(t, str) for t in tokens):
            tokens = None  # RxR files carry word strings here; only vocabulary ids are kept
        elif not all(isinstance(t, int) and not isinstance(t, bool) for t in tokens):
            raise ctx.fail("instruction.instruction_tokens", "expected integer token ids (or words)")
    timed = raw.get("timed_instruction")
    timed_words = None
    if timed is not None:
        if not isinstance(timed, list):
            raise ctx.fail("instruction.timed_instruction", "expected a list")
        words = []
        for i, w in enumerate(timed):
            name = f"instruction.timed_instruction[{i}]"
            word = ctx.get(w, "word", str, f"{name}.")
            times = []
            for key in ("start_time", "end_time"):
                t = w.get(key)
                if t is not None and not _is_num(t):
                    raise ctx.fail(f"{name}.{key}", f"expected a number, got {t!r}")
                times.append(None if t is None or not math.isfinite(t) else float(t))
            words.append(TimedWord(word, times[0], times[1]))
        timed_words = tuple(words)
    opt_str = {}
    for key in ("instruction_id", "language", "annotator_id"):
        v = raw.get(key)
        if v is not None and not isinstance(v, (str, int)):
            raise ctx.fail(f"instruction.{key}", f"expected a string, got {type(v).__name__}")
        opt_str[key] = None if v is None else str(v)
    ed = raw.get("edit_distance")
    if ed is not None and not _is_num(ed):
        raise ctx.fail("instruction.edit_distance", f"expected a number, got {ed!r}")
    return Instruction(
        text=text,
        tokens=None if tokens is None else tuple(tokens),
        edit_distance=None if ed is None else float(ed),
        timed_instruction=timed_words,
        **opt_str,
    )


def _parse_goal(raw: Mapping[str, Any], ctx: _Ctx) -> tuple[np.ndarray | None, float | None]:
    """The first goal's position and radius; ``(None, None)`` for ``"goals": []`` or ``null`` (a test
    split: the goal is unknown). A record without the ``goals`` key is an error."""
    if "goals" not in raw:
        raise ctx.fail("goals", 'missing (a test split without goals lists "goals": [])')
    goals = raw["goals"]
    if goals is None or goals == []:
        return None, None
    if not isinstance(goals, list):
        raise ctx.fail("goals", f"expected a list, got {type(goals).__name__}")
    goal = ctx.vec(ctx.get(goals[0], "position", list, "goals[0]."), "goals[0].position", 3)
    radius = goals[0].get("radius")
    if radius is not None and not (_is_num(radius) and radius >= 0):
        raise ctx.fail("goals[0].radius", f"expected a non-negative number, got {radius!r}")
    return goal, None if radius is None else float(radius)


def _parse_reference_path(raw: Mapping[str, Any], ctx: _Ctx, has_goal: bool) -> np.ndarray:
    """The reference path; an episode without a goal may have none (absent, null or []: (0, 3))."""
    if not has_goal and raw.get("reference_path") in (None, []):
        return np.zeros((0, 3), dtype=np.float64)
    return ctx.path_points(ctx.get(raw, "reference_path", list), "reference_path")


def _parse_episode(raw: Any, path: Path, frame: Frame, order: str, role: str | None) -> NavEpisode:
    ctx = _Ctx(path)
    if not isinstance(raw, Mapping):
        raise EpisodeFileError(f"{path}: an entry of 'episodes' is a {type(raw).__name__}, not an object")
    eid = ctx.get(raw, "episode_id", (int, str))
    ctx.episode_id = eid
    scene = ctx.get(raw, "scene_id", str)
    start = ctx.vec(ctx.get(raw, "start_position", list), "start_position", 3)
    rot = ctx.vec(ctx.get(raw, "start_rotation", list), "start_rotation", 4)
    try:
        if frame == HABITAT_FRAME:
            if order != "xyzw":
                rot = rot[[1, 2, 3, 0]]
            q_world = habitat_quaternion_to_world(rot)
            heading = habitat_heading(rot)
        else:
            q_world = unit_quaternion(rot if order == "wxyz" else rot[[3, 0, 1, 2]], "start_rotation")
            heading = world_heading(q_world)
    except ValueError as exc:
        raise ctx.fail("start_rotation", str(exc)) from None
    goal, radius = _parse_goal(raw, ctx)
    info = raw.get("info") or {}
    geo = info.get("geodesic_distance") if isinstance(info, Mapping) else None
    if geo is not None and not (_is_num(geo) and math.isfinite(geo) and geo >= 0):
        raise ctx.fail("info.geodesic_distance", f"expected a finite non-negative number, got {geo!r}")
    ref = _parse_reference_path(raw, ctx, goal is not None)
    instruction = _parse_instruction(ctx.get(raw, "instruction", dict), ctx)
    traj = raw.get("trajectory_id")
    return NavEpisode(
        episode_id=str(eid),
        scene_id=scene,
        start_position=_to_world_points(start, frame),
        start_rotation=q_world,
        start_heading=heading,
        goal_position=None if goal is None else _to_world_points(goal, frame),
        goal_radius=radius,
        geodesic_distance=None if geo is None else float(geo),
        reference_path=_to_world_points(ref, frame),
        instruction=instruction,
        trajectory_id=None if traj is None else str(traj),
        role=role,
    )


def _parse_gt(doc: Any, path: Path, frame: Frame) -> dict[str, tuple[np.ndarray, tuple[int, ...] | None]]:
    if not isinstance(doc, Mapping):
        raise EpisodeFileError(f"{path}: top level must be an object keyed by episode id")
    out = {}
    for eid, entry in doc.items():
        ctx = _Ctx(path, eid)
        locs = ctx.path_points(ctx.get(entry, "locations", list), "locations")
        actions = entry.get("actions")
        if actions is not None and not (
            isinstance(actions, list) and all(isinstance(a, int) and not isinstance(a, bool) for a in actions)
        ):
            raise ctx.fail("actions", "expected a list of integer action ids")
        bad = sorted({a for a in actions or [] if not 0 <= a <= 3})
        if bad:
            raise ctx.fail("actions", f"action ids must be 0..3 (STOP, FORWARD, LEFT, RIGHT), got {bad}")
        out[str(eid)] = (_to_world_points(locs, frame), None if actions is None else tuple(actions))
    return out


def load_episode_file(
    path: str | Path,
    gt_path: str | Path | None = None,
    *,
    require_vocab: bool = False,
    role: str | None = None,
) -> tuple[list[NavEpisode], tuple[str, ...] | None]:
    """Parse one VLN-CE-schema episode file (and its ground-truth file) into world-frame episodes."""
    path = Path(path)
    doc = _read_json_gz(path)
    ctx = _Ctx(path)
    if not isinstance(doc, Mapping):
        raise EpisodeFileError(f"{path}: top level must be an object with 'episodes'")
    frame, order = _frame_of(doc, ctx)
    raw_eps = ctx.get(doc, "episodes", list)
    vocab = None
    if "instruction_vocab" in doc:
        words = ctx.get(ctx.get(doc, "instruction_vocab", dict), "word_list", list, "instruction_vocab.")
        if not all(isinstance(w, str) for w in words):
            raise ctx.fail("instruction_vocab.word_list", "expected a list of strings")
        vocab = tuple(words)
    elif require_vocab:
        raise ctx.fail("instruction_vocab", "missing (required for R2R-CE)")
    episodes = [_parse_episode(raw, path, frame, order, role) for raw in raw_eps]
    if gt_path is not None:
        gt_path = Path(gt_path)
        gt = _parse_gt(_read_json_gz(gt_path), gt_path, frame)
        for i, ep in enumerate(episodes):
            if ep.episode_id not in gt:
                raise EpisodeFileError(f"{gt_path}: episode {ep.episode_id}: missing (listed in {path})")
            locs, actions = gt[ep.episode_id]
            episodes[i] = _with_gt(ep, locs, actions)
    return episodes, vocab


def _with_gt(ep: NavEpisode, locs: np.ndarray, actions: tuple[int, ...] | None) -> NavEpisode:
    fields = {f: getattr(ep, f) for f in ep.__dataclass_fields__}
    fields.update(gt_locations=locs, gt_actions=actions)
    return NavEpisode(**fields)


def _dataset(
    name: str,
    split: str,
    episodes: Sequence[NavEpisode],
    vocab: tuple[str, ...] | None,
    sources: Iterable[Path],
) -> EpisodeDataset:
    by_id: dict[str, NavEpisode] = {}
    for ep in episodes:
        if ep.episode_id in by_id:
            files = [str(s) for s in sources]
            raise EpisodeFileError(f"{files}: episode {ep.episode_id}: duplicate episode id")
        by_id[ep.episode_id] = ep
    return EpisodeDataset(name, split, tuple(episodes), vocab, by_id)


def _gt_if_present(path: Path, with_gt: bool | None) -> Path | None:
    """``with_gt=None``: use the gt file if it exists (test splits have none); True: require it."""
    if with_gt is False:
        return None
    if path.is_file():
        return path
    if with_gt:
        raise EpisodeFileError(f"{path}: ground-truth file not found")
    return None


def load_r2r_ce(root: str | Path, split: str, *, with_gt: bool | None = None) -> EpisodeDataset:
    """R2R-CE ``{root}/{split}/{split}.json.gz`` (vocabulary required) plus ``{split}_gt.json.gz``."""
    d = Path(root) / split
    main, gt = d / f"{split}.json.gz", _gt_if_present(d / f"{split}_gt.json.gz", with_gt)
    episodes, vocab = load_episode_file(main, gt, require_vocab=True)
    return _dataset("r2r-ce", split, episodes, vocab, [main])


def load_reverie_ce(root: str | Path, split: str, *, with_gt: bool | None = None) -> EpisodeDataset:
    """REVERIE-CE: the R2R-CE layout and episode schema, vocabulary optional."""
    d = Path(root) / split
    main, gt = d / f"{split}.json.gz", _gt_if_present(d / f"{split}_gt.json.gz", with_gt)
    episodes, vocab = load_episode_file(main, gt, require_vocab=False)
    return _dataset("reverie-ce", split, episodes, vocab, [main])


def load_rxr_ce(
    root: str | Path,
    split: str,
    *,
    roles: Sequence[str] = ("guide",),
    languages: Sequence[str] | None = None,
    with_gt: bool | None = None,
) -> EpisodeDataset:
    """RxR-CE ``{root}/{split}/{split}_{role}.json.gz`` (+ ``_gt``) for each role, optionally by language."""
    bad = [r for r in roles if r not in RXR_ROLES]
    if bad or not roles:
        raise ValueError(f"roles: expected a non-empty subset of {RXR_ROLES}, got {list(roles)}")
    d = Path(root) / split
    episodes: list[NavEpisode] = []
    sources = []
    for role in roles:
        main = d / f"{split}_{role}.json.gz"
        gt = _gt_if_present(d / f"{split}_{role}_gt.json.gz", with_gt)
        eps, _ = load_episode_file(main, gt, role=role)
        episodes += eps
        sources.append(main)
    if languages is not None:
        keep = set(languages)
        episodes = [e for e in episodes if e.instruction.language in keep]
    return _dataset("rxr-ce", split, episodes, None, sources)


def load_image2sim_episodes(
    path: str | Path, gt_path: str | Path | None = None, split: str = "custom"
) -> EpisodeDataset:
    """Episodes written by the data engine (VLN-CE schema; ``frame``/``quaternion_order`` honoured)."""
    episodes, vocab = load_episode_file(path, gt_path)
    return _dataset("image2sim", split, episodes, vocab, [Path(path)])
