"""Scene assets (navigation map + graph, identity Gaussians) shared across runs, keyed by content.

``data episodes --cache DIR`` keeps what a scene needs besides its episodes under
``DIR/<key>/``, where ``<key>`` hashes the capture's files (names and bytes) with the kind and
version of the asset. A second run on the same capture (into another ``--out``, or another
experiment) copies them instead of rebuilding them; an edited capture gets a new key. Entries are
written whole (temp folder + rename), so a killed run never leaves a half entry.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from collections.abc import Callable
from pathlib import Path

from image2sim.simulator.io.atomic import sweep_stale_temps, temp_sibling

__all__ = ["content_key", "cached"]

ASSET_VERSIONS = {"navigation": 2, "gaussians": 1}
"""Bump when the way an asset is built changes: old entries are then never used again."""


def content_key(capture_dir: str | Path, kind: str, extra: str = "") -> str:
    """sha256 over every file of the capture (relative name and bytes), the asset kind, its version
    and ``extra`` (e.g. the config it is built with)."""
    root = Path(capture_dir)
    h = hashlib.sha256(f"{kind}:{ASSET_VERSIONS[kind]}:{extra}".encode())
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        h.update(str(path.relative_to(root)).encode() + b"\0")
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()[:32]


def cached(
    cache_dir: str | Path | None,
    key: Callable[[], str],
    names: list[str],
    dest: Path,
    build: Callable[[], None],
) -> bool:
    """Make ``names`` (files or folders) exist in ``dest``: copied from ``cache_dir/key`` when cached,
    else ``build()`` (which writes them into ``dest``) and stored in the cache. Returns True on a hit.
    Without a cache dir it only builds what ``dest`` lacks."""
    dest.mkdir(parents=True, exist_ok=True)
    if all((dest / n).exists() for n in names):
        return False
    entry = Path(cache_dir) / key() if cache_dir is not None else None  # hashing only when needed
    if entry is not None and all((entry / n).exists() for n in names):
        for n in names:
            _copy(entry / n, dest / n)
        return True
    build()
    if entry is not None and all((dest / n).exists() for n in names):
        sweep_stale_temps(entry)
        tmp = temp_sibling(entry, ".tmp")
        tmp.mkdir(parents=True)
        for n in names:
            _copy(dest / n, tmp / n)
        if entry.exists():  # another run stored it meanwhile: keep theirs
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            os.replace(tmp, entry)
    return False


def _copy(src: Path, dst: Path) -> None:
    if src.is_dir():
        tmp = temp_sibling(dst, ".tmp")
        shutil.copytree(src, tmp)
        if dst.exists():
            shutil.rmtree(dst)
        os.replace(tmp, dst)
    else:
        tmp = temp_sibling(dst, dst.suffix)
        shutil.copy2(src, tmp)
        os.replace(tmp, dst)
