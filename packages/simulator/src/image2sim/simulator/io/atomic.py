"""Atomic file output: write to a temp file in the destination folder, then rename over the target.

Every file the repository writes for later stages (configs, manifests, maps, episodes, reports,
checkpoints) goes through here, so an interrupted job never leaves a torn file behind: readers see
either the old file or the complete new one. The temp file lives in the same folder because
``os.replace`` is atomic only within one filesystem; it is removed when the write fails. There is no
fsync: the guarantee is against killed jobs (the case resumable stages meet), not power loss, and
shard writers create thousands of small files.

A SIGKILL cannot clean up, so temp names carry their writer (:func:`temp_sibling`: host tag and
pid) and the next write of the same target removes the temps of writers that no longer run
(:func:`sweep_stale_temps`); a live writer's temp is never touched. Folder writers (scenes,
captures, shards) use the same two functions.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import socket
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

__all__ = [
    "sweep_stale_temps",
    "temp_sibling",
    "atomic_path",
    "atomic_dir",
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


def _host_tag() -> str:
    return f"{zlib.crc32(socket.gethostname().encode()):08x}"


def temp_sibling(path: str | os.PathLike, suffix: str = "") -> Path:
    """A fresh name beside ``path`` for a temp file or folder:
    ``.<name>.<host tag>-<pid>-<random><suffix>`` (the writer is recorded for the sweep)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{_host_tag()}-{os.getpid()}-{secrets.token_hex(4)}{suffix}")


def _pid_running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def sweep_stale_temps(path: str | os.PathLike) -> list[Path]:
    """Remove the temp siblings of ``path`` (see :func:`temp_sibling`) whose writer ran on this host and
    no longer runs: leftovers of a killed write. Returns what was removed."""
    import shutil

    path = Path(path)
    if not path.parent.is_dir():
        return []
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.(?P<host>[0-9a-f]{{8}})-(?P<pid>\d+)-[0-9a-f]{{8}}")
    host, removed = _host_tag(), []
    for candidate in path.parent.iterdir():
        m = pattern.match(candidate.name)
        if m is None or m["host"] != host or _pid_running(int(m["pid"])):
            continue
        if candidate.is_dir() and not candidate.is_symlink():
            shutil.rmtree(candidate, ignore_errors=True)
        else:
            candidate.unlink(missing_ok=True)
        removed.append(candidate)
    return removed


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temp path beside ``path``; on a clean exit it is renamed to ``path``.

    For writers that take a file name (``np.savez``, ``safetensors.save_file``, ``PIL.Image.save``).
    ``suffix`` defaults to the target's, since some writers pick the format from it (and
    ``np.savez`` appends ``.npz`` to a name without it).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sweep_stale_temps(path)
    # The target's suffix last: some writers pick the format from it.
    final_tmp = temp_sibling(path, path.suffix if suffix is None else suffix)
    # 0666 less the umask, as open(..., "w") gives (mkstemp's 0600 made outputs private to the writer).
    os.close(os.open(final_tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
    try:
        yield final_tmp
        os.replace(final_tmp, path)
    except BaseException:
        final_tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_dir(folder: str | os.PathLike) -> Iterator[Path]:
    """Yield an empty temp folder beside ``folder``; on a clean exit it replaces ``folder`` whole.

    For outputs that are several files read together (exports: weights + config + card). An old
    ``folder`` is moved aside, the new one renamed in and the old one removed, so a killed writer
    leaves the old folder or the complete new one (plus temps the next write sweeps). The folder
    gets a plain ``mkdir``'s mode (``mkdtemp``'s 0700 would make an export private).
    """
    import shutil

    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    sweep_stale_temps(folder)
    tmp = temp_sibling(folder, ".tmp")
    tmp.mkdir()  # 0777 less the umask, as a plain mkdir
    try:
        yield tmp
        if folder.exists():
            old = temp_sibling(folder, ".old")
            os.replace(folder, old)
            os.replace(tmp, folder)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
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
