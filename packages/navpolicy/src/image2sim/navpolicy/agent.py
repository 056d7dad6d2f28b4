"""Streaming Image2Nav inference with KV-cache reuse.

Each call to :meth:`Image2NavAgent.act` adds one observation, builds the sparse-dense context (up to
``sparse_frames`` history frames on a uniform stride grid over the episode plus the ``dense_frames``
most recent frames), and greedily decodes the next two actions. The KV cache keeps the longest prefix
of the previous step's tokens (system prompt, history turns, the previous reply) that the new context
shares — compared token by token, images by frame identity — and only the rest is run through the
model. Positions (Qwen3-VL's 3-D M-RoPE) are computed for the whole context every time, so the cached
and recomputed paths see identical inputs; ``reuse_cache=False`` recomputes everything (the
reference the tests compare against).

The history grid uses a power-of-two stride, so the history part of the context changes only when
the stride doubles or a new grid frame enters; while the episode has at most
``sparse_frames + dense_frames`` observations, the context only grows and is reused entirely.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from image2sim.navpolicy.actions import ACTIONS_PER_STEP, parse_actions
from image2sim.navpolicy.collate import image_end_positions, image_token_counts
from image2sim.navpolicy.config import AgentConfig
from image2sim.navpolicy.data import select_context_frames
from image2sim.navpolicy.model import NavPolicy, base_qwen
from image2sim.navpolicy.prompting import IMAGE_TOKEN, PromptBuilder, Turn, common_prefix_length
from image2sim.simulator.conventions import Action


@dataclass
class StepInfo:
    """Diagnostics of one :meth:`Image2NavAgent.act` call."""

    actions: list[Action]
    generated_ids: list[int]
    context_tokens: int
    reused_tokens: int
    fallback: bool
    step_logits: list[torch.Tensor] = field(default_factory=list)
    goal_probability: float | None = None
    """The goal head's probability that the instruction's goal is in view (``agent.stop_gate`` on)."""
    stop_allowed: bool = True
    """Whether STOP could be decoded at this step (the caller's ``allow_stop`` and the gate)."""


def check_stop_gate(policy: NavPolicy, cfg: AgentConfig) -> None:
    """``agent.stop_gate`` needs a policy with a goal head; refuse it by name otherwise."""
    if cfg.stop_gate is not None and policy.goal_head is None:
        raise ValueError(
            f"agent.stop_gate={cfg.stop_gate} needs a policy with a goal head (an export with "
            "goal_head.safetensors: train with train.goal_aux_weight > 0); this policy has none"
        )


def last_image_position(mm: list[int]) -> int:
    """Index of the last image token of a prompt (the newest observation's last token: the last of
    the collator's :func:`~image2sim.navpolicy.collate.image_end_positions`)."""
    ends = image_end_positions(torch.tensor([mm]))
    if not len(ends):
        raise ValueError("the prompt holds no image")
    return int(ends[-1, 1])


class Image2NavAgent:
    """Greedy streaming policy: ``reset(instruction)``, then ``act(rgb)`` -> two actions per step."""

    def __init__(self, policy: NavPolicy, cfg: AgentConfig, system_prompt: str) -> None:
        self.policy = policy
        self.cfg = cfg
        self.qwen = base_qwen(policy.model)
        self.prompts = PromptBuilder(policy.tokenizer, policy.codec, system_prompt)
        self.im_end_id = self.prompts.im_end_id
        check_stop_gate(policy, cfg)
        self.history: list[StepInfo] = []
        self.reset("")

    # ---------------------------------------------------------------------------------------- state
    def reset(self, instruction: str, seed: int = 0) -> None:
        """Start a new episode (clears frames, replies and the KV cache)."""
        self.instruction = instruction
        self.seed = seed
        self.frames: list[np.ndarray] = []
        self.executed: list[tuple[int, ...]] = []  # executed[k]: actions between frame k-1 and frame k
        self.replies: list[tuple[int, ...]] = []
        self._pixels: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        self._cache = None
        self._cache_keys: list[tuple] = []
        self._rope_cache: torch.Tensor | None = None
        self.history = []

    def _image(self, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        if k not in self._pixels:
            out = self.policy.image_processor(images=[self.frames[k]], return_tensors="pt")
            self._pixels[k] = (out["pixel_values"], out["image_grid_thw"])
        return self._pixels[k]

    def _context(self):
        n = len(self.frames)
        idx = select_context_frames(n, self.cfg.sparse_frames, self.cfg.dense_frames)
        turns, prev = [], None
        for k in idx:
            executed = (
                () if prev is None else tuple(a for j in range(prev + 1, k + 1) for a in self.executed[j])
            )
            n_tok = image_token_counts(self._image(k)[1], self.policy.image_processor.merge_size)[0]
            target = self.replies[k] if k < n - 1 else None
            turns.append(Turn(frame_key=k, num_image_tokens=n_tok, executed=executed, target=target))
            prev = k
        return idx, turns

    # ------------------------------------------------------------------------------------ model I/O
    def _rope(self, ids: list[int], mm: list[int], grids: torch.Tensor | None) -> torch.Tensor:
        """(3, L) M-RoPE positions of a token sequence that starts at position 0."""
        if grids is None:
            return torch.arange(len(ids)).view(1, -1).expand(3, -1)
        rope, _ = self.qwen.model.get_rope_index(
            torch.tensor([ids]), mm_token_type_ids=torch.tensor([mm]), image_grid_thw=grids
        )
        return rope[:, 0]

    def _run(self, ids, mm, keys, frame_idx: list[int], start: int, goal_at: int | None = None):
        """Feed tokens ``[start:]`` given a cache holding ``[:start]``; returns last-position logits,
        the start actually used and, with ``goal_at`` (a position among the fed tokens), the goal
        head's probability there (else None)."""
        # Never split an image block: move ``start`` back to the block's first token.
        while 0 < start < len(mm) and mm[start] == IMAGE_TOKEN and mm[start - 1] == IMAGE_TOKEN:
            start -= 1
        if self._cache is None or start == 0:
            from transformers import DynamicCache

            self._cache = DynamicCache(config=self.qwen.config.text_config)
            start = 0
        else:
            excess = self._cache.get_seq_length() - start
            if excess > 0:
                self._cache.crop(-excess)
        # Images whose tokens are new (blocks are contiguous and in frame order).
        new_frames, seen = [], set()
        for j in range(start, len(keys)):
            fk = keys[j][1]
            if mm[j] == IMAGE_TOKEN and fk not in seen:
                seen.add(fk)
                new_frames.append(fk)
        new_grids = torch.cat([self._image(k)[1] for k in new_frames]) if new_frames else None
        if start > 0 and self.cfg.reuse_cache and self._rope_cache is not None:
            # Qwen3-VL positions continue at max(previous) + 1 after any text or image group, so the
            # suffix's positions are its own, shifted; the cached prefix's positions are unchanged.
            prefix = self._rope_cache[:, :start]
            rope = torch.cat(
                [prefix, self._rope(ids[start:], mm[start:], new_grids) + int(prefix.max()) + 1], 1
            )
        else:
            grids = torch.cat([self._image(k)[1] for k in frame_idx]) if frame_idx else None
            rope = self._rope(ids, mm, grids)
        self._rope_cache = rope
        text = torch.arange(start, len(ids)).view(1, 1, -1)  # plain index: drives the causal mask
        pos = torch.cat([text, rope[:, None, start:]], dim=0)
        kwargs = {}
        if new_frames:
            kwargs["pixel_values"] = torch.cat([self._image(k)[0] for k in new_frames])
            kwargs["image_grid_thw"] = new_grids
        out = self.qwen(
            input_ids=torch.tensor([ids[start:]]),
            mm_token_type_ids=torch.tensor([mm[start:]]),
            position_ids=pos,
            past_key_values=self._cache,
            use_cache=True,
            logits_to_keep=1,
            output_hidden_states=goal_at is not None,
            **kwargs,
        )
        goal_p = None
        if goal_at is not None:
            if goal_at < start:
                raise ValueError(f"goal_at={goal_at} lies in the cached prefix (fed from {start})")
            goal_p = float(self.policy.goal_head.probability(out.hidden_states, 0, goal_at - start))
        self._cache_keys = list(keys)
        return out.logits[0, -1].float(), start, goal_p

    # ------------------------------------------------------------------------------------------ act
    def _observe(self, rgb: np.ndarray, executed: list[int] | None):
        """Record the new observation (and what was executed since the last one); encode the context."""
        self.qwen.eval()
        if self.frames:
            if executed is None:
                prev = list(self.replies[-1])
                executed = prev[: prev.index(Action.STOP) + 1] if Action.STOP in prev else prev
            self.executed.append(tuple(int(a) for a in executed))
        else:
            self.executed.append(())
        self.frames.append(np.asarray(rgb))
        frame_idx, turns = self._context()
        return frame_idx, self.prompts.encode(self.instruction, turns, add_generation_prompt=True)

    @torch.no_grad()
    def act(
        self, rgb: np.ndarray, executed: list[int] | None = None, allow_stop: bool = True
    ) -> list[Action]:
        """Observe ``rgb`` (H, W, 3 uint8) and return the next two actions.

        ``executed`` lists the actions actually carried out since the previous call (default: the
        previous reply, cut after a STOP). ``allow_stop=False`` decodes the best actions other than
        STOP (a stop gate decided outside the language model; unconstrained decoding replaces a
        STOP by ``fallback_action``).
        """
        frame_idx, enc = self._observe(rgb, executed)
        ids, mm, keys = list(enc.input_ids), list(enc.mm_token_type_ids), list(enc.keys)
        reuse = common_prefix_length(self._cache_keys, keys) if self.cfg.reuse_cache else 0
        reuse = min(reuse, len(ids) - 1)  # always run at least one token to get logits
        gate = self.cfg.stop_gate
        # The newest frame's tokens are never cached (it was just appended), so the head's position
        # is always among the fed ones.
        goal_at = last_image_position(mm) if gate is not None else None
        logits, start, goal_p = self._run(ids, mm, keys, frame_idx, reuse, goal_at)
        if gate is not None:
            allow_stop = allow_stop and goal_p >= gate
        exclude = () if allow_stop else (Action.STOP,)
        generated, step_logits = [], [logits]
        actions: list[Action] = []
        fallback = False
        if self.cfg.constrained:
            for position in range(ACTIONS_PER_STEP):
                prefix: list[int] = []
                while True:
                    allowed = self.policy.codec.allowed_next(position, prefix, exclude)
                    tok = allowed[int(torch.argmax(logits[allowed]))]
                    prefix.append(tok)
                    generated.append(tok)
                    done = self.policy.codec.match(position, prefix)
                    last = done is not None and position == ACTIONS_PER_STEP - 1
                    if not last:
                        ids, mm, keys = ids + [tok], mm + [0], keys + [(tok, None, 0)]
                        logits, _, _ = self._run(ids, mm, keys, frame_idx, len(ids) - 1)
                        step_logits.append(logits)
                    if done is not None:
                        actions.append(done)
                        break
        else:
            for _ in range(self.cfg.max_new_tokens):
                tok = int(torch.argmax(logits))
                generated.append(tok)
                if tok == self.im_end_id:
                    break
                ids, mm, keys = ids + [tok], mm + [0], keys + [(tok, None, 0)]
                logits, _, _ = self._run(ids, mm, keys, frame_idx, len(ids) - 1)
                step_logits.append(logits)
            text = self.policy.tokenizer.decode([t for t in generated if t != self.im_end_id])
            actions = parse_actions(text, self.policy.codec.texts)[:ACTIONS_PER_STEP]
            if exclude and Action.STOP in actions:
                fallback = True
                actions = [Action(self.cfg.fallback_action) if a in exclude else a for a in actions]
            if len(actions) < ACTIONS_PER_STEP:
                fallback = True
                actions = actions + [Action(self.cfg.fallback_action)] * (ACTIONS_PER_STEP - len(actions))
        self.replies.append(tuple(int(a) for a in actions))
        self.history.append(
            StepInfo(
                actions=list(actions),
                generated_ids=generated,
                context_tokens=len(enc),
                reused_tokens=start,
                fallback=fallback,
                step_logits=step_logits,
                goal_probability=goal_p,
                stop_allowed=allow_stop,
            )
        )
        return list(actions)


class BatchedImage2NavAgent:
    """Several episodes stepped together: one left-padded model call per decoding step.

    Every step runs each active agent's full context (contexts of different episodes change
    differently, so there is no cross-step cache reuse here; use :class:`Image2NavAgent` for a
    single stream). Decoding is constrained greedy; the actions equal those of independent
    :class:`Image2NavAgent` instances (tested). ``None`` observations skip an agent for that step.
    """

    def __init__(self, policy: NavPolicy, cfg: AgentConfig, system_prompt: str, num_agents: int) -> None:
        if num_agents < 1:
            raise ValueError("num_agents must be >= 1")
        self.agents = [Image2NavAgent(policy, cfg, system_prompt) for _ in range(num_agents)]
        self.policy = policy
        self.qwen = self.agents[0].qwen
        self.pad_id = int(policy.tokenizer.pad_token_id)
        self.gate = cfg.stop_gate
        """``agent.stop_gate`` of every row (None: off)."""

    def reset(self, index: int, instruction: str, seed: int = 0) -> None:
        """Start a new episode for agent ``index``."""
        self.agents[index].reset(instruction, seed)

    @torch.no_grad()
    def act(self, observations, executed=None, allow_stop=None) -> list[list[Action] | None]:
        """Two actions for every agent whose observation is not None (None for the others);
        ``allow_stop`` (one bool per agent) withholds STOP like :meth:`Image2NavAgent.act`'s."""
        from transformers import DynamicCache

        n = len(self.agents)
        if len(observations) != n:
            raise ValueError(f"expected {n} observations, got {len(observations)}")
        if allow_stop is not None and len(allow_stop) != n:
            raise ValueError(f"expected {n} allow_stop flags, got {len(allow_stop)}")
        gate = self.gate
        active = [i for i, o in enumerate(observations) if o is not None]
        out: list[list[Action] | None] = [None] * n
        if not active:
            return out
        encs, frames = [], []
        for i in active:
            fi, enc = self.agents[i]._observe(observations[i], None if executed is None else executed[i])
            encs.append(enc)
            frames.append(fi)
        B, L = len(active), max(len(e) for e in encs)
        ids = torch.full((B, L), self.pad_id, dtype=torch.long)
        attn = torch.zeros((B, L), dtype=torch.long)
        mm = torch.zeros((B, L), dtype=torch.long)
        pos = torch.zeros((4, B, L), dtype=torch.long)
        pixels, grids, next_rope, goal_at = [], [], [], []
        for b, (i, enc, fi) in enumerate(zip(active, encs, frames, strict=True)):
            agent, m, off = self.agents[i], len(enc), L - len(enc)
            goal_at.append(off + last_image_position(list(enc.mm_token_type_ids)))
            ids[b, off:] = torch.tensor(enc.input_ids)
            attn[b, off:] = 1
            mm[b, off:] = torch.tensor(enc.mm_token_type_ids)
            g = torch.cat([agent._image(k)[1] for k in fi])
            rope = agent._rope(enc.input_ids, enc.mm_token_type_ids, g)
            pos[0, b, off:] = torch.arange(m)
            pos[1:, b, off:] = rope
            next_rope.append(int(rope.max()) + 1)
            pixels += [agent._image(k)[0] for k in fi]
            grids.append(g)
        cache = DynamicCache(config=self.qwen.config.text_config)
        res = self.qwen(
            input_ids=ids,
            attention_mask=attn,
            mm_token_type_ids=mm,
            position_ids=pos,
            pixel_values=torch.cat(pixels),
            image_grid_thw=torch.cat(grids),
            past_key_values=cache,
            use_cache=True,
            logits_to_keep=1,
            output_hidden_states=gate is not None,
        )
        logits = res.logits[:, -1].float()
        allowed_stop = [True if allow_stop is None else bool(allow_stop[i]) for i in active]
        goal_p: list[float | None] = [None] * B
        if gate is not None:
            head = self.policy.goal_head
            goal_p = [
                float(v) for v in head.probability(res.hidden_states, torch.arange(B), torch.tensor(goal_at))
            ]
            allowed_stop = [a and p >= gate for a, p in zip(allowed_stop, goal_p, strict=True)]
        exclude = [() if a else (Action.STOP,) for a in allowed_stop]
        codec = self.policy.codec
        position, prefix = [0] * B, [[] for _ in range(B)]
        actions: list[list[Action]] = [[] for _ in range(B)]
        generated: list[list[int]] = [[] for _ in range(B)]
        seen_logits: list[list[torch.Tensor]] = [[] for _ in range(B)]
        text_next = torch.tensor([len(e) for e in encs])
        rope_next = torch.tensor(next_rope)
        while True:
            toks = []
            for b in range(B):
                if position[b] >= ACTIONS_PER_STEP:
                    toks.append(self.pad_id)  # finished: a dummy token whose output is never read
                    continue
                allowed = codec.allowed_next(position[b], prefix[b], exclude[b])
                seen_logits[b].append(logits[b])
                tok = allowed[int(torch.argmax(logits[b, allowed]))]
                prefix[b].append(tok)
                generated[b].append(tok)
                done = codec.match(position[b], prefix[b])
                if done is not None:
                    actions[b].append(done)
                    position[b] += 1
                    prefix[b] = []
                toks.append(tok)
            if all(p >= ACTIONS_PER_STEP for p in position):
                break
            attn = torch.cat([attn, torch.ones((B, 1), dtype=torch.long)], 1)
            step_pos = torch.cat([text_next.view(1, B, 1), rope_next.view(1, B, 1).expand(3, B, 1)], 0)
            res = self.qwen(
                input_ids=torch.tensor(toks).view(B, 1),
                attention_mask=attn,
                position_ids=step_pos,
                past_key_values=cache,
                use_cache=True,
                logits_to_keep=1,
            )
            logits = res.logits[:, -1].float()
            text_next, rope_next = text_next + 1, rope_next + 1
        for b, i in enumerate(active):
            agent = self.agents[i]
            agent.replies.append(tuple(int(a) for a in actions[b]))
            agent.history.append(
                StepInfo(
                    actions=list(actions[b]),
                    generated_ids=generated[b],
                    context_tokens=len(encs[b]),
                    reused_tokens=0,
                    fallback=False,
                    step_logits=seen_logits[b],
                    goal_probability=goal_p[b],
                    stop_allowed=allowed_stop[b],
                )
            )
            out[i] = list(actions[b])
        return out
