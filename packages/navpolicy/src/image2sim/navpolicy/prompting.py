"""Chat prompts for Image2Nav, built directly as token ids with exact label positions.

Layout (Qwen chat format; ``<img>`` = ``<|vision_start|>`` + n x ``<|image_pad|>`` + ``<|vision_end|>``)::

    <|im_start|>system\\n{system prompt}\\nInstruction: {instruction}<|im_end|>\\n
    <|im_start|>user\\n<img><|im_end|>\\n<|im_start|>assistant\\nFORWARD FORWARD<|im_end|>\\n
    <|im_start|>user\\nExecuted: FORWARD FORWARD LEFT\\n<img><|im_end|>\\n
    <|im_start|>assistant\\nLEFT FORWARD<|im_end|>\\n
    ...
    <|im_start|>user\\nExecuted: ...\\n<img><|im_end|>\\n<|im_start|>assistant\\n        <- generation prompt

Each user turn carries one observation and the actions executed since the previous observation in
the context; the assistant replies with the next two actions. Labels are set only on the tokens of
the two action words of each reply (not on the image, prompt, ``<|im_end|>`` or separators outside
action encodings). Building ids directly (instead of templating text and re-tokenizing) makes label
positions exact and lets the agent compare contexts token by token for KV-cache reuse.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field

from image2sim.navpolicy.actions import ACTIONS_PER_STEP, ActionCodec, actions_to_text
from image2sim.navpolicy.tokenizer import check_special_tokens

IGNORE_INDEX = -100
"""Label value ignored by the cross-entropy loss."""

TEXT_TOKEN, IMAGE_TOKEN = 0, 1
"""``mm_token_type_ids`` values (Qwen3-VL: 0 text, 1 image, 2 video)."""


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
        self.image_pad_id = ids["<|image_pad|>"]
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

    def encode(
        self, instruction: str, turns: Sequence[Turn], add_generation_prompt: bool = False
    ) -> EncodedPrompt:
        """Encode a conversation. With ``add_generation_prompt`` the last turn must have no target and
        the prompt ends right after ``<|im_start|>assistant\\n``; otherwise every turn needs a target."""
        if not turns:
            raise ValueError("a navigation prompt needs at least one observation turn")
        out = EncodedPrompt()
        out.extend_text(self._enc(f"<|im_start|>system\n{self.system_text(instruction)}<|im_end|>\n"))
        for k, turn in enumerate(turns):
            last = k == len(turns) - 1
            if turn.target is None and not (last and add_generation_prompt):
                raise ValueError(
                    f"turn {k} has no target actions (only the last turn of a generation prompt may)"
                )
            if turn.target is not None and last and add_generation_prompt:
                raise ValueError("the last turn of a generation prompt must not have a target")
            if turn.num_image_tokens <= 0:
                raise ValueError(f"turn {k}: num_image_tokens must be positive, got {turn.num_image_tokens}")
            head = "<|im_start|>user\n"
            if turn.executed:
                head += f"Executed: {actions_to_text(turn.executed, self.codec.texts)}\n"
            out.extend_text(self._enc(head + "<|vision_start|>"))
            out.extend_image(self.image_pad_id, turn.num_image_tokens, turn.frame_key)
            out.extend_text(self._enc("<|vision_end|><|im_end|>\n<|im_start|>assistant\n"))
            if turn.target is None:
                break
            if len(turn.target) != ACTIONS_PER_STEP:
                raise ValueError(f"turn {k}: target must hold {ACTIONS_PER_STEP} actions, got {turn.target}")
            for piece in self.codec.encode(turn.target):
                out.extend_text(piece, labelled=True)
            out.extend_text(self._enc("<|im_end|>\n"))
        return out


def common_prefix_length(a: Sequence[tuple], b: Sequence[tuple]) -> int:
    """Number of leading positions where two key sequences agree."""
    n = min(len(a), len(b))
    i = 0
    while i < n and a[i] == b[i]:
        i += 1
    return i
