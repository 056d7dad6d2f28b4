"""Training data for Image2Nav: trajectory records, an on-disk shard format and samples (batches:
:mod:`image2sim.navpolicy.collate`).

Shard format ``image2sim-navshard`` v1 (one folder; what the data engine writes)::

    <shard>/manifest.json        {"format": "image2sim-navshard", "version": 1, "num_trajectories": N,
                                  "action_ids": {"STOP": 0, ...}, "observation": {...free-form camera info}}
    <shard>/trajectories.jsonl   one JSON object per line, in order:
                                   {"episode_id": str, "scene_id": str, "instruction": str,
                                    "actions": [int, ...],        # T actions; action t is taken at step t
                                    "frame_steps": [int, ...],    # steps whose observation is stored
                                    "frames": "frames/000000.npz", "extra": {...}}
    <shard>/frames/NNNNNN.npz    key "rgb": (len(frame_steps), H, W, 3) uint8, frame i observed at step
                                 frame_steps[i] (before action frame_steps[i] is taken); no pickles.

Step ``t`` means "the agent is at state t, sees frame t and takes actions[t]"; the last action of a
finished trajectory is STOP. The frames may be a subset of the steps (the data engine can pre-render
only the frames it will ever sample). Every file is written to a temp name and renamed.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from image2sim.navpolicy.actions import ACTIONS_PER_STEP
from image2sim.navpolicy.config import GOAL_LABELS
from image2sim.simulator.conventions import Action
from image2sim.simulator.io.atomic import write_bytes_atomic

SHARD_FORMAT = "image2sim-navshard"
SHARD_VERSION = 1


class ShardError(ValueError):
    """A shard file is missing or malformed; the message names the file and the problem."""


GOAL_IN_VIEW = "goal_in_view"
"""Optional per-frame record field (``extra``): 1 where the instruction's goal object is in the
frame's view (the data engine's ``goal_in_view``); the target of ``train.goal_aux_weight``."""
GOAL_CATEGORY = "goal_category"
"""Key of ``Trajectory.extra`` naming the goal object's category (the data engine's episodes with a
goal object); the wrong-goal end samples of ``data.wrong_goal_stop_probability`` swap by it."""


@dataclass
class Trajectory:
    """One expert trajectory with (some of) its rendered observations.

    Attributes:
        instruction: natural-language instruction.
        actions: the T action ids taken at steps 0..T-1 (ends with STOP when the episode finished).
        frames: (N, H, W, 3) uint8 observations.
        frame_steps: the N strictly increasing steps (in [0, T-1]) at which ``frames`` were observed.
        episode_id: identifier of the episode.
        scene_id: identifier of the scene.
        extra: free-form JSON-able metadata (camera, start pose, ...).
    """

    instruction: str
    actions: list[int]
    frames: np.ndarray
    frame_steps: list[int]
    episode_id: str = ""
    scene_id: str = ""
    extra: dict = field(default_factory=dict)

    def validate(self, where: str = "trajectory") -> Trajectory:
        """Raise :class:`ShardError` naming ``where`` if the record is inconsistent."""
        valid = {int(a) for a in Action}
        if not self.actions:
            raise ShardError(f"{where}: empty action list")
        bad = [a for a in self.actions if int(a) not in valid]
        if bad:
            raise ShardError(f"{where}: unknown action ids {sorted(set(bad))}")
        f = np.asarray(self.frames)
        if f.ndim != 4 or f.shape[-1] != 3 or f.dtype != np.uint8:
            raise ShardError(f"{where}: frames must be (N, H, W, 3) uint8, got {f.shape} {f.dtype}")
        steps = list(self.frame_steps)
        if len(steps) != f.shape[0] or not steps:
            raise ShardError(f"{where}: {f.shape[0]} frames but {len(steps)} frame_steps")
        increasing = all(b > a for a, b in zip(steps, steps[1:], strict=False))
        if not increasing or steps[0] < 0 or steps[-1] >= len(self.actions):
            raise ShardError(
                f"{where}: frame_steps must increase strictly inside [0, {len(self.actions) - 1}]"
            )
        seen = self.extra.get(GOAL_IN_VIEW) if isinstance(self.extra, dict) else None
        if seen is not None and (len(seen) != len(steps) or any(int(v) not in (0, 1) for v in seen)):
            raise ShardError(f"{where}: extra.{GOAL_IN_VIEW} must hold one 0/1 per frame ({len(steps)})")
        return self


@dataclass
class NavSample:
    """One training sample: up to 32 observations of a trajectory and two action labels each.

    Attributes:
        instruction: the instruction.
        observations: (n, H, W, 3) uint8 images, in trajectory order.
        steps: the step of each observation.
        executed: for each observation, the actions executed since the previous one (empty first).
        targets: for each observation, the next two actions (labels).
        episode_id: source episode.
    """

    instruction: str
    observations: np.ndarray
    steps: list[int]
    executed: list[tuple[int, ...]]
    targets: list[tuple[int, ...]]
    episode_id: str = ""
    goal_in_view: list[int] | None = None
    """Per observation, the grounding head's 0/1 target (``data.goal_label``: the goal is in view, or
    the trajectory's end is near); None: the trajectory has no such labels."""
    stop_negative: bool = False
    """A wrong-goal end sample: the instruction names a goal that is not where the trajectory ends,
    so its actions are not labels; only STOP at the last observation is penalised."""

    @property
    def num_labels(self) -> int:
        return sum(len(t) for t in self.targets)


def uniform_indices(n: int, k: int, rng: np.random.Generator | None = None) -> list[int]:
    """``min(n, k)`` sorted distinct indices in ``[0, n)`` spread uniformly; index 0 always included.

    Without ``rng``: evenly spaced including both ends. With ``rng``: stratified — ``[0, n)`` is cut
    into ``k`` equal bins and one index is drawn per bin (the first bin always yields 0, the start).
    """
    if n <= 0 or k <= 0:
        return []
    if n <= k:
        return list(range(n))
    if rng is None:
        return sorted({int(round(x)) for x in np.linspace(0, n - 1, k)})
    out = [0]
    for i in range(1, k):
        # Bin i is [i*n/k, (i+1)*n/k); its integers start at ceil(i*n/k). Integer arithmetic: a float
        # edge such as 63.0000000001 would move an index into the next bin.
        lo, hi = -(-i * n // k), -(-(i + 1) * n // k)
        out.append(int(rng.integers(lo, max(lo + 1, hi))))
    return out


def next_actions(actions: Sequence[int], step: int, count: int = ACTIONS_PER_STEP) -> tuple[int, ...]:
    """The ``count`` actions from ``step`` on; past the end of the trajectory the label is STOP."""
    return tuple(int(actions[t]) if t < len(actions) else int(Action.STOP) for t in range(step, step + count))


def select_context_frames(n: int, sparse: int, dense: int) -> list[int]:
    """Frame indices (sorted) of the streaming agent's context for an episode with ``n`` observations.

    All frames while ``n <= sparse + dense``; otherwise the ``dense`` latest frames plus every
    ``stride``-th earlier frame (0, s, 2s, ...), with ``stride`` the smallest power of two giving at
    most ``sparse`` of them.
    """
    if n <= 0:
        return []
    if n <= sparse + dense:
        return list(range(n))
    history = n - dense
    if sparse <= 0:
        return list(range(history, n))
    stride = 1
    while -(-history // stride) > sparse:
        stride *= 2
    return list(range(0, history, stride)) + list(range(history, n))


def sample_options(cfg) -> dict:
    """Dataset keyword arguments of a :class:`~image2sim.navpolicy.config.NavPolicyConfig`: the sample
    layout (``data.sampling``: the streaming layout takes the agent's sparse/dense frame counts)."""
    d = cfg.data
    context = (cfg.agent.sparse_frames, cfg.agent.dense_frames) if d.sampling == "streaming" else None
    return {
        "max_observations": d.max_observations,
        "max_action_labels": d.max_action_labels,
        "jitter": d.jitter,
        "stride": d.observation_stride,
        "context": context,
        "end_cut_probability": d.end_cut_probability,
        "late_start_probability": d.late_start_probability,
        "wrong_goal_stop_probability": d.wrong_goal_stop_probability,
        "goal_label": d.goal_label,
        "near_end_forward_steps": d.near_end_forward_steps,
    }


def make_sample(
    traj: Trajectory,
    max_observations: int = 32,
    max_action_labels: int = 64,
    rng: np.random.Generator | None = None,
    stride: int = 1,
    context: tuple[int, int] | None = None,
    end_cut_probability: float = 0.0,
    late_start_probability: float = 0.0,
    goal_label: str = "in_view",
    near_end_forward_steps: int = 10,
) -> NavSample:
    """Sample observations of ``traj`` and pair each with its next two actions.

    ``stride``: only frames at steps that are multiples of it are candidates. With
    ``stride = ACTIONS_PER_STEP`` (2) a sample looks like what the streaming agent sees at inference
    (an observation every two actions, ``Executed:`` lists of two), also on short trajectories where
    stride 1 would show every step.

    ``context=None`` (the paper's layout): observations spread uniformly over the *whole* trajectory,
    so the last one is always its end (labelled STOP). ``context=(sparse, dense)``: the streaming
    agent's layout at a cut drawn uniformly among the candidates (the last one without ``rng``): the
    frames :func:`select_context_frames` gives for the candidates up to the cut. The sample then ends
    where an agent at that point of the episode would be asked, so STOP is the last label only when
    the cut is the end, not whenever the context is full (a small policy trained on whole-trajectory
    samples learns "16 observations in the context: stop"). ``end_cut_probability``: the cut is the
    end with this probability (else uniform), so the final STOP, one label in a whole trajectory, is
    seen often enough to be learned. ``late_start_probability``: the sample's episode starts at a
    later candidate, as if the agent had been placed there (any suffix of an expert path is an expert
    path). The number of candidates seen is drawn uniformly, the same way whether the cut is the end
    or not, so the length of the context says nothing about STOP and only the view can (without it a
    full 16-frame context ends in STOP half again as often as an 8-15-frame one, and a context under 8
    frames never does).
    """
    n_obs = min(max_observations, max_action_labels // ACTIONS_PER_STEP)
    if n_obs < 1:
        raise ValueError(f"max_action_labels={max_action_labels} leaves room for no observation")
    if stride < 1:
        raise ValueError(f"observation stride must be >= 1, got {stride}")
    cand = [i for i, s in enumerate(traj.frame_steps) if int(s) % stride == 0] or [0]
    if context is None:
        idx = [cand[i] for i in uniform_indices(len(cand), n_obs, rng)]
    else:
        sparse, dense = (int(v) for v in context)
        if dense < 1 or sparse < 0 or sparse + dense > n_obs:
            raise ValueError(
                f"streaming context ({sparse} sparse + {dense} dense frames) must have dense >= 1 and fit "
                f"the {n_obs} observations a sample holds"
            )
        last, start = len(cand) - 1, 0
        if rng is None or rng.random() < end_cut_probability:
            cut = last
        else:
            cut = int(rng.integers(len(cand)))
        # Drawn only when enabled, so runs without it keep their sample stream.
        if rng is not None and late_start_probability > 0 and rng.random() < late_start_probability:
            # The number of candidates the agent has seen is drawn first, the same way for final and
            # other cuts, so it says nothing about STOP: a cut other than the end falls before it.
            seen = int(rng.integers(1, len(cand) + 1))
            if cut != last and seen <= last:
                cut = int(rng.integers(seen - 1, last))
            else:
                cut = last
            start = cut + 1 - seen
        idx = [cand[start + i] for i in select_context_frames(cut + 1 - start, sparse, dense)]
    steps = [int(traj.frame_steps[i]) for i in idx]
    executed, prev = [], None
    for s in steps:
        executed.append(() if prev is None else tuple(int(a) for a in traj.actions[prev:s]))
        prev = s
    seen = frame_goal_labels(traj, goal_label, near_end_forward_steps)
    return NavSample(
        instruction=traj.instruction,
        observations=np.asarray(traj.frames)[idx],
        steps=steps,
        executed=executed,
        targets=[oracle_targets(traj, s) for s in steps],
        episode_id=traj.episode_id,
        goal_in_view=None if seen is None else [int(seen[i]) for i in idx],
    )


def frame_goal_labels(
    traj: Trajectory, goal_label: str, near_end_forward_steps: int = 10
) -> list[int] | None:
    """The grounding head's target for each stored frame of ``traj`` (``data.goal_label``), or None
    when the trajectory has none: ``in_view`` reads the record's ``goal_in_view``; ``near_end`` is 1
    where at most ``near_end_forward_steps`` MOVE_FORWARD actions remain before the final STOP (the
    path left to the goal, 0.25 m each; None for a trajectory that does not end in STOP)."""
    if goal_label == "in_view":
        seen = traj.extra.get(GOAL_IN_VIEW) if isinstance(traj.extra, dict) else None
        return None if seen is None else [int(v) for v in seen]
    if goal_label != "near_end":
        raise ValueError(f"goal label {goal_label!r}: expected one of {GOAL_LABELS}")
    if not traj.actions or int(traj.actions[-1]) != int(Action.STOP):
        return None
    forward = np.asarray(traj.actions) == int(Action.MOVE_FORWARD)
    remaining = np.cumsum(forward[::-1])[::-1]  # forward moves from step t to the end
    return [int(remaining[int(s)] <= near_end_forward_steps) for s in traj.frame_steps]


def oracle_targets(traj: Trajectory, step: int) -> tuple[int, ...]:
    """Labels at ``step``: ``extra["oracle_labels"][step]`` when present (DAgger: the executed
    ``actions`` may be the model's, the labels are the oracle's), else the next executed actions."""
    labels = traj.extra.get("oracle_labels") if traj.extra else None
    if labels is None:
        return next_actions(traj.actions, step)
    if len(labels) != len(traj.actions):
        raise ShardError(
            f"{traj.episode_id}: extra.oracle_labels has {len(labels)} entries for {len(traj.actions)} steps"
        )
    return tuple(int(a) for a in labels[step])


# ----------------------------------------------------------------------------------------------- shards


class ShardWriter:
    """Writes trajectories into a shard folder; use as a context manager.

    Frames go to ``frames/NNNNNN.npz`` as they come; ``trajectories.jsonl`` and ``manifest.json`` are
    written atomically on :meth:`close`, so a reader never sees a shard that lists missing frames.
    """

    def __init__(self, root: str | Path, observation: dict | None = None, compress: bool = True) -> None:
        self.root = Path(root)
        if (self.root / "manifest.json").exists():
            raise ShardError(f"{self.root}: a shard already exists here")
        (self.root / "frames").mkdir(parents=True, exist_ok=True)
        self.observation = dict(observation or {})
        self.compress = compress
        self._lines: list[str] = []

    def add(self, traj: Trajectory) -> None:
        k = len(self._lines)
        traj.validate(f"{self.root} trajectory {k} ({traj.episode_id})")
        rel = f"frames/{k:06d}.npz"
        from image2sim.simulator.io.npz import FRAMES_LEVEL, npz_bytes

        level = FRAMES_LEVEL if self.compress else None
        write_bytes_atomic(self.root / rel, npz_bytes({"rgb": np.ascontiguousarray(traj.frames)}, level))
        rec = {
            "episode_id": traj.episode_id,
            "scene_id": traj.scene_id,
            "instruction": traj.instruction,
            "actions": [int(a) for a in traj.actions],
            "frame_steps": [int(s) for s in traj.frame_steps],
            "frames": rel,
            "extra": traj.extra,
        }
        self._lines.append(json.dumps(rec))

    def close(self) -> Path:
        write_bytes_atomic(self.root / "trajectories.jsonl", ("\n".join(self._lines) + "\n").encode())
        manifest = {
            "format": SHARD_FORMAT,
            "version": SHARD_VERSION,
            "num_trajectories": len(self._lines),
            "action_ids": {a.name: int(a) for a in Action},
            "observation": self.observation,
        }
        write_bytes_atomic(self.root / "manifest.json", json.dumps(manifest, indent=2).encode())
        return self.root

    def __enter__(self) -> ShardWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()


def write_shard(
    root: str | Path, trajectories: Sequence[Trajectory], observation: dict | None = None
) -> Path:
    """Write ``trajectories`` as one shard at ``root``."""
    with ShardWriter(root, observation) as w:
        for t in trajectories:
            w.add(t)
    return Path(root)


class ShardReader:
    """Random access to the trajectories of one shard (``cache_frames``: decoded frames kept in
    memory after their first read)."""

    def __init__(self, root: str | Path, cache_frames: bool = False) -> None:
        self.root = Path(root)
        self._frames: dict[int, np.ndarray] | None = {} if cache_frames else None
        mpath = self.root / "manifest.json"
        if not mpath.is_file():
            raise ShardError(f"{mpath}: missing (not a {SHARD_FORMAT} folder)")
        self.manifest = json.loads(mpath.read_text())
        if self.manifest.get("format") != SHARD_FORMAT or self.manifest.get("version") != SHARD_VERSION:
            raise ShardError(
                f"{mpath}: format {self.manifest.get('format')!r} v{self.manifest.get('version')} "
                f"is not {SHARD_FORMAT} v{SHARD_VERSION}"
            )
        ids = self.manifest.get("action_ids", {})
        if ids and ids != {a.name: int(a) for a in Action}:
            raise ShardError(f"{mpath}: action_ids {ids} disagree with the conventions")
        jpath = self.root / "trajectories.jsonl"
        try:
            self.records = [json.loads(line) for line in jpath.read_text().splitlines() if line.strip()]
        except (OSError, json.JSONDecodeError) as exc:
            raise ShardError(f"{jpath}: {exc}") from exc
        if len(self.records) != self.manifest.get("num_trajectories"):
            raise ShardError(
                f"{jpath}: {len(self.records)} records but the manifest says "
                f"{self.manifest.get('num_trajectories')}"
            )

    def __len__(self) -> int:
        return len(self.records)

    def frames(self, i: int) -> np.ndarray:
        """Trajectory ``i``'s frames (T, H, W, 3) uint8 (read-only when cached: samples share it)."""
        if self._frames is not None and i in self._frames:
            return self._frames[i]
        fpath = self.root / self.records[i]["frames"]
        try:
            with np.load(fpath, allow_pickle=False) as z:
                frames = z["rgb"]
        except (OSError, KeyError, ValueError) as exc:
            raise ShardError(f"{fpath}: cannot read frames ({exc})") from exc
        if self._frames is not None:
            frames.setflags(write=False)
            self._frames[i] = frames
        return frames

    def __getitem__(self, i: int) -> Trajectory:
        rec = self.records[i]
        frames = self.frames(i)
        return Trajectory(
            instruction=rec["instruction"],
            actions=list(rec["actions"]),
            frames=frames,
            frame_steps=list(rec["frame_steps"]),
            episode_id=rec.get("episode_id", ""),
            scene_id=rec.get("scene_id", ""),
            extra=rec.get("extra", {}),
        ).validate(f"{self.root} line {i + 1}")


def shard_instructions(shards: Sequence[str | Path]) -> list[str]:
    """Every trajectory's instruction in ``shards``, in order (records only; no frames are read)."""
    return [str(rec["instruction"]) for root in shards for rec in ShardReader(root).records]


@dataclass(frozen=True)
class SampleLayout:
    """How a dataset turns a trajectory into a training sample: the arguments of
    :func:`make_sample` other than the trajectory and the generator (see it for their meaning)."""

    max_observations: int = 32
    max_action_labels: int = 64
    stride: int = 1
    context: tuple[int, int] | None = None
    end_cut_probability: float = 0.0
    late_start_probability: float = 0.0
    goal_label: str = "in_view"
    near_end_forward_steps: int = 10

    def sample(self, traj: Trajectory, rng: np.random.Generator | None) -> NavSample:
        return make_sample(
            traj,
            self.max_observations,
            self.max_action_labels,
            rng,
            self.stride,
            self.context,
            self.end_cut_probability,
            self.late_start_probability,
            self.goal_label,
            self.near_end_forward_steps,
        )


def layout_of(arguments: dict) -> SampleLayout:
    """The :class:`SampleLayout` named by a dataset constructor's arguments (its fields, by name)."""
    return SampleLayout(**{f.name: arguments[f.name] for f in dataclasses.fields(SampleLayout)})


class _SamplingDataset(torch.utils.data.Dataset):
    """What the shard and in-memory datasets share: item ``i`` of epoch ``e`` is
    ``layout.sample(trajectory i)`` with the generator of (seed, e, i) (no generator without jitter),
    or, with ``wrong_goal_stop_probability``, sometimes a wrong-goal end sample of it."""

    def __init__(
        self, layout: SampleLayout, jitter: bool, seed: int, wrong_goal_stop_probability: float = 0.0
    ):
        self.layout, self.jitter, self.seed, self.epoch = layout, jitter, seed, 0
        if not 0.0 <= wrong_goal_stop_probability <= 1.0:
            raise ValueError(
                f"wrong_goal_stop_probability must be in [0, 1], got {wrong_goal_stop_probability}"
            )
        self.wrong_goal_stop_probability = float(wrong_goal_stop_probability)
        self._goals: dict[str, list[tuple[int, str]]] | None = None

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def trajectory(self, i: int) -> Trajectory:
        raise NotImplementedError

    def goal_of(self, i: int) -> tuple[str, str]:
        """(scene id, goal category) of trajectory ``i`` without loading its frames ("" if unknown)."""
        raise NotImplementedError

    def instruction_of(self, i: int) -> str:
        raise NotImplementedError

    def __getitem__(self, i: int) -> NavSample:
        return self.item(i, np.random.default_rng([self.seed, self.epoch, i]) if self.jitter else None)

    def item(self, i: int, rng: np.random.Generator | None) -> NavSample:
        """Trajectory ``i`` sampled with ``rng``: a wrong-goal end sample with probability
        ``wrong_goal_stop_probability`` (never without a generator), else :meth:`sample`."""
        # Drawn only when enabled, so runs without it keep their sample stream.
        if rng is not None and self.wrong_goal_stop_probability > 0:
            if rng.random() < self.wrong_goal_stop_probability:
                other = self.wrong_goal_source(i, rng)
                if other is not None:
                    return self.wrong_goal_sample(self.trajectory(i), self.instruction_of(other), rng)
        return self.sample(self.trajectory(i), rng)

    def sample(self, traj: Trajectory, rng: np.random.Generator | None) -> NavSample:
        """``traj`` as this dataset samples it (observation layout, stride, context)."""
        return self.layout.sample(traj, rng)

    def wrong_goal_source(self, i: int, rng: np.random.Generator) -> int | None:
        """A trajectory whose goal category differs from trajectory ``i``'s, from the same scene when
        the scene has one (its instruction then names an object of this house, elsewhere), else from
        any scene; None when ``i`` has no known category or no other category exists."""
        if self._goals is None:  # scene -> [(trajectory, category)], read once
            self._goals = {}
            for j in range(len(self)):
                scene_j, category_j = self.goal_of(j)
                if category_j:
                    self._goals.setdefault(scene_j, []).append((j, category_j))
        scene, category = self.goal_of(i)
        if not category:
            return None
        pool = [j for j, c in self._goals.get(scene, []) if c != category]  # this house first
        if not pool:
            pool = [j for entries in self._goals.values() for j, c in entries if c != category]
        return int(pool[int(rng.integers(len(pool)))]) if pool else None

    def wrong_goal_sample(self, traj: Trajectory, instruction: str, rng: np.random.Generator) -> NavSample:
        """``traj`` cut at its end (the expert's STOP beside its goal) under ``instruction``, which
        names another goal: a sample whose only training signal is "do not STOP here"."""
        if self.layout.context is None:  # whole-trajectory layout: unjittered, so it ends at the end
            end = self.layout.sample(traj, None)
        else:
            end = dataclasses.replace(self.layout, end_cut_probability=1.0).sample(traj, rng)
        return dataclasses.replace(end, instruction=instruction, goal_in_view=None, stop_negative=True)


class NavShardDataset(_SamplingDataset):
    """Samples over one or more shards; item ``i`` of epoch ``e`` is reproducible from (seed, e, i)."""

    def __init__(
        self,
        shards: Sequence[str | Path],
        max_observations: int = 32,
        max_action_labels: int = 64,
        jitter: bool = True,
        seed: int = 0,
        stride: int = 1,
        context: tuple[int, int] | None = None,
        end_cut_probability: float = 0.0,
        late_start_probability: float = 0.0,
        max_trajectories: int | None = None,
        cache_frames: bool = False,
        shuffle_instructions: bool = False,
        wrong_goal_stop_probability: float = 0.0,
        goal_label: str = "in_view",
        near_end_forward_steps: int = 10,
    ) -> None:
        layout = layout_of(locals())
        super().__init__(layout, jitter, seed, wrong_goal_stop_probability)
        if not shards:
            raise ShardError("no shard folders given")
        self.readers = [ShardReader(s, cache_frames) for s in shards]
        self.index = [(r, i) for r in range(len(self.readers)) for i in range(len(self.readers[r]))]
        if max_trajectories is not None:
            if max_trajectories < 1:
                raise ValueError(f"max_trajectories must be >= 1, got {max_trajectories}")
            self.index = self.index[:max_trajectories]  # the first ones, in shard order
        # data.shuffle_instructions: trajectory i is told the instruction of trajectory source[i].
        self.instruction_source = (
            np.random.default_rng([seed, 4441]).permutation(len(self.index)) if shuffle_instructions else None
        )

    def __len__(self) -> int:
        return len(self.index)

    def trajectory(self, i: int) -> Trajectory:
        r, j = self.index[i]
        traj = self.readers[r][j]
        if self.instruction_source is not None:
            r2, j2 = self.index[int(self.instruction_source[i])]
            traj.instruction = self.readers[r2].records[j2]["instruction"]
            # Its goal labels describe its own goal, not the borrowed instruction's: drop them.
            traj.extra = {k: v for k, v in traj.extra.items() if k != GOAL_IN_VIEW}
        return traj

    def _record(self, i: int) -> dict:
        r, j = self.index[i]
        return self.readers[r].records[j]

    def goal_of(self, i: int) -> tuple[str, str]:
        rec = self._record(i)
        return str(rec.get("scene_id", "")), str((rec.get("extra") or {}).get(GOAL_CATEGORY, ""))

    def instruction_of(self, i: int) -> str:
        return str(self._record(i)["instruction"])


class InMemoryNavDataset(_SamplingDataset):
    """Samples over trajectories held in memory (tests, DAgger's online buffer)."""

    def __init__(
        self,
        trajectories: Sequence[Trajectory],
        max_observations: int = 32,
        max_action_labels: int = 64,
        jitter: bool = True,
        seed: int = 0,
        stride: int = 1,
        context: tuple[int, int] | None = None,
        end_cut_probability: float = 0.0,
        late_start_probability: float = 0.0,
        wrong_goal_stop_probability: float = 0.0,
        goal_label: str = "in_view",
        near_end_forward_steps: int = 10,
    ) -> None:
        layout = layout_of(locals())
        super().__init__(layout, jitter, seed, wrong_goal_stop_probability)
        self.trajectories = list(trajectories)

    def __len__(self) -> int:
        return len(self.trajectories)

    def trajectory(self, i: int) -> Trajectory:
        return self.trajectories[i]

    def goal_of(self, i: int) -> tuple[str, str]:
        t = self.trajectories[i]
        return t.scene_id, str((t.extra or {}).get(GOAL_CATEGORY, ""))

    def instruction_of(self, i: int) -> str:
        return self.trajectories[i].instruction


# --------------------------------------------------------------------------------- observations


def observation_from_panorama(pano: np.ndarray, yaw_deg: float, obs) -> np.ndarray:
    """The policy's observation (H, W, 3 uint8) cut from an equirectangular panorama.

    ``obs`` is an :class:`~image2sim.navpolicy.config.ObservationConfig`: the paper's pinhole
    (90 x 90 deg) gives a pinhole view; FOVs of 180 deg or more (the 180 x 118 deg ultra-wide
    setting) give an equirectangular crop. ``yaw_deg`` turns the view right of the panorama centre.
    """
    from image2sim.simulator.geometry import perspective_from_equirect

    p = np.asarray(pano)
    if p.ndim != 3 or p.shape[-1] != 3 or p.dtype != np.uint8:
        raise ValueError(f"panorama must be (H, W, 3) uint8, got {p.shape} {p.dtype}")
    t = torch.from_numpy(np.ascontiguousarray(p)).permute(2, 0, 1)[None].float() / 255.0
    view = perspective_from_equirect(t, yaw_deg, 0.0, obs.hfov_deg, obs.vfov_deg, obs.height, obs.width)
    return (view[0].permute(1, 2, 0).clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).numpy()


# ------------------------------------------------------------------------------------ synthetic data

_ACTION_COLOURS = np.array([[230, 230, 230], [40, 200, 60], [50, 80, 220], [220, 60, 50]], dtype=np.float32)


def synthetic_trajectories(
    n: int, min_len: int = 6, max_len: int = 40, height: int = 64, width: int = 64, seed: int = 0
) -> list[Trajectory]:
    """Toy trajectories whose frames reveal the action to take (for tests and CPU smoke runs only).

    Actions are runs of FORWARD with occasional LEFT/RIGHT turns, ending with STOP. Frame t is tinted
    with the colour of action t (STOP white, FORWARD green, LEFT blue, RIGHT red) plus a gradient and
    noise, so a policy can learn the first label from the image and the second from the sequence.
    """
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    ramp = (0.35 * (yy / max(1, height - 1)) + 0.15 * (xx / max(1, width - 1)))[..., None]
    out = []
    for k in range(n):
        T = int(rng.integers(min_len, max_len + 1))
        acts: list[int] = []
        while len(acts) < T - 1:
            if rng.random() < 0.3:
                turn = int(rng.choice([Action.TURN_LEFT, Action.TURN_RIGHT]))
                acts.extend([turn] * int(rng.integers(1, 4)))
            else:
                acts.extend([int(Action.MOVE_FORWARD)] * int(rng.integers(2, 6)))
        acts = acts[: T - 1] + [int(Action.STOP)]
        base = _ACTION_COLOURS[np.array(acts)][:, None, None, :]
        noise = rng.normal(0.0, 12.0, size=(T, height, width, 3)).astype(np.float32)
        frames = np.clip(base * (0.65 + ramp[None]) + noise, 0, 255).astype(np.uint8)
        out.append(
            Trajectory(
                instruction=f"synthetic episode {k}: follow the coloured cues and stop on white",
                actions=acts,
                frames=frames,
                frame_steps=list(range(T)),
                episode_id=f"synthetic-{seed}-{k:05d}",
                scene_id="synthetic",
            )
        )
    return out
