"""Just-in-time C++ extension builds (torch's ``cpp_extension.load``) that survive killed builds.

torch serialises builders of one folder with a ``lock`` file (its ``FileBaton``) that only a clean
exit removes: a build killed half-way (a timeout, a stopped job, a session that ends) leaves it, and
every later build of that folder waits for it forever, silently. :func:`build_guard` puts an
``flock`` around the build, which the OS releases when its holder dies, and clears such a file under
it. Our own kernel (``splatting/backends/cpu_kernel.py``) and DeepSpeed's CPU communication op
(``navpolicy.train``) build through it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

__all__ = ["build_guard", "torch_extension_dir"]


@contextlib.contextmanager
def build_guard(build: Path) -> Iterator[None]:
    """Hold ``build``'s builder lock (an ``flock``, released by the OS when its holder dies) and clear
    the ``lock`` file of torch's ``FileBaton`` if one is left: every builder of the folder goes through
    this guard, so under it such a file can only come from a killed build, and torch would wait for
    it forever."""
    try:
        import fcntl
    except ImportError:  # not POSIX: torch's own baton only
        yield
        return
    build.mkdir(parents=True, exist_ok=True)
    with open(build / "builder.flock", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            (build / "lock").unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def torch_extension_dir(name: str) -> Path:
    """The folder torch builds extension ``name`` in when the caller gives none (``$TORCH_EXTENSIONS_DIR``
    or torch's default root, per torch version and accelerator), as ``cpp_extension.load`` picks it."""
    from torch.utils.cpp_extension import _get_build_directory

    return Path(_get_build_directory(name, verbose=False))
