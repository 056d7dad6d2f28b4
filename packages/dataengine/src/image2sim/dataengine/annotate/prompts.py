"""Annotation requests, the style router and the interleaved VLM prompt.

Styles (paper appendix): ``r2r`` (fine-grained, sequential), ``reverie`` (object-centric, passive
voice), ``demand`` (casual human request). Each has structure and tone variants. The prompt
interleaves [image 1] -> [movement 1] -> [image 2] -> ... -> [STOP] and asks for a REASONING block,
a VERDICT (visual freezing, clipping through walls) and the INSTRUCTION; objects may be named only
if they are visible in the frames or are the goal.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "STYLES",
    "STYLE_WEIGHTS",
    "STRUCTURES",
    "TONES",
    "AnnotationRequest",
    "Annotation",
    "route_style",
    "build_messages",
]

STYLES = ("r2r", "reverie", "demand")
STYLE_WEIGHTS = (0.4, 0.3, 0.3)
"""Default style mix."""
STRUCTURES = ("sequential", "landmark_first", "compact")
TONES = ("neutral", "polite", "terse")


@dataclass
class AnnotationRequest:
    """Everything an annotator may use for one episode."""

    episode_id: str
    movements: list[str]
    """Movement text of each macro-step (the last is "stop")."""
    images: list[np.ndarray]
    """180 degree view (H, W, 3) uint8 at each macro-step start (may be empty for the template)."""
    goal: dict
    """Goal object record (category, room_type, position, ...)."""
    visible: list[list[str]]
    """Categories visible at each macro-step start (anti-hallucination allow-list and landmarks)."""
    rooms: list[str | None]
    """Room type at each macro-step start, when known."""
    style: str
    structure: str
    tone: str
    seed: int = 0
    near: list[str] = field(default_factory=list)
    """Categories of objects near the goal (same storey, within a stated distance, mutually visible;
    :func:`image2sim.dataengine.visibility.near_categories`): the only ones "the goal near the X" may
    name."""
    distances: list[float] = field(default_factory=list)
    """Metres walked in each macro-step (landmark-free path instructions give distances)."""
    turns: list[float] = field(default_factory=list)
    """Signed net heading change of each macro-step in degrees (positive = left)."""
    features: list[list[str]] = field(default_factory=list)
    """Path features of each macro-step: ``doorway``, ``stairs_up``, ``stairs_down``
    (:func:`image2sim.dataengine.chunking.path_features`)."""

    @property
    def allowed_objects(self) -> set[str]:
        out = {self.goal.get("category", "")}
        for v in self.visible:
            out.update(v)
        return {c for c in out if c}


@dataclass
class Annotation:
    """An annotator's result for one request."""

    episode_id: str
    text: str
    style: str
    structure: str
    tone: str
    accepted: bool
    reason: str = ""
    """Why it was rejected or dropped ("" when accepted)."""
    attempts: int = 1
    reasoning: str = ""
    issues: tuple[str, ...] = field(default_factory=tuple)


def route_style(rng: np.random.Generator, weights=STYLE_WEIGHTS) -> tuple[str, str, str]:
    """Draw (style, structure, tone) for one episode."""
    w = np.asarray(weights, dtype=np.float64)
    style = STYLES[int(rng.choice(len(STYLES), p=w / w.sum()))]
    return style, STRUCTURES[int(rng.integers(len(STRUCTURES)))], TONES[int(rng.integers(len(TONES)))]


_STYLE_GUIDE = {
    "r2r": "Write an R2R-style instruction: fine-grained and sequential, one clause per movement, "
    "mentioning landmarks the agent passes, ending where it should stop.",
    "reverie": "Write a REVERIE-style instruction: object-centric and in the passive voice, focused on "
    "the goal "
    "object and where it is located (room, nearby objects), with little route detail.",
    "demand": "Write a Demand-style instruction: a casual human request expressing a need that the "
    "goal object "
    "satisfies, without naming the route step by step.",
}


def build_messages(req: AnnotationRequest) -> list[dict]:
    """OpenAI-style chat messages; user content interleaves images and movement texts.

    Images appear as ``{"type": "image", "image": array}``; backends convert them to their wire form.
    """
    goal = req.goal.get("category", "object").replace("_", " ")
    room = req.goal.get("room_type")
    system = (
        "You annotate navigation trajectories recorded in a simulator. First write REASONING: check "
        "the frames "
        "for visual freezing (consecutive frames identical although the agent moved) and "
        "clipping through walls. "
        "Then write VERDICT: VALID or VERDICT: INVALID, then ISSUES: a comma separated list (or none), then "
        "INSTRUCTION: one instruction for the whole trajectory. Only the VERDICT line decides. "
        "Name only objects "
        "that are visible in the frames or are the goal."
    )
    content: list[dict] = []
    for i, mv in enumerate(req.movements):
        if i < len(req.images):
            content.append({"type": "text", "text": f"[image {i + 1}]"})
            content.append({"type": "image", "image": req.images[i]})
        content.append({"type": "text", "text": "[STOP]" if mv == "stop" else f"[movement {i + 1}] {mv}"})
    task = (
        f"Goal object: {goal}"
        + (f" in the {room.replace('_', ' ')}" if room else "")
        + ". "
        + _STYLE_GUIDE[req.style]
        + f" Structure: {req.structure}. Tone: {req.tone}."
    )
    content.append({"type": "text", "text": task})
    return [{"role": "system", "content": system}, {"role": "user", "content": content}]
