"""Child processes end with the process that started them.

A worker pool's processes outlive a killed driver by default (SIGTERM or SIGKILL reaches only the
parent), and keep computing for nobody. :func:`die_with_parent` is a pool ``initializer``: on Linux
it asks the kernel to send the worker SIGTERM when its parent dies (``PR_SET_PDEATHSIG``); elsewhere
it does nothing. It is checked once after arming, since the parent may have died in between.

:func:`spawn_pool` is the one worker pool every parallel job uses (the data engine's scenes and
episode rendering, ``eval nav``'s scenes): spawned processes (torch and OpenMP do not survive
``fork`` reliably) with one BLAS/OpenMP thread each (:data:`WORKER_ENV`, torch at one thread, so
``n`` workers use ``n`` cores without oversubscribing them) that end with the process that made them.
"""

from __future__ import annotations

import os
import signal
import sys
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any

__all__ = ["WORKER_ENV", "die_with_parent", "spawn_pool", "torch_threads", "worker_init"]

WORKER_ENV = {
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
}
"""Environment of every worker (local or Ray): one thread per BLAS/OpenMP pool (one task = one core)."""

_PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int | None = None) -> bool:
    """Arm parent-death SIGTERM for this process; True when armed. ``parent_pid``: the expected
    parent (default: the current one); if it is already gone, exit now."""
    if not sys.platform.startswith("linux"):
        return False
    import ctypes

    parent = os.getppid() if parent_pid is None else parent_pid
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) != 0:
            return False
    except (OSError, AttributeError):
        return False
    if os.getppid() != parent:  # the parent died before the signal was armed
        os._exit(1)
    return True


@contextmanager
def torch_threads(n: int):
    """Run torch ops on ``n`` threads inside the block, the count before it after (0: unchanged).

    For a process whose cores other processes hold for a while (its workers, a build beside it):
    its own intra-op threads would oversubscribe them, and on a 2-core machine that made the data
    engine's navigation map ~3x slower than on one thread."""
    import torch

    before = torch.get_num_threads()
    if n > 0 and n != before:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


def worker_init(parent_pid: int, setup: Any = None, *setup_args: Any) -> None:
    """Worker start: die with ``parent_pid``, one thread per pool, then ``setup(*setup_args)``."""
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
