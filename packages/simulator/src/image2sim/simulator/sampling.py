"""Step-indexed, rank-sharded data order shared by the Lightning trainers (renderer, Image2Nav).

The data order is a pure function of the global sample position, so a run resumed at step k reads
exactly the samples the uninterrupted run would have read next, on one rank or many. With W ranks,
rank r reads the global positions ``p * W + r`` for its own positions ``p = start .. stop - 1``:
together the ranks' batches cover the global order once, each position on one rank. The trainers
therefore pass ``use_distributed_sampler=False`` to Lightning (its ``DistributedSampler`` would
reshuffle and re-split the order and break exact resume).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

from torch.utils.data import Sampler

__all__ = ["StepSampler"]


class StepSampler(Sampler[int]):
    """Global positions ``start * W + r, (start + 1) * W + r, ...`` below ``stop * W`` for rank ``r``
    of ``W``, each mapped through ``index_of`` (global position -> dataset index) when given.

    ``start`` and ``stop`` count this rank's samples (step x per-rank batch size), so a resume passes
    ``global_step * batch_size`` whatever the number of ranks.
    """

    def __init__(
        self,
        start: int,
        stop: int,
        rank: int = 0,
        world_size: int = 1,
        index_of: Callable[[int], int] | None = None,
    ) -> None:
        if world_size < 1 or not 0 <= rank < world_size:
            raise ValueError(f"StepSampler needs 0 <= rank < world_size, got rank {rank} of {world_size}")
        if start < 0:
            raise ValueError(f"StepSampler start must be >= 0, got {start}")
        self.start, self.stop = int(start), int(stop)
        self.rank, self.world_size = int(rank), int(world_size)
        self.index_of = index_of

    @classmethod
    def for_trainer(
        cls, trainer: Any, start: int, stop: int, index_of: Callable[[int], int] | None = None
    ) -> StepSampler:
        """This process's share under a Lightning ``trainer`` (rank 0 of 1 when there is none)."""
        if trainer is None:
            return cls(start, stop, index_of=index_of)
        return cls(start, stop, trainer.global_rank, trainer.world_size, index_of)

    def positions(self) -> range:
        """The global positions this rank reads, in order."""
        return range(self.start * self.world_size + self.rank, self.stop * self.world_size, self.world_size)

    def __iter__(self) -> Iterator[int]:
        if self.index_of is None:
            return iter(self.positions())
        return (self.index_of(p) for p in self.positions())

    def __len__(self) -> int:
        return max(0, self.stop - self.start)
