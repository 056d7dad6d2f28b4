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
    ``global_step * batch_size`` whatever the number of ranks. ``start`` may be a function, read
    each time the sampler is iterated (see :meth:`for_trainer`).
    """

    def __init__(
        self,
        start: int | Callable[[], int],
        stop: int,
        rank: int = 0,
        world_size: int = 1,
        index_of: Callable[[int], int] | None = None,
    ) -> None:
        if world_size < 1 or not 0 <= rank < world_size:
            raise ValueError(f"StepSampler needs 0 <= rank < world_size, got rank {rank} of {world_size}")
        if not callable(start) and start < 0:
            raise ValueError(f"StepSampler start must be >= 0, got {start}")
        self._start = start if callable(start) else int(start)
        self.stop = int(stop)
        self.rank, self.world_size = int(rank), int(world_size)
        self.index_of = index_of

    @property
    def start(self) -> int:
        """This rank's first sample position (read now when ``start`` is a function)."""
        start = int(self._start()) if callable(self._start) else self._start
        if start < 0:
            raise ValueError(f"StepSampler start must be >= 0, got {start}")
        return start

    @classmethod
    def for_trainer(
        cls, trainer: Any, per_step: int, stop: int, index_of: Callable[[int], int] | None = None
    ) -> StepSampler:
        """This process's share under a Lightning ``trainer`` (rank 0 of 1 when there is none),
        starting at ``trainer.global_step * per_step`` *each time it is iterated*.

        Reading the step live is what makes resume exact: after a mid-epoch resume Lightning counts
        the restored batches against the new loader's length, ends the epoch early and iterates the
        sampler again; a start fixed when the loader was made would then replay old samples.
        """
        if trainer is None:
            return cls(0, stop, index_of=index_of)
        live_start = lambda: int(trainer.global_step) * per_step  # noqa: E731
        return cls(live_start, stop, trainer.global_rank, trainer.world_size, index_of)

    def positions(self) -> range:
        """The global positions this rank reads, in order."""
        start = self.start
        return range(start * self.world_size + self.rank, self.stop * self.world_size, self.world_size)

    def __iter__(self) -> Iterator[int]:
        if self.index_of is None:
            return iter(self.positions())
        return (self.index_of(p) for p in self.positions())

    def __len__(self) -> int:
        return max(0, self.stop - self.start)
