"""Client of the Image2Nav policy server (``image2sim nav serve``), over httpx.

* :class:`PolicyClient`: one method per endpoint; a refused request raises :class:`ServerError`
  with the status and the server's message.
* :class:`RemoteAgent`: the streaming-agent interface of
  :class:`~image2sim.navpolicy.agent.Image2NavAgent` (``reset(instruction, seed)``,
  ``act(rgb, executed) -> [Action, Action]``) backed by one server session per episode, so anything
  that drives the in-process agent (the evaluation runner's ``Image2NavAdapter``) drives the server.

Observations travel as PNG (lossless: the server sees exactly the array the client holds).
"""

from __future__ import annotations

import base64
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
from image2sim.simulator.conventions import Action


class ServerError(RuntimeError):
    """The server answered with an error status (``status``, ``detail``)."""

    def __init__(self, method: str, path: str, status: int, detail: str) -> None:
        super().__init__(f"{method} {path}: HTTP {status}: {detail}")
        self.status, self.detail = status, detail


def token_from_env(var: str | None, environ: dict | None = None) -> str | None:
    """The bearer token held by environment variable ``var`` (None when no variable is named)."""
    if not var:
        return None
    value = (os.environ if environ is None else environ).get(var, "")
    if not value:
        raise ValueError(f"token_env: the environment variable {var} is unset or empty")
    return value


def encode_png(rgb: np.ndarray) -> bytes:
    """(H, W, 3) uint8 RGB -> PNG bytes."""
    import cv2

    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb: expected (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError("rgb: OpenCV could not encode the PNG")
    return buf.tobytes()


@dataclass(frozen=True)
class StepReply:
    """The server's answer to one observation."""

    actions: list[Action]
    step: int


class PolicyClient:
    """Small synchronous client. ``client`` may be any ``httpx.Client`` (e.g. FastAPI's TestClient);
    otherwise one is opened on ``base_url``. The token goes in an ``Authorization: Bearer`` header."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        token: str | None = None,
        timeout_s: float = 60.0,
        client: Any | None = None,
        encoding: str = "multipart",
    ) -> None:
        import httpx

        if encoding not in ("multipart", "json"):
            raise ValueError(f"encoding: expected 'multipart' or 'json', got {encoding!r}")
        self.encoding = encoding
        self._own = client is None
        self.http = client if client is not None else httpx.Client(base_url=base_url, timeout=timeout_s)
        self.headers = {"Authorization": f"Bearer {token}"} if token else {}

    def _request(self, method: str, path: str, **kw) -> Any:
        r = self.http.request(method, path, headers=self.headers, **kw)
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except ValueError:
                detail = r.text
            raise ServerError(method, path, r.status_code, str(detail))
        return None if r.status_code == 204 else r.json()

    def health(self) -> dict:
        return self._request("GET", "/healthz")

    def info(self) -> dict:
        return self._request("GET", "/v1/info")

    def create_session(self, instruction: str, seed: int = 0) -> str:
        return self._request("POST", "/v1/sessions", json={"instruction": instruction, "seed": int(seed)})[
            "session_id"
        ]

    def step(self, session_id: str, rgb: np.ndarray, executed: list[int] | None = None) -> StepReply:
        """Send one observation (and the actions executed since the previous one, if given)."""
        png = encode_png(rgb)
        names = None if executed is None else [Action(int(a)).name for a in executed]
        path = f"/v1/sessions/{session_id}/step"
        if self.encoding == "json":
            body: dict = {"image_b64": base64.b64encode(png).decode("ascii")}
            if names is not None:
                body["executed"] = names
            doc = self._request("POST", path, json=body)
        else:
            data = None if names is None else {"executed": ",".join(names)}
            doc = self._request("POST", path, files={"image": ("obs.png", png, "image/png")}, data=data)
        return StepReply([Action[a] for a in doc["actions"]], int(doc["step"]))

    def close_session(self, session_id: str) -> None:
        self._request("DELETE", f"/v1/sessions/{session_id}")

    def close(self) -> None:
        if self._own:
            self.http.close()

    def __enter__(self) -> PolicyClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RemoteAgent:
    """:class:`~image2sim.navpolicy.agent.Image2NavAgent`'s interface over a server session.

    ``reset`` closes the previous episode's session and opens a new one; ``act`` sends the frame.
    """

    def __init__(self, client: PolicyClient) -> None:
        self.client = client
        self.session_id: str | None = None

    def reset(self, instruction: str, seed: int = 0) -> None:
        self.close()
        self.session_id = self.client.create_session(instruction, seed)

    def act(self, rgb: np.ndarray, executed: list[int] | None = None) -> list[Action]:
        if self.session_id is None:
            raise RuntimeError("RemoteAgent.act before reset: no session")
        return self.client.step(self.session_id, rgb, executed).actions

    def close(self) -> None:
        """Close the open session (if the server still has it)."""
        sid, self.session_id = self.session_id, None
        if sid is not None:
            try:
                self.client.close_session(sid)
            except ServerError as exc:
                if exc.status != 404:  # already expired: nothing to close
                    raise
