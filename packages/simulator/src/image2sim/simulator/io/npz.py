"""``.npz`` archives as bytes: what ``np.load`` reads, byte-identical across runs, at a chosen
deflate level.

``np.savez_compressed`` stamps each member with the current time (so two runs never write the same
bytes) and always deflates at zlib's default level 6. Rendered frames compress to about half at any
level; level 1 writes them ~1.7x faster than level 6 for ~6 % more bytes (336 px HM3D episode
frames, docs/dataengine.md), so the training shards use :data:`FRAMES_LEVEL`.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Mapping

import numpy as np

__all__ = ["FRAMES_LEVEL", "npz_bytes"]

FRAMES_LEVEL = 1
"""Deflate level of training-shard frames (``frames/NNNNNN.npz``)."""


def npz_bytes(arrays: Mapping[str, np.ndarray], level: int | None = 6) -> bytes:
    """The ``.npz`` archive of ``arrays`` (members in name order, fixed timestamps, no pickle).

    ``level``: zlib deflate level 0-9, or None to store uncompressed (``np.savez``'s layout).
    """
    if level is not None and (isinstance(level, bool) or not isinstance(level, int) or not 0 <= level <= 9):
        raise ValueError(f"npz_bytes: level must be 0-9 or None, got {level!r}")
    method = zipfile.ZIP_STORED if level is None else zipfile.ZIP_DEFLATED
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:  # each member sets its own method and level
        for name in sorted(arrays):
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = method
            info.external_attr = 0o644 << 16
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asanyarray(arrays[name]), allow_pickle=False)
            zf.writestr(info, member.getbuffer(), compresslevel=level)
    return out.getvalue()
