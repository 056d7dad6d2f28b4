"""Fixtures for the navpolicy tests: one tiny policy per session (single-threaded torch: the
root conftest pins every test to one thread)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_cfg():
    from image2sim.navpolicy.config import tiny_config

    return tiny_config()


@pytest.fixture(scope="session")
def tiny_policy(tiny_cfg):
    """A from-scratch tiny policy (seed 0). Tests must not train it in place (use a copy)."""
    from image2sim.navpolicy.model import build_policy

    return build_policy(tiny_cfg, seed=0)


@pytest.fixture(scope="session")
def batch(tiny_policy, tiny_cfg):
    """A collated batch of two synthetic samples (6 observations, 12 action labels each)."""
    import numpy as np
    from image2sim.navpolicy.collate import NavCollator
    from image2sim.navpolicy.data import make_sample, synthetic_trajectories
    from image2sim.navpolicy.prompting import PromptBuilder

    trajs = synthetic_trajectories(2, min_len=8, max_len=30, seed=5)
    samples = [make_sample(t, 6, 12, np.random.default_rng(i)) for i, t in enumerate(trajs)]
    col = NavCollator(
        PromptBuilder(tiny_policy.tokenizer, tiny_policy.codec, tiny_cfg.system_prompt),
        tiny_policy.image_processor,
    )
    return col(samples)
