"""The bad-input matrix (issue 23): every command that reads a capture meets a dozen broken captures.

Each pair must end with one clear line naming the bad file or field, exit status 2 (bad input), no
traceback and no output written. The captures are copies of one procedural capture with a single
defect each, so a new reader or command inherits the whole matrix by being added to ``COMMANDS``.
"""

from __future__ import annotations

import json
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

FRAME = "00001"


def _png_declaring(width: int, height: int) -> bytes:
    """A PNG whose header declares ``width x height`` 16-bit grey pixels, with almost no data."""
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    body = struct.pack(">I", len(ihdr)) + chunk + struct.pack(">I", zlib.crc32(chunk))
    idat = zlib.compress(b"\0" * 1024)
    body += struct.pack(">I", len(idat)) + b"IDAT" + idat + struct.pack(">I", zlib.crc32(b"IDAT" + idat))
    end = struct.pack(">I", 0) + b"IEND" + struct.pack(">I", zlib.crc32(b"IEND"))
    return b"\x89PNG\r\n\x1a\n" + body + end


def _pose(cap: Path, edit) -> Path:
    path = cap / "frames" / f"{FRAME}_pose.json"
    doc = json.loads(path.read_text())
    m = np.array(doc["cam_to_world"], dtype=float)
    edit(m)
    path.write_text(json.dumps({"cam_to_world": m.tolist()}))  # json writes NaN as NaN
    return path


def _depth_like(cap: Path, value: int) -> Path:
    path = cap / "frames" / f"{FRAME}_depth.png"
    h, w = np.asarray(Image.open(path)).shape[:2]
    Image.fromarray(np.full((h, w), value, dtype=np.uint16)).save(path)
    return path


def _nan_pose(cap):
    return _pose(cap, lambda m: m.__setitem__((0, 3), np.nan))


def _skewed_pose(cap):
    return _pose(cap, lambda m: m.__setitem__((slice(0, 3), 0), m[:3, 0] * 1.5))


def _missing(name):
    def mutate(cap):
        path = cap / "frames" / f"{FRAME}_{name}"
        path.unlink()
        return path

    return mutate


def _garbage_rgb(cap):
    path = cap / "frames" / f"{FRAME}_rgb.png"
    path.write_bytes(b"this is not an image")
    return path


def _truncated_depth(cap):
    path = cap / "frames" / f"{FRAME}_depth.png"
    path.write_bytes(path.read_bytes()[:60])
    return path


def _huge_depth(cap):
    path = cap / "frames" / f"{FRAME}_depth.png"
    path.write_bytes(_png_declaring(32768, 16384))
    return path


def _small_rgb(cap):
    path = cap / "frames" / f"{FRAME}_rgb.png"
    img = Image.open(path)
    img.resize((img.width // 2, img.height // 2)).save(path)
    return path


def _bad_manifest(cap):
    path = cap / "manifest.json"
    path.write_text("{ not json")
    return path


def _no_frames(cap):
    shutil.rmtree(cap / "frames")
    (cap / "frames").mkdir()
    return cap / "frames"


DEFECTS = {
    "nan_pose": _nan_pose,
    "skewed_pose": _skewed_pose,
    "missing_pose": _missing("pose.json"),
    "missing_rgb": _missing("rgb.png"),
    "missing_depth": _missing("depth.png"),
    "garbage_rgb": _garbage_rgb,
    "truncated_depth": _truncated_depth,
    "huge_depth_header": _huge_depth,
    "zero_depth": lambda cap: _depth_like(cap, 0),
    "saturated_depth": lambda cap: _depth_like(cap, 65535),
    "rgb_depth_size_mismatch": _small_rgb,
    "bad_manifest": _bad_manifest,
    "no_frames": _no_frames,
}

COMMANDS = {
    "data inspect": lambda cap, out: ["data", "inspect", str(cap)],
    "data ingest": lambda cap, out: ["data", "ingest", str(cap), "--out", str(out)],
    "data fuse": lambda cap, out: ["data", "fuse", str(cap), "--out", str(out / "cloud.ply")],
    "sim navmap": lambda cap, out: ["sim", "navmap", str(cap), "--out", str(out / "n.npz"), "--no-graph"],
    "sim build-scene": lambda cap, out: ["sim", "build-scene", str(cap), "--out", str(out)],
}


@pytest.fixture(scope="module")
def good_capture(tmp_path_factory):
    from image2sim.dataengine.procedural import preset, synthesize

    return synthesize(preset("tiny"), tmp_path_factory.mktemp("good"), scenes=1, seed=0, progress=False)[0]


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_the_good_capture_passes(good_capture, tmp_path, command, run_main):
    code, output = run_main(COMMANDS[command](good_capture, tmp_path / "out"))
    assert code == 0, output


@pytest.mark.parametrize("defect", sorted(DEFECTS))
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_bad_capture_is_one_clear_error(good_capture, tmp_path, command, defect, run_main):
    cap = tmp_path / "cap"
    shutil.copytree(good_capture, cap)
    victim = DEFECTS[defect](cap)
    out = tmp_path / "out"
    code, output = run_main(COMMANDS[command](cap, out))
    assert code == 2, f"{command} on {defect}: exit {code}\n{output[-3000:]}"
    assert "Traceback" not in output, output[-3000:]
    named = {victim.name, FRAME, "manifest"} if defect != "no_frames" else {"frame", "no "}
    assert any(n in output for n in named), f"{command} on {defect} names neither file nor frame:\n{output}"
    written = [p for p in out.rglob("*") if p.is_file()] if out.exists() else []
    assert not written, f"{command} on {defect} wrote {written}"


# --- run inputs: configs and resume checkpoints ----------------------------------------------------


BAD_CONFIGS = {  # YAML text, what the error must name
    "config_unknown_key": ("curriculum:\n  total_stepz: 3\n", "total_stepz"),
    "config_not_yaml": ("curriculum: [1, 2\n", "cannot parse"),
    "config_bad_value": ("curriculum:\n  total_steps: -3\n", "total_steps"),
}


def _write_input(kind: str, folder: Path) -> tuple[Path, str]:
    """A broken run input and the text its error must contain."""
    if kind in BAD_CONFIGS:
        text, expected = BAD_CONFIGS[kind]
        path = folder / "cfg.yaml"
        path.write_text(text)
        return path, expected
    if kind == "checkpoint_garbage":
        path = folder / "bad.ckpt"
        path.write_bytes(b"garbage")
        return path, "bad.ckpt"
    if kind == "checkpoint_not_lightning":
        import torch

        path = folder / "weights.ckpt"
        torch.save({"weight": torch.zeros(2)}, path)
        return path, "not from Lightning"
    if kind == "checkpoint_pickled_object":
        import pickle

        path = folder / "evil.ckpt"
        path.write_bytes(pickle.dumps(Path("/")))  # a pickle, never unpickled beyond weights_only
        return path, "evil.ckpt"
    raise AssertionError(kind)


RUN_INPUTS = (
    *BAD_CONFIGS,
    "checkpoint_garbage",
    "checkpoint_not_lightning",
    "checkpoint_pickled_object",
)


@pytest.mark.parametrize("kind", RUN_INPUTS)
def test_sim_train_refuses_a_bad_config_or_checkpoint_before_writing(tmp_path, kind, run_main):
    path, expected = _write_input(kind, tmp_path)
    out = tmp_path / "run"
    flag = "--config" if kind.startswith("config") else "--resume"
    code, output = run_main(["sim", "train", flag, str(path), "--out", str(out), "--max-steps", "1"])
    assert code == 2 and expected in output, output[-3000:]
    assert "Traceback" not in output and not out.exists()
