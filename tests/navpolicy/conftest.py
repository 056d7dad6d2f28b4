"""Fixtures for the navpolicy tests: one tiny policy per session, single-threaded torch.

Tiny models are dominated by per-op overhead; on a shared 2-core machine one thread is ~10x faster
than two fighting for the cores, so these tests pin torch to one thread and restore it afterwards.
"""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def tiny_cfg():
    from image2sim.navpolicy.config import tiny_config

    return tiny_config()


@pytest.fixture(scope="session")
def tiny_policy(tiny_cfg):
    """A from-scratch tiny policy (seed 0). Tests must not train it in place (use a copy)."""
    from image2sim.navpolicy.model import build_policy

    return build_policy(tiny_cfg, seed=0)
