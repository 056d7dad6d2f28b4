"""Training-data fast paths against what they stand in for: the vectorised frame patchifier vs the Qwen
image processor, and the in-memory frame cache vs reading the shard."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from image2sim.navpolicy.collate import patchify_batch
from image2sim.navpolicy.config import tiny_config
from image2sim.navpolicy.model import make_image_processor


def processor(height: int, width: int, patch: int = 8):
    obs = dataclasses.replace(tiny_config().observation, height=height, width=width)
    return make_image_processor(obs, patch)


@pytest.mark.parametrize("height, width, patch", [(64, 64, 8), (32, 48, 8), (64, 96, 16)])
def test_equal_to_the_processor_bit_for_bit(height, width, patch):
    p = processor(height, width, patch)
    rng = np.random.default_rng(height + width)
    frames = [rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in range(5)]
    frames.append(np.full((height, width, 3), 255, dtype=np.uint8))  # the extremes of the table
    frames.append(np.zeros((height, width, 3), dtype=np.uint8))
    ref = p(images=frames, return_tensors="pt")
    fast = patchify_batch(frames, p)
    assert fast is not None
    assert torch.equal(fast[0], ref["pixel_values"]) and torch.equal(fast[1], ref["image_grid_thw"])


def test_frames_the_processor_would_change_go_to_the_processor():
    p = processor(64, 64)
    rng = np.random.default_rng(0)
    same = rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)
    assert (
        patchify_batch([same, rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)], p) is None
    )  # sizes differ
    assert patchify_batch([rng.integers(0, 256, (60, 60, 3), dtype=np.uint8)], p) is None  # would be resized
    assert patchify_batch([same.astype(np.float32)], p) is None  # not uint8
    assert patchify_batch([same[..., :1]], p) is None  # not RGB
    assert patchify_batch([], p) is None
    p.do_normalize = False
    assert patchify_batch([same], p) is None


def test_cached_frames_are_read_once_and_equal(tmp_path):
    from image2sim.navpolicy.data import NavShardDataset, ShardReader, synthetic_trajectories, write_shard

    shard = write_shard(tmp_path / "shard", synthetic_trajectories(3, seed=0))
    plain, cached = ShardReader(shard), ShardReader(shard, cache_frames=True)
    first = [cached[i].frames for i in range(len(cached))]
    for f in (shard / "frames").glob("*.npz"):
        f.unlink()  # a cached reader never reads them again
    for i in range(len(cached)):
        assert np.array_equal(cached[i].frames, first[i]) and not cached[i].frames.flags.writeable
    with pytest.raises(Exception, match="cannot read frames"):
        plain[0]
    ds = NavShardDataset([shard], cache_frames=True, max_observations=4, max_action_labels=8)
    with pytest.raises(Exception, match="cannot read frames"):
        ds[0]  # its own cache is empty: the files are gone
