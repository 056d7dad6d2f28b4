"""``image2sim data lift`` end to end on RGB-only procedural houses, video frame selection, and errors.

Depth comes from a stub that returns each view's exact depth in reconstruction units (part B's
depth sources are tested in tests/simulator/test_lift_depth.py and test_lift_mvs.py), so what is
checked here is everything around it: poses, scale, gravity, the written capture, confidence,
panorama assembly and the manifest record.
"""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest
from image2sim.simulator.io import open_capture
from image2sim.simulator.lift import capture as lift_capture
from image2sim.simulator.lift.frames import load_frames
from image2sim.simulator.lift.scale import rotation_errors_deg, scale_error, umeyama

from tests.simulator.lift_helpers import (
    PANO_WALK,
    WALK,
    eye_height,
    gt_poses,
    rgb_folder,
    synth_house,
    truth_depth_fn,
)


@pytest.fixture(autouse=True)
def _one_sfm_thread(monkeypatch):
    """COLMAP's verification and mapping are not reproducible with several threads (docs/lift.md,
    "Reproducibility of SfM"): under CI load a second lift of the same photos once found no floor.
    One thread makes every lift in these tests the same reconstruction."""
    run_sfm = lift_capture.run_sfm
    monkeypatch.setattr(
        lift_capture,
        "run_sfm",
        lambda frames, options, **kw: run_sfm(frames, dataclasses.replace(options, num_threads=1), **kw),
    )


def _abs_rel(est, true):
    ok = (est > 0) & (true > 0)
    return float(np.mean(np.abs(est[ok] - true[ok]) / true[ok])), float(ok.mean())


def _check_lifted(out, scene, *, max_scale_error, max_abs_rel):
    cap = open_capture(out)
    truth = gt_poses(scene)
    gt = open_capture(scene)
    ids = cap.frame_ids
    est = cap.poses
    true = np.stack([truth[f] for f in ids])
    # Metric and gravity-aligned: an SE(3) about +Z alone (no scale) must bring the poses home.
    s, R, _ = umeyama(est[:, :3, 3], true[:, :3, 3])
    assert abs(1 / s - 1) < max_scale_error and scale_error(est[:, :3, 3], true[:, :3, 3]) < max_scale_error
    assert np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))) < 1.0  # world up already +Z
    assert np.abs(est[:, 2, 3] - true[:, 2, 3]).max() < 0.05  # heights above the floor (z = 0)
    assert rotation_errors_deg(est[:, :3, :3], true[:, :3, :3], R).max() < 1.0
    rels = []
    for i, fid in enumerate(ids):
        frame = cap[i]
        assert frame.confidence is not None and frame.confidence.shape == frame.depth.shape
        rel, cover = _abs_rel(frame.depth, gt[gt.frame_ids.index(fid)].depth)
        rels.append(rel)
        assert cover > 0.9
    assert np.median(rels) < max_abs_rel
    return cap


@pytest.mark.slow
def test_lift_pinhole_house_writes_a_metric_capture(tmp_path, run_main, monkeypatch):
    scene = synth_house(tmp_path / "pin", camera="pinhole", views=20, height=240, width=320, config=WALK)
    monkeypatch.setattr(lift_capture, "_default_depth_fn", lambda: truth_depth_fn(scene))
    images = rgb_folder(scene, tmp_path / "photos")
    out = tmp_path / "lifted"
    eye = eye_height(scene)
    code, text = run_main(["data", "lift", str(images), "--out", str(out), "--camera-height", f"{eye}"])
    assert code == 0, text
    cap = _check_lifted(out, scene, max_scale_error=0.03, max_abs_rel=0.03)
    # A view facing a bare wall may not register: it is dropped, named, and the rest is lifted.
    assert len(cap) >= 18 and f"lifted {len(cap)} of 20 frames" in text
    assert cap.camera.model == "pinhole" and cap.camera.fx == pytest.approx(160.0, rel=0.01)
    record = json.loads((out / "manifest.json").read_text())["metadata"]["lift"]
    assert record["scale_method"] == "camera_height" and record["depth_source"] == "mvs"
    assert record["registered"] == len(cap) and len(record["dropped"]) == 20 - len(cap)
    for item in record["dropped"]:
        assert f"dropped {item['frame_id']}: not registered by structure-from-motion" in text
    assert 0 < record["scale_uncertainty"] < 0.03
    assert set(record["timings_s"]) == {"frames", "sfm", "depth", "scale", "planes", "write"}
    assert record["plane_fill"]["confidence"] == 0.03 and record["plane_fill"]["pixels"] >= 0
    # An existing output is refused before any work, naming it.
    code, text = run_main(["data", "lift", str(images), "--out", str(out), "--camera-height", "1.5"])
    assert code == 2 and "lifted: already exists" in text and "Traceback" not in text


def _true_length(scene, frame_id: str, a, b) -> float:
    """Metres between the surface points seen at pixels ``a`` and ``b`` (column, row) of a pinhole frame."""
    gt = open_capture(scene)
    frame = gt[gt.frame_ids.index(frame_id)]
    cam, pose = gt.camera, gt_poses(scene)[frame_id]
    ends = []
    for x, y in (a, b):
        z = float(frame.depth[y, x])
        assert z > 0
        p = np.array([(x + 0.5 - cam.cx) / cam.fx * z, (y + 0.5 - cam.cy) / cam.fy * z, z])
        ends.append(pose[:3, :3] @ p + pose[:3, 3])
    return float(np.linalg.norm(ends[1] - ends[0]))


@pytest.mark.slow
def test_a_known_object_size_sets_the_scale(tmp_path, run_main, monkeypatch):
    """Two lengths measured between pixels of two photos (here from the house's exact depth, as a
    user would from a tape measure) scale the capture to metres, recorded with their uncertainty."""
    scene = synth_house(tmp_path / "pin", camera="pinhole", views=20, height=240, width=320, config=WALK)
    monkeypatch.setattr(lift_capture, "_default_depth_fn", lambda: truth_depth_fn(scene))
    images = rgb_folder(scene, tmp_path / "photos")
    gt = open_capture(scene)
    ids = gt.frame_ids
    # The two photos that see farthest (a view facing a bare wall may not register).
    far = sorted(ids, key=lambda f: -float(np.median(gt[ids.index(f)].depth)))[:2]
    sizes = []
    for fid, a, b in ((far[0], (60, 150), (260, 200)), (far[1], (40, 120), (280, 120))):
        sizes += ["--object-size", f"{fid}:{a[0]},{a[1]}:{b[0]},{b[1]}={_true_length(scene, fid, a, b):.4f}"]
    out = tmp_path / "lifted"
    code, text = run_main(["data", "lift", str(images), "--out", str(out), *sizes])
    assert code == 0, text
    _check_lifted(out, scene, max_scale_error=0.03, max_abs_rel=0.03)
    record = json.loads((out / "manifest.json").read_text())["metadata"]["lift"]
    assert record["scale_method"] == "object_size" and len(record["object_sizes"]) == 2
    assert 0 < record["scale_uncertainty"] < 0.03
    # Bad sizes are one-line errors before any work: an unknown image, a pixel outside it.
    for bad, message in [
        ("nope:1,1:5,5=1", "no input image 'nope'"),
        (f"{ids[0]}:1,1:500,5=1", "pixel (500, 5) lies outside the 320x240 image"),
        (f"{ids[0]}:1,1:5,5", "expected FRAME:X0,Y0:X1,Y1=METRES"),
    ]:
        code, text = run_main(
            ["data", "lift", str(images), "--out", str(tmp_path / "o"), "--object-size", bad]
        )
        assert code == 2 and message in text and "Traceback" not in text, (bad, text)
        assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_frames_without_valid_depth_are_dropped_and_named(tmp_path, run_main, monkeypatch):
    """A view the depth source leaves empty (a plain wall: MVS has no confident pixel) is not written:
    the strict reader refuses an all-invalid depth image, so the capture would not open."""
    scene = synth_house(tmp_path / "pin", camera="pinhole", views=10, height=240, width=320, config=WALK)
    truth = truth_depth_fn(scene)
    blank: set[bytes] = set()

    def depth_fn(views, **kw):
        out = truth(views, **kw)
        blank.add(views[2].image.tobytes())
        for view, est in zip(views, out, strict=True):
            if view.image.tobytes() in blank:
                est.depth[:] = 0.0
                est.confidence[:] = 0.0
        return out

    monkeypatch.setattr(lift_capture, "_default_depth_fn", lambda: depth_fn)
    # The floor fill could give the blank view's floor pixels depth; here the view stays empty.
    monkeypatch.setattr(lift_capture, "fill_floor", lambda views, estimates, *a, **k: (estimates, 0))
    images = rgb_folder(scene, tmp_path / "photos")
    out = tmp_path / "lifted"
    eye = eye_height(scene)
    # So could the plane fill, from the neighbours' depth projected into it (checked below).
    args = ["data", "lift", str(images), "--camera-height", f"{eye}"]
    code, text = run_main([*args, "--out", str(out), "--no-plane-fill"])
    assert code == 0, text
    record = json.loads((out / "manifest.json").read_text())["metadata"]["lift"]
    assert record["plane_fill"] == {"pixels": 0, "confidence": None} and "planes" not in record["timings_s"]
    empty = [d for d in record["dropped"] if d["reason"].startswith("no valid depth")]
    assert len(empty) == 1 and record["written"] == record["registered"] - 1
    assert f"dropped {empty[0]['frame_id']}: no valid depth" in text
    assert f"lifted {record['written']} of 10 frames" in text
    cap = open_capture(out)
    assert empty[0]["frame_id"] not in cap.frame_ids and len(cap) == record["written"]
    for i in range(len(cap)):
        assert cap[i].depth.any()  # every written frame reads under the strict reader
    # With the plane fill, the neighbours' depth may complete the blank view's planar segments (a
    # fresh-clone CI run wrote it so); whatever depth it then has is the plane fill's alone.
    filled_out = tmp_path / "lifted_planes"
    code, text = run_main([*args, "--out", str(filled_out)])
    assert code == 0, text
    refilled = open_capture(filled_out)
    if empty[0]["frame_id"] in refilled.frame_ids:  # written: its depth is the plane fill's alone
        frame = refilled[refilled.frame_ids.index(empty[0]["frame_id"])]
        conf = frame.confidence[frame.depth > 0]
        assert conf.size and np.all(np.abs(conf - 8 / 255) < 0.5 / 255)
    # No frame with any depth: an error naming the input, nothing written.
    monkeypatch.setattr(
        lift_capture,
        "_default_depth_fn",
        lambda: (
            lambda views, **kw: [
                type(e)(depth=np.zeros_like(e.depth), confidence=np.zeros_like(e.confidence))
                for e in truth(views, **kw)
            ]
        ),
    )
    code, text = run_main(["data", "lift", str(images), "--out", str(tmp_path / "none")])
    assert code == 2 and "no registered frame got any valid depth" in text and "Traceback" not in text
    assert not (tmp_path / "none").exists()


@pytest.mark.parametrize("mapper", ["incremental", pytest.param("global", marks=pytest.mark.slow)])
def test_lift_panorama_house_writes_an_equirect_capture(tmp_path, run_main, monkeypatch, mapper):
    scene = synth_house(
        tmp_path / "pano", camera="equirect", views=8, height=256, width=512, config=PANO_WALK
    )
    truth = truth_depth_fn(scene)
    asked: list[dict] = []

    def depth_fn(views, **kw):
        asked.append({k: kw.get(k) for k in ("source", "model_dir")})
        return truth(views, **kw)

    monkeypatch.setattr(lift_capture, "_default_depth_fn", lambda: depth_fn)
    out = tmp_path / "lifted"
    args = ["data", "lift", str(rgb_folder(scene, tmp_path / "panos")), "--out", str(out)]
    args += ["--depth", "mvs+model", "--depth-model", str(tmp_path / "prior")]
    code, text = run_main([*args, "--camera-height", f"{eye_height(scene)}", "--mapper", mapper])
    assert code == 0, text
    assert asked == [{"source": "mvs+model", "model_dir": str(tmp_path / "prior")}]
    cap = _check_lifted(out, scene, max_scale_error=0.03, max_abs_rel=0.05)
    assert cap.camera.model == "equirect" and (cap.camera.height, cap.camera.width) == (256, 512)
    record = json.loads((out / "manifest.json").read_text())["metadata"]["lift"]
    assert record["sfm"]["mapper"] == mapper and record["depth_source"] == "mvs+model"
    assert record["depth_model"] == str(tmp_path / "prior") and "depth mvs+model" in text


def test_bad_options_are_one_line_errors(tmp_path, run_main):
    folder = tmp_path / "imgs"
    folder.mkdir()
    cases = [
        (["--depth", "lidar"], "--depth must be mvs, model or mvs+model"),
        (["--depth", "mvs+model"], "--depth mvs+model needs --depth-model"),
        (["--depth", "model"], "--depth model needs --depth-model"),
        (["--baseline", "1.0"], "--baseline needs --baseline-frames"),
        (["--camera-height", "1.5", "--baseline", "1", "--baseline-frames", "a", "b"], "not both"),
        (
            ["--camera-height", "1.5", "--object-size", "a:1,1:2,2=1"],
            "not both --camera-height and --object-size",
        ),
        (["--camera-model", "FISHEYE"], "--camera-model must be one of SIMPLE_PINHOLE, PINHOLE"),
        (["--mapper", "hierarchical"], "--mapper must be one of incremental, global"),
        ([], "no images (.png, .jpg, .jpeg) in this folder"),
    ]
    for extra, message in cases:
        code, text = run_main(["data", "lift", str(folder), "--out", str(tmp_path / "o"), *extra])
        assert code == 2 and message in text and "Traceback" not in text, (extra, text)
        assert not (tmp_path / "o").exists()
    code, text = run_main(["data", "lift", str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "o")])
    assert code == 2 and "missing.mp4: no such folder or video file" in text


def test_video_frames_skip_blurred_and_redundant_ones(tmp_path):
    scene = synth_house(tmp_path / "vid", camera="pinhole", views=8, height=240, width=320, config=WALK)
    frames = [cv2.imread(str(p)) for p in sorted((scene / "frames").glob("*_rgb.png"))]
    video = tmp_path / "walk.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 4.0, (320, 240))
    sequence = []
    for i, f in enumerate(frames):
        sequence.append(cv2.GaussianBlur(f, (0, 0), 4.0) if i == 3 else f)  # frame 3: motion blur
        if i == 5:
            sequence.append(f)  # frame 5 twice: the camera stood still
    for f in sequence:
        writer.write(f)
    writer.release()
    got = load_frames(video, fps=4.0)
    assert not got.panorama and got.ids == [f"f{i:06d}" for i in range(len(got))]
    reasons = dict(got.rejected)
    assert reasons["video frame 3"].startswith("blurred")
    assert reasons["video frame 6"].startswith("redundant")
    assert len(got) == 7
    assert len(load_frames(video, fps=2.0)) < len(got)  # sampling every other frame
    capped = load_frames(video, fps=4.0, max_frames=3)
    assert len(capped) == 3 and sum(r.startswith("left out") for _, r in capped.rejected) == 4


def test_train_depth_prior_cli_trains_saves_and_refuses_bad_input(tmp_path, run_main):
    house = synth_house(tmp_path / "h", camera="equirect", views=2, height=32, width=64, config=PANO_WALK)
    out = tmp_path / "prior"
    small = ["--set", "image_size=28", "--set", "hidden_size=16", "--set", "heads=2", "--set", "batch_size=2"]
    command = ["data", "train-depth-prior"]
    code, text = run_main([*command, str(house), "--out", str(out), "--steps", "2", *small])
    assert code == 0, text
    assert "depth prior:" in text and "saved to" in text
    assert (out / "model.safetensors").is_file() and (out / "preprocessor_config.json").is_file()
    record = json.loads((out / "depth_prior.json").read_text())
    assert record["config"]["steps"] == 2 and record["config"]["image_size"] == 28
    cases = [
        (["--set", "size=3"], "unknown depth-prior option(s) ['size']"),
        (["--set", "image_size=30"], "multiple of 14"),
        (["--set", "oops"], "expected KEY=VALUE"),
    ]
    for extra, message in cases:
        code, text = run_main([*command, str(house), "--out", str(tmp_path / "x"), *extra])
        assert code == 2 and message in text, text
    code, text = run_main([*command, str(house), "--out", str(out)])
    assert code == 2 and "already exists" in text
    code, text = run_main([*command, str(tmp_path / "absent"), "--out", str(tmp_path / "y")])
    assert code == 2 and "absent" in text
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
