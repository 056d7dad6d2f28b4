"""Tokenizers for Image2Nav: an offline tiny byte-level BPE, or a local Qwen3-VL tokenizer.

No tokenizer ships offline, and nothing is ever downloaded: the tiny tokenizer is trained on the fly
(well under a second) on a small built-in corpus of navigation prose and the prompt template, with
the Qwen special tokens at the front of the vocabulary and the action words added as whole tokens
(in both positions, with and without the leading separator) so that every action is one token.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from image2sim.navpolicy.actions import ACTION_TEXT, SEPARATOR

QWEN_SPECIAL_TOKENS: tuple[str, ...] = (
    "<|endoftext|>",
    "<|im_start|>",
    "<|im_end|>",
    "<|vision_start|>",
    "<|vision_end|>",
    "<|image_pad|>",
    "<|video_pad|>",
)
"""Special tokens the Qwen3-VL chat format and multimodal placeholders rely on."""

_CORPUS: tuple[str, ...] = (
    "system user assistant",
    "You are a navigation agent in an indoor environment. Follow the instruction.",
    "Actions: STOP, FORWARD (move 0.25 m), LEFT (turn 15 degrees), RIGHT (turn 15 degrees).",
    "After each observation reply with the next two actions, separated by a space.",
    "Executed since the previous observation: FORWARD FORWARD LEFT",
    "Instruction: walk past the kitchen table, turn left at the hallway and stop by the bedroom door.",
    "Go up the stairs, enter the living room and wait next to the sofa near the window.",
    "Exit the bathroom, turn right, walk down the corridor and stop in front of the plant.",
    "Move forward until you reach the fridge, then turn around and stop at the chair.",
    "Head towards the bed, pass the desk and the lamp, and stop at the wardrobe in the office.",
    "Leave the room through the doorway on your right and halt beside the couch and the television.",
)


def build_tiny_tokenizer(
    vocab_size: int = 512,
    extra_corpus: Iterable[str] = (),
    action_texts=ACTION_TEXT,
):
    """Train a byte-level BPE tokenizer offline and wrap it as ``PreTrainedTokenizerFast``.

    Args:
        vocab_size: target BPE vocabulary size (special and action tokens come on top of merges;
            the trainer stops early when the corpus has no more pairs to merge).
        extra_corpus: more text (e.g. the instructions of a dataset) to train merges on.
        action_texts: spoken form of each action; each becomes one added token, with and without the
            leading separator.

    Returns:
        A ``PreTrainedTokenizerFast`` with ``eos_token = <|im_end|>`` and ``pad_token = <|endoftext|>``
        (the Qwen3-VL instruct convention); the special tokens have ids 0..6 in the order of
        :data:`QWEN_SPECIAL_TOKENS`.
    """
    from tokenizers import AddedToken, Tokenizer, decoders, models, pre_tokenizers, trainers
    from transformers import PreTrainedTokenizerFast

    if vocab_size < 256 + len(QWEN_SPECIAL_TOKENS):
        raise ValueError(f"vocab_size={vocab_size} is below the 256-byte alphabet plus the special tokens")
    tok = Tokenizer(models.BPE())
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size,
        special_tokens=list(QWEN_SPECIAL_TOKENS),
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        min_frequency=1,
        show_progress=False,
    )
    # Repeat the corpus so frequent words win merges deterministically.
    tok.train_from_iterator([*_CORPUS, *extra_corpus] * 4, trainer)
    words = list(action_texts.values())
    tok.add_tokens([AddedToken(w, normalized=False) for w in words])
    tok.add_tokens([AddedToken(SEPARATOR + w, normalized=False) for w in words])
    return PreTrainedTokenizerFast(
        tokenizer_object=tok,
        eos_token="<|im_end|>",
        pad_token="<|endoftext|>",
        bos_token=None,
        unk_token=None,
        padding_side="right",
    )


def load_tokenizer(path: str | Path):
    """Load a tokenizer saved on disk (a Qwen3-VL checkpoint folder or a saved tiny tokenizer).

    Only local paths: a string that is not an existing directory raises ``FileNotFoundError``
    rather than being treated as a hub id.
    """
    from transformers import AutoTokenizer

    p = Path(path)
    if not p.is_dir():
        raise FileNotFoundError(f"tokenizer folder {p} does not exist (hub ids are never downloaded)")
    tok = AutoTokenizer.from_pretrained(str(p), local_files_only=True)
    if tok.pad_token is None:
        tok.pad_token = "<|endoftext|>"
    check_special_tokens(tok)
    return tok


def special_token_ids(tokenizer) -> dict[str, int]:
    """Id of each Qwen special token in ``tokenizer``."""
    return {s: int(tokenizer.convert_tokens_to_ids(s)) for s in QWEN_SPECIAL_TOKENS}


def check_special_tokens(tokenizer) -> dict[str, int]:
    """Return :func:`special_token_ids`, raising ``ValueError`` if a token is missing or split."""
    ids = special_token_ids(tokenizer)
    unk = getattr(tokenizer, "unk_token_id", None)
    for s, i in ids.items():
        enc = tokenizer(s, add_special_tokens=False)["input_ids"]
        if i is None or i < 0 or (unk is not None and i == unk) or enc != [i]:
            raise ValueError(f"tokenizer lacks the special token {s!r} as a single token (got {enc})")
    return ids
