"""Atomic file output: write to a temp file in the destination folder, then rename over the target.

Every file the repository writes for later stages (configs, manifests, maps, episodes, reports,
checkpoints) goes through here, so an interrupted job never leaves a torn file behind: readers see
either the old file or the complete new one. The temp file lives in the same folder because
``os.replace`` is atomic only within one filesystem; it is removed when the write fails. There is no
fsync: the guarantee is against killed jobs (the case resumable stages meet), not power loss, and
shard writers create thousands of small files.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

__all__ = [
    "atomic_path",
    "atomic_open",
    "write_bytes_atomic",
    "write_text_atomic",
    "write_json_atomic",
]


def process_umask() -> int:
    """The process umask, read without changing it where the OS tells (Linux ``/proc``); elsewhere
    set-and-restored once (a brief window other threads could see)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _default_file_mode() -> int:
    """The mode ``open(..., "w")`` would give a new file: 0666 minus the process umask."""
    return 0o666 & ~process_umask()


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temp path beside ``path``; on a clean exit it is renamed to ``path``.

    For writers that take a file name (``np.savez``, ``safetensors.save_file``, ``PIL.Image.save``).
    ``suffix`` defaults to the target's, since some writers pick the format from it (and
    ``np.savez`` appends ``.npz`` to a name without it).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        dir=path.parent, prefix=f".{path.name}.", suffix=(path.suffix if suffix is None else suffix) + ".tmp"
    )
    os.close(fd)
    os.chmod(tmp_name, _default_file_mode())  # mkstemp's 0600 would make outputs private to the writer
    tmp = Path(tmp_name)
    # mkstemp's ".tmp" ending would hide the real suffix from format-sniffing writers: drop it.
    final_tmp = tmp.with_name(tmp.name[: -len(".tmp")])
    tmp.replace(final_tmp)
    try:
        yield final_tmp
        os.replace(final_tmp, path)
    except BaseException:
        final_tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_open(
    path: str | os.PathLike, mode: str = "w", encoding: str | None = "utf-8"
) -> Iterator[IO[Any]]:
    """``open`` for writing whose result appears at ``path`` only when the block finishes cleanly."""
    if "w" not in mode:
        raise ValueError(f"atomic_open writes whole files; mode must contain 'w', got {mode!r}")
    with atomic_path(path) as tmp:
        with open(tmp, mode, encoding=None if "b" in mode else encoding) as handle:
            yield handle


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_open(path, "wb") as handle:
        handle.write(data)
    return Path(path)


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    with atomic_open(path, "w") as handle:
        handle.write(text)
    return Path(path)


def write_json_atomic(
    path: str | os.PathLike, obj: Any, indent: int | None = 2, default: Callable[[Any], Any] | None = None
) -> Path:
    """Write ``obj`` as JSON (with a final newline) to ``path`` atomically; returns the path.

    Non-finite floats are refused (``allow_nan=False``): JSON has no NaN, and a NaN metric must be
    an error where it is produced, not a string another tool cannot parse. ``default`` converts
    objects ``json`` cannot (e.g. numpy scalars), as in ``json.dumps``.
    """
    text = json.dumps(obj, indent=indent, allow_nan=False, default=default)
    return write_text_atomic(path, text + "\n")
