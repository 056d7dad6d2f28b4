"""The step-indexed, rank-sharded data order shared by the renderer and Image2Nav trainers."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st
from image2sim.simulator.sampling import StepSampler


@given(st.integers(1, 5), st.integers(0, 7), st.integers(0, 7))
def test_ranks_cover_the_global_order_once_and_resume_at_their_share(world, start, extra):
    stop = start + extra
    shares = [list(StepSampler(start, stop, r, world)) for r in range(world)]
    merged = sorted(p for share in shares for p in share)
    assert merged == list(range(start * world, stop * world))
    for r, share in enumerate(shares):
        assert len(share) == len(StepSampler(start, stop, r, world)) == extra
        assert all(p % world == r for p in share)
        # Resuming one step later drops exactly the first position of each rank's share.
        assert list(StepSampler(start + 1, stop, r, world)) == share[1:]


def test_index_of_maps_positions_and_bad_arguments_are_named():
    assert list(StepSampler(0, 3, 1, 2, index_of=lambda p: 100 + p)) == [101, 103, 105]
    assert list(StepSampler(4, 2)) == [] and len(StepSampler(4, 2)) == 0
    with pytest.raises(ValueError, match="rank 2 of 2"):
        StepSampler(0, 1, rank=2, world_size=2)
    with pytest.raises(ValueError, match="world_size"):
        StepSampler(0, 1, rank=0, world_size=0)
    with pytest.raises(ValueError, match="start"):
        StepSampler(-1, 1)


def test_a_trainer_sampler_starts_at_the_live_global_step_each_time_it_is_iterated():
    """Lightning iterates a loader again when it ends a restored epoch early; the new pass must start
    at the current step, not where the loader was made (the renderer's resume once replayed batches)."""
    from types import SimpleNamespace

    trainer = SimpleNamespace(global_step=2, global_rank=1, world_size=2)
    sampler = StepSampler.for_trainer(trainer, 3, 12)
    assert list(sampler) == list(StepSampler(6, 12, 1, 2)) and len(sampler) == 6
    trainer.global_step = 3
    assert list(sampler) == list(StepSampler(9, 12, 1, 2)) and len(sampler) == 3
    assert list(StepSampler.for_trainer(None, 3, 4)) == [0, 1, 2, 3]
