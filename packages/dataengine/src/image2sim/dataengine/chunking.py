"""Odometry-based macro-steps: cut a rollout where 1.0 m was travelled, 45 degrees turned, or at STOP.

Each macro-step covers states [start, end] of the rollout; its movement text comes from the
accumulated motion ("walk forward", "walk forward while turning right", "turn left", ...). A 180 degree
view is rendered at every macro-step start for the annotator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from image2sim.simulator.conventions import Action

__all__ = ["MacroStep", "ChunkConfig", "macro_steps", "movement_text"]


@dataclass(frozen=True)
class ChunkConfig:
    """Macro-step boundaries."""

    distance: float = 1.0
    """Close a macro-step after this many metres travelled."""
    turn_deg: float = 45.0
    """Close a macro-step after this much accumulated absolute turning (degrees)."""
    straight_deg: float = 20.0
    """Net turning below this (degrees) counts as going straight in the movement text."""
    still_distance: float = 0.2
    """Travel below this (metres) counts as turning in place."""


@dataclass
class MacroStep:
    """States ``start``..``end`` (inclusive indices into the rollout), their motion and a text."""

    start: int
    end: int
    distance: float
    """Metres travelled."""
    net_turn_deg: float
    """Signed net heading change in degrees (positive = left, counter-clockwise)."""
    stop: bool
    """The macro-step ends with STOP."""
    text: str


def _wrap(a: float) -> float:
    return math.remainder(a, 2 * math.pi)


def movement_text(distance: float, net_turn_deg: float, config: ChunkConfig) -> str:
    """Words for an accumulated motion."""
    side = "left" if net_turn_deg > 0 else "right"
    big = abs(net_turn_deg) >= config.straight_deg
    if distance < config.still_distance:
        if abs(net_turn_deg) < 1e-6:
            return "stay in place"
        if not big:
            return f"turn slightly {side}"
        return f"turn around to the {side}" if abs(net_turn_deg) >= 135 else f"turn {side}"
    if not big:
        return "walk forward"
    if abs(net_turn_deg) >= 75:
        return f"turn {side} and walk forward"
    return f"walk forward while turning {side}"


def macro_steps(
    actions, positions: np.ndarray, headings: np.ndarray, config: ChunkConfig | None = None
) -> list[MacroStep]:
    """Split a rollout (T actions, T + 1 states) into macro-steps."""
    cfg = config or ChunkConfig()
    acts = [int(a) for a in actions]
    if len(positions) != len(acts) + 1 or len(headings) != len(acts) + 1:
        raise ValueError(
            f"macro_steps: {len(acts)} actions need {len(acts) + 1} states, got "
            f"{len(positions)} positions and {len(headings)} headings"
        )
    out: list[MacroStep] = []
    s, dist, turn, net = 0, 0.0, 0.0, 0.0
    for t, a in enumerate(acts):
        if a == int(Action.STOP):
            if t > s:
                out.append(
                    MacroStep(
                        s, t, dist, math.degrees(net), False, movement_text(dist, math.degrees(net), cfg)
                    )
                )
            out.append(MacroStep(t, t + 1, 0.0, 0.0, True, "stop"))
            return out
        step = float(np.linalg.norm(positions[t + 1, :2] - positions[t, :2]))
        dh = _wrap(float(headings[t + 1] - headings[t]))
        dist += step
        turn += abs(dh)
        net += dh
        if dist >= cfg.distance - 1e-9 or math.degrees(turn) >= cfg.turn_deg - 1e-9:
            out.append(
                MacroStep(
                    s, t + 1, dist, math.degrees(net), False, movement_text(dist, math.degrees(net), cfg)
                )
            )
            s, dist, turn, net = t + 1, 0.0, 0.0, 0.0
    if s < len(acts):
        out.append(
            MacroStep(
                s, len(acts), dist, math.degrees(net), False, movement_text(dist, math.degrees(net), cfg)
            )
        )
    return out
