"""The model card (``README.md``) of an exported Image2Nav policy.

Hugging Face YAML front matter (``library_name``, ``pipeline_tag``, ``tags``, ``base_model`` when the
base is a hub checkpoint) and sections: the model (config summary, parameter count, LoRA), how to load
and prompt it, its training data (every shard with its trajectory count and content hashes), the
training settings, metrics (from a metrics JSON, when given) and intended use and limitations.
Nothing is downloaded; the card only describes local files.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from image2sim.simulator.io.digest import file_sha256

CARD_FILE = "README.md"
"""File name of the card inside the export folder (what the Hugging Face hub shows)."""

RUN_FILE = "training_run.json"
"""The export's record of its run: the resolved config and the data lineage (the card is rebuilt
from it by :func:`update_model_card`)."""

_HUB_ID = re.compile(r"^[A-Za-z0-9][\w.-]*/[\w.-]+$")
_MAX_METRIC_ROWS = 60


def _read_json_object(path: Path, what: str) -> dict[str, Any]:
    """A JSON file's top-level object; errors name the file and the problem."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what} not found")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(doc, Mapping):
        raise ValueError(f"{path}: expected a JSON object ({what}), got {type(doc).__name__}")
    return dict(doc)


def data_lineage(sources: Iterable[str | Path]) -> list[dict[str, Any]]:
    """One record per training source: a shard folder (format, trajectory count and the SHA-256 of
    its ``manifest.json`` and ``trajectories.jsonl``, which list every trajectory and frame file) or a
    file (its SHA-256). A source that is gone is recorded as ``missing``."""
    out = []
    for src in sources:
        path = Path(src)
        rec: dict[str, Any] = {"path": str(src)}
        if path.is_dir() and (path / "manifest.json").is_file():
            manifest = _read_json_object(path / "manifest.json", "shard manifest")
            rec.update(
                kind="shard", format=manifest.get("format"), trajectories=manifest.get("num_trajectories")
            )
            rec["sha256"] = {
                name: file_sha256(path / name)
                for name in ("manifest.json", "trajectories.jsonl")
                if (path / name).is_file()
            }
        elif path.is_file():
            rec.update(kind="file", sha256={path.name: file_sha256(path)})
        else:
            rec["kind"] = "missing"
        out.append(rec)
    return out


def metric_rows(path: str | Path) -> list[tuple[str, float | None]]:
    """The numbers of a metrics JSON as ``(dotted key, value)`` rows, ``None`` for a metric that is
    n/a (null, e.g. SR on a test split without goals); protocol and config sections, strings and
    lists left out; at most 60 rows."""
    doc = _read_json_object(Path(path), "metrics file")
    rows: list[tuple[str, float | None]] = []

    def walk(node: Mapping, prefix: str) -> None:
        for key, value in node.items():
            if key in ("protocol", "config", "format", "version"):
                continue
            if isinstance(value, Mapping):
                walk(value, f"{prefix}{key}.")
            elif value is None or (isinstance(value, (int, float)) and not isinstance(value, bool)):
                rows.append((f"{prefix}{key}", None if value is None else float(value)))

    walk(doc, "")
    return rows[:_MAX_METRIC_ROWS]


def _hub_base_model(cfg) -> str | None:
    """The hub id of the base checkpoint (``_name_or_path`` in its ``config.json``), when it has one."""
    if cfg is None or cfg.model.source == "tiny":
        return None
    config = Path(cfg.model.source) / "config.json"
    try:
        name = json.loads(config.read_text()).get("_name_or_path", "")
    except (OSError, json.JSONDecodeError):
        return None
    return name if isinstance(name, str) and _HUB_ID.match(name) else None


def _front_matter(cfg, adapter: bool) -> str:
    """Hugging Face YAML metadata block."""
    import yaml

    meta: dict[str, Any] = {
        "library_name": "transformers",
        "pipeline_tag": "image-text-to-text",
        "tags": ["image2sim", "image2nav", "vision-language-navigation", "qwen3_vl", "robotics"]
        + (["lora", "peft"] if adapter else []),
    }
    base = _hub_base_model(cfg)
    if base:
        meta["base_model"] = base
    return "---\n" + yaml.safe_dump(meta, sort_keys=False) + "---\n"


def _table(header: tuple[str, ...], rows: Iterable[tuple]) -> list[str]:
    """A Markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return lines


def _model_section(model, cfg, adapter: bool) -> list[str]:
    """Architecture, sizes, parameter count and LoRA settings."""
    qc = model.config
    tc, vc = qc.text_config, qc.vision_config
    total = sum(p.numel() for p in model.parameters())
    source = "from scratch (`tiny` preset)" if cfg is None or cfg.model.source == "tiny" else cfg.model.source
    rows = [
        ("architecture", ", ".join(qc.architectures or [type(model).__name__])),
        ("parameters", f"{total:,}"),
        ("initialised from", source if cfg is not None else "see the training run"),
        (
            "language model",
            f"{tc.num_hidden_layers} layers, hidden {tc.hidden_size}, {tc.num_attention_heads} heads",
        ),
        ("vocabulary", f"{tc.vocab_size:,} tokens"),
        ("vision tower", f"{vc.depth} layers, hidden {vc.hidden_size}, patch {vc.patch_size}"),
        ("dtype", str(getattr(qc, "dtype", None) or next(model.parameters()).dtype).replace("torch.", "")),
    ]
    if cfg is not None:
        ob = cfg.observation
        rows.append(("observation", f"{ob.camera} {ob.width}x{ob.height} RGB"))
        lora = cfg.model.lora
        rows.append(
            ("LoRA", f"r {lora.r}, alpha {lora.alpha} (merged; adapter in `adapter/`)" if adapter else "no")
        )
    return ["## Model", "", *_table(("property", "value"), rows), ""]


def _usage_section(adapter: bool, goal_head: bool = False) -> list[str]:
    """How to load the folder and build the prompt."""
    lines = [
        "## Use",
        "",
        "```python",
        "from transformers import AutoImageProcessor, AutoModelForImageTextToText, AutoTokenizer",
        "",
        'model = AutoModelForImageTextToText.from_pretrained("<this folder>")',
        'tokenizer = AutoTokenizer.from_pretrained("<this folder>")   # carries the chat template',
        'image_processor = AutoImageProcessor.from_pretrained("<this folder>")',
        "```",
        "",
        "The chat template formats the policy's prompt: a system turn with the instruction, then one user",
        "turn per observation (`Executed: <actions>` since the previous one, then the image) and the",
        "assistant's two next actions (`STOP`, `FORWARD`, `LEFT`, `RIGHT`). `PromptBuilder.messages` in",
        "`image2sim.navpolicy.prompting` builds these messages; `image2sim nav serve --model <this folder>`",
        "and `image2sim eval nav --agent image2nav --model <this folder>` run the streaming agent.",
        "",
    ]
    if adapter:
        lines += [
            "The unmerged LoRA adapter (with the trained vision-language projectors) is in `adapter/`:",
            "",
            "```python",
            "from peft import PeftModel",
            'policy = PeftModel.from_pretrained(base_model, "<this folder>/adapter")',
            "```",
            "",
            "`base_model` is the checkpoint training started from (see *initialised from*).",
            "",
        ]
    if goal_head:
        lines += [
            "`goal_head.safetensors` is the grounding head trained with the language model (a linear",
            "probe, at an image's last token, of whether the instruction's goal is in view; the hidden",
            "state it reads is in its metadata). `build_policy` loads it with the model, and the agent's",
            "`agent.stop_gate` lets STOP through only where it says so.",
            "",
        ]
    return lines


def _data_section(lineage: list[dict[str, Any]], cfg) -> list[str]:
    """Training data lineage and the training settings."""
    from image2sim.simulator.tracking import git_commit

    lines = ["## Training data", ""]
    if lineage:
        rows = []
        for rec in lineage:
            hashes = ", ".join(f"`{name}` {digest[:16]}" for name, digest in rec.get("sha256", {}).items())
            rows.append((f"`{rec['path']}`", rec["kind"], rec.get("trajectories", ""), hashes or "-"))
        lines += _table(("source", "kind", "trajectories", "sha256 (first 16 hex)"), rows)
    else:
        lines.append("No shard or episode file was recorded (in-memory data).")
    lines.append("")
    if cfg is not None:
        t = cfg.train
        lines += [
            f"Behaviour cloning: {t.max_steps} steps, batch {t.batch_size}, learning rate {t.lr}, "
            f"seed {t.seed};",
            f"samples `{cfg.data.sampling}` with at most {cfg.data.max_observations} observations.",
            f"Code: git commit `{git_commit(Path(__file__).parent) or 'unknown'}`.",
            "",
        ]
    return lines


def _metrics_section(metrics: str | Path | None) -> list[str]:
    """Metrics from a metrics JSON, or a note that none were given."""
    if metrics is None:
        return [
            "## Metrics",
            "",
            "None given (`image2sim nav card <folder> --metrics metrics/nav.json` adds them).",
            "",
        ]
    rows = [(f"`{k}`", "n/a" if v is None else f"{v:.4g}") for k, v in metric_rows(metrics)]
    return ["## Metrics", "", f"From `{Path(metrics).name}`:", "", *_table(("metric", "value"), rows), ""]


_LIMITATIONS = [
    "## Intended use and limitations",
    "",
    "Research on vision-language navigation in simulated indoor scenes (Image2Sim): the policy reads",
    "egocentric RGB observations and an instruction and outputs discrete actions for a ground robot",
    "(0.25 m forward steps, 15 degree turns). It is not a safety-rated controller: on a real robot run it",
    "behind collision avoidance and a human stop. It was trained on the scenes and instructions listed",
    "above only; expect lower success on other buildings, cameras, heights or languages. Policies trained",
    "from scratch (the `tiny` preset) are plumbing checks, not navigators.",
    "",
]


def model_card(
    model,
    cfg=None,
    lineage: list[dict[str, Any]] | None = None,
    metrics=None,
    adapter: bool = False,
    goal_head: bool = False,
) -> str:
    """The card's Markdown text (front matter first)."""
    name = cfg.name if cfg is not None else "export"
    lines = [f"# Image2Nav policy ({name})", ""]
    lines += [
        "Qwen3-VL fine-tuned to follow navigation instructions from egocentric images: for every",
        "observation it predicts the next two actions.",
        "",
    ]
    lines += _model_section(model, cfg, adapter)
    lines += _usage_section(adapter, goal_head)
    lines += _data_section(lineage or [], cfg)
    lines += _metrics_section(metrics)
    lines += _LIMITATIONS
    return _front_matter(cfg, adapter) + "\n" + "\n".join(lines)


def write_model_card(
    folder: str | Path,
    model,
    cfg=None,
    metrics: str | Path | None = None,
    adapter: bool = False,
    data: Iterable[str | Path] | None = None,
    goal_head: bool = False,
) -> Path:
    """Write ``<folder>/README.md`` and ``<folder>/training_run.json`` (config + lineage), each
    atomically; ``data`` lists the training sources (default: the config's ``data.shards``). Returns
    the card's path."""
    from image2sim.simulator.io.atomic import write_json_atomic, write_text_atomic

    sources = list(data) if data is not None else list(cfg.data.shards if cfg is not None else [])
    lineage = data_lineage(sources)
    run = {"config": cfg.to_dict() if cfg is not None else None, "data": lineage, "adapter": adapter}
    write_json_atomic(Path(folder) / RUN_FILE, run)
    card = model_card(model, cfg, lineage, metrics, adapter, goal_head)
    return write_text_atomic(Path(folder) / CARD_FILE, card)


def update_model_card(
    folder: str | Path, metrics: str | Path | None = None, out: str | Path | None = None
) -> Path:
    """Rewrite an export's card with ``metrics`` (e.g. after ``eval nav``): config, lineage and LoRA
    come from its ``training_run.json``, sizes and parameter count from the saved model. ``out``
    writes the card there instead of ``<folder>/README.md`` (a pipeline may not modify another
    stage's output in place)."""
    from image2sim.navpolicy.config import from_dict
    from image2sim.simulator.io.atomic import write_text_atomic
    from transformers import AutoModelForImageTextToText

    folder = Path(folder)
    run = _read_json_object(folder / RUN_FILE, "run record of a policy export (nav train writes it)")
    if metrics is not None:
        metric_rows(metrics)  # a bad metrics file fails before the model is loaded
    cfg = from_dict(run["config"]) if run.get("config") else None
    model = AutoModelForImageTextToText.from_pretrained(str(folder), local_files_only=True)
    from image2sim.navpolicy.model import GOAL_HEAD_FILE

    head = (folder / GOAL_HEAD_FILE).is_file()
    text = model_card(model, cfg, run.get("data") or [], metrics, bool(run.get("adapter")), head)
    return write_text_atomic(folder / CARD_FILE if out is None else Path(out), text)
