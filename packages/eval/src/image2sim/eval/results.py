"""Result files: every file carries its protocol; per-episode JSONL logs that survive interruption.

* :func:`write_result_file` / :func:`read_result_file`: one JSON document (atomic temp + rename)
  with ``format``, ``version`` and the full ``protocol`` record next to the payload.
* :class:`EpisodeLog`: a JSONL file whose first line is the protocol header and every further line
  one finished episode, flushed and fsynced as it is appended, so a killed run can resume from the
  episodes already on disk. A torn last line (the process died mid-write) is dropped with a
  warning; a corrupt line anywhere else is an error naming the line.
* :func:`write_metrics_file` / :func:`read_metrics_file`: a headline metrics file (``metrics/*.json``,
  which DVC lists under ``metrics:``) holds measured numbers only; its protocol, configuration and
  labels go to ``<name>.protocol.json`` beside it (:func:`split_metrics`), and reading joins the two
  back into one document (a file without the sidecar, written before the split, reads as it is).
"""

from __future__ import annotations

import json
import math
import os
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from image2sim.eval.metrics.nav import AggregateReport, EpisodeResult, aggregate
from image2sim.eval.protocols import PROTOCOL_KEY, Protocol, ProtocolError, ProtocolMismatchError

RESULT_FORMAT = "image2sim-eval-result"
"""``format`` field of result JSON files."""
EPISODE_LOG_FORMAT = "image2sim-eval-episodes"
"""``format`` field of the header line of episode JSONL logs."""
FORMAT_VERSION = 1
"""Version of both layouts."""


class ResultFileError(ValueError):
    """A result file is malformed; the message names the file (and line)."""


def _json_default(obj: Any) -> Any:
    """Serialise numpy scalars/arrays and tensors that slipped into a payload."""
    if hasattr(obj, "tolist"):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _dumps(obj: Any, **kwargs: Any) -> str:
    # allow_nan=False: NaN/inf are not JSON; a non-finite metric must be handled before writing.
    return json.dumps(obj, default=_json_default, allow_nan=False, **kwargs)


def write_json_atomic(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as JSON to ``path`` atomically (numpy values converted; NaN/inf refused)."""
    from image2sim.simulator.io import atomic

    return atomic.write_json_atomic(path, obj, default=_json_default)


CONTEXT_KEYS = ("format", "version", PROTOCOL_KEY, "header", "policies")
"""Top-level keys of a metrics document that are never metrics (whatever their values)."""
_MISSING = object()


def protocol_path(path: str | Path) -> Path:
    """The sidecar of a metrics file: ``metrics/render.json`` -> ``metrics/render.protocol.json``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.protocol.json")


def _is_number(value: Any) -> bool:
    """A metric leaf: a number (bool included: a measured yes/no) or null (not measured)."""
    return value is None or isinstance(value, (int, float))


def _all_numbers(value: Any) -> bool:
    if isinstance(value, Mapping):
        return all(_all_numbers(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return all(_all_numbers(v) for v in value)
    return _is_number(value)


def _split(value: Any) -> tuple[Any, Any]:
    """``(numbers, the rest)`` of one value, ``_MISSING`` where a side is empty. Mappings split key
    by key; a list goes whole to the side of its leaves (to the rest if any leaf is not a number)."""
    if isinstance(value, Mapping):
        if not value:
            return dict(value), _MISSING
        numbers, rest = {}, {}
        for key, item in value.items():
            n, r = _split(item)
            if n is not _MISSING:
                numbers[key] = n
            if r is not _MISSING:
                rest[key] = r
        return (numbers or _MISSING), (rest or _MISSING)
    if _all_numbers(value):
        return value, _MISSING
    return _MISSING, value


def split_metrics(doc: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """Split a metrics document into ``(metrics, context)``.

    ``metrics`` keeps the measured numbers (every leaf a number or null); ``context`` gets the
    :data:`CONTEXT_KEYS` sections whole (protocol, configuration, format header, labels) and every
    other non-numeric leaf (method notes, names), at the same place in the tree. :func:`join_metrics`
    inverts it.
    """
    metrics: dict[str, Any] = {}
    context: dict[str, Any] = {}
    for key, value in doc.items():
        n, r = (_MISSING, value) if key in CONTEXT_KEYS else _split(value)
        if n is not _MISSING:
            metrics[key] = n
        if r is not _MISSING:
            context[key] = r
    return metrics, context


def join_metrics(metrics: Mapping[str, Any], context: Mapping[str, Any]) -> dict[str, Any]:
    """One document from :func:`split_metrics`'s two halves (context keys first at the top level)."""
    out: dict[str, Any] = {k: v for k, v in context.items() if k not in metrics}
    for key, value in metrics.items():
        extra = context.get(key)
        if isinstance(value, Mapping) and isinstance(extra, Mapping):
            out[key] = join_metrics(value, extra)
        else:
            out[key] = value
    return out


def write_metrics_file(path: str | Path, doc: Mapping[str, Any]) -> Path:
    """Write a headline metrics document as ``path`` (numbers only, what DVC lists as metrics) and
    ``<name>.protocol.json`` beside it (protocol, configuration, labels), each atomically; returns
    ``path``."""
    metrics, context = split_metrics(json.loads(_dumps(doc)))  # numpy scalars become numbers first
    write_json_atomic(protocol_path(path), context)
    return write_json_atomic(path, metrics)


def read_metrics_file(path: str | Path) -> dict[str, Any]:
    """The document :func:`write_metrics_file` wrote (a file without its sidecar reads as it is).

    Raises ``FileNotFoundError`` / ``ResultFileError`` naming the file that is missing or broken.
    """
    path = Path(path)
    doc = _read_json(path)
    sidecar = protocol_path(path)
    if not sidecar.is_file():
        return doc
    return join_metrics(doc, _read_json(sidecar))


def _read_json(path: Path) -> dict[str, Any]:
    """A JSON object from ``path``; a clear error naming the file otherwise."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise FileNotFoundError(f"{path}: no such file") from exc
    except (OSError, json.JSONDecodeError) as exc:
        raise ResultFileError(f"{path}: cannot read JSON ({exc})") from exc
    if not isinstance(doc, dict):
        raise ResultFileError(f"{path}: top level is not an object")
    return doc


def result_document(protocol: Protocol, payload: Mapping[str, Any], where: str | Path = "") -> dict[str, Any]:
    """``payload`` under the format header and the full protocol record."""
    reserved = {"format", "version", PROTOCOL_KEY} & set(payload)
    if reserved:
        raise ValueError(f"{where}: payload may not contain the reserved key(s) {sorted(reserved)}")
    return {"format": RESULT_FORMAT, "version": FORMAT_VERSION, PROTOCOL_KEY: protocol.to_dict(), **payload}


def write_result_file(path: str | Path, protocol: Protocol, payload: Mapping[str, Any]) -> Path:
    """Write ``payload`` with the format header and the full protocol record, atomically."""
    return write_json_atomic(path, result_document(protocol, payload, path))


def read_result_file(path: str | Path) -> tuple[Protocol, dict[str, Any]]:
    """Read a result file: its protocol and the payload (without the header keys). A headline metrics
    file (:func:`write_metrics_file`) is read joined with its ``.protocol.json``."""
    path = Path(path)
    try:
        doc = read_metrics_file(path)
    except (OSError, ResultFileError) as exc:
        raise ResultFileError(f"{path}: cannot read result file ({exc})") from exc
    if not isinstance(doc, dict) or doc.get("format") != RESULT_FORMAT:
        raise ResultFileError(
            f"{path}: not an {RESULT_FORMAT!r} file (format={doc.get('format')!r})"
            if isinstance(doc, dict)
            else f"{path}: top level is not an object"
        )
    if doc.get("version") != FORMAT_VERSION:
        version = doc.get("version")
        raise ResultFileError(f"{path}: unsupported version {version!r} (expected {FORMAT_VERSION})")
    try:
        protocol = Protocol.from_dict(doc.get(PROTOCOL_KEY), f"{path}: {PROTOCOL_KEY}")
    except ProtocolError as exc:
        raise ResultFileError(str(exc)) from exc
    payload = {k: v for k, v in doc.items() if k not in ("format", "version", PROTOCOL_KEY)}
    return protocol, payload


def write_aggregate(
    path: str | Path, report: AggregateReport, extra: Mapping[str, Any] | None = None
) -> Path:
    """Write an :class:`AggregateReport` (means with episode counts) as a result file."""
    body = report.to_dict()
    body.pop(PROTOCOL_KEY)
    for name, summary in body["metrics"].items():
        if summary["mean"] is not None and not math.isfinite(summary["mean"]):
            summary["mean"] = str(summary["mean"])  # "inf" (e.g. PSNR of identical images) as a string
            body["metrics"][name] = summary
    return write_result_file(path, report.protocol, {**body, **(extra or {})})


class EpisodeLog:
    """Append-only per-episode JSONL log under one protocol (resumable)."""

    def __init__(self, path: str | Path, protocol: Protocol) -> None:
        """Open (or create) the log at ``path``; an existing log must have the same protocol."""
        self.path = Path(path)
        self.protocol = protocol
        if self.path.exists() and self.path.stat().st_size > 0:
            existing = read_episode_log_protocol(self.path)
            if existing != protocol:
                raise ProtocolMismatchError(
                    f"{self.path}: log was written under protocol {existing.name!r}, refusing to append "
                    f"results of protocol {protocol.name!r}"
                )
            self._repair_torn_tail()
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._append_line(
                {"format": EPISODE_LOG_FORMAT, "version": FORMAT_VERSION, PROTOCOL_KEY: protocol.to_dict()}
            )

    def _repair_torn_tail(self) -> None:
        """Cut a partial last line left by a killed writer so that appends start on a fresh line."""
        data = self.path.read_bytes()
        if data and not data.endswith(b"\n"):
            cut = data.rfind(b"\n") + 1
            warnings.warn(f"{self.path}: dropping a torn last line ({len(data) - cut} bytes)", stacklevel=3)
            with open(self.path, "r+b") as f:
                f.truncate(cut)

    def _append_line(self, obj: Any) -> None:
        line = _dumps(obj, separators=(",", ":")) + "\n"
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())

    def done_ids(self) -> set[str]:
        """Episode ids already in the log (to skip on resume)."""
        return {r.episode_id for r in self}

    def append(self, result: EpisodeResult) -> None:
        """Append one finished episode (its protocol must be the log's)."""
        if result.protocol != self.protocol:
            raise ProtocolMismatchError(
                f"{self.path}: episode {result.episode_id} was run under protocol {result.protocol.name!r}, "
                f"the log under {self.protocol.name!r}"
            )
        metrics = {}
        for k, v in result.metrics.items():
            if v is not None and not math.isfinite(v):
                raise ValueError(
                    f"{self.path}: episode {result.episode_id}: metric {k!r} is {v}; "
                    "non-finite values are errors"
                )
            metrics[k] = None if v is None else float(v)
        self._append_line({"episode_id": result.episode_id, "metrics": metrics})

    def __iter__(self) -> Iterator[EpisodeResult]:
        return iter(read_episode_log(self.path)[1])

    def aggregate(self) -> AggregateReport:
        """Aggregate every logged episode (see :func:`image2sim.eval.metrics.nav.aggregate`)."""
        return aggregate(list(self))


def _parse_header(path: Path, line: str) -> Protocol:
    try:
        header = json.loads(line)
    except json.JSONDecodeError as exc:
        raise ResultFileError(f"{path}:1: header is not JSON ({exc})") from exc
    if not isinstance(header, dict) or header.get("format") != EPISODE_LOG_FORMAT:
        raise ResultFileError(f"{path}:1: not an {EPISODE_LOG_FORMAT!r} log")
    if header.get("version") != FORMAT_VERSION:
        raise ResultFileError(f"{path}:1: unsupported version {header.get('version')!r}")
    try:
        return Protocol.from_dict(header.get(PROTOCOL_KEY), f"{path}:1: {PROTOCOL_KEY}")
    except ProtocolError as exc:
        raise ResultFileError(str(exc)) from exc


def episode_logs(folder: str | Path) -> list[Path]:
    """The per-episode logs in an agent's run folder (``<scene>.jsonl``; their ``.traj.jsonl``
    trajectory companions excluded), sorted."""
    return sorted(p for p in Path(folder).glob("*.jsonl") if not p.name.endswith(".traj.jsonl"))


def read_episode_log_protocol(path: str | Path) -> Protocol:
    """The protocol in the header line of an episode log."""
    path = Path(path)
    with open(path, encoding="utf-8") as f:
        return _parse_header(path, f.readline())


def read_episode_log(path: str | Path) -> tuple[Protocol, list[EpisodeResult]]:
    """Read an episode log: its protocol and every complete episode line, in order."""
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    lines = text.split("\n")
    if not lines or not lines[0]:
        raise ResultFileError(f"{path}: empty episode log (no header)")
    protocol = _parse_header(path, lines[0])
    torn = not text.endswith("\n")
    body = lines[1:]
    results: list[EpisodeResult] = []
    for n, line in enumerate(body, start=2):
        if not line:
            continue
        is_last = n == len(lines)
        try:
            rec = json.loads(line)
            eid, metrics = rec["episode_id"], rec["metrics"]
            if not isinstance(eid, str) or not isinstance(metrics, dict):
                raise TypeError("episode_id must be a string and metrics an object")
        except (json.JSONDecodeError, KeyError, TypeError) as exc:
            if torn and is_last:
                warnings.warn(f"{path}:{n}: ignoring a torn last line", stacklevel=2)
                break
            reason = f"{type(exc).__name__}: {exc}"
            raise ResultFileError(f"{path}:{n}: malformed episode line ({reason})") from exc
        results.append(EpisodeResult(eid, metrics, protocol))
    return protocol, results
