"""Named random streams: one generator per (seed, name), e.g. per house, independent of the other
houses and of the order in which they are processed (so parallel and resumed runs draw the same)."""

from __future__ import annotations

import zlib

import numpy as np

__all__ = ["named_rng"]


def named_rng(seed: int, name: str) -> np.random.Generator:
    """The generator of stream ``name`` under base ``seed`` (crc32 of the name: stable across runs and
    Python versions, unlike ``hash``)."""
    return np.random.default_rng([int(seed), zlib.crc32(name.encode())])
