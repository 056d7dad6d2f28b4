"""Protocol records: published values, round trip, strict parsing, the mixing guard."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
from image2sim.eval.protocols import (
    IMAGE2SIM,
    PROTOCOLS,
    RXR_HABITAT,
    VLNCE,
    CameraSpec,
    Protocol,
    ProtocolError,
    ProtocolMismatchError,
    ensure_same_protocol,
    get_protocol,
)


def test_published_values() -> None:
    assert (IMAGE2SIM.max_steps, IMAGE2SIM.turn_angle_deg, IMAGE2SIM.forward_step_m) == (300, 15.0, 0.25)
    assert (IMAGE2SIM.camera.width, IMAGE2SIM.camera.height, IMAGE2SIM.camera.hfov_deg) == (336, 336, 90.0)
    assert IMAGE2SIM.allow_sliding and IMAGE2SIM.success_distance_m == 3.0
    assert (VLNCE.max_steps, VLNCE.turn_angle_deg, VLNCE.forward_step_m) == (500, 15.0, 0.25)
    assert (VLNCE.camera.width, VLNCE.camera.height, VLNCE.camera.hfov_deg) == (224, 224, 90.0)
    assert (VLNCE.agent_height_m, VLNCE.agent_radius_m, VLNCE.success_distance_m) == (1.5, 0.1, 3.0)
    # R2R-CE's camera is Habitat's default RGB sensor, 1.25 m up, not the 1.5 m agent height.
    assert VLNCE.eye_height_m == 1.25 and IMAGE2SIM.eye_height_m == IMAGE2SIM.agent_height_m == 1.25
    assert RXR_HABITAT.eye_height_m == RXR_HABITAT.agent_height_m == 0.88
    older = {k: v for k, v in VLNCE.to_dict().items() if k != "camera_height_m"}
    assert Protocol.from_dict(older).eye_height_m == 1.5  # records written before the field existed
    with pytest.raises(ProtocolError, match="camera_height_m"):
        dataclasses.replace(VLNCE, camera_height_m=2.0)
    cam = RXR_HABITAT.camera
    assert (RXR_HABITAT.turn_angle_deg, cam.width, cam.height) == (30.0, 640, 480)
    assert RXR_HABITAT.camera.hfov_deg == 79.0 and not RXR_HABITAT.allow_sliding
    wide = PROTOCOLS["image2sim-180"]
    assert (wide.camera.kind, wide.camera.width, wide.camera.height) == ("equirect", 512, 336)
    assert (wide.camera.hfov_deg, wide.camera.vfov_deg, wide.max_steps) == (180.0, 118.0, 300)
    assert set(PROTOCOLS) == {"image2sim", "image2sim-180", "vlnce", "rxr-habitat"}
    assert get_protocol("rxr-habitat") is RXR_HABITAT
    with pytest.raises(ProtocolError, match="unknown protocol 'r2r'"):
        get_protocol("r2r")


def test_pinhole_vfov_follows_aspect() -> None:
    cam = CameraSpec.pinhole(640, 480, 79.0)
    expected = math.degrees(2 * math.atan(math.tan(math.radians(39.5)) * 480 / 640))
    assert cam.vfov_deg == pytest.approx(expected, abs=1e-5)
    assert CameraSpec.pinhole(336, 336, 90.0).vfov_deg == pytest.approx(90.0)


@pytest.mark.parametrize("proto", list(PROTOCOLS.values()), ids=list(PROTOCOLS))
def test_round_trip_through_json(proto: Protocol) -> None:
    again = Protocol.from_dict(json.loads(json.dumps(proto.to_dict())))
    assert again == proto


def test_frozen_and_validated() -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        VLNCE.max_steps = 10  # type: ignore[misc]
    with pytest.raises(ProtocolError, match="success_distance_m"):
        dataclasses.replace(VLNCE, success_distance_m=-1.0)
    with pytest.raises(ProtocolError, match="max_steps"):
        dataclasses.replace(VLNCE, max_steps=0)
    with pytest.raises(ProtocolError, match="dtw"):
        dataclasses.replace(VLNCE, dtw="fast")  # type: ignore[arg-type]
    with pytest.raises(ProtocolError, match="camera.width"):
        CameraSpec("pinhole", 0, 10, 90.0, 90.0)


def test_from_dict_rejects_unknown_and_missing_fields() -> None:
    d = VLNCE.to_dict()
    d["succes_distance"] = 2.0
    with pytest.raises(ProtocolError, match=r"protocol: unknown field\(s\) \['succes_distance'\]"):
        Protocol.from_dict(d)
    d = VLNCE.to_dict()
    del d["camera"]["hfov_deg"]
    with pytest.raises(ProtocolError, match=r"protocol.camera: missing field\(s\) \['hfov_deg'\]"):
        Protocol.from_dict(d)


def test_guard_refuses_mixing() -> None:
    assert ensure_same_protocol([VLNCE, {"protocol": VLNCE.to_dict()}]) == VLNCE
    with pytest.raises(ProtocolMismatchError, match="'image2sim'.*'vlnce'"):
        ensure_same_protocol([VLNCE, IMAGE2SIM])
    # Same name, different value: still refused, and the differing field is named.
    tweaked = dataclasses.replace(VLNCE, success_distance_m=2.5)
    with pytest.raises(ProtocolMismatchError, match="success_distance_m"):
        ensure_same_protocol([{"protocol": VLNCE.to_dict()}, {"protocol": tweaked.to_dict()}])
    with pytest.raises(ProtocolError, match=r"result\[1\]: has no 'protocol'"):
        ensure_same_protocol([VLNCE, {"metrics": {}}])
    with pytest.raises(ProtocolError, match="no results"):
        ensure_same_protocol([])


def test_load_protocol_by_name_or_file(tmp_path) -> None:
    from image2sim.eval.protocols import load_protocol

    assert load_protocol("vlnce") == VLNCE
    tweaked = dataclasses.replace(VLNCE, name="mine", success_distance_m=0.5)
    bare, wrapped = tmp_path / "bare.json", tmp_path / "result.json"
    bare.write_text(json.dumps(tweaked.to_dict()))
    wrapped.write_text(json.dumps({"protocol": tweaked.to_dict(), "metrics": {}}))
    assert load_protocol(bare) == load_protocol(str(wrapped)) == tweaked
    with pytest.raises(ProtocolError, match="'nope' is neither a protocol name"):
        load_protocol("nope")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ProtocolError, match="invalid JSON"):
        load_protocol(tmp_path / "bad.json")
