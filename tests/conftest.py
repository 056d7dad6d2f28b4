"""Session-wide test configuration.

Real data lives outside the repository in ``../shared/data`` (or ``$IMAGE2SIM_SHARED_DATA``) and is
read in place; tests that need it use the ``hm3d_scene_dir`` fixture, which skips when it is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, settings

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("IMAGE2SIM_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))
HM3D_SCENE = SHARED_DATA / "hm3d_360" / "00000-kfPV7w3FaU5"

settings.register_profile(
    "image2sim", deadline=None, max_examples=200, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile("image2sim")

# One intra-op thread: the tests use small tensors, and on a shared 2-core machine OpenMP threads
# oversubscribe (measured 10-100x slower small convolutions with 2 threads under load).
torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _one_thread():
    """Every test starts on one intra-op thread, whatever the test before it set, and what it sets
    itself is undone after it."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def hm3d_scene_dir() -> Path:
    """The real HM3D panoramic sample, read in place; skips the test when it is absent."""
    if not HM3D_SCENE.is_dir():
        pytest.skip(f"real sample data not found at {HM3D_SCENE}")
    return HM3D_SCENE


@pytest.fixture
def tiny_dinov3():
    """Factory of tiny randomly initialised transformers ``DINOv3ViTModel``s: the real class that
    loads the paper's DINOv3 weights, which do not exist on this machine."""
    transformers = pytest.importorskip("transformers")

    def make(hidden: int = 32, patch_size: int = 16, registers: int = 4):
        config = transformers.DINOv3ViTConfig(
            hidden_size=hidden,
            num_hidden_layers=1,
            num_attention_heads=2,
            intermediate_size=2 * hidden,
            patch_size=patch_size,
            image_size=4 * patch_size,
            num_register_tokens=registers,
        )
        return transformers.DINOv3ViTModel(config)

    return make


@pytest.fixture
def run_main(capsys):
    """``run_main(args) -> (exit status, stdout + stderr)``: ``image2sim ARGS`` through ``main``, the
    CLI's error boundary (one line and a status per error class, as a user sees it)."""
    from image2sim.simulator.cli import main

    def run(args: list[str]) -> tuple[int, str]:
        try:
            main(args)
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        captured = capsys.readouterr()
        return code, captured.out + captured.err

    return run


# torch.distributed's rendezvous variables. An in-process Lightning or DeepSpeed run of an earlier
# test leaves them in os.environ, and its store may still listen on MASTER_PORT: a DDP subprocess
# that inherited them failed with EADDRINUSE. Without them, Lightning picks a free port itself.
DIST_VARS = (
    "MASTER_ADDR",
    "MASTER_PORT",
    "WORLD_SIZE",
    "RANK",
    "LOCAL_RANK",
    "NODE_RANK",
    "GROUP_RANK",
    "LOCAL_WORLD_SIZE",
)


@pytest.fixture
def ddp_subprocess_env() -> dict[str, str]:
    """The environment of a multi-process (DDP) subprocess: this one's, without the rendezvous
    variables of earlier in-process runs, one OpenMP thread per rank."""
    env = {k: v for k, v in os.environ.items() if k not in DIST_VARS}
    env["OMP_NUM_THREADS"] = "1"
    return env
