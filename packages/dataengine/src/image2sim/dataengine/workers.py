"""Local worker processes of the data engine: scenes in parallel (``distributed``) and, when there are
fewer scenes than cores, episodes of one scene rendered in parallel (``pipeline``).

Workers are spawned (torch and OpenMP do not survive ``fork`` reliably), run one BLAS/OpenMP thread
each (:data:`WORKER_ENV`, torch at one thread: ``n`` workers use ``n`` cores without oversubscribing
them) and end with the process that made them (:func:`~image2sim.simulator.lifetime.die_with_parent`).
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from typing import Any

__all__ = ["WORKER_ENV", "spawn_pool", "worker_init"]

WORKER_ENV = {
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
}
"""Environment of every worker (local or Ray): one thread per BLAS/OpenMP pool (one task = one core)."""


def worker_init(parent_pid: int, setup: Any = None, *setup_args: Any) -> None:
    """Worker start: die with ``parent_pid``, one thread per pool, then ``setup(*setup_args)``."""
    from image2sim.simulator.lifetime import die_with_parent

    die_with_parent(parent_pid)
    os.environ.update(WORKER_ENV)
    import torch

    torch.set_num_threads(1)
    if setup is not None:
        setup(*setup_args)


def spawn_pool(workers: int, setup: Any = None, *setup_args: Any) -> ProcessPoolExecutor:
    """A pool of ``workers`` spawned processes that end with this one; ``setup(*setup_args)`` runs once
    in each (a top-level function, so it pickles)."""
    import multiprocessing as mp

    return ProcessPoolExecutor(
        workers,
        mp_context=mp.get_context("spawn"),
        initializer=worker_init,
        initargs=(os.getpid(), setup, *setup_args),
    )
