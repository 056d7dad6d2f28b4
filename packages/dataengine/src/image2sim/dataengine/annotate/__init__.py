"""Instruction annotation: prompts and style router, template / transformers / openai backends, QA.

``build_annotator("template")`` is the offline default; ``build_annotator("openai", base_url=...)`` and
``build_annotator("transformers", path=...)`` use a VLM. Every backend has ``annotate(requests) ->
annotations`` (same order).
"""

from __future__ import annotations

from collections.abc import Iterable

from image2sim.dataengine.annotate.prompts import (
    STYLES,
    Annotation,
    AnnotationRequest,
    build_messages,
    route_style,
)
from image2sim.dataengine.annotate.qa import MalformedReply, ParsedReply, hallucinated_objects, parse_reply
from image2sim.dataengine.annotate.template import TemplateAnnotator, compose

__all__ = [
    "STYLES",
    "Annotation",
    "AnnotationRequest",
    "build_messages",
    "route_style",
    "MalformedReply",
    "ParsedReply",
    "hallucinated_objects",
    "parse_reply",
    "TemplateAnnotator",
    "compose",
    "build_annotator",
    "ANNOTATORS",
]

ANNOTATORS = ("template", "transformers", "openai")


def build_annotator(name: str, vocabulary: Iterable[str] = (), **options):
    """Backend by name; ``options`` go to its config (openai) or constructor (transformers: ``path``)."""
    if name == "template":
        if options:
            raise ValueError(f"template annotator takes no options, got {sorted(options)}")
        return TemplateAnnotator()
    if name == "openai":
        from image2sim.dataengine.annotate.openai_vlm import OpenAIAnnotator, OpenAIConfig

        if "api_key" in options:
            raise ValueError(
                "openai annotator: the API key is never an option (options are written to run.json and "
                "visible in the process list); export it as IMAGE2SIM_ANNOTATOR_API_KEY (or name another "
                "variable with api_key_env=VAR)"
            )
        known = set(OpenAIConfig.__dataclass_fields__)
        unknown = sorted(set(options) - known)
        if unknown:
            raise ValueError(f"openai annotator: unknown option(s) {unknown}; known: {sorted(known)}")
        return OpenAIAnnotator(OpenAIConfig(**options), vocabulary)
    if name == "transformers":
        from image2sim.dataengine.annotate.transformers_vlm import TransformersAnnotator

        if "path" not in options:
            raise ValueError("transformers annotator needs path=<local Qwen3-VL checkpoint folder>")
        return TransformersAnnotator(vocabulary=vocabulary, **options)
    raise ValueError(f"unknown annotator {name!r}; choose one of {ANNOTATORS}")
