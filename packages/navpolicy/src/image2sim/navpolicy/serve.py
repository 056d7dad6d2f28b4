"""Serve Image2Nav to a robot over HTTP (``image2sim nav serve``): one streaming agent per session.

API (JSON answers; errors are ``{"detail": "<field>: <problem>"}`` with a 4xx status)::

    GET    /healthz                      -> {"status": "ok"}                  (no token needed)
    GET    /v1/info                      -> model, observation size, actions, limits
    POST   /v1/sessions                  {"instruction": str, "seed"?: int} -> {"session_id": str}
    POST   /v1/sessions/{id}/step        image (multipart field ``image``, or JSON ``image_b64``),
                                         optional ``executed`` -> {"actions": [...], "step": int}
    DELETE /v1/sessions/{id}             -> 204

Each session owns an :class:`~image2sim.navpolicy.agent.Image2NavAgent` (its frames, replies and KV
cache), so the same observations give exactly the in-process agent's actions. Model calls are
serialised by one lock (one model, shared by every session); a second step on a session whose step
is still running answers 409. Sessions idle for ``session_ttl_s`` expire (404 afterwards); more than
``max_sessions`` open sessions answer 429.

Security: the bearer token (if any) comes from the environment (``--token-env``), never from a flag
value; :func:`bind_error` refuses a non-loopback bind without one. Request bodies over
``max_body_bytes`` answer 413 before they are read; an image's type, size and dimensions are checked
from its header (:func:`image2sim.simulator.io.images.header_size`) before it is decoded. Nothing is
unpickled: requests are JSON or multipart, weights load through the policy loaders (safetensors).

Pure pieces (:func:`check_image`, :func:`decode_image`, :func:`parse_executed`, :func:`bind_error`)
are functions; state lives in :class:`SessionStore` and the app of :func:`create_app`. Nothing here
opens a socket at import; :func:`serve` and :class:`ServerThread` do when called.
"""

# No ``from __future__ import annotations``: FastAPI reads the handlers' annotations (Request) at
# definition time, and those names are imported inside :func:`create_app`.
import base64
import binascii
import hmac
import ipaddress
import json
import logging
import secrets
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from image2sim.simulator.conventions import Action
from image2sim.simulator.io.images import MAX_IMAGE_PIXELS, header_size

log = logging.getLogger("image2sim.navpolicy.serve")

ACTION_NAMES = tuple(a.name for a in Action)
"""Action names of the API (``image2sim.simulator.conventions.Action``)."""

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"
_JPEG_MAGIC = b"\xff\xd8"
_JPEG_END = b"\xff\xd9"


class ApiError(Exception):
    """A request the server refuses: HTTP ``status`` and a message naming the field and the problem."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message


@dataclass(frozen=True)
class ServeSettings:
    """Limits and security settings of the policy server."""

    max_sessions: int = 8
    """Open sessions at most; one more answers 429 (expired sessions are dropped first)."""
    session_ttl_s: float = 600.0
    """A session idle for this long expires (its id then answers 404)."""
    max_body_bytes: int = 8 * 1024 * 1024
    """Largest request body; larger ones answer 413 before they are read."""
    max_image_pixels: int = 4096 * 4096
    """Largest image (width x height) accepted, checked from the header before decoding."""
    min_image_side: int = 16
    """Smallest image side in pixels."""
    max_aspect_ratio: float = 20.0
    """Longest over shortest side at most (Qwen's resizing refuses extreme ratios)."""
    max_steps_per_session: int = 2000
    """Steps per session at most (each keeps its frame in memory for the context); then 409."""
    max_instruction_chars: int = 4000
    """Longest instruction accepted."""
    token: str | None = field(default=None, repr=False)
    """Bearer token every ``/v1`` request must carry (None: no authentication; loopback only)."""
    model_name: str = "tiny"
    """Shown by ``/v1/info``."""
    observation: dict = field(default_factory=dict)
    """The policy's observation camera (``camera``, ``height``, ``width``), shown by ``/v1/info``."""

    def __post_init__(self) -> None:
        for name in ("max_sessions", "max_body_bytes", "max_image_pixels", "min_image_side"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"ServeSettings.{name} must be >= 1, got {getattr(self, name)}")
        if int(self.max_image_pixels) > MAX_IMAGE_PIXELS:
            raise ValueError(
                f"ServeSettings.max_image_pixels must be <= {MAX_IMAGE_PIXELS} (the repository's image "
                f"limit), got {self.max_image_pixels}"
            )
        if not self.session_ttl_s > 0:
            raise ValueError(f"ServeSettings.session_ttl_s must be > 0, got {self.session_ttl_s}")
        if not self.max_aspect_ratio >= 1:
            raise ValueError(f"ServeSettings.max_aspect_ratio must be >= 1, got {self.max_aspect_ratio}")
        if self.token is not None and not self.token:
            raise ValueError("ServeSettings.token must be None or a non-empty string")

    def limits(self) -> dict:
        """The limits as shown by ``/v1/info``."""
        skip = {"token", "model_name", "observation"}
        return {k: v for k, v in asdict(self).items() if k not in skip}


# ------------------------------------------------------------------------------------ pure checks


def is_loopback(host: str) -> bool:
    """``localhost`` or a loopback IP address (127.0.0.0/8, ::1)."""
    if host.strip().lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: it may resolve to anything


def bind_error(host: str, token_env: str | None, environ: dict) -> str | None:
    """Why the server must not start on ``host`` with the token from ``environ[token_env]``, or None.

    A named variable must be set and non-empty; binding anything but loopback needs a token.
    """
    if token_env and not environ.get(token_env):
        return f"--token-env {token_env}: the environment variable {token_env} is unset or empty"
    if not is_loopback(host) and not token_env:
        return (
            f"refusing to bind {host}: serving beyond this machine needs a bearer token; put it in an "
            "environment variable and pass its name with --token-env VAR"
        )
    return None


def check_image(data: bytes, settings: ServeSettings, where: str = "image") -> tuple[str, int, int]:
    """(format, height, width) of a PNG or JPEG from its header, without decoding it.

    Raises :class:`ApiError`: 415 for another type, 413 for more pixels than allowed, 422 for an
    empty, truncated or degenerate image.
    """
    if not data:
        raise ApiError(422, f"{where}: empty")
    if data.startswith(_PNG_MAGIC):
        fmt, end = "png", _PNG_END
    elif data.startswith(_JPEG_MAGIC):
        fmt, end = "jpeg", _JPEG_END
    else:
        raise ApiError(415, f"{where}: not a PNG or JPEG image (starts with {data[:8].hex()})")
    size = header_size(data)
    if size is None:
        raise ApiError(422, f"{where}: the {fmt.upper()} header gives no image size (corrupt or truncated)")
    h, w = size
    if h < 1 or w < 1:
        raise ApiError(422, f"{where}: the header declares {w} x {h} pixels")
    if h * w > settings.max_image_pixels:
        raise ApiError(
            413,
            f"{where}: the header declares {w} x {h} pixels ({h * w / 1e6:.1f} MP), above the server's "
            f"{settings.max_image_pixels / 1e6:.1f} MP limit; refused before decoding",
        )
    if min(h, w) < settings.min_image_side:
        raise ApiError(422, f"{where}: {w} x {h} pixels; each side must be >= {settings.min_image_side}")
    if max(h, w) / min(h, w) > settings.max_aspect_ratio:
        raise ApiError(
            422, f"{where}: {w} x {h} pixels; the aspect ratio must be <= {settings.max_aspect_ratio:g}"
        )
    if not data.rstrip(b"\x00").endswith(end):
        raise ApiError(422, f"{where}: the {fmt.upper()} data is truncated (no end marker)")
    return fmt, h, w


def decode_image(data: bytes, settings: ServeSettings, where: str = "image") -> np.ndarray:
    """Check the header (:func:`check_image`), then decode to (H, W, 3) uint8 RGB."""
    import cv2

    _, h, w = check_image(data, settings, where)
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None or bgr.shape[:2] != (h, w):
        raise ApiError(422, f"{where}: cannot decode the image (corrupt data)")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def parse_executed(value: Any, where: str = "executed") -> list[int] | None:
    """Action names (a list, or a comma-separated string from a form) -> action ids; None: absent."""
    if value is None:
        return None
    if isinstance(value, str):
        value = [v.strip() for v in value.split(",") if v.strip()]
    if not isinstance(value, list) or len(value) > 64:
        raise ApiError(422, f"{where}: expected a list of at most 64 action names from {list(ACTION_NAMES)}")
    out = []
    for i, name in enumerate(value):
        if not isinstance(name, str) or name not in ACTION_NAMES:
            raise ApiError(
                422, f"{where}[{i}]: {name!r} is not an action; expected one of {list(ACTION_NAMES)}"
            )
        out.append(int(Action[name]))
    return out


def _json_object(body: bytes, allowed: set[str], required: set[str]) -> dict:
    try:
        doc = json.loads(body)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ApiError(400, f"request body is not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise ApiError(422, f"request body: expected a JSON object, got {type(doc).__name__}")
    unknown = sorted(set(doc) - allowed)
    if unknown:
        raise ApiError(422, f"unknown field(s) {unknown}; allowed: {sorted(allowed)}")
    missing = sorted(required - set(doc))
    if missing:
        raise ApiError(422, f"missing field(s) {missing}")
    return doc


def parse_session_request(body: bytes, settings: ServeSettings) -> tuple[str, int]:
    """``{"instruction": str, "seed"?: int}`` -> (instruction, seed)."""
    doc = _json_object(body, {"instruction", "seed"}, {"instruction"})
    instruction, seed = doc["instruction"], doc.get("seed", 0)
    if not isinstance(instruction, str):
        raise ApiError(422, f"instruction: expected a string, got {type(instruction).__name__}")
    if len(instruction) > settings.max_instruction_chars:
        raise ApiError(
            422, f"instruction: {len(instruction)} characters, at most {settings.max_instruction_chars}"
        )
    if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed < 2**32:
        raise ApiError(422, f"seed: expected an integer in [0, 2**32), got {seed!r}")
    return instruction, seed


def parse_json_step(body: bytes) -> tuple[bytes, list[int] | None]:
    """``{"image_b64": str, "executed"?: [names]}`` -> (image bytes, executed ids or None)."""
    doc = _json_object(body, {"image_b64", "executed"}, {"image_b64"})
    b64 = doc["image_b64"]
    if not isinstance(b64, str):
        raise ApiError(422, f"image_b64: expected a base64 string, got {type(b64).__name__}")
    try:
        data = base64.b64decode(b64, validate=True)
    except (binascii.Error, ValueError):
        raise ApiError(422, "image_b64: not valid base64") from None
    return data, parse_executed(doc.get("executed"))


def media_type(content_type: str | None) -> str:
    """``multipart/form-data; boundary=...`` -> ``multipart/form-data``."""
    return (content_type or "").split(";", 1)[0].strip().lower()


# ------------------------------------------------------------------------------------ sessions


@dataclass
class Session:
    """One robot's episode: its agent (frames, replies, KV cache) and bookkeeping."""

    id: str
    agent: Any
    instruction: str
    last_used: float
    steps: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)


class SessionLimitError(Exception):
    """Every session slot is taken."""


class SessionStore:
    """Open sessions with an idle TTL and a cap; thread-safe. ``clock`` is injectable for tests."""

    def __init__(self, max_sessions: int, ttl_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.max_sessions, self.ttl_s, self.clock = int(max_sessions), float(ttl_s), clock
        self._sessions: dict[str, Session] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        with self._lock:
            return len(self._sessions)

    def _expire_locked(self) -> None:
        now = self.clock()
        for sid, s in list(self._sessions.items()):
            if now - s.last_used > self.ttl_s and not s.lock.locked():
                del self._sessions[sid]

    def expire(self) -> None:
        """Drop sessions idle for longer than the TTL (never one whose step is running)."""
        with self._lock:
            self._expire_locked()

    def create(self, agent_factory: Callable[[], Any], instruction: str, seed: int) -> Session:
        """A new session with a fresh agent reset to ``instruction``; :class:`SessionLimitError` if full."""
        with self._lock:
            self._expire_locked()
            if len(self._sessions) >= self.max_sessions:
                raise SessionLimitError
            agent = agent_factory()
            agent.reset(instruction, seed=seed)
            s = Session(secrets.token_urlsafe(16), agent, instruction, self.clock())
            self._sessions[s.id] = s
            return s

    def get(self, sid: str) -> Session | None:
        """The open session ``sid`` (touched: its TTL restarts), or None if unknown or expired."""
        with self._lock:
            self._expire_locked()
            s = self._sessions.get(sid)
            if s is not None:
                s.last_used = self.clock()
            return s

    def touch(self, s: Session) -> None:
        with self._lock:
            s.last_used = self.clock()

    def delete(self, sid: str) -> bool:
        """Close ``sid``; False if it was not open."""
        with self._lock:
            return self._sessions.pop(sid, None) is not None


# ------------------------------------------------------------------------------------ ASGI app


class _BodyTooLarge(Exception):
    pass


class BodyLimitMiddleware:
    """413 for a body over ``max_bytes``: from Content-Length before reading, else while streaming."""

    def __init__(self, app, max_bytes: int) -> None:
        self.app, self.max_bytes = app, int(max_bytes)

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        message = f"request body: larger than the server's limit of {self.max_bytes} bytes"
        headers = dict(scope.get("headers") or [])
        declared = headers.get(b"content-length")
        if declared is not None:
            try:
                too_large = int(declared) > self.max_bytes
            except ValueError:
                return await self._reply(send, 400, "Content-Length: not an integer")
            if too_large:
                return await self._reply(send, 413, message)
        seen, started = 0, False

        async def limited_receive():
            nonlocal seen
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > self.max_bytes:
                    raise _BodyTooLarge
            return msg

        async def tracked_send(msg):
            nonlocal started
            if msg["type"] == "http.response.start":
                started = True
            await send(msg)

        try:
            await self.app(scope, limited_receive, tracked_send)
        except _BodyTooLarge:
            if started:
                raise
            await self._reply(send, 413, message)

    @staticmethod
    async def _reply(send, status: int, detail: str) -> None:
        body = json.dumps({"detail": detail}).encode()
        headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})


def create_app(
    agent_factory: Callable[[], Any],
    settings: ServeSettings | None = None,
    clock: Callable[[], float] = time.monotonic,
):
    """The FastAPI app: sessions of agents from ``agent_factory()`` (``reset(instruction, seed)``,
    ``act(rgb, executed) -> [Action, Action]``). No network until a server runs it."""
    from fastapi import Depends, FastAPI, Request
    from fastapi.responses import JSONResponse, Response
    from starlette.concurrency import run_in_threadpool
    from starlette.datastructures import UploadFile

    settings = settings or ServeSettings()
    store = SessionStore(settings.max_sessions, settings.session_ttl_s, clock)
    model_lock = threading.Lock()  # one model shared by every session: its calls run one at a time
    app = FastAPI(title="Image2Nav policy server", docs_url=None, redoc_url=None, openapi_url=None)
    app.state.store, app.state.settings = store, settings

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError):
        headers = {"WWW-Authenticate": "Bearer"} if exc.status == 401 else None
        return JSONResponse({"detail": exc.message}, status_code=exc.status, headers=headers)

    def require_token(request: Request) -> None:
        if settings.token is None:
            return
        scheme, _, given = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not given:
            raise ApiError(401, "Authorization: missing bearer token")
        if not hmac.compare_digest(given.strip().encode(), settings.token.encode()):
            raise ApiError(401, "Authorization: wrong bearer token")

    def session_or_404(sid: str) -> Session:
        s = store.get(sid)
        if s is None:
            raise ApiError(404, f"session {sid!r}: unknown or expired")
        return s

    auth = [Depends(require_token)]

    @app.get("/healthz")
    def healthz() -> dict:
        return {"status": "ok"}

    @app.get("/v1/info", dependencies=auth)
    def info() -> dict:
        return {
            "model": settings.model_name,
            "observation": settings.observation,
            "actions": list(ACTION_NAMES),
            "actions_per_step": 2,
            "open_sessions": len(store),
            "limits": settings.limits(),
        }

    @app.post("/v1/sessions", dependencies=auth)
    async def create_session(request: Request):
        if media_type(request.headers.get("content-type")) != "application/json":
            raise ApiError(415, "Content-Type: expected application/json")
        instruction, seed = parse_session_request(await request.body(), settings)
        try:
            s = store.create(agent_factory, instruction, seed)
        except SessionLimitError:
            raise ApiError(
                429,
                f"too many open sessions (limit {settings.max_sessions}): delete one, or wait for an idle "
                f"one to expire ({settings.session_ttl_s:g} s)",
            ) from None
        return JSONResponse({"session_id": s.id}, status_code=201)

    @app.post("/v1/sessions/{sid}/step", dependencies=auth)
    async def step(sid: str, request: Request):
        s = session_or_404(sid)
        kind = media_type(request.headers.get("content-type"))
        if kind == "application/json":
            data, executed = parse_json_step(await request.body())
        elif kind == "multipart/form-data":
            try:
                form = await request.form(max_files=1, max_fields=4)
            except _BodyTooLarge:
                raise
            except Exception as exc:  # malformed multipart: python-multipart / starlette errors
                why = getattr(exc, "detail", exc)
                raise ApiError(400, f"multipart body cannot be parsed ({why})") from None
            try:
                upload = form.get("image")
                if not isinstance(upload, UploadFile):
                    raise ApiError(422, "image: missing (send the image as multipart file field 'image')")
                data = await upload.read()
                executed = parse_executed(form.get("executed"))
            finally:
                await form.close()
        else:
            raise ApiError(
                415, f"Content-Type: expected multipart/form-data or application/json, got {kind or 'none'!r}"
            )
        check_image(data, settings)  # cheap header checks before a worker thread decodes
        if not s.lock.acquire(blocking=False):
            raise ApiError(409, f"session {sid!r}: a step is already running; send steps one at a time")
        try:
            if s.steps >= settings.max_steps_per_session:
                raise ApiError(
                    409,
                    f"session {sid!r}: reached {settings.max_steps_per_session} steps; start a new session",
                )
            rgb = await run_in_threadpool(decode_image, data, settings)
            actions = await run_in_threadpool(_act, s, rgb, executed, model_lock)
            s.steps += 1
            store.touch(s)
            return {"actions": [Action(a).name for a in actions], "step": s.steps}
        except ApiError:
            raise
        except Exception:
            log.exception("session %s: step %d failed", sid, s.steps + 1)
            store.delete(sid)  # its agent may hold a half-recorded step: never reuse it
            return JSONResponse(
                {"detail": f"session {sid!r}: internal error while stepping; the session was closed"},
                status_code=500,
            )
        finally:
            s.lock.release()

    @app.delete("/v1/sessions/{sid}", dependencies=auth)
    def delete_session(sid: str):
        if not store.delete(sid):
            raise ApiError(404, f"session {sid!r}: unknown or expired")
        return Response(status_code=204)

    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_body_bytes)
    return app


def _act(session: Session, rgb: np.ndarray, executed: list[int] | None, model_lock: threading.Lock):
    with model_lock:
        actions = session.agent.act(rgb, executed=executed)
    history = getattr(session.agent, "history", None)
    if isinstance(history, list):
        history.clear()  # per-step diagnostics (logits) would grow without bound in a server
    return actions


def policy_agent_factory(cfg) -> Callable[[], Any]:
    """Build the policy of ``cfg`` once (weights via the policy loaders) and return a factory of
    streaming agents sharing it (seed 0 for a tiny model, as ``eval nav --agent image2nav``)."""
    from image2sim.navpolicy.agent import Image2NavAgent
    from image2sim.navpolicy.model import build_policy

    policy = build_policy(cfg, seed=0)
    policy.model.eval()
    return lambda: Image2NavAgent(policy, cfg.agent, cfg.system_prompt)


# ------------------------------------------------------------------------------------ servers


def bind_socket(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (port 0: an ephemeral port)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    # Accepted connections inherit TCP_NODELAY (Linux); asyncio does not set it on sockets accepted
    # from a listening socket it did not create, and a response written as headers + body then
    # waits for the client's delayed ACK: ~40 ms per keep-alive request.
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.bind((host.strip("[]"), int(port)))
    sock.listen(128)
    return sock


def _uvicorn_server(app, log_level: str):
    import uvicorn

    config = uvicorn.Config(app, log_level=log_level, access_log=False, server_header=False, lifespan="off")
    return uvicorn.Server(config)


def serve(app, host: str, port: int, on_ready: Callable[[str], None] | None = None, log_level="info") -> None:
    """Run ``app`` with uvicorn on ``host:port`` until interrupted; ``on_ready(url)`` once bound."""
    sock = bind_socket(host, port)
    actual = sock.getsockname()[1]
    url = f"http://{f'[{host}]' if ':' in host else host}:{actual}"
    if on_ready is not None:
        on_ready(url)
    _uvicorn_server(app, log_level).run(sockets=[sock])


class ServerThread:
    """uvicorn serving ``app`` on 127.0.0.1 (an ephemeral port) in a daemon thread: tests, benchmarks.

    ``with ServerThread(app) as url: ...`` starts it, waits until it accepts, and stops it on exit.
    """

    def __init__(self, app, host: str = "127.0.0.1", port: int = 0) -> None:
        self.sock = bind_socket(host, port)
        self.url = f"http://{host}:{self.sock.getsockname()[1]}"
        self.server = _uvicorn_server(app, "warning")
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)

    def __enter__(self) -> str:
        self.thread.start()
        deadline = time.monotonic() + 30
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("the policy server thread did not start")
            time.sleep(0.01)
        return self.url

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=30)
        self.sock.close()
