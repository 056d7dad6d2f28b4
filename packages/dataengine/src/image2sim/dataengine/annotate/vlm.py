"""Shared VLM annotation loop: prompt -> reply -> quality gate -> anti-hallucination -> retry or drop.

A backend supplies ``complete(messages) -> str`` (raising on transport failure). Malformed replies
and transport errors are retried up to ``max_attempts`` times. A request whose last attempt still
failed in transport raises that error: an unreachable endpoint fails the scene (it is not marked
done, so a resumed run retries it) instead of yielding a "successful" empty dataset. Otherwise the
request is dropped with the last reason. An INVALID verdict rejects (no retry: the model judged
the trajectory, not the text). A reply naming objects outside the allow-list is retried, then
dropped ("hallucination").
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

from image2sim.dataengine.annotate.prompts import Annotation, AnnotationRequest, build_messages
from image2sim.dataengine.annotate.qa import MalformedReply, hallucinated_objects, parse_reply

__all__ = ["annotate_one"]


def annotate_one(
    req: AnnotationRequest,
    complete: Callable[[list[dict]], str],
    vocabulary: Iterable[str],
    max_attempts: int = 3,
    transient: Sequence[type[BaseException]] = (),
) -> Annotation:
    """Annotate one request with retries (see the module docstring)."""
    messages = build_messages(req)
    vocab = list(vocabulary)
    reason = ""
    transport_error: BaseException | None = None
    for attempt in range(1, max_attempts + 1):
        try:
            reply = complete(messages)
        except tuple(transient) as err:  # transport trouble after the backend's own retries
            reason = f"transport: {type(err).__name__}: {err}"
            transport_error = err
            continue
        transport_error = None
        try:
            parsed = parse_reply(reply)
        except MalformedReply as err:
            reason = f"malformed: {err}"
            continue
        base = dict(
            episode_id=req.episode_id,
            style=req.style,
            structure=req.structure,
            tone=req.tone,
            attempts=attempt,
            reasoning=parsed.reasoning,
            issues=parsed.issues,
        )
        if not parsed.valid:
            return Annotation(
                text="",
                accepted=False,
                reason="invalid verdict" + (f" ({', '.join(parsed.issues)})" if parsed.issues else ""),
                **base,
            )
        bad = hallucinated_objects(parsed.instruction, req.allowed_objects, vocab)
        if bad:
            reason = f"hallucination: {sorted(bad)}"
            continue
        return Annotation(text=parsed.instruction, accepted=True, **base)
    if transport_error is not None:  # the endpoint never answered the last attempt: fatal
        raise transport_error
    return Annotation(
        req.episode_id,
        "",
        req.style,
        req.structure,
        req.tone,
        False,
        reason or "no attempt",
        attempts=max_attempts,
    )
