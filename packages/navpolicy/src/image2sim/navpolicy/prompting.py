"""Chat prompts for Image2Nav, built directly as token ids with exact label positions.

Layout (Qwen chat format; ``<img>`` = ``<|vision_start|>`` + n x ``<|image_pad|>`` + ``<|vision_end|>``)::

    <|im_start|>system\\n{system prompt}\\nInstruction: {instruction}<|im_end|>\\n
    <|im_start|>user\\n<img><|im_end|>\\n<|im_start|>assistant\\nFORWARD FORWARD<|im_end|>\\n
    <|im_start|>user\\nExecuted: FORWARD FORWARD LEFT\\n<img><|im_end|>\\n
    <|im_start|>assistant\\nLEFT FORWARD<|im_end|>\\n
    ...
    <|im_start|>user\\nExecuted: ...\\n<img><|im_end|>\\n<|im_start|>assistant\\n        <- generation prompt

Each user turn carries one observation and the actions executed since the previous observation in
the context; the assistant replies with the next two actions. The same layout as chat messages
(:meth:`PromptBuilder.messages`) and a Jinja chat template (:func:`chat_template`, saved with every
export) come from the same pieces below, so ``apply_chat_template`` reproduces the prompt. Labels
are set only on the tokens of the two action words of each reply (not on the image, prompt,
``<|im_end|>`` or separators outside action encodings). Building ids directly (instead of templating
text and re-tokenizing) makes label positions exact and lets the agent compare contexts token by
token for KV-cache reuse.
"""

from __future__ import annotations

import json
from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field

from image2sim.navpolicy.actions import ACTIONS_PER_STEP, ActionCodec, actions_to_text
from image2sim.navpolicy.tokenizer import check_special_tokens

IGNORE_INDEX = -100
"""Label value ignored by the cross-entropy loss."""

TEXT_TOKEN, IMAGE_TOKEN = 0, 1
"""``mm_token_type_ids`` values (Qwen3-VL: 0 text, 1 image, 2 video)."""

TURN_END = "<|im_end|>\n"
"""Closes every turn."""

IMAGE_OPEN, IMAGE_PAD, IMAGE_CLOSE = "<|vision_start|>", "<|image_pad|>", "<|vision_end|>"
"""An image is ``IMAGE_OPEN`` + n x ``IMAGE_PAD`` + ``IMAGE_CLOSE`` (the processor expands one pad)."""


def turn_start(role: str) -> str:
    """Opens a turn of ``role`` (system, user, assistant)."""
    return f"<|im_start|>{role}\n"


def chat_template() -> str:
    """The Jinja chat template of the policy's prompt, built from the same pieces as
    :meth:`PromptBuilder.encode`: messages from :meth:`PromptBuilder.messages` (text items verbatim,
    ``{"type": "image"}`` as one image placeholder) render to exactly the encoded prompt."""
    q = json.dumps  # a JSON string literal is a valid Jinja string literal with the same escapes
    image = q(IMAGE_OPEN + IMAGE_PAD + IMAGE_CLOSE)
    return (
        "{%- for message in messages -%}"
        # turn_start itself, with the role filled in by Jinja
        f"{{{{- {q(turn_start('@'))}.replace('@', message['role']) -}}}}"
        "{%- if message['content'] is string -%}{{- message['content'] -}}"
        "{%- else -%}{%- for item in message['content'] -%}"
        f"{{%- if item['type'] == 'image' -%}}{{{{- {image} -}}}}"
        "{%- elif item['type'] == 'text' -%}{{- item['text'] -}}{%- endif -%}"
        "{%- endfor -%}{%- endif -%}"
        f"{{{{- {q(TURN_END)} -}}}}"
        "{%- endfor -%}"
        f"{{%- if add_generation_prompt -%}}{{{{- {q(turn_start('assistant'))} -}}}}{{%- endif -%}}"
    )


@dataclass(frozen=True)
class Turn:
    """One observation in the context.

    Attributes:
        frame_key: identity of the observation image (e.g. its step index); two turns with equal keys
            and token counts must show the same image (used to decide KV-cache reuse).
        num_image_tokens: ``<|image_pad|>`` tokens of the image (grid h*w / merge^2).
        executed: actions executed since the previous observation of the context (empty first).
        target: the assistant reply (two actions); ``None`` only for the last turn of a generation
            prompt.
    """

    frame_key: Hashable
    num_image_tokens: int
    executed: tuple[int, ...] = ()
    target: tuple[int, ...] | None = None


@dataclass
class EncodedPrompt:
    """Token-level encoding of a prompt; all lists have the same length."""

    input_ids: list[int] = field(default_factory=list)
    mm_token_type_ids: list[int] = field(default_factory=list)
    labels: list[int] = field(default_factory=list)
    keys: list[tuple] = field(default_factory=list)
    """Per-token identity ``(token_id, frame_key or None, index inside the image)``."""

    def __len__(self) -> int:
        return len(self.input_ids)

    def extend_text(self, ids: Sequence[int], labelled: bool = False) -> None:
        self.input_ids.extend(ids)
        self.mm_token_type_ids.extend([TEXT_TOKEN] * len(ids))
        self.labels.extend(ids if labelled else [IGNORE_INDEX] * len(ids))
        self.keys.extend((i, None, 0) for i in ids)

    def extend_image(self, pad_id: int, n: int, frame_key: Hashable) -> None:
        self.input_ids.extend([pad_id] * n)
        self.mm_token_type_ids.extend([IMAGE_TOKEN] * n)
        self.labels.extend([IGNORE_INDEX] * n)
        self.keys.extend((pad_id, frame_key, j) for j in range(n))


class PromptBuilder:
    """Encodes navigation conversations for one tokenizer and action codec."""

    def __init__(self, tokenizer, codec: ActionCodec, system_prompt: str) -> None:
        self.tokenizer = tokenizer
        self.codec = codec
        self.system_prompt = system_prompt
        ids = check_special_tokens(tokenizer)
        self.image_pad_id = ids[IMAGE_PAD]
        self.im_end_id = ids["<|im_end|>"]
        self._cache: dict[str, list[int]] = {}

    def _enc(self, text: str) -> list[int]:
        if text not in self._cache:
            if len(self._cache) > 4096:
                self._cache.clear()
            self._cache[text] = list(self.tokenizer(text, add_special_tokens=False)["input_ids"])
        return self._cache[text]

    def system_text(self, instruction: str) -> str:
        """The system turn's content."""
        return f"{self.system_prompt}\nInstruction: {instruction.strip()}"

    def executed_text(self, executed: Sequence[int]) -> str:
        """The user turn's text before its image: the actions executed since the previous one."""
        return f"Executed: {actions_to_text(executed, self.codec.texts)}\n" if executed else ""

    def _check_turn(self, k: int, turn: Turn, last: bool, add_generation_prompt: bool) -> None:
        """Raise ``ValueError`` naming turn ``k`` when it cannot be part of the prompt."""
        if turn.target is None and not (last and add_generation_prompt):
            raise ValueError(
                f"turn {k} has no target actions (only the last turn of a generation prompt may)"
            )
        if turn.target is not None and last and add_generation_prompt:
            raise ValueError("the last turn of a generation prompt must not have a target")
        if turn.num_image_tokens <= 0:
            raise ValueError(f"turn {k}: num_image_tokens must be positive, got {turn.num_image_tokens}")
        if turn.target is not None and len(turn.target) != ACTIONS_PER_STEP:
            raise ValueError(f"turn {k}: target must hold {ACTIONS_PER_STEP} actions, got {turn.target}")

    def messages(
        self, instruction: str, turns: Sequence[Turn], add_generation_prompt: bool = False
    ) -> list[dict]:
        """The conversation as chat messages (``role`` + ``content`` items, images as
        ``{"type": "image"}`` in the order of ``turns``): :func:`chat_template` renders them, with the
        same ``add_generation_prompt``, to the text of :meth:`encode` (one pad per image)."""
        if not turns:
            raise ValueError("a navigation prompt needs at least one observation turn")
        out = [{"role": "system", "content": [{"type": "text", "text": self.system_text(instruction)}]}]
        for k, turn in enumerate(turns):
            self._check_turn(k, turn, k == len(turns) - 1, add_generation_prompt)
            user = [{"type": "text", "text": self.executed_text(turn.executed)}] if turn.executed else []
            out.append({"role": "user", "content": [*user, {"type": "image"}]})
            if turn.target is not None:
                reply = actions_to_text(turn.target, self.codec.texts)
                out.append({"role": "assistant", "content": [{"type": "text", "text": reply}]})
        return out

    def encode(
        self, instruction: str, turns: Sequence[Turn], add_generation_prompt: bool = False
    ) -> EncodedPrompt:
        """Encode a conversation. With ``add_generation_prompt`` the last turn must have no target and
        the prompt ends right after ``<|im_start|>assistant\\n``; otherwise every turn needs a target."""
        if not turns:
            raise ValueError("a navigation prompt needs at least one observation turn")
        out = EncodedPrompt()
        out.extend_text(self._enc(turn_start("system") + self.system_text(instruction) + TURN_END))
        for k, turn in enumerate(turns):
            self._check_turn(k, turn, k == len(turns) - 1, add_generation_prompt)
            out.extend_text(self._enc(turn_start("user") + self.executed_text(turn.executed) + IMAGE_OPEN))
            out.extend_image(self.image_pad_id, turn.num_image_tokens, turn.frame_key)
            out.extend_text(self._enc(IMAGE_CLOSE + TURN_END + turn_start("assistant")))
            if turn.target is None:
                break
            for piece in self.codec.encode(turn.target):
                out.extend_text(piece, labelled=True)
            out.extend_text(self._enc(TURN_END))
        return out


def common_prefix_length(a: Sequence[tuple], b: Sequence[tuple]) -> int:
    """Number of leading positions where two key sequences agree."""
    n = min(len(a), len(b))
    i = 0
    while i < n and a[i] == b[i]:
        i += 1
    return i
