"""Run metadata for experiment tracking, and the one W&B logger every training command uses.

Every tracked run carries the same metadata (issue: reproducible pipeline): the git commit, the DVC
stage (``$DVC_STAGE``, which ``dvc repro`` sets), the params profile and the resolved configuration.
:func:`run_metadata` builds it; :func:`wandb_logger` builds Lightning's ``WandbLogger`` with it,
offline unless the user configured W&B, and never uploads checkpoints (``log_model=False``: DVC owns
artifacts). Nothing here imports wandb or touches the network at import time.
"""

from __future__ import annotations

import os
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["git_commit", "run_metadata", "wandb_logger"]


def git_commit(cwd: str | Path | None = None) -> str | None:
    """The current git commit (short), or None outside a repository."""
    try:
        res = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return res.stdout.strip() or None


def run_metadata(
    stage: str | None = None,
    profile: str | None = None,
    config: Mapping[str, Any] | None = None,
    params_file: str | Path = "params.yaml",
) -> dict[str, Any]:
    """Run metadata: git commit, DVC stage, params profile and the resolved configuration.

    The commit is that of the repository holding ``params_file`` (DVC runs stages at its root),
    else that of the checkout this module is installed from. The stage defaults to ``$DVC_STAGE``;
    the profile to ``$IMAGE2SIM_PROFILE``, else the ``profile`` key of ``params_file``.
    ``resolved_config`` holds ``command`` (the command's own settings) and ``params`` (the stage's
    section of ``params_file``, when the file has one).
    """
    stage = stage or os.environ.get("DVC_STAGE")
    params: Mapping[str, Any] = {}
    path = Path(params_file)
    if path.is_file():
        import yaml

        loaded = yaml.safe_load(path.read_text(encoding="utf-8"))
        if loaded is not None and not isinstance(loaded, Mapping):
            raise ValueError(f"{path}: expected a mapping of stage sections, got {type(loaded).__name__}")
        params = loaded or {}
    section = params.get(stage) if stage else None
    return {
        # The commit of the project the params file belongs to, else of this code's checkout.
        "git_commit": git_commit(path.resolve().parent) or git_commit(Path(__file__).resolve().parent),
        "dvc_stage": stage,
        "params_profile": profile or os.environ.get("IMAGE2SIM_PROFILE") or params.get("profile"),
        "resolved_config": {
            "command": dict(config or {}),
            "params": dict(section) if isinstance(section, Mapping) else None,
        },
    }


def wandb_logger(save_dir: str | Path, project: str, config: Mapping[str, Any], stage: str | None = None):
    """Lightning ``WandbLogger`` whose run config is :func:`run_metadata` of ``config``.

    Offline unless ``WANDB_MODE`` says otherwise; ``log_model=False`` so no checkpoint is ever
    uploaded (DVC owns them); no code snapshot.
    """
    from lightning.pytorch.loggers import WandbLogger

    os.environ.setdefault("WANDB_MODE", "offline")
    return WandbLogger(
        save_dir=str(save_dir),
        project=project,
        offline=os.environ["WANDB_MODE"] == "offline",
        log_model=False,
        config=run_metadata(stage, config=config),
        save_code=False,
    )
