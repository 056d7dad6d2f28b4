"""Baseline navigation agents behind the evaluation runner's agent interface.

Interface (:class:`image2sim.eval.runner.NavAgent`): ``needs_images``, ``reset(episode, backend,
seed)``, ``act(obs) -> action id`` with ``obs`` a :class:`~image2sim.eval.runner.StepObservation`
(``collided`` says whether the last action hit an obstacle).

One implementation per baseline, repository-wide:

* ``random`` (VLN-CE's i.i.d. actions), ``forward`` (N forward steps then STOP) and ``oracle`` (the
  shortest-path follower) live in :mod:`image2sim.eval.runner` and are re-exported here (imported
  lazily: navpolicy does not need eval installed until a baseline is asked for);
* ``forward_turn`` (forward until a collision, then turn) lives here: :class:`ForwardTurnAgent`;
  the runner's registry imports it lazily.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

import numpy as np
from image2sim.simulator.conventions import Action

_FROM_EVAL = ("RandomAgent", "ForwardAgent", "OracleAgent")


@dataclass
class ForwardTurnAgent:
    """Blind bump-and-turn: MOVE_FORWARD until a step collides, then turn ``turn_steps`` times.

    The turn direction (left/right) and the number of turns (uniform in ``[min_turns, max_turns]``)
    are drawn per collision from the episode seed, so an episode is a function of its seed. STOP
    after ``stop_after`` actions (``0``: never; the runner's step limit ends the episode).
    """

    min_turns: int = 2
    """Fewest turns after a collision (2 x 15 deg = 30 deg)."""
    max_turns: int = 12
    """Most turns after a collision (12 x 15 deg = 180 deg)."""
    stop_after: int = 0
    """Issue STOP after this many actions (0 = never)."""
    needs_images: bool = False

    def __post_init__(self) -> None:
        if not 1 <= int(self.min_turns) <= int(self.max_turns):
            raise ValueError(
                f"ForwardTurnAgent: need 1 <= min_turns <= max_turns, got {self.min_turns}, {self.max_turns}"
            )
        if int(self.stop_after) < 0:
            raise ValueError(f"ForwardTurnAgent.stop_after must be >= 0, got {self.stop_after}")
        self.reset(None, None, 0)

    def reset(self, episode: Any, backend: Any, seed: int) -> None:
        self._rng = np.random.default_rng(seed)
        self._turns: list[int] = []
        self._t = 0

    def act(self, obs: Any) -> int:
        self._t += 1
        if self.stop_after and self._t > self.stop_after:
            return int(Action.STOP)
        if bool(getattr(obs, "collided", False)) and not self._turns:
            turn = int(Action.TURN_LEFT if self._rng.random() < 0.5 else Action.TURN_RIGHT)
            self._turns = [turn] * int(self._rng.integers(self.min_turns, self.max_turns + 1))
        if self._turns:
            return self._turns.pop()
        return int(Action.MOVE_FORWARD)


def __getattr__(name: str):
    if name in _FROM_EVAL:
        try:
            return getattr(importlib.import_module("image2sim.eval.runner"), name)
        except ImportError as exc:  # pragma: no cover - depends on the installation
            raise ImportError(
                f"navpolicy.baselines.{name} lives in image2sim-eval, which is not installed"
            ) from exc
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


BASELINES = ("random", "forward", "forward_turn", "oracle")
"""Names accepted by :func:`make_baseline`."""


def make_baseline(name: str, **options: Any):
    """A baseline agent by name (``random``, ``forward``, ``forward_turn``, ``oracle``)."""
    classes = {
        "random": "RandomAgent",
        "forward": "ForwardAgent",
        "oracle": "OracleAgent",
    }
    if name == "forward_turn":
        return ForwardTurnAgent(**options)
    if name not in classes:
        raise ValueError(f"unknown baseline {name!r}; known: {list(BASELINES)}")
    return __getattr__(classes[name])(**options)
