"""Parsing of annotator replies: REASONING block, verdict field, instruction; anti-hallucination check.

Reply format the prompts ask for::

    REASONING: <free text, may span lines>
    VERDICT: VALID | INVALID
    ISSUES: <comma separated: visual_freezing, wall_clipping, ...>   (optional)
    INSTRUCTION: <the instruction>

Only the ``VERDICT`` field decides: a word such as "INVALID" inside the reasoning never rejects.
A reply without exactly one verdict field, or a VALID reply without an instruction, is malformed.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass

__all__ = ["MalformedReply", "ParsedReply", "parse_reply", "mentioned_objects", "hallucinated_objects"]

_FIELD = re.compile(
    r"^\s*(?:\*\*)?(REASONING|VERDICT|ISSUES|INSTRUCTION)(?:\*\*)?\s*:\s*(.*)$", re.IGNORECASE
)


class MalformedReply(ValueError):
    """The reply does not follow the required format; the message says what is missing."""


@dataclass(frozen=True)
class ParsedReply:
    """A well-formed annotator reply."""

    valid: bool
    """The verdict field says VALID."""
    reasoning: str
    issues: tuple[str, ...]
    instruction: str


def parse_reply(text: str) -> ParsedReply:
    """Split a reply into its fields (see the module docstring); raises :class:`MalformedReply`."""
    if not isinstance(text, str) or not text.strip():
        raise MalformedReply("empty reply")
    fields: dict[str, list[str]] = {}
    order: list[str] = []
    current = None
    for line in text.splitlines():
        m = _FIELD.match(line)
        if m:
            current = m.group(1).upper()
            if current in fields:
                raise MalformedReply(f"field {current} appears more than once")
            fields[current] = [m.group(2)]
            order.append(current)
        elif current is not None:
            fields[current].append(line)
    if "VERDICT" not in fields:
        raise MalformedReply("no VERDICT field")
    verdict = " ".join(fields["VERDICT"]).strip().strip("*").strip().upper()
    verdict = re.sub(r"[^A-Z_]", "", verdict.split()[0]) if verdict else ""
    if verdict not in ("VALID", "INVALID"):
        raise MalformedReply(f"VERDICT must be VALID or INVALID, got {verdict or 'nothing'!r}")
    if "REASONING" in fields and order.index("REASONING") > order.index("VERDICT"):
        raise MalformedReply("REASONING must come before VERDICT")
    instruction = " ".join(s.strip() for s in fields.get("INSTRUCTION", [])).strip()
    if verdict == "VALID" and not instruction:
        raise MalformedReply("VALID verdict without an INSTRUCTION")
    issues = tuple(
        s.strip().lower()
        for s in " ".join(fields.get("ISSUES", [])).split(",")
        if s.strip() and s.strip().lower() not in ("none", "-", "n/a")
    )
    return ParsedReply(
        verdict == "VALID", "\n".join(fields.get("REASONING", [])).strip(), issues, instruction
    )


def _phrases(category: str) -> list[str]:
    words = category.replace("_", " ").lower()
    return [words, words + "s", words + "es"] if not words.endswith("s") else [words]


def mentioned_objects(text: str, vocabulary: Iterable[str]) -> set[str]:
    """Categories of ``vocabulary`` named in ``text`` (whole words, underscores read as spaces)."""
    low = " " + re.sub(r"[^a-z ]", " ", text.lower()) + " "
    found = set()
    for cat in vocabulary:
        if any(f" {p} " in low for p in _phrases(cat)):
            found.add(cat)
    # A longer name ("table lamp") also contains a shorter one ("lamp"); keep only the longer.
    return {c for c in found if not any(c != o and c.replace("_", " ") in o.replace("_", " ") for o in found)}


def hallucinated_objects(text: str, allowed: Iterable[str], vocabulary: Iterable[str]) -> set[str]:
    """Named categories that are neither visible in the frames nor the goal (anti-hallucination rule)."""
    allowed = set(allowed)
    return {c for c in mentioned_objects(text, vocabulary) if c not in allowed}
