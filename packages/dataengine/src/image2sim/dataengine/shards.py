"""Training shards in the navpolicy ``image2sim-navshard`` v1 folder format (see
``image2sim.navpolicy.data``; re-implemented here because the data engine must not import navpolicy).

One shard per scene: ``manifest.json``, ``trajectories.jsonl`` and ``frames/NNNNNN.npz`` (key ``rgb``,
(N, H, W, 3) uint8, no pickle). Frames are written as they come; the record list and the manifest are
written atomically last, into a temp folder that is renamed into place, so a reader never sees a
half-written shard.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
from image2sim.simulator.conventions import Action
from image2sim.simulator.io.atomic import sweep_stale_temps, temp_sibling, write_bytes_atomic
from image2sim.simulator.io.npz import FRAMES_LEVEL, npz_bytes

__all__ = ["SHARD_FORMAT", "SHARD_VERSION", "SceneShardWriter"]

SHARD_FORMAT = "image2sim-navshard"
SHARD_VERSION = 1


class SceneShardWriter:
    """Collects trajectories of one scene and publishes them as one shard folder on :meth:`close`."""

    def __init__(self, root: str | Path, observation: dict | None = None) -> None:
        self.root = Path(root)
        sweep_stale_temps(self.root)
        self.tmp = temp_sibling(self.root, ".tmp")
        (self.tmp / "frames").mkdir(parents=True)
        self.observation = dict(observation or {})
        self.lines: list[str] = []

    def add(
        self,
        episode_id: str,
        scene_id: str,
        instruction: str,
        actions,
        frames: np.ndarray,
        frame_steps,
        extra: dict | None = None,
    ) -> None:
        f = np.asarray(frames)
        acts = [int(a) for a in actions]
        steps = [int(s) for s in frame_steps]
        if f.ndim != 4 or f.shape[-1] != 3 or f.dtype != np.uint8 or len(f) != len(steps) or not steps:
            raise ValueError(
                f"shard {self.root}: episode {episode_id}: frames must be (N, H, W, 3) uint8 with one "
                f"step each, got {f.shape} {f.dtype} for {len(steps)} steps"
            )
        if not acts or acts[-1] != int(Action.STOP) or steps[-1] >= len(acts):
            raise ValueError(
                f"shard {self.root}: episode {episode_id}: actions must end with STOP and cover the frames"
            )
        rel = f"frames/{len(self.lines):06d}.npz"
        write_bytes_atomic(self.tmp / rel, npz_bytes({"rgb": np.ascontiguousarray(f)}, FRAMES_LEVEL))
        self.lines.append(
            json.dumps(
                {
                    "episode_id": episode_id,
                    "scene_id": scene_id,
                    "instruction": instruction,
                    "actions": acts,
                    "frame_steps": steps,
                    "frames": rel,
                    "extra": extra or {},
                }
            )
        )

    def close(self) -> Path:
        (self.tmp / "trajectories.jsonl").write_text("".join(line + "\n" for line in self.lines))
        manifest = {
            "format": SHARD_FORMAT,
            "version": SHARD_VERSION,
            "num_trajectories": len(self.lines),
            "action_ids": {a.name: int(a) for a in Action},
            "observation": self.observation,
        }
        (self.tmp / "manifest.json").write_text(json.dumps(manifest, indent=2))
        if self.root.exists():  # a previous, unfinished attempt of the same scene
            shutil.rmtree(self.root)
        os.replace(self.tmp, self.root)
        return self.root

    def abort(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)
