"""OpenAI-compatible chat-completions backend (e.g. vLLM serving Qwen3-VL-32B-Instruct).

Images go as ``data:image/png;base64`` URLs in ``image_url`` parts. Requests are sent concurrently
with at most ``max_concurrency`` in flight, each with a timeout; timeouts, connection errors, 429
and 5xx answers are retried with exponential backoff; other 4xx answers fail at once. Only the
standard library is used for HTTP.
"""

from __future__ import annotations

import base64
import json
import os
import time
import urllib.error
import urllib.request
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from image2sim.dataengine.annotate.prompts import Annotation, AnnotationRequest
from image2sim.dataengine.annotate.vlm import annotate_one

__all__ = ["OpenAIConfig", "OpenAIAnnotator", "TransportError", "encode_image"]


class TransportError(RuntimeError):
    """The endpoint could not be reached or kept failing after all retries."""


@dataclass(frozen=True)
class OpenAIConfig:
    """Endpoint and robustness settings."""

    base_url: str = "http://127.0.0.1:8000/v1"
    """Server root; requests go to ``{base_url}/chat/completions``."""
    model: str = "Qwen/Qwen3-VL-32B-Instruct"
    """Model name sent in the request."""
    api_key_env: str = "IMAGE2SIM_ANNOTATOR_API_KEY"
    """Name of the environment variable holding the bearer token (unset or empty: none is sent). The
    key itself is never an option: options are recorded in ``run.json`` and visible in ``ps``."""
    timeout: float = 60.0
    """Seconds per HTTP request."""
    retries: int = 3
    """Transport retries per request (timeouts, connection errors, 429, 5xx)."""
    backoff: float = 1.0
    """First backoff in seconds; doubles after every retry."""
    max_concurrency: int = 8
    """Requests in flight at most."""
    batch_size: int = 32
    """Requests submitted together (one pool round)."""
    max_attempts: int = 3
    """Annotation attempts per episode (malformed or hallucinating replies are re-asked)."""
    temperature: float = 0.7
    max_tokens: int = 512

    def __post_init__(self) -> None:
        if not self.api_key_env.isidentifier():
            raise ValueError(
                f"OpenAIConfig.api_key_env must name an environment variable, got {self.api_key_env!r}"
            )
        if self.timeout <= 0 or self.retries < 0 or self.backoff < 0:
            raise ValueError("OpenAIConfig: timeout must be > 0, retries and backoff >= 0")
        if self.max_concurrency < 1 or self.batch_size < 1 or self.max_attempts < 1:
            raise ValueError("OpenAIConfig: max_concurrency, batch_size and max_attempts must be >= 1")


def encode_image(img: np.ndarray) -> str:
    """PNG data URL of an (H, W, 3) uint8 image."""
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(np.asarray(img, np.uint8)[..., ::-1]))
    if not ok:
        raise ValueError("cannot PNG-encode image")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def _wire(messages: list[dict]) -> list[dict]:
    out = []
    for m in messages:
        c = m["content"]
        if isinstance(c, list):
            c = [
                {"type": "image_url", "image_url": {"url": encode_image(p["image"])}}
                if p["type"] == "image"
                else p
                for p in c
            ]
        out.append({"role": m["role"], "content": c})
    return out


class OpenAIAnnotator:
    """Annotates batches of requests against an OpenAI-compatible endpoint."""

    name = "openai"

    def __init__(self, config: OpenAIConfig, vocabulary: Iterable[str] = ()) -> None:
        self.config = config
        self.vocabulary = list(vocabulary)
        self.requests_sent = 0

    def complete(self, messages: list[dict]) -> str:
        """One chat completion with transport retries and backoff; raises :class:`TransportError`."""
        cfg = self.config
        body = json.dumps(
            {
                "model": cfg.model,
                "messages": _wire(messages),
                "temperature": cfg.temperature,
                "max_tokens": cfg.max_tokens,
            }
        ).encode()
        headers = {"Content-Type": "application/json"}
        key = os.environ.get(cfg.api_key_env, "")
        if key:
            headers["Authorization"] = f"Bearer {key}"
        url = cfg.base_url.rstrip("/") + "/chat/completions"
        delay, last = cfg.backoff, ""
        for attempt in range(cfg.retries + 1):
            if attempt:
                time.sleep(delay)
                delay *= 2
            self.requests_sent += 1
            try:
                req = urllib.request.Request(url, data=body, headers=headers, method="POST")
                with urllib.request.urlopen(req, timeout=cfg.timeout) as resp:
                    doc = json.loads(resp.read().decode("utf-8"))
                return str(doc["choices"][0]["message"]["content"])
            except urllib.error.HTTPError as err:
                last = f"HTTP {err.code}"
                if err.code != 429 and err.code < 500:
                    raise TransportError(f"{url}: {last} (not retried)") from None
            except TimeoutError as err:
                last = f"timeout after {cfg.timeout}s ({err})"
            except urllib.error.URLError as err:
                last = f"connection error: {err.reason}"
            except (KeyError, IndexError, json.JSONDecodeError, UnicodeDecodeError) as err:
                last = f"unexpected response body ({type(err).__name__}: {err})"
        raise TransportError(f"{url}: giving up after {cfg.retries + 1} tries: {last}")

    def annotate(self, requests: list[AnnotationRequest]) -> list[Annotation]:
        out: list[Annotation] = []
        cfg = self.config
        with ThreadPoolExecutor(max_workers=cfg.max_concurrency) as pool:  # caps requests in flight
            for s in range(0, len(requests), cfg.batch_size):
                batch = requests[s : s + cfg.batch_size]
                out += list(
                    pool.map(
                        lambda r: annotate_one(
                            r, self.complete, self.vocabulary, cfg.max_attempts, (TransportError,)
                        ),
                        batch,
                    )
                )
        return out
