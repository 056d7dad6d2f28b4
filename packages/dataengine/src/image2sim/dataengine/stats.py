"""Dataset statistics like the paper's appendix: style mix, instruction length (words), trajectory
length (m) and step-count histograms, as JSON and PNG."""

from __future__ import annotations

import gzip
import json
from collections import Counter
from pathlib import Path

import numpy as np
from image2sim.simulator.io.atomic import write_bytes_atomic

__all__ = ["episode_stats", "write_stats"]


def _hist(values, bins) -> dict:
    counts, edges = np.histogram(np.asarray(values, dtype=np.float64), bins=bins)
    return {"edges": [float(e) for e in edges], "counts": [int(c) for c in counts]}


def _summary(values) -> dict:
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return {"count": 0}
    return {
        "count": int(v.size),
        "mean": float(v.mean()),
        "std": float(v.std()),
        "min": float(v.min()),
        "median": float(np.median(v)),
        "max": float(v.max()),
    }


def episode_stats(episodes: list[dict], gt: dict | None = None, extras: dict | None = None) -> dict:
    """Statistics of a list of episode records (the ``episodes`` of a written file); the engine's own
    fields (style, bucket, goal object, path length, steps) come from ``extras`` by episode id (the
    ``{split}_extras.json`` sidecar), or from the records themselves in files written before it."""
    extras = extras or {}
    episodes = [{**e, **extras.get(e["episode_id"], {})} for e in episodes]
    words = [len(e["instruction"]["instruction_text"].split()) for e in episodes]
    lengths = [float(e.get("path_length", e["info"]["geodesic_distance"])) for e in episodes]
    steps = [
        int(e.get("num_steps", len((gt or {}).get(e["episode_id"], {}).get("actions", [])))) for e in episodes
    ]
    styles = Counter(e.get("style", "unknown") for e in episodes)
    n = max(1, len(episodes))
    return {
        "episodes": len(episodes),
        "scenes": len({e["scene_id"] for e in episodes}),
        "style_mix": {k: {"count": v, "fraction": v / n} for k, v in sorted(styles.items())},
        "buckets": dict(Counter(e.get("bucket", "unknown") for e in episodes)),
        "goal_categories": dict(
            Counter(e.get("goal_object", {}).get("category", "unknown") for e in episodes)
        ),
        "distinct_instructions": len({e["instruction"]["instruction_text"] for e in episodes}),
        "instruction_words": {
            **_summary(words),
            "histogram": _hist(words, np.arange(0, max(words + [1]) + 6, 5)),
        },
        "trajectory_length_m": {
            **_summary(lengths),
            "histogram": _hist(lengths, np.arange(0, max(lengths + [1]) + 1.5, 1.0)),
        },
        "steps": {**_summary(steps), "histogram": _hist(steps, np.arange(0, max(steps + [1]) + 11, 10))},
    }


def write_stats(episode_file: str | Path, out_dir: str | Path, gt_file: str | Path | None = None) -> dict:
    """Read an episode file, write ``stats.json`` and ``stats.png`` into ``out_dir``."""
    episode_file = Path(episode_file)
    with gzip.open(episode_file, "rt", encoding="utf-8") as fh:
        doc = json.load(fh)
    gt = None
    if gt_file is not None and Path(gt_file).is_file():
        with gzip.open(gt_file, "rt", encoding="utf-8") as fh:
            gt = json.load(fh)
    from image2sim.dataengine.episodes import read_extras

    stats = episode_stats(doc["episodes"], gt, read_extras(episode_file))
    stats["source"] = str(episode_file)
    out = Path(out_dir)
    write_bytes_atomic(out / "stats.json", json.dumps(stats, indent=1).encode())
    _plot(stats, out / "stats.png")
    return stats


def _panel(title: str, labels: list[str], counts: list[int], w: int = 320, h: int = 240) -> np.ndarray:
    """One bar chart drawn with OpenCV (matplotlib is not part of this stack)."""
    import cv2

    img = np.full((h, w, 3), 255, np.uint8)
    cv2.putText(img, title, (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    n = max(1, len(counts))
    top = max([1, *counts])
    x0, y0, x1, y1 = 30, 30, w - 8, h - 34
    cv2.line(img, (x0, y1), (x1, y1), (0, 0, 0), 1)
    bw = (x1 - x0) / n
    for i, (lab, c) in enumerate(zip(labels, counts, strict=True)):
        bh = int(round((y1 - y0) * c / top))
        a, b = int(x0 + i * bw + 1), int(x0 + (i + 1) * bw - 1)
        cv2.rectangle(img, (a, y1 - bh), (max(a, b), y1), (176, 114, 76), -1)
        if c:
            cv2.putText(
                img, str(c), (a, y1 - bh - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.3, (0, 0, 0), 1, cv2.LINE_AA
            )
        if n <= 8 or i % max(1, n // 6) == 0:
            cv2.putText(
                img,
                lab,
                (a, y1 + 14 + 10 * (i % 2)),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.3,
                (0, 0, 0),
                1,
                cv2.LINE_AA,
            )
    return img


def _plot(stats: dict, path: Path) -> None:
    import cv2

    mix = stats["style_mix"]
    panels = [_panel("instruction style", list(mix), [v["count"] for v in mix.values()])]
    for key, title in (
        ("instruction_words", "instruction length (words)"),
        ("trajectory_length_m", "trajectory length (m)"),
        ("steps", "steps"),
    ):
        h = stats[key].get("histogram", {"edges": [0, 1], "counts": [0]})
        panels.append(_panel(title, [f"{e:g}" for e in h["edges"][:-1]], h["counts"]))
    img = np.concatenate(panels, axis=1)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValueError(f"{path}: cannot encode the statistics figure")
    write_bytes_atomic(path, buf.tobytes())
