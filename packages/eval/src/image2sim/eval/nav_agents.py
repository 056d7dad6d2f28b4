"""Navigation agents for the evaluation runner: ``reset`` per episode, then ``act`` once per step.

The baselines ``random`` (VLN-CE's random action distribution), ``forward`` (N forward steps then
STOP) and ``oracle`` (the shortest-path follower of :mod:`image2sim.simulator.navigation`);
``image2nav`` (navpolicy's streaming agent, imported lazily inside the adapter) and
``image2nav_http`` (the same adapter driving a policy server, ``image2sim nav serve``). Agents are
built from picklable :class:`AgentSpec` records through the :data:`AGENTS` registry, so worker
processes can make their own.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar
from typing import Protocol as TypingProtocol

import numpy as np
from image2sim.eval.datasets import NavEpisode
from image2sim.eval.nav_env import NeuralSimBackend, RunnerError, StepObservation
from image2sim.simulator.conventions import Action

__all__ = [
    "AGENTS",
    "AgentSpec",
    "ForwardAgent",
    "Image2NavAdapter",
    "Image2NavHttpAdapter",
    "NavAgent",
    "OracleAgent",
    "RandomAgent",
    "make_agent",
    "needs_goal",
]


# ------------------------------------------------------------------------------------------ agents


class NavAgent(TypingProtocol):
    """An agent: ``reset`` per episode, then ``act`` once per step (one action id)."""

    needs_images: bool

    def reset(self, episode: NavEpisode, backend: Any, seed: int) -> None: ...

    def act(self, obs: StepObservation) -> int: ...


@dataclass
class RandomAgent:
    """VLN-CE's random baseline: i.i.d. actions from the R2R-CE training action distribution."""

    probabilities: tuple[float, float, float, float] = (0.02, 0.68, 0.15, 0.15)
    """P(STOP), P(FORWARD), P(LEFT), P(RIGHT) (VLN-CE, Krantz et al. 2020, Sec. 5 'Random')."""
    needs_images: bool = False

    def __post_init__(self) -> None:
        p = np.asarray(self.probabilities, dtype=np.float64)
        if p.shape != (4,) or (p < 0).any() or not math.isclose(float(p.sum()), 1.0, abs_tol=1e-9):
            raise ValueError(
                f"RandomAgent.probabilities must be 4 non-negative numbers summing to 1, "
                f"got {self.probabilities}"
            )
        self._p = p
        self._rng = np.random.default_rng(0)

    def reset(self, episode: NavEpisode, backend: Any, seed: int) -> None:
        self._rng = np.random.default_rng(seed)

    def act(self, obs: StepObservation) -> int:
        return int(self._rng.choice(4, p=self._p))


@dataclass
class ForwardAgent:
    """Blind baseline: ``forward_steps`` MOVE_FORWARD actions, then STOP."""

    forward_steps: int = 37
    """Forward actions before STOP. 37 follows the hand-crafted baseline of VLN-CE (Krantz et al. 2020),
    which first turns to a random heading; this agent keeps the start heading (fully deterministic)."""
    needs_images: bool = False

    def __post_init__(self) -> None:
        if int(self.forward_steps) < 0:
            raise ValueError(f"ForwardAgent.forward_steps must be >= 0, got {self.forward_steps}")
        self._t = 0

    def reset(self, episode: NavEpisode, backend: Any, seed: int) -> None:
        self._t = 0

    def act(self, obs: StepObservation) -> int:
        self._t += 1
        return int(Action.MOVE_FORWARD) if self._t <= self.forward_steps else int(Action.STOP)


@dataclass
class OracleAgent:
    """Privileged shortest-path follower (:class:`~image2sim.simulator.navigation.OracleFollower`)."""

    follower: dict = field(default_factory=dict)
    """:class:`FollowerConfig` overrides (smoothing_window, lookahead, stop_radius, ...)."""
    needs_images: bool = False
    goal_needed_for: ClassVar[str] = "it follows the planner's shortest path to the episode's goal"
    """Why the agent needs the goal: it cannot run on a split without goals (:func:`needs_goal`)."""

    def reset(self, episode: NavEpisode, backend: Any, seed: int) -> None:
        from image2sim.simulator.navigation import FollowerConfig, OracleFollower

        if not episode.has_goal:
            raise RunnerError(
                f"episode {episode.episode_id}: the oracle agent needs the goal ({self.goal_needed_for})"
            )
        if not isinstance(backend, NeuralSimBackend):
            raise RunnerError("the oracle agent needs the NeuralSimulator backend (planner access)")
        self.backend = backend
        cfg = FollowerConfig.from_dict(self.follower, "oracle.follower")
        self._f = OracleFollower(backend.planner, backend.sim.embodiment, cfg)
        self._f.reset(backend.agent_state().position, backend.goal_map)

    def act(self, obs: StepObservation) -> int:
        return int(self._f.act(self.backend.agent_state(), obs.collided))


class Image2NavAdapter:
    """navpolicy's streaming Image2Nav agent (two actions per model call) as a runner agent.

    navpolicy is imported here and only here (lazily), so ``image2sim.eval`` works without it.
    ``model``: an exported policy folder or ``"tiny"`` (an untrained tiny model, for plumbing runs).
    """

    needs_images = True

    def __init__(self, model: str = "tiny", config: str = "tiny") -> None:
        try:
            from image2sim.navpolicy.agent import Image2NavAgent
            from image2sim.navpolicy.config import load_config
            from image2sim.navpolicy.model import build_policy
        except ImportError as exc:
            raise RunnerError(f"the image2nav agent needs image2sim-navpolicy installed ({exc})") from exc
        cfg = load_config(config, {"model": {"source": model}} if model != "tiny" else None)
        self._init(Image2NavAgent(build_policy(cfg, seed=0), cfg.agent, cfg.system_prompt))

    def _init(self, agent: Any) -> None:
        self._agent = agent
        self._queue: list[int] = []
        self._executed: list[int] | None = None

    @classmethod
    def from_agent(cls, agent: Any) -> Image2NavAdapter:
        """Wrap an already built streaming agent (``reset(instruction, seed)``, ``act(rgb, executed)``)."""
        self = cls.__new__(cls)
        self._init(agent)
        return self

    def reset(self, episode: NavEpisode, backend: Any, seed: int) -> None:
        import torch

        torch.manual_seed(seed)
        self._agent.reset(episode.instruction.text, seed=seed)
        self._queue, self._executed = [], None

    def stop_allowed(self, obs: StepObservation) -> bool:
        """Whether the policy may say STOP at this observation (always; a subclass may withhold it,
        e.g. a privileged measurement of how much a better STOP would gain)."""
        return True

    def act(self, obs: StepObservation) -> int:
        if not self._queue:
            if obs.rgb is None:
                raise RunnerError("image2nav: no image in the observation")
            withheld = {} if self.stop_allowed(obs) else {"allow_stop": False}
            self._queue = [int(a) for a in self._agent.act(obs.rgb, executed=self._executed, **withheld)]
            self._executed = []
        a = self._queue.pop(0)
        self._executed.append(a)
        if a == int(Action.STOP):
            self._queue = []
        return a

    @staticmethod
    def observation_size(options: Mapping[str, Any]) -> tuple[int, int] | None:
        """The policy's pinhole input size (height, width) from its config, or None."""
        from image2sim.navpolicy.config import load_config

        model = options.get("model", "tiny")
        cfg = load_config(
            options.get("config", "tiny"), {"model": {"source": model}} if model != "tiny" else None
        )
        obs = cfg.observation
        return (obs.height, obs.width) if obs.camera == "pinhole" else None

    @property
    def wants_image(self) -> bool:
        """An image is needed at the next step only when the action queue is empty."""
        return not self._queue


class Image2NavHttpAdapter(Image2NavAdapter):
    """Image2Nav behind a policy server (``image2sim nav serve``): the same two-action adapter, its
    streaming agent a :class:`~image2sim.navpolicy.client.RemoteAgent` (one server session per
    episode). ``token_env`` names the environment variable holding the bearer token (never the token
    itself, so run records do not hold it)."""

    needs_images = True

    def __init__(self, server: str, token_env: str = "", timeout_s: float = 60.0) -> None:
        self._init(_remote_agent(server, token_env, timeout_s))

    @staticmethod
    def observation_size(options: Mapping[str, Any]) -> tuple[int, int] | None:
        """The served policy's pinhole input size (height, width), asked from the server."""
        client = _remote_agent(options["server"], options.get("token_env", ""), 60.0).client
        try:
            obs = client.info()["observation"]
        finally:
            client.close()
        return (int(obs["height"]), int(obs["width"])) if obs.get("camera") == "pinhole" else None


def _remote_agent(server: str, token_env: str, timeout_s: float) -> Any:
    try:
        from image2sim.navpolicy.client import PolicyClient, RemoteAgent, token_from_env
    except ImportError as exc:
        raise RunnerError(f"the image2nav_http agent needs image2sim-navpolicy installed ({exc})") from exc
    try:
        token = token_from_env(token_env)
    except ValueError as exc:
        raise RunnerError(str(exc)) from exc
    return RemoteAgent(PolicyClient(server, token=token, timeout_s=timeout_s))


@dataclass(frozen=True)
class AgentSpec:
    """A picklable agent description: registry name + constructor options."""

    name: str
    """``random``, ``forward``, ``oracle`` or ``image2nav``."""
    options: Mapping[str, Any] = field(default_factory=dict)
    """Keyword arguments of the agent class."""


AGENTS: dict[str, Callable[..., Any]] = {
    "random": RandomAgent,
    "forward": ForwardAgent,
    "oracle": OracleAgent,
    "image2nav": Image2NavAdapter,
    "image2nav_http": Image2NavHttpAdapter,
}
"""Agent registry."""


def _forward_turn_agent(**options: Any) -> Any:
    """navpolicy's forward-until-collision-then-turn baseline (one implementation, imported lazily)."""
    try:
        from image2sim.navpolicy.baselines import ForwardTurnAgent
    except ImportError as exc:
        raise RunnerError(f"the forward_turn agent needs image2sim-navpolicy installed ({exc})") from exc
    return ForwardTurnAgent(**options)


AGENTS["forward_turn"] = _forward_turn_agent


def needs_goal(agent: str) -> str | None:
    """Why the registered agent needs each episode's goal (its ``goal_needed_for``), or None when it
    runs on splits without goals (test splits: random, forward, image2nav...)."""
    return getattr(AGENTS.get(agent), "goal_needed_for", None)


def make_agent(spec: AgentSpec) -> Any:
    """Build an agent from its spec; unknown names and options are errors naming them."""
    if spec.name not in AGENTS:
        raise RunnerError(f"unknown agent {spec.name!r}; known: {sorted(AGENTS)}")
    try:
        return AGENTS[spec.name](**dict(spec.options))
    except TypeError as exc:
        raise RunnerError(f"agent {spec.name!r}: bad options {dict(spec.options)} ({exc})") from exc
