"""Run metadata for experiment tracking, and the CSV and W&B loggers every training command uses.

Every tracked run carries the same metadata (issue: reproducible pipeline): the git commit, the DVC
stage (``$DVC_STAGE``, which ``dvc repro`` sets), the params profile and the resolved configuration.
:func:`run_metadata` builds it; :func:`wandb_logger` builds Lightning's ``WandbLogger`` with it,
offline unless the user configured W&B, and never uploads checkpoints (``log_model=False``: DVC owns
artifacts). :func:`csv_logger` writes ``logs/version_N/metrics.csv`` so that a resumed run continues
its log without gaps or duplicate steps; :func:`write_loss_curve` turns the logs of one or more runs
into the tidy ``step,<loss columns>`` CSV that the pipelines declare as DVC ``plots:``. Nothing here
imports wandb or lightning, or touches the network, at import time.
"""

from __future__ import annotations

import os
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = [
    "csv_logger",
    "git_commit",
    "latest_metrics_csv",
    "run_metadata",
    "run_group",
    "trim_metrics_csv",
    "wandb_logger",
    "wandb_mode",
    "write_loss_curve",
]


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


WANDB_MODES = ("disabled", "offline", "online")
"""Values of ``tracking.wandb`` in ``params.yaml`` (and of the trainers' ``--wandb``)."""


def wandb_mode(requested: str, env: str | None = None) -> str | None:
    """The W&B mode a run uses: None (no W&B logger), ``"offline"`` or ``"online"``.

    ``requested`` comes from the params (``tracking.wandb``); ``env`` (default ``$WANDB_MODE``) can
    only make it more private: ``offline`` / ``disabled`` there win over ``online``, so the network
    is used only when both the params and the environment allow it.
    """
    if requested not in WANDB_MODES:
        raise ValueError(f"tracking.wandb: expected one of {', '.join(WANDB_MODES)}, got {requested!r}")
    env = os.environ.get("WANDB_MODE") if env is None else env
    if requested == "disabled" or env == "disabled":
        return None
    return "offline" if env in ("offline", "dryrun") else requested


def run_group() -> str:
    """The W&B group of this run: the DVC experiment (``$DVC_EXP_NAME``, set by ``dvc exp run``),
    else ``commit-<short sha>``, else ``local``. Every stage of one experiment lands in one group."""
    exp = os.environ.get("DVC_EXP_NAME")
    if exp:
        return exp
    commit = git_commit(Path.cwd()) or git_commit(Path(__file__).resolve().parent)
    return f"commit-{commit}" if commit else "local"


def wandb_logger(
    save_dir: str | Path,
    project: str,
    config: Mapping[str, Any],
    stage: str | None = None,
    mode: str | None = None,
):
    """Lightning ``WandbLogger`` whose run config is :func:`run_metadata` of ``config``.

    ``mode`` is ``offline`` or ``online`` (:func:`wandb_mode`); None keeps ``$WANDB_MODE``, else
    offline. The run is grouped by :func:`run_group` and tagged with the stage (``$DVC_STAGE`` by
    default), its ``job_type``. ``log_model=False`` so no checkpoint is ever uploaded (DVC owns
    them); no code snapshot. wandb is imported here, not when this module is.
    """
    from lightning.pytorch.loggers import WandbLogger

    mode = mode or os.environ.get("WANDB_MODE") or "offline"
    os.environ["WANDB_MODE"] = mode  # what wandb.init reads
    stage = stage or os.environ.get("DVC_STAGE")
    return WandbLogger(
        save_dir=str(save_dir),
        project=project,
        offline=mode == "offline",
        log_model=False,
        config=run_metadata(stage, config=config),
        save_code=False,
        group=run_group(),
        tags=[stage] if stage else None,
        job_type=stage,
    )


def trim_metrics_csv(path: str | Path, first_step: int) -> int:
    """Drop the rows of a Lightning ``metrics.csv`` logged at ``step >= first_step`` (and a torn
    last line), atomically; returns how many rows were dropped. A run killed after its last checkpoint
    logged steps that the resumed run logs again."""
    import csv
    import io

    from image2sim.simulator.io.atomic import write_text_atomic

    path = Path(path)
    if not path.is_file():
        return 0
    text = path.read_text(encoding="utf-8")
    lines = text.splitlines(keepends=True)
    torn = bool(lines) and not lines[-1].endswith("\n")  # a kill mid-write
    rows = list(csv.DictReader(io.StringIO("".join(lines[:-1] if torn else lines))))
    if not rows:
        return int(torn)
    fields = list(rows[0].keys())

    def before(row: dict) -> bool:
        try:
            return int(float(row.get("step") or -1)) < first_step
        except ValueError:
            return False

    kept = [r for r in rows if before(r)]
    dropped = len(rows) - len(kept) + int(torn)
    if dropped:
        out = io.StringIO()
        writer = csv.DictWriter(out, fieldnames=fields, lineterminator="\n")
        writer.writeheader()
        writer.writerows(kept)
        write_text_atomic(path, out.getvalue())
    return dropped


def _latest_version(logs: Path) -> int | None:
    versions = [
        int(p.name.split("_", 1)[1])
        for p in logs.glob("version_*")
        if p.is_dir() and p.name.split("_", 1)[1].isdigit()
    ]
    return max(versions) if versions else None


def csv_logger(save_dir: str | Path, resume: bool, name: str = "logs"):
    """Lightning ``CSVLogger`` at ``save_dir/name/version_N/metrics.csv``, flushed every step.

    A fresh run starts a new ``version_N``; a resumed one (``resume=True``) continues the latest
    version: its rows before the first step the resumed run logs are kept, the later ones (logged
    after the last checkpoint by the interrupted run) are replaced. So a run interrupted and resumed
    any number of times leaves one file with every step once, like an uninterrupted run.
    """
    from lightning.pytorch.loggers import CSVLogger
    from lightning.pytorch.utilities import rank_zero_only

    class _ResumableCSVLogger(CSVLogger):
        def __init__(self) -> None:
            version = _latest_version(Path(save_dir) / name) if resume else None
            # Flushing every step: rows buffered since the last flush would be lost by a kill, and
            # the resumed run restarts at the last checkpoint, after them (a gap).
            super().__init__(str(save_dir), name=name, version=version, flush_logs_every_n_steps=1)
            self._kept: Path | None = None
            if resume and version is not None:
                # Lightning's writer deletes an existing metrics.csv when it opens the folder: set the
                # rows aside (a rename, so a kill before they are restored loses nothing).
                log = Path(self.log_dir) / "metrics.csv"
                kept = log.with_name("metrics.before_resume.csv")
                if log.is_file():
                    os.replace(log, kept)
                self._kept = kept if kept.is_file() else None

        def _restore(self, first_step: int) -> None:
            if self._kept is None:
                return
            _ = self.experiment  # the writer exists (and has cleared the folder) before the restore
            trim_metrics_csv(self._kept, first_step)
            os.replace(self._kept, Path(self.log_dir) / "metrics.csv")
            self._kept = None

        @rank_zero_only
        def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
            self._restore(int(step) if step is not None else 0)
            super().log_metrics(metrics, step)

        @rank_zero_only
        def finalize(self, status: str) -> None:
            super().finalize(status)
            if self._kept is not None and not (Path(self.log_dir) / "metrics.csv").exists():
                os.replace(self._kept, Path(self.log_dir) / "metrics.csv")  # resumed with nothing to log
                self._kept = None

    return _ResumableCSVLogger()


def latest_metrics_csv(run_dir: str | Path, name: str = "logs") -> Path:
    """``run_dir/logs/version_N/metrics.csv`` of the latest version (what :func:`csv_logger` wrote)."""
    logs = Path(run_dir) / name
    version = _latest_version(logs)
    path = logs / f"version_{version}" / "metrics.csv"
    if version is None or not path.is_file():
        raise FileNotFoundError(
            f"{run_dir}: no {name}/version_N/metrics.csv (was the run trained with the CSV logger?)"
        )
    return path


def _curve_rows(path: Path, suffix: str) -> tuple[list[str], list[dict[str, float]]]:
    """The ``step`` and ``*<suffix>`` columns of one ``metrics.csv``, rows where a loss was logged."""
    import csv

    with path.open(encoding="utf-8", newline="") as fh:
        rows = list(csv.DictReader(fh))
    columns = [c for c in (rows[0] if rows else {}) if c.endswith(suffix)]
    if not columns:
        raise ValueError(f"{path}: no column ending in {suffix!r}")
    out = []
    for row in rows:
        if row.get("step") in (None, "") or all(row[c] in (None, "") for c in columns):
            continue
        out.append(
            {
                "step": int(float(row["step"])),
                **{c: float(row[c]) for c in columns if row[c] not in (None, "")},
            }
        )
    return columns, out


def write_loss_curve(run_dirs: list[str | Path], out_csv: str | Path, suffix: str = "loss") -> Path:
    """Write the loss curve of ``run_dirs`` (trained one after the other) as one CSV, atomically.

    Columns: ``step`` (the runs' steps, each run's shifted to start after the previous run's last
    step, so DAgger rounds continue BC), ``run`` (the run's index) and every logged column ending in
    ``suffix`` with ``/`` written ``_`` (``train/loss`` -> ``train_loss``, a plain field name for DVC's
    plot templates). DVC declares it under ``plots:`` with ``x: step``.
    """
    import csv
    import io

    from image2sim.simulator.io.atomic import write_text_atomic

    if not run_dirs:
        raise ValueError("write_loss_curve: no run folders given")
    columns: list[str] = []
    rows: list[dict[str, float]] = []
    offset = 0
    for index, run in enumerate(run_dirs):
        cols, run_rows = _curve_rows(latest_metrics_csv(run), suffix)
        columns += [c for c in cols if c not in columns]
        first = min((r["step"] for r in run_rows), default=0)
        for r in run_rows:
            rows.append({**r, "step": r["step"] - first + offset, "run": index})
        offset = max((r["step"] for r in rows), default=offset - 1) + 1
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=["step", "run", *columns], lineterminator="\n")
    writer.writerow({c: c.replace("/", "_") for c in writer.fieldnames})  # the header, plain names
    writer.writerows(rows)
    Path(out_csv).parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(out_csv, buf.getvalue())
