"""Instruction annotation: quality gate, anti-hallucination, template variety, OpenAI backend on loopback."""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest
from image2sim.dataengine.annotate import (
    AnnotationRequest,
    MalformedReply,
    TemplateAnnotator,
    build_annotator,
    build_messages,
    compose,
    hallucinated_objects,
    parse_reply,
    route_style,
)
from image2sim.dataengine.annotate.openai_vlm import OpenAIAnnotator, OpenAIConfig, TransportError

VOCAB = ["sofa", "fridge", "table_lamp", "lamp", "chair", "dining_table", "bed"]


def _req(eid="e0", style="r2r", structure="sequential", tone="neutral", seed=0, images=()):
    return AnnotationRequest(
        episode_id=eid,
        movements=["walk forward", "turn left", "walk forward while turning right", "stop"],
        images=list(images),
        goal={"category": "fridge", "room_type": "kitchen"},
        visible=[["sofa", "chair"], ["chair"], ["fridge"], ["fridge"]],
        rooms=["living_room", "living_room", "kitchen", "kitchen"],
        style=style,
        structure=structure,
        tone=tone,
        seed=seed,
    )


# ----------------------------------------------------------------------------------------- parsing


def test_invalid_inside_reasoning_does_not_reject():
    r = parse_reply(
        "REASONING: frames look fine, nothing INVALID here, no clipping.\n"
        "VERDICT: VALID\nISSUES: none\nINSTRUCTION: Walk to the fridge."
    )
    assert r.valid and r.instruction == "Walk to the fridge." and r.issues == ()


def test_invalid_verdict_rejects_even_if_reasoning_says_valid():
    r = parse_reply(
        "REASONING: looks VALID at first.\nVERDICT: INVALID\nISSUES: wall_clipping, visual_freezing\n"
        "INSTRUCTION: Walk to the fridge."
    )
    assert not r.valid and r.issues == ("wall_clipping", "visual_freezing")


def test_multiline_fields_and_markdown_bold():
    r = parse_reply(
        "**REASONING**: line one\nline two\n**VERDICT**: VALID\n**INSTRUCTION**: Go ahead,\nthen stop."
    )
    assert r.valid and r.reasoning == "line one\nline two" and r.instruction == "Go ahead, then stop."


@pytest.mark.parametrize(
    "reply, why",
    [
        ("", "empty"),
        ("REASONING: fine\nINSTRUCTION: go", "no VERDICT"),
        ("VERDICT: MAYBE\nINSTRUCTION: go", "VALID or INVALID"),
        ("VERDICT: VALID\nVERDICT: INVALID\nINSTRUCTION: go", "more than once"),
        ("VERDICT: VALID\nREASONING: after\nINSTRUCTION: go", "before VERDICT"),
        ("REASONING: ok\nVERDICT: VALID", "without an INSTRUCTION"),
    ],
)
def test_malformed_replies(reply, why):
    with pytest.raises(MalformedReply, match=why):
        parse_reply(reply)


def test_hallucination_check_uses_allow_list_and_longest_names():
    assert hallucinated_objects("Pass the sofa and stop at the fridge.", {"sofa", "fridge"}, VOCAB) == set()
    assert hallucinated_objects("Walk past the bed to the fridge.", {"sofa", "fridge"}, VOCAB) == {"bed"}
    assert hallucinated_objects("Stop by the table lamp.", {"table_lamp"}, VOCAB) == set()  # not "lamp"
    assert hallucinated_objects("Go past the chairs.", {"fridge"}, VOCAB) == {"chair"}  # plural
    assert hallucinated_objects("Enter the bedroom.", {"fridge"}, VOCAB) == set()  # whole words only


# ---------------------------------------------------------------------------------------- template


def test_template_is_deterministic_and_lexically_varied():
    texts = {
        compose(_req(seed=s, style=st, structure=sc, tone=t))
        for s in range(6)
        for st in ("r2r", "reverie", "demand")
        for sc in ("sequential", "landmark_first", "compact")
        for t in ("neutral", "polite", "terse")
    }
    assert len(texts) > 60
    assert compose(_req(seed=4)) == compose(_req(seed=4))
    vocab = {w for t in texts for w in t.lower().split()}
    assert len(vocab) > 80


def test_template_names_only_allowed_objects():
    for s in range(40):
        for style in ("r2r", "reverie", "demand"):
            req = _req(seed=s, style=style)
            assert hallucinated_objects(compose(req), req.allowed_objects, VOCAB) == set(), compose(req)


def test_template_styles_differ_in_form():
    r2r = compose(_req(style="r2r", structure="sequential", seed=1))
    rev = [compose(_req(style="reverie", seed=s)) for s in range(10)]
    assert "fridge" in r2r.lower()
    assert any(" be " in t or "has been" in t or "is to be" in t for t in rev)  # passive voice


def test_style_router_mix():
    rng = np.random.default_rng(0)
    draws = [route_style(rng)[0] for _ in range(3000)]
    frac = {s: draws.count(s) / len(draws) for s in ("r2r", "reverie", "demand")}
    assert abs(frac["r2r"] - 0.4) < 0.04 and abs(frac["reverie"] - 0.3) < 0.04


def test_prompt_interleaves_images_and_movements():
    img = np.zeros((4, 8, 3), np.uint8)
    msgs = build_messages(_req(images=[img] * 4))
    parts = msgs[1]["content"]
    kinds = [p["type"] if p["type"] == "image" else p["text"].split("]")[0] + "]" for p in parts[:-1]]
    assert kinds == [
        "[image 1]",
        "image",
        "[movement 1]",
        "[image 2]",
        "image",
        "[movement 2]",
        "[image 3]",
        "image",
        "[movement 3]",
        "[image 4]",
        "image",
        "[STOP]",
    ]
    assert "VERDICT" in msgs[0]["content"] and "REASONING" in msgs[0]["content"]


def test_unknown_annotator_and_options_are_rejected():
    with pytest.raises(ValueError, match="unknown annotator"):
        build_annotator("gpt")
    with pytest.raises(ValueError, match="unknown option"):
        build_annotator("openai", base_urll="http://x")
    assert isinstance(build_annotator("template"), TemplateAnnotator)


# ------------------------------------------------------------------------------ openai on loopback


class _Server:
    """A minimal chat-completions server; ``script`` maps the n-th request to (status, reply or delay)."""

    def __init__(self, script):
        self.script = script
        self.requests: list[dict] = []
        self.auth: list[str | None] = []
        self.lock = threading.Lock()
        self.in_flight = 0
        self.max_in_flight = 0
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):  # keep pytest output clean
                pass

            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                with outer.lock:
                    n = len(outer.requests)
                    outer.requests.append(body)
                    outer.auth.append(self.headers.get("Authorization"))
                    outer.in_flight += 1
                    outer.max_in_flight = max(outer.max_in_flight, outer.in_flight)
                try:
                    status, payload = outer.script(n, body)
                    if status == "sleep":
                        time.sleep(payload)
                        status, payload = 200, "VERDICT: VALID\nINSTRUCTION: late."
                    if status != 200:
                        self.send_response(status)
                        self.end_headers()
                        return
                    data = json.dumps(
                        {"choices": [{"message": {"role": "assistant", "content": payload}}]}
                    ).encode()
                    self.send_response(200)
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(data)))
                    self.end_headers()
                    self.wfile.write(data)
                except (BrokenPipeError, ConnectionResetError):
                    pass
                finally:
                    with outer.lock:
                        outer.in_flight -= 1

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/v1"

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def server_factory():
    servers = []

    def make(script):
        s = _Server(script)
        servers.append(s)
        return s

    yield make
    for s in servers:
        s.close()


GOOD = (
    "REASONING: the frames move, no INVALID geometry.\nVERDICT: VALID\nISSUES: none\n"
    "INSTRUCTION: Walk past the sofa and stop at the fridge."
)


def _ann(url, **kw):
    opts = dict(
        base_url=url, timeout=2.0, retries=2, backoff=0.01, max_concurrency=2, batch_size=4, max_attempts=2
    )
    opts.update(kw)
    return OpenAIAnnotator(OpenAIConfig(**opts), VOCAB)


def test_openai_sends_images_and_accepts_valid_reply(server_factory):
    srv = server_factory(lambda n, body: (200, GOOD))
    img = np.full((6, 10, 3), 200, np.uint8)
    out = _ann(srv.url).annotate([_req(images=[img] * 4)])
    assert out[0].accepted and out[0].text == "Walk past the sofa and stop at the fridge."
    parts = srv.requests[0]["messages"][1]["content"]
    urls = [p["image_url"]["url"] for p in parts if p["type"] == "image_url"]
    assert len(urls) == 4 and all(u.startswith("data:image/png;base64,") for u in urls)
    import base64

    import cv2

    dec = cv2.imdecode(np.frombuffer(base64.b64decode(urls[0].split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)
    assert dec.shape == (6, 10, 3) and int(dec[0, 0, 0]) == 200


def test_openai_retries_5xx_then_succeeds(server_factory):
    srv = server_factory(lambda n, body: (503, "") if n < 2 else (200, GOOD))
    out = _ann(srv.url).annotate([_req()])
    assert out[0].accepted and len(srv.requests) == 3


def test_openai_does_not_retry_4xx(server_factory):
    srv = server_factory(lambda n, body: (400, ""))
    with pytest.raises(TransportError, match="HTTP 400 \\(not retried\\)"):  # e.g. a wrong model name: fatal
        _ann(srv.url, max_attempts=1).annotate([_req()])
    assert len(srv.requests) == 1


def test_openai_timeout_is_retried(server_factory):
    srv = server_factory(lambda n, body: ("sleep", 1.5) if n == 0 else (200, GOOD))
    t0 = time.perf_counter()
    out = _ann(srv.url, timeout=0.3).annotate([_req()])
    assert out[0].accepted and len(srv.requests) == 2
    assert time.perf_counter() - t0 < 1.5  # the client did not wait for the slow answer


def test_openai_gives_up_after_retries(server_factory):
    srv = server_factory(lambda n, body: (500, ""))
    ann = _ann(srv.url, retries=1, max_attempts=2)
    with pytest.raises(TransportError, match="giving up after 2"):
        ann.complete(build_messages(_req()))
    # Transport failures that outlast the retries are fatal, never a dropped ("done") request.
    with pytest.raises(TransportError, match="giving up after 2"):
        ann.annotate([_req()])
    # One transport failure, then an answer: the request goes through.
    srv2 = server_factory(lambda n, body: (500, "") if n < 2 else (200, GOOD))
    out = _ann(srv2.url, retries=1, max_attempts=2).annotate([_req()])
    assert out[0].accepted and out[0].attempts == 2


def test_malformed_reply_is_retried_then_dropped_with_reason(server_factory):
    srv = server_factory(lambda n, body: (200, "I think this is fine."))
    out = _ann(srv.url, max_attempts=3).annotate([_req()])
    assert not out[0].accepted and out[0].reason == "malformed: no VERDICT field" and out[0].attempts == 3
    assert len(srv.requests) == 3
    srv2 = server_factory(lambda n, body: (200, "no verdict") if n == 0 else (200, GOOD))
    out = _ann(srv2.url).annotate([_req()])
    assert out[0].accepted and out[0].attempts == 2


def test_invalid_verdict_rejects_without_retry(server_factory):
    srv = server_factory(
        lambda n, body: (
            200,
            "REASONING: frozen frames.\nVERDICT: INVALID\nISSUES: visual_freezing\nINSTRUCTION: x",
        )
    )
    out = _ann(srv.url).annotate([_req()])
    assert not out[0].accepted and "visual_freezing" in out[0].reason and len(srv.requests) == 1


def test_hallucinating_reply_is_retried_then_dropped(server_factory):
    bad = "VERDICT: VALID\nINSTRUCTION: Walk past the bed to the fridge."
    srv = server_factory(lambda n, body: (200, bad))
    out = _ann(srv.url, max_attempts=2).annotate([_req()])
    assert not out[0].accepted and "bed" in out[0].reason


def test_concurrency_cap_and_order(server_factory):
    srv = server_factory(lambda n, body: ("sleep", 0.1))
    reqs = [_req(eid=f"e{i}") for i in range(7)]
    out = _ann(srv.url, max_concurrency=3, batch_size=5, timeout=5).annotate(reqs)
    assert [a.episode_id for a in out] == [f"e{i}" for i in range(7)]
    assert all(a.accepted for a in out)
    assert 1 < srv.max_in_flight <= 3


# ------------------------------------------------------------------------- template grammar and truth

_IMPERATIVE_VERBS = {
    "walk", "go", "head", "continue", "move", "turn", "make", "rotate", "face", "curve", "veer", "take",
    "pause", "bear", "stop", "wait", "halt", "find", "check", "inspect", "locate", "get", "bring", "grab",
    "fetch", "climb", "pass",
}  # fmt: skip
_MOVEMENTS = [
    "walk forward", "turn left", "turn right", "walk forward while turning left",
    "walk forward while turning right", "turn left and walk forward", "turn right and walk forward",
    "turn around to the left", "turn around to the right", "turn slightly left", "turn slightly right",
]  # fmt: skip


def _sentences(text: str) -> list[str]:
    import re

    return [s for s in re.split(r"(?<=[.?])\s+", text.strip()) if s]


def _grammar_problems(text: str) -> list[str]:
    """Rules every template sentence must satisfy (each one a defect seen in generated data)."""
    import re

    bad = []
    if re.search(r"\s{2,}|\s[,.?;]|,,|\.\.|\?\.|\.\?", text):
        bad.append("spacing or doubled punctuation")
    if re.search(r"\b(the|a|and|then|to)\s+\1\b", text, flags=re.I):
        bad.append("doubled word")
    for s in _sentences(text):
        if not (s[0].isupper() and s[-1] in ".?"):
            bad.append(f"sentence not capitalised or not closed: {s!r}")
        words = s.rstrip(".?").replace(",", "").split()
        if words[0] in ("Please", "Kindly") or words[:2] == ["Could", "you"]:
            verb = words[2] if words[0] == "Could" else words[1]
            if verb not in _IMPERATIVE_VERBS:
                bad.append(f"polite word before a non-verb {verb!r}: {s!r}")
        if words[:2] == ["Could", "you"] and not s.endswith("?"):
            bad.append(f"question without '?': {s!r}")
        if s.endswith("?") and not re.search(r"^(Could|Can|What|Where|Is)\b|,\s*(can|could) you\b", s):
            bad.append(f"'?' on a statement: {s!r}")
        for m in re.finditer(r"\b(if you|to reach it,)\s+(\w+)", s):
            if m.group(2) not in _IMPERATIVE_VERBS:
                bad.append(f"{m.group(1)!r} followed by {m.group(2)!r}")
    return bad


GOALS = ["fridge", "table_lamp", "widget"]  # a demand entry, a two-word name, an unknown category


def test_every_template_and_fill_renders_a_grammatical_instruction():
    """All styles x structures x tones, every movement alone and in sequences, with and without room,
    landmarks and near objects, over many seeds (the synonym and join choices): no broken sentence
    ("Could you your target is ...", "Kindly the clock ... needs to be checked")."""
    from image2sim.dataengine.annotate.prompts import STRUCTURES, TONES

    seqs = (
        [[m] for m in _MOVEMENTS]
        + [
            [
                _MOVEMENTS[i],
                _MOVEMENTS[(3 * i + 1) % len(_MOVEMENTS)],
                _MOVEMENTS[(5 * i + 2) % len(_MOVEMENTS)],
            ]
            for i in range(len(_MOVEMENTS))
        ]
        + [[]]
    )
    n = 0
    problems = []
    for style in ("r2r", "reverie", "demand"):
        for structure in STRUCTURES:
            for tone in TONES:
                for k, moves in enumerate(seqs):
                    for room in ("kitchen", None):
                        for seed in range(12):
                            # Every other request carries the engine's geometry (distances, turns,
                            # doorways), which R2R routes are built from.
                            geo = seed % 4 < 2 and bool(moves)
                            dist = [
                                0.0 if m.startswith("turn") else 0.8 + 0.7 * j for j, m in enumerate(moves)
                            ]
                            req = AnnotationRequest(
                                episode_id="g",
                                movements=[*moves, "stop"],
                                images=[],
                                goal={"category": GOALS[seed % 3], "room_type": room},
                                visible=[["sofa", "dining_table"], ["chair"], []][: len(moves)] + [[]],
                                rooms=[room] * (len(moves) + 1),
                                style=style,
                                structure=structure,
                                tone=tone,
                                seed=seed + 100 * k,
                                near=["sofa", "floor_lamp"] if seed % 2 else [],
                                distances=[*dist, 0.0] if geo else [],
                                turns=[(-1) ** j * 40.0 * (j + 1) for j in range(len(moves))] + [0.0]
                                if geo
                                else [],
                                features=[["doorway"] if j == 1 else [] for j in range(len(moves) + 1)]
                                if geo
                                else [],
                            )
                            text = compose(req)
                            n += 1
                            problems += [(p, text) for p in _grammar_problems(text)]
    assert n > 4000
    assert not problems, problems[:5]


@pytest.mark.parametrize(
    "text",
    [
        "Could you your target is the table lamp. walk forward?",
        "Kindly the clock in the kitchen near the small plant needs to be checked.",
        "Please the tv near the bed is to be found.",
        "Walk forward,  and stop.",
        "Could you walk forward.",
    ],
)
def test_the_grammar_rules_catch_the_reported_sentences(text):
    assert _grammar_problems(text)


def test_r2r_routes_from_geometry_give_distances_turns_doorways_landmarks_and_the_goal():
    """With the engine's geometry an R2R instruction is a followable route: walks summed into metres,
    turns of 30 degrees or more, doorways, objects seen along a walk (never the goal), then the goal."""
    moves = ["walk forward"] * 3 + ["turn left", "walk forward", "walk forward", "stop"]
    texts = []
    for seed in range(30):
        req = AnnotationRequest(
            episode_id="r",
            movements=moves,
            images=[],
            goal={"category": "fridge", "room_type": "kitchen"},
            visible=[["sofa"], ["sofa"], ["chair"], [], ["fridge"], ["fridge"], ["fridge"]],
            rooms=["living_room"] * 4 + ["kitchen"] * 3,
            style="r2r",
            structure="sequential",
            tone="neutral",
            seed=seed,
            distances=[1.0, 1.0, 1.0, 0.0, 1.0, 1.0, 0.0],
            turns=[0.0, 0.0, 0.0, 90.0, 0.0, 0.0, 0.0],
            features=[[], [], [], [], ["doorway"], [], []],
        )
        text = compose(req)
        texts.append(text)
        assert "3 meters" in text and "left" in text and "door" in text and "fridge" in text, text
        assert text.index("3 meters") < text.index("left") < text.index("door") < text.index("fridge"), text
        assert text.count("fridge") == 1, text  # the goal is never a landmark of the route
    assert any("sofa" in t or "chair" in t for t in texts)  # landmarks appear
    assert not all("sofa" in t or "chair" in t for t in texts)  # but not always
    # The compact structure keeps the whole route and names no landmark.
    compact = compose(dataclasses.replace(req, structure="compact"))
    assert "3 meters" in compact and "door" in compact and "sofa" not in compact and "chair" not in compact


def test_template_near_names_only_objects_near_the_goal():
    """A REVERIE "near X" names only ``req.near``, never just any visible object."""
    for s in range(60):
        req = _req(seed=s, style="reverie")
        req.near = ["sofa"] if s % 2 else []
        text = compose(req)
        if " near the " in text:
            assert s % 2 and "near the sofa" in text, text


def test_the_api_key_comes_only_from_the_environment(server_factory, monkeypatch):
    srv = server_factory(lambda n, body: (200, GOOD))
    monkeypatch.delenv("IMAGE2SIM_ANNOTATOR_API_KEY", raising=False)
    _ann(srv.url).annotate([_req()])
    monkeypatch.setenv("IMAGE2SIM_ANNOTATOR_API_KEY", "s3cret")
    _ann(srv.url).annotate([_req()])
    monkeypatch.setenv("MY_KEY", "other")
    _ann(srv.url, api_key_env="MY_KEY").annotate([_req()])
    assert srv.auth == [None, "Bearer s3cret", "Bearer other"]
    with pytest.raises(ValueError, match="never an option.*IMAGE2SIM_ANNOTATOR_API_KEY"):
        build_annotator("openai", VOCAB, api_key="s3cret")
    with pytest.raises(ValueError, match="api_key_env"):
        build_annotator("openai", VOCAB, api_key_env="not a name")
