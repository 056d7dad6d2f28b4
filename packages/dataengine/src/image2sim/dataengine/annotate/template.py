"""Offline, deterministic template annotator: instructions from macro-steps, rooms and mined objects.

Three styles (R2R, REVERIE, Demand) with structure and tone variants and synonym choices drawn from a
per-episode seed, so instructions vary lexically but the same request always gives the same text.
Only objects of the request's allow-list (visible at a macro-step start, or the goal) are named.
A request without a goal object (``data episodes --detector none``) gets a landmark-free R2R-style
path instruction: turns, distances, doorways and stairs (:func:`compose_path`). An R2R instruction to a
goal object is the same route (:func:`route_clauses`) with landmarks seen along it, then the goal,
when the request carries the macro-steps' geometry (the engine's always do).
"""

from __future__ import annotations

import numpy as np
from image2sim.dataengine.annotate.prompts import Annotation, AnnotationRequest

__all__ = ["TemplateAnnotator", "compose", "compose_path", "route_clauses"]

_VERB_SYNONYMS = {
    "walk forward": ["walk forward", "go straight", "head straight ahead", "continue forward", "move ahead"],
    "turn left": ["turn left", "make a left", "rotate to your left", "face left"],
    "turn right": ["turn right", "make a right", "rotate to your right", "face right"],
    "walk forward while turning left": [
        "walk forward while bearing left",
        "curve to the left as you walk",
        "veer left while moving ahead",
    ],
    "walk forward while turning right": [
        "walk forward while bearing right",
        "curve to the right as you walk",
        "veer right while moving ahead",
    ],
    "turn left and walk forward": [
        "turn left and walk ahead",
        "go left and continue",
        "take a left and keep going",
    ],
    "turn right and walk forward": [
        "turn right and walk ahead",
        "go right and continue",
        "take a right and keep going",
    ],
    "turn around to the left": ["turn around", "turn all the way around to your left"],
    "turn around to the right": ["turn around", "turn all the way around to your right"],
    "stay in place": ["pause for a moment"],
    "turn slightly left": ["turn slightly left", "bear a little to the left"],
    "turn slightly right": ["turn slightly right", "bear a little to the right"],
}
_STOP = [
    "stop next to the {g}",
    "wait beside the {g}",
    "stop when you reach the {g}",
    "halt near the {g}",
    "your destination is the {g}",
]
_PASS = ["past the {l}", "towards the {l}", "by the {l}", "alongside the {l}"]
_JOIN = ["then", "and then", "after that", "next"]
_DEMAND = {
    "fridge": ["I'm thirsty, can you grab me something cold?", "Could you get me a cold drink?"],
    "sofa": ["I'm tired and need to sit down somewhere comfy.", "Find me a place to relax, please."],
    "armchair": ["I'd like to sit down for a bit.", "Find me a comfortable seat."],
    "bed": ["I'm exhausted, I need somewhere to lie down.", "Take me where I can take a nap."],
    "tv": ["I want to watch the news.", "Let's watch a show."],
    "stove": ["I want to cook some pasta.", "Let's heat up dinner."],
    "sink": ["My hands are dirty, I need to wash them.", "I need some water to rinse this cup."],
    "toilet": ["I really need the restroom.", "Where can I go to the toilet?"],
    "bathtub": ["I'd love a warm bath.", "I want to soak for a while."],
    "desk": ["I need somewhere to write a letter.", "I have to get some work done at a table."],
    "bookshelf": ["I'm looking for something to read.", "Fetch me a good book."],
    "book_stack": ["I'm looking for something to read.", "Grab me a book, would you?"],
    "laptop": ["I need to check my email.", "Could you bring me the computer?"],
    "kettle": ["I'd like a cup of tea.", "Let's boil some water."],
    "microwave": ["I want to warm up my leftovers.", "Heat this up for me."],
    "cup": ["I need something to drink from.", "Bring me a mug, please."],
    "plant": ["The plants need watering.", "I want to check on the greenery."],
    "small_plant": ["The little plant needs water.", "Check whether the potted plant is dry."],
    "washing_machine": ["I need to do the laundry.", "These clothes need washing."],
    "wardrobe": ["I need a clean shirt.", "Get me a jacket, please."],
    "mirror": ["I want to check how I look.", "Is my hair a mess?"],
    "clock": ["What time is it?", "I need to check the time."],
    "dining_table": ["Let's have dinner.", "Where can we eat?"],
    "floor_lamp": ["It's too dark in here.", "Could you turn on some light?"],
    "table_lamp": ["It's too dark to read.", "I need more light."],
}
_POLITE = ["Please ", "Could you ", "Kindly "]
_AT = ["at the {l}", "by the {l}"]
"""Landmarks of turns in place (one does not turn "past" something)."""
_TURNS_IN_PLACE = {m for m in _VERB_SYNONYMS if m.startswith("turn") and "walk forward" not in m}


def _name(cat: str) -> str:
    return cat.replace("_", " ")


def _pick(rng: np.random.Generator, options):
    return options[int(rng.integers(len(options)))]


def _room(room: str | None) -> str:
    return _name(room) if room else ""


def _sentence(text: str, question: bool = False) -> str:
    """Capitalised, with one final mark."""
    text = text.strip().rstrip(".?")
    return text[0].upper() + text[1:] + ("?" if question else ".")


def _imperative(rng: np.random.Generator, text: str, tone: str) -> str:
    """One imperative sentence (lower-case verb first, no final mark) in the request's tone."""
    if tone == "polite":
        word = _pick(rng, _POLITE)
        return _sentence(word + text[0].lower() + text[1:], question=word.startswith("Could"))
    return _sentence(text)


_WALK_DISTANCE = [
    "walk forward about {n} meters",
    "go straight for about {n} meters",
    "continue ahead for about {n} meters",
    "head straight on for roughly {n} meters",
]
_WALK_SHORT = ["take a few steps forward", "walk forward a little", "move ahead a short way"]
_DOORWAY = ["go through the doorway", "pass through the doorway", "walk through the door"]
_STAIRS = {
    "stairs_up": ["go up the stairs", "walk up the stairs", "climb the stairs"],
    "stairs_down": ["go down the stairs", "walk down the stairs", "take the stairs down"],
}
_PATH_STOP = ["stop", "stop there", "wait there", "stop and wait"]


_TURN_CLAUSE = {
    "left": ["turn left", "make a left", "go left"],
    "right": ["turn right", "make a right", "go right"],
    "around": ["turn around", "turn all the way around"],
}
_TURN_MIN_DEG = 30.0
"""Net turns below this (in place, or accumulated while walking) are not mentioned."""
_CURVE_DEG = 60.0
"""Heading change accumulated while walking that closes the walk with a turn clause."""


def _turn_words(deg: float) -> str | None:
    if abs(deg) < _TURN_MIN_DEG:
        return None
    if abs(deg) >= 135.0:
        return "around"
    return "left" if deg > 0 else "right"


def _has_geometry(req: AnnotationRequest) -> bool:
    """Whether the request carries each macro-step's distance and turn (the engine's requests do;
    hand-made ones and older callers may give movement texts only)."""
    n = len([m for m in req.movements if m != "stop"])
    return n > 0 and len(req.distances) >= n and len(req.turns) >= n


def route_clauses(
    req: AnnotationRequest, rng: np.random.Generator, landmark_probability: float = 0.0
) -> list[str]:
    """The route as imperative clauses, from the macro-steps' geometry.

    Turns in place are summed into one clause ("turn left", "turn around"); walking steps are summed
    into one distance ("walk forward about 4 meters") until the heading has drifted by 60 degrees, a
    doorway or stairs come, or a turn in place; turns under 30 degrees are not mentioned. With
    ``landmark_probability`` > 0 a walk may name one object visible at one of its macro-steps
    ("... past the sofa"; never the goal, each object once)."""
    clauses: list[str] = []
    walk, drift, turn = 0.0, 0.0, 0.0
    seen: list[str] = []
    used: set[str] = {req.goal.get("category", "")}

    def say(clause: str) -> None:
        if not clauses or clauses[-1] != clause:
            clauses.append(clause)

    def flush_walk(merge_drift: bool = False) -> None:
        """Say the walk; its heading drift is said as a turn, or added to the pending turn in place
        (a curve to the right and a turn right read as one "turn right")."""
        nonlocal walk, drift, turn
        clause = None
        if walk >= 1.5:
            clause = _pick(rng, _WALK_DISTANCE).format(n=int(round(walk)))
        elif walk > 0.2:
            clause = _pick(rng, _WALK_SHORT)
        if clause is not None:
            marks = [v for v in seen if v not in used]
            if marks and landmark_probability > 0 and rng.random() < landmark_probability:
                mark = marks[int(rng.integers(len(marks)))]
                used.add(mark)
                clause += " " + _pick(rng, _PASS).format(l=_name(mark))
            say(clause)
        seen.clear()
        side = None if merge_drift else _turn_words(drift)
        if merge_drift:
            turn += drift
        walk, drift = 0.0, 0.0
        if side is not None:
            say(_pick(rng, _TURN_CLAUSE[side]))

    def flush_turn() -> None:
        nonlocal turn
        side = _turn_words(turn)
        turn = 0.0
        if side is not None:
            say(_pick(rng, _TURN_CLAUSE[side]))

    for i, move in enumerate(req.movements):
        if move == "stop":
            break
        features = req.features[i] if i < len(req.features) else []
        dist = req.distances[i] if i < len(req.distances) else 0.0
        deg = req.turns[i] if i < len(req.turns) else 0.0
        stairs = [f for f in features if f in _STAIRS]
        if stairs:
            flush_walk(merge_drift=_turn_words(turn) is not None)
            flush_turn()
            say(_pick(rng, _STAIRS[stairs[0]]))
            continue
        if dist < 0.2:  # a turn in place: said when the walk resumes, if large enough
            turn += deg
            continue
        if _turn_words(turn) is not None:
            flush_walk(merge_drift=True)
            flush_turn()
        else:  # too small to mention: part of the walk's drift
            drift, turn = drift + turn, 0.0
        walk += dist
        drift += deg
        seen.extend(v for v in (req.visible[i] if i < len(req.visible) else []) if v not in seen)
        if "doorway" in features:
            flush_walk()
            say(_pick(rng, _DOORWAY))
        elif abs(drift) >= _CURVE_DEG:
            flush_walk()
    flush_walk(merge_drift=_turn_words(turn) is not None)
    flush_turn()
    return clauses


def _join(rng: np.random.Generator, clauses: list[str], tone: str) -> str:
    joins = [", " if tone == "terse" else f", {_pick(rng, _JOIN)} " for _ in clauses[1:]]
    return clauses[0] + "".join(j + c for j, c in zip(joins, clauses[1:], strict=True)) if clauses else ""


def compose_path(req: AnnotationRequest) -> str:
    """A landmark-free R2R-style instruction from the macro-steps alone (no goal object): the
    :func:`route_clauses` joined like :func:`compose`'s R2R style, so the tones apply unchanged (the
    ``compact`` structure keeps every clause: without landmarks each one is needed)."""
    rng = np.random.default_rng([req.seed, 11])
    body = _join(rng, route_clauses(req, rng), req.tone)
    stop = _pick(rng, _PATH_STOP)
    return _imperative(rng, (body + ", and " + stop) if body else stop, req.tone)


_R2R_LANDMARK_PROBABILITY = 0.6
"""Chance that an R2R clause names an object seen along it."""


def _r2r_sentence(
    req: AnnotationRequest, rng: np.random.Generator, clauses: list[str], goal: str, room: str
) -> str:
    """The route's clauses, then the stop at the goal (optionally led by "Your target is ...")."""
    # "your destination is ..." only joins a route ("walk ..., and your destination is ..."): alone
    # it is no imperative.
    stops = _STOP if clauses else [t for t in _STOP if not t.startswith("your")]
    stop = _pick(rng, stops).format(g=goal) + (f" in the {room}" if room and rng.random() < 0.5 else "")
    if req.structure == "landmark_first":
        head = _sentence(f"your target is the {goal}" + (f" in the {room}" if room else "")) + " "
    else:
        head = ""
    body = _join(rng, clauses, req.tone)
    return head + _imperative(rng, (body + ", and " if body else "") + stop, req.tone)


def compose(req: AnnotationRequest) -> str:
    """The instruction text of one request (deterministic in ``req.seed``).

    Every sentence is built whole in its tone: a polite request wraps an imperative ("Please walk ...",
    "Could you find ...?"), never a declarative ("Could you your target is ..."); declaratives ("The
    painting ... needs to be checked.") stand alone. "Near" names only ``req.near`` (objects that are
    near the goal in the geometry).
    """
    if not req.goal.get("category"):
        return compose_path(req)
    rng = np.random.default_rng([req.seed, 7])
    goal = _name(req.goal.get("category", "object"))
    room = _room(req.goal.get("room_type"))
    moves = [m for m in req.movements if m != "stop" and m != "stay in place"]
    # Collapse consecutive duplicates ("walk forward, walk forward" -> one clause).
    merged: list[tuple[str, int]] = []
    for i, m in enumerate(req.movements):
        if m in ("stop", "stay in place"):
            continue
        if merged and merged[-1][0] == m:
            continue
        merged.append((m, i))
    if req.style == "r2r" and _has_geometry(req):
        # The route as walked: distances, turns, doorways and stairs, with landmarks (none in the
        # compact structure, which otherwise keeps every clause: each one is needed to follow it).
        clauses = route_clauses(req, rng, 0.0 if req.structure == "compact" else _R2R_LANDMARK_PROBABILITY)
        text = _r2r_sentence(req, rng, clauses, goal, room)
    elif req.style == "r2r":  # movement texts only (no geometry): one clause per kind of movement
        clauses = []
        used: set[str] = set()
        for m, i in merged:
            c = _pick(rng, _VERB_SYNONYMS.get(m, [m]))
            marks = [
                v
                for v in (req.visible[i] if i < len(req.visible) else [])
                if v not in used and v != req.goal.get("category")
            ]
            if marks and req.structure != "compact" and rng.random() < _R2R_LANDMARK_PROBABILITY:
                lm = marks[int(rng.integers(len(marks)))]
                used.add(lm)
                c += " " + _pick(rng, _AT if m in _TURNS_IN_PLACE else _PASS).format(l=_name(lm))
            clauses.append(c)
        if req.structure == "compact" and len(clauses) > 3:
            clauses = [clauses[0], clauses[len(clauses) // 2], clauses[-1]]
        text = _r2r_sentence(req, rng, clauses, goal, room)
    elif req.style == "reverie":
        where = f" in the {room}" if room else ""
        near = [v for v in req.near if v != req.goal.get("category")]
        near_txt = f" near the {_name(_pick(rng, near))}" if near and rng.random() < 0.7 else ""
        route = ""
        if req.structure == "sequential" and moves:
            route = _pick(rng, _VERB_SYNONYMS.get(moves[0], [moves[0]]))
        if req.tone == "polite":
            verb = _pick(rng, ["find", "check", "inspect", "locate"])
            text = _imperative(rng, f"{verb} the {goal}{where}{near_txt}", "polite")
            if route:
                text += " " + _sentence(f"to reach it, {route} and keep going until it is close")
        else:
            first = _pick(
                rng,
                [
                    f"the {goal}{where}{near_txt} should be inspected",
                    f"the {goal}{where}{near_txt} needs to be checked",
                    f"the {goal}{near_txt}{where} is to be found",
                    f"the {goal}{where} has been left{near_txt} and must be located",
                ],
            )
            tail = f"; it is reached if you {route} and keep going until it is close" if route else ""
            text = _sentence(first + tail)
    else:  # demand
        need = _pick(
            rng,
            _DEMAND.get(
                req.goal.get("category", ""), [f"I need the {goal}.", f"Can you find the {goal} for me?"]
            ),
        )
        ask = _pick(
            rng,
            [
                f"go to the {goal}",
                f"find the {goal}" + (f" in the {room}" if room else ""),
                "take me there",
                f"head over to the {goal} and wait there",
            ],
        )
        text = need if req.structure == "compact" else need + " " + _sentence(ask)
    return text


class TemplateAnnotator:
    """The offline default backend (never rejects: its inputs come from verified rollouts)."""

    name = "template"

    def annotate(self, requests: list[AnnotationRequest]) -> list[Annotation]:
        return [Annotation(r.episode_id, compose(r), r.style, r.structure, r.tone, True) for r in requests]
