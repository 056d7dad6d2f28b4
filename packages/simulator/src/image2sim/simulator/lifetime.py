"""Child processes end with the process that started them.

A worker pool's processes outlive a killed driver by default (SIGTERM or SIGKILL reaches only the
parent), and keep computing for nobody. :func:`die_with_parent` is a pool ``initializer``: on Linux
it asks the kernel to send the worker SIGTERM when its parent dies (``PR_SET_PDEATHSIG``); elsewhere
it does nothing. It is checked once after arming, since the parent may have died in between.
"""

from __future__ import annotations

import os
import signal
import sys

__all__ = ["die_with_parent"]

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
