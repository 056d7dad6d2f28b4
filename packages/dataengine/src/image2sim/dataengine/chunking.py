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

__all__ = ["MacroStep", "ChunkConfig", "PathFeatureConfig", "macro_steps", "movement_text", "path_features"]


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


@dataclass(frozen=True)
class PathFeatureConfig:
    """What counts as a doorway or a staircase along a path (landmark-free instructions)."""

    stairs_rise: float = 0.25
    """A macro-step whose feet height changes by more than this (metres) goes up or down stairs."""
    doorway_clearance: float = 0.5
    """A doorway: the clearance to the nearest obstacle drops below this (a passage under 1 m wide)..."""
    open_clearance: float = 0.8
    """...between states within ``flank`` metres before and after it where it is above this."""
    flank: float = 1.5


def path_features(
    steps: list[MacroStep],
    positions: np.ndarray,
    clearance: np.ndarray,
    config: PathFeatureConfig | None = None,
) -> list[list[str]]:
    """Per macro-step: ``stairs_up`` / ``stairs_down`` (feet height change) and ``doorway`` (a narrow
    point flanked by open space, from the clearance of every state, in metres). Each doorway is given
    to the macro-step where the path is narrowest."""
    cfg = config or PathFeatureConfig()
    pos = np.asarray(positions, dtype=np.float64)
    clear = np.asarray(clearance, dtype=np.float64)
    out: list[list[str]] = [[] for _ in steps]
    for k, m in enumerate(steps):
        rise = float(pos[m.end, 2] - pos[m.start, 2])
        if rise > cfg.stairs_rise:
            out[k].append("stairs_up")
        elif rise < -cfg.stairs_rise:
            out[k].append("stairs_down")
    along = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(pos[:, :2], axis=0), axis=1))))
    narrow = clear < cfg.doorway_clearance
    t = 0
    while t < len(clear):
        if not narrow[t]:
            t += 1
            continue
        run_end = t
        while run_end + 1 < len(clear) and narrow[run_end + 1]:
            run_end += 1
        before = (along >= along[t] - cfg.flank) & (np.arange(len(clear)) < t)
        after = (along <= along[run_end] + cfg.flank) & (np.arange(len(clear)) > run_end)
        wide_before = before.any() and clear[before].max() > cfg.open_clearance
        wide_after = after.any() and clear[after].max() > cfg.open_clearance
        short = along[run_end] - along[t] <= cfg.flank  # a corridor is not a doorway
        if wide_before and wide_after and short:
            tightest = t + int(np.argmin(clear[t : run_end + 1]))
            for k, m in enumerate(steps):
                if m.start <= tightest < max(m.end, m.start + 1) and not m.stop:
                    if "doorway" not in out[k]:
                        out[k].append("doorway")
                    break
        t = run_end + 1
    return out
