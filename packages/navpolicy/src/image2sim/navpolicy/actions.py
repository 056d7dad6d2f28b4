"""Discrete actions <-> text <-> token ids for Image2Nav.

The action ids come from :class:`image2sim.simulator.conventions.Action` (STOP=0, MOVE_FORWARD=1,
TURN_LEFT=2, TURN_RIGHT=3). The policy speaks them as words: the assistant reply for one step is
``"<first> <second>"``, e.g. ``"FORWARD LEFT"``. A tokenizer may split a word into several tokens;
:class:`ActionCodec` stores the exact token sequence of every action in both positions (first, and
after the separator), checks that the sequences are prefix-free so that greedy decoding over a
token trie is unambiguous, and says whether every action is a single token.
"""

from __future__ import annotations

import re
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass

from image2sim.simulator.conventions import Action

ACTION_TEXT: dict[Action, str] = {
    Action.STOP: "STOP",
    Action.MOVE_FORWARD: "FORWARD",
    Action.TURN_LEFT: "LEFT",
    Action.TURN_RIGHT: "RIGHT",
}
"""Default spoken form of each action (upper case so it never collides with instruction words)."""

ACTIONS_PER_STEP = 2
"""The policy predicts this many actions per observation (paper: two)."""

SEPARATOR = " "
"""Text between the two actions of one reply (and between executed actions in a user turn)."""


def action_text(action: int | Action, texts: dict[Action, str] = ACTION_TEXT) -> str:
    """Spoken form of ``action``; raises ``ValueError`` for ids outside the action set."""
    try:
        return texts[Action(int(action))]
    except ValueError as exc:
        raise ValueError(f"unknown action id {action!r}; valid ids are {[int(a) for a in Action]}") from exc


def actions_to_text(actions: Iterable[int | Action], texts: dict[Action, str] = ACTION_TEXT) -> str:
    """``[1, 2] -> "FORWARD LEFT"``."""
    return SEPARATOR.join(action_text(a, texts) for a in actions)


def parse_actions(text: str, texts: dict[Action, str] = ACTION_TEXT) -> list[Action]:
    """All action words in ``text`` in order (case-sensitive whole words); unknown words are skipped.

    Also accepts the enum names (``MOVE_FORWARD``, ``TURN_LEFT``, ...), which a model fine-tuned on
    another vocabulary might emit.
    """
    lookup = {word: action for action, word in texts.items()}
    lookup.update({a.name: a for a in Action})
    return [lookup[w] for w in re.findall(r"[A-Za-z_]+", text) if w in lookup]


class ActionCodecError(ValueError):
    """The tokenizer cannot represent the action vocabulary unambiguously."""


@dataclass(frozen=True)
class ActionCodec:
    """Exact token sequences of the actions for one tokenizer.

    Attributes:
        first: token ids of each action when it starts the reply (no leading separator).
        following: token ids of each action when it follows another one (separator included).
        texts: the spoken form of each action.
    """

    first: dict[Action, tuple[int, ...]]
    following: dict[Action, tuple[int, ...]]
    texts: dict[Action, str]

    @classmethod
    def from_tokenizer(cls, tokenizer, texts: dict[Action, str] = ACTION_TEXT) -> ActionCodec:
        """Tokenize every action in both positions and validate the result.

        Raises :class:`ActionCodecError` if an action encodes to nothing, if the encoding in context
        (``"A B"``) differs from the concatenation of the parts (BPE merging across the separator),
        or if one action's token sequence is a prefix of another's in the same position.
        """
        missing = [a for a in Action if a not in texts]
        if missing:
            raise ActionCodecError(f"action texts lack {[a.name for a in missing]}")

        def enc(s: str) -> tuple[int, ...]:
            return tuple(tokenizer(s, add_special_tokens=False)["input_ids"])

        first = {a: enc(texts[a]) for a in Action}
        following = {a: enc(SEPARATOR + texts[a]) for a in Action}
        for a in Action:
            if not first[a] or not following[a]:
                raise ActionCodecError(f"action {a.name} ({texts[a]!r}) encodes to no tokens")
        for a in Action:
            for b in Action:
                joined = enc(texts[a] + SEPARATOR + texts[b])
                if joined != first[a] + following[b]:
                    raise ActionCodecError(
                        f"'{texts[a]}{SEPARATOR}{texts[b]}' tokenizes as {joined}, not as the concatenation "
                        f"{first[a] + following[b]} of its parts; choose other action texts"
                    )
        for table, where in ((first, "first"), (following, "following")):
            for a in Action:
                for b in Action:
                    if a != b and table[b][: len(table[a])] == table[a]:
                        raise ActionCodecError(
                            f"{where} encoding of {a.name} {table[a]} is a prefix of {b.name} {table[b]}"
                        )
        return cls(first=first, following=following, texts=dict(texts))

    @property
    def single_token(self) -> bool:
        """True when every action is exactly one token in both positions."""
        return all(len(v) == 1 for v in (*self.first.values(), *self.following.values()))

    def table(self, position: int) -> dict[Action, tuple[int, ...]]:
        """Token sequences for the action at ``position`` (0 = first of the reply)."""
        return self.first if position == 0 else self.following

    def encode(self, actions: Sequence[int | Action]) -> list[list[int]]:
        """Token ids of each action of one reply, in order (their concatenation is the reply)."""
        return [list(self.table(i)[Action(int(a))]) for i, a in enumerate(actions)]

    def allowed_next(
        self, position: int, prefix: Sequence[int], exclude: Collection[Action] = ()
    ) -> list[int]:
        """Token ids that extend ``prefix`` towards some action at ``position`` (trie children),
        leaving out the paths that lead only to actions in ``exclude``."""
        n = len(prefix)
        out = {
            seq[n]
            for a, seq in self.table(position).items()
            if a not in exclude and len(seq) > n and tuple(seq[:n]) == tuple(prefix)
        }
        return sorted(out)

    def match(self, position: int, prefix: Sequence[int]) -> Action | None:
        """The action whose full token sequence at ``position`` equals ``prefix``, else None."""
        for a, seq in self.table(position).items():
            if tuple(prefix) == seq:
                return a
        return None

    def all_token_ids(self) -> set[int]:
        """Every token id that occurs in some action encoding."""
        return {t for seq in (*self.first.values(), *self.following.values()) for t in seq}
