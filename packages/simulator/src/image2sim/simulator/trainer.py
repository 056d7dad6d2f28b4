"""Where and how a Lightning training stage runs: one config section and the Trainer arguments it
implies, shared by the renderer (`sim train`) and the scene encoder's stage 1 (`sim train-geometry`).

Both stages read their data in a step-indexed order split over ranks by
:class:`~image2sim.simulator.sampling.StepSampler`, so Lightning's ``DistributedSampler`` stays off.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = [
    "CheckpointError",
    "TrainerConfig",
    "check_trainer_config",
    "lightning_trainer_args",
    "resume_checkpoint",
    "with_overrides",
]


class CheckpointError(ValueError):
    """A resume checkpoint is missing or unreadable (bad input: the CLI answers with exit status 2)."""

    cli_exit_code = 2


def resume_checkpoint(resume: str | Path | None, out_dir: str | Path) -> str | None:
    """The checkpoint a run resumes from (``"last"`` = ``out_dir/checkpoints/last.ckpt``), checked
    before the run writes anything: it exists and loads with ``torch.load(weights_only=True)``
    (memory-mapped, so the tensors are not read). A corrupt file is one clear error, not Lightning's
    unpickling traceback after the output folder was made."""
    if resume is None or str(resume) == "":
        return None
    path = Path(out_dir) / "checkpoints" / "last.ckpt" if str(resume) == "last" else Path(resume)
    if not path.is_file():
        raise CheckpointError(f"resume checkpoint {path}: not found")
    import torch

    try:
        state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as err:  # zip, pickle or weights_only refusal: all mean "not our checkpoint"
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CheckpointError(
            f"resume checkpoint {path}: not a readable Lightning checkpoint ({first})"
        ) from None
    if not isinstance(state, dict) or "state_dict" not in state or "global_step" not in state:
        raise CheckpointError(
            f"resume checkpoint {path}: no 'state_dict' or 'global_step' (not from Lightning)"
        )
    return str(path)


STRATEGIES = ("auto", "ddp")
PRECISIONS = ("32-true", "bf16-mixed", "16-mixed")
ACCELERATORS = ("cpu", "gpu", "auto")


@dataclass
class TrainerConfig:
    """Hardware and distribution of one training stage."""

    accelerator: str = "cpu"
    """Lightning accelerator: ``cpu``, ``gpu`` or ``auto``."""
    devices: int = 1
    """Processes per node (GPUs, or CPU processes with gloo); each takes the stage's per-device batch."""
    num_nodes: int = 1
    """Nodes; the global batch is the per-device batch x ``devices`` x ``num_nodes``."""
    strategy: str = "auto"
    """``auto`` (one process) or ``ddp``. DDP looks for unused parameters every step: the renderer's
    curriculum freezes part of the network mid-run, and DDP would otherwise wait for their gradients."""
    precision: str = "32-true"
    """Lightning precision: ``32-true``, ``bf16-mixed`` or ``16-mixed``."""


def check_trainer_config(tc: TrainerConfig, where: str = "trainer") -> None:
    """Raise ``ValueError`` naming ``where.<field>`` when ``tc`` is inconsistent."""
    if tc.strategy not in STRATEGIES:
        raise ValueError(f"{where}.strategy must be one of {STRATEGIES}, got {tc.strategy!r}")
    if tc.precision not in PRECISIONS:
        raise ValueError(f"{where}.precision must be one of {PRECISIONS}, got {tc.precision!r}")
    if tc.accelerator not in ACCELERATORS:
        raise ValueError(f"{where}.accelerator must be one of {ACCELERATORS}, got {tc.accelerator!r}")
    if tc.devices < 1 or tc.num_nodes < 1:
        raise ValueError(
            f"{where}.devices and {where}.num_nodes must be >= 1, got {tc.devices} and {tc.num_nodes}"
        )
    if tc.strategy == "auto" and tc.devices * tc.num_nodes > 1:
        raise ValueError(f"{where}.strategy 'auto' runs one process: use 'ddp' for devices * num_nodes > 1")


def lightning_trainer_args(tc: TrainerConfig, precision: str | None = None) -> dict[str, Any]:
    """Keyword arguments of ``lightning.Trainer`` for ``tc`` (``precision`` overrides its own)."""
    strategy: Any = tc.strategy
    if tc.strategy == "ddp":
        from lightning.pytorch.strategies import DDPStrategy

        strategy = DDPStrategy(find_unused_parameters=True)
    return {
        "accelerator": tc.accelerator,
        "devices": tc.devices,
        "num_nodes": tc.num_nodes,
        "strategy": strategy,
        "precision": precision or tc.precision,
        "use_distributed_sampler": False,  # StepSampler splits the step-indexed order over ranks
    }


def with_overrides(
    tc: TrainerConfig, accelerator: str = "", devices: int = 0, num_nodes: int = 0, strategy: str = ""
) -> TrainerConfig:
    """``tc`` with the command line's non-empty ``--accelerator/--devices/--num-nodes/--strategy``."""
    import dataclasses

    given = {"accelerator": accelerator, "devices": devices, "num_nodes": num_nodes, "strategy": strategy}
    out = dataclasses.replace(tc, **{k: v for k, v in given.items() if v})
    check_trainer_config(out)
    return out
