"""Named evaluation protocols: the settings that make two navigation numbers comparable.

Published VLN-CE numbers are often incomparable because the protocol differs silently (success
radius, step limit, turn angle, camera, exact vs approximate DTW). Every result file written by
:mod:`image2sim.eval` therefore carries the full :class:`Protocol` record, and
:func:`ensure_same_protocol` refuses to combine results produced under different protocols.

Built-in protocols
    ``image2sim``    the seed paper's: 300 steps, 15° turns, 0.25 m forward, 336×336 pinhole at
                     90° HFOV/VFOV, sliding on, success 3.0 m, agent radius 0.15 m, eye 1.25 m.
    ``vlnce``        R2R-CE as published (VLN-CE ``vlnce_task.yaml`` + Habitat defaults): 500 steps,
                     15° turns, 0.25 m forward, 224×224 RGB at HFOV 90, agent height 1.5 m,
                     radius 0.1 m, sliding on, success 3.0 m.
    ``image2sim-180`` as ``image2sim`` with the paper's ultra-wide camera: a 512×336 equirectangular
                     crop covering 180° × 118°.
    ``rxr-habitat``  the RxR-Habitat challenge (``rxr_vlnce_*_task.yaml``): 500 steps, 30° turns,
                     0.25 m forward, 640×480 RGB at HFOV 79, agent height 0.88 m, radius 0.18 m,
                     sliding off, success 3.0 m.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

CameraKind = Literal["pinhole", "equirect"]

PROTOCOL_KEY = "protocol"
"""Key under which every result file stores its protocol record."""


class ProtocolError(ValueError):
    """A protocol record is malformed or unknown."""


class ProtocolMismatchError(ValueError):
    """Results produced under different protocols were about to be combined."""


def _from_mapping(cls: type, data: Mapping[str, Any], where: str) -> dict[str, Any]:
    """Check ``data`` has exactly the fields of dataclass ``cls``; name ``where`` in errors."""
    if not isinstance(data, Mapping):
        raise ProtocolError(f"{where}: expected a mapping, got {type(data).__name__}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ProtocolError(f"{where}: unknown field(s) {unknown}; allowed: {sorted(names)}")
    optional = {f.name for f in dataclasses.fields(cls) if f.default is not dataclasses.MISSING}
    missing = sorted(names - set(data) - optional)  # optional fields may be absent in older records
    if missing:
        raise ProtocolError(f"{where}: missing field(s) {missing}")
    return dict(data)


@dataclass(frozen=True)
class CameraSpec:
    """The observation camera of a protocol."""

    kind: CameraKind
    """``"pinhole"`` or ``"equirect"``."""
    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    hfov_deg: float
    """Horizontal field of view in degrees."""
    vfov_deg: float
    """Vertical field of view in degrees (for a pinhole with square pixels it follows from hfov)."""

    def __post_init__(self) -> None:
        if self.kind not in ("pinhole", "equirect"):
            raise ProtocolError(f"camera.kind: expected 'pinhole' or 'equirect', got {self.kind!r}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                raise ProtocolError(f"camera.{name}: expected a positive int, got {value!r}")
        for name in ("hfov_deg", "vfov_deg"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0.0 < value <= 360.0):
                raise ProtocolError(f"camera.{name}: expected a value in (0, 360], got {value!r}")

    @classmethod
    def pinhole(cls, width: int, height: int, hfov_deg: float) -> CameraSpec:
        """A square-pixel pinhole camera; the vertical FOV follows from the aspect ratio."""
        half = math.radians(hfov_deg) / 2.0
        vfov = math.degrees(2.0 * math.atan(math.tan(half) * height / width))
        return cls("pinhole", width, height, float(hfov_deg), round(vfov, 6))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "camera") -> CameraSpec:
        """Inverse of :meth:`to_dict`; rejects unknown or missing fields."""
        return cls(**_from_mapping(cls, data, where))


@dataclass(frozen=True)
class Protocol:
    """A complete navigation evaluation protocol. Frozen: a protocol is an identity, not a knob."""

    name: str
    """Registry name, e.g. ``"vlnce"``."""
    max_steps: int
    """Episode step limit (actions, STOP included); the episode ends unsuccessfully beyond it."""
    turn_angle_deg: float
    """TURN_LEFT / TURN_RIGHT rotation in degrees."""
    forward_step_m: float
    """MOVE_FORWARD translation in metres."""
    camera: CameraSpec
    """The RGB observation camera."""
    agent_height_m: float
    """Agent body height above the floor in metres (also the camera height unless
    ``camera_height_m`` is set)."""
    agent_radius_m: float
    """Agent collision radius in metres."""
    allow_sliding: bool
    """Whether a blocked forward step slides along the obstacle."""
    success_distance_m: float
    """Success / oracle-success radius: geodesic distance to goal strictly below this counts."""
    ndtw_threshold_m: float
    """The ``threshold`` of nDTW / sDTW (VLN-CE uses the success distance)."""
    dtw: Literal["exact"]
    """DTW algorithm; only exact O(nm) DTW is implemented (VLN-CE's fastdtw is approximate)."""
    source: str
    """Where the values come from (paper / config file)."""
    camera_height_m: float | None = None
    """Camera height above the floor in metres when it differs from the body height (Habitat's RGB
    sensor sits at 1.25 m on a 1.5 m agent in R2R-CE); ``None``: ``agent_height_m``."""

    @property
    def eye_height_m(self) -> float:
        """Height of the observation camera above the floor."""
        return float(self.camera_height_m if self.camera_height_m is not None else self.agent_height_m)

    def __post_init__(self) -> None:
        if not self.name:
            raise ProtocolError("protocol.name: must be a non-empty string")
        if not isinstance(self.max_steps, int) or isinstance(self.max_steps, bool) or self.max_steps <= 0:
            raise ProtocolError(
                f"protocol {self.name}: max_steps must be a positive int, got {self.max_steps!r}"
            )
        for field in ("turn_angle_deg", "forward_step_m", "agent_height_m", "agent_radius_m",
                      "success_distance_m", "ndtw_threshold_m"):
            value = getattr(self, field)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ProtocolError(
                    f"protocol {self.name}: {field} must be a finite positive number, got {value!r}"
                )
        if self.camera_height_m is not None:
            h = self.camera_height_m
            if not (isinstance(h, (int, float)) and math.isfinite(h) and 0 < h <= self.agent_height_m):
                raise ProtocolError(
                    f"protocol {self.name}: camera_height_m must be a finite number in "
                    f"(0, agent_height_m = {self.agent_height_m}], got {h!r}"
                )
        if not isinstance(self.allow_sliding, bool):
            raise ProtocolError(f"protocol {self.name}: allow_sliding must be a bool")
        if self.dtw != "exact":
            raise ProtocolError(f"protocol {self.name}: dtw must be 'exact', got {self.dtw!r}")
        if not isinstance(self.camera, CameraSpec):
            raise ProtocolError(f"protocol {self.name}: camera must be a CameraSpec")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record (nested camera as a dict)."""
        out = dataclasses.asdict(self)
        out["camera"] = self.camera.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = PROTOCOL_KEY) -> Protocol:
        """Inverse of :meth:`to_dict`; rejects unknown or missing fields, naming ``where``."""
        fields = _from_mapping(cls, data, where)
        fields["camera"] = CameraSpec.from_dict(fields["camera"], f"{where}.camera")
        return cls(**fields)


IMAGE2SIM = Protocol(
    name="image2sim",
    max_steps=300,
    turn_angle_deg=15.0,
    forward_step_m=0.25,
    camera=CameraSpec("pinhole", 336, 336, 90.0, 90.0),
    agent_height_m=1.25,
    agent_radius_m=0.15,
    allow_sliding=True,
    success_distance_m=3.0,
    ndtw_threshold_m=3.0,
    dtw="exact",
    source="Image2Sim paper: Sec. 4 (336x336, 90 deg HFOV/VFOV) and appendix (radius 0.15 m, eye 1.25 m, "
    "0.25 m / 15 deg actions, wall sliding); 300-step limit",
)

VLNCE = Protocol(
    name="vlnce",
    max_steps=500,
    turn_angle_deg=15.0,
    forward_step_m=0.25,
    camera=CameraSpec("pinhole", 224, 224, 90.0, 90.0),
    agent_height_m=1.5,
    agent_radius_m=0.1,
    allow_sliding=True,
    success_distance_m=3.0,
    ndtw_threshold_m=3.0,
    dtw="exact",
    source="R2R-CE: VLN-CE habitat_extensions/config/vlnce_task.yaml with Habitat agent defaults "
    "(agent 1.5 m tall, radius 0.1 m; RGB sensor at the default position [0, 1.25, 0])",
    camera_height_m=1.25,
)

RXR_HABITAT = Protocol(
    name="rxr-habitat",
    max_steps=500,
    turn_angle_deg=30.0,
    forward_step_m=0.25,
    camera=CameraSpec.pinhole(640, 480, 79.0),
    agent_height_m=0.88,
    agent_radius_m=0.18,
    allow_sliding=False,
    success_distance_m=3.0,
    ndtw_threshold_m=3.0,
    dtw="exact",
    source="RxR-Habitat challenge: VLN-CE habitat_extensions/config/rxr_vlnce_english_task.yaml",
)

IMAGE2SIM_180 = dataclasses.replace(
    IMAGE2SIM,
    name="image2sim-180",
    camera=CameraSpec("equirect", 512, 336, 180.0, 118.0),
    source="Image2Sim paper: the ultra-wide setting of Table 2 (512x336 equirectangular crop, "
    "180 deg HFOV x 118 deg VFOV); otherwise as 'image2sim'",
)

PROTOCOLS: Mapping[str, Protocol] = {p.name: p for p in (IMAGE2SIM, IMAGE2SIM_180, VLNCE, RXR_HABITAT)}
"""Built-in protocols by name."""


def get_protocol(name: str) -> Protocol:
    """Look a built-in protocol up by name; the error lists the known names."""
    try:
        return PROTOCOLS[name]
    except KeyError:
        raise ProtocolError(f"unknown protocol {name!r}; known: {sorted(PROTOCOLS)}") from None


def load_protocol(name_or_file: str | Path) -> Protocol:
    """A built-in protocol by name, or the protocol record in a JSON file (bare, or under the
    ``protocol`` key of a result file); the error names the value and the known names."""
    if str(name_or_file) in PROTOCOLS:
        return PROTOCOLS[str(name_or_file)]
    path = Path(name_or_file)
    if not path.is_file():
        raise ProtocolError(
            f"{str(name_or_file)!r} is neither a protocol name {sorted(PROTOCOLS)} nor a file"
        )
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ProtocolError(f"{path}: invalid JSON ({exc})") from None
    if not isinstance(doc, Mapping):
        raise ProtocolError(f"{path}: expected a JSON object holding a protocol record")
    return Protocol.from_dict(doc.get(PROTOCOL_KEY, doc), str(path))


def protocol_of(record: Protocol | Mapping[str, Any], where: str = "result") -> Protocol:
    """The protocol of a result record: a :class:`Protocol`, or a mapping with a ``protocol`` key."""
    if isinstance(record, Protocol):
        return record
    if not isinstance(record, Mapping) or PROTOCOL_KEY not in record:
        raise ProtocolError(
            f"{where}: has no {PROTOCOL_KEY!r} record; results without a protocol are refused"
        )
    value = record[PROTOCOL_KEY]
    return value if isinstance(value, Protocol) else Protocol.from_dict(value, f"{where}.{PROTOCOL_KEY}")


def ensure_same_protocol(records: Iterable[Protocol | Mapping[str, Any]]) -> Protocol:
    """Return the single protocol shared by ``records``; raise if they differ or there are none.

    Two records match only if every field is equal, so a locally modified copy of ``vlnce`` (say
    with a 2.5 m success radius) is refused even though its name is the same.
    """
    first: Protocol | None = None
    for i, record in enumerate(records):
        proto = protocol_of(record, f"result[{i}]")
        if first is None:
            first = proto
        elif proto != first:
            diff = sorted(k for k, v in proto.to_dict().items() if first.to_dict()[k] != v)
            raise ProtocolMismatchError(
                f"result[{i}] was produced under protocol {proto.name!r}, result[0] under {first.name!r} "
                f"(differing fields: {diff}); results from different protocols are never averaged together"
            )
    if first is None:
        raise ProtocolError("no results given: cannot determine a protocol")
    return first
