"""Atomic output: the target holds the old or the complete new content, never a torn file."""

from __future__ import annotations

import json

import numpy as np
import pytest
from image2sim.simulator.io.atomic import atomic_open, atomic_path, write_json_atomic, write_text_atomic
from image2sim.simulator.io.ply import PlyError, read_ply, write_ply_vertices


def test_failed_write_keeps_the_old_file_and_leaves_no_temp(tmp_path):
    target = tmp_path / "a.txt"
    write_text_atomic(target, "old")
    with pytest.raises(RuntimeError), atomic_open(target) as handle:
        handle.write("half of the new")
        raise RuntimeError("killed mid-write")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_atomic_path_keeps_the_suffix_for_format_sniffing_writers(tmp_path):
    target = tmp_path / "sub" / "arrays.npz"
    with atomic_path(target) as tmp:
        assert tmp.suffix == ".npz" and tmp.parent == target.parent
        np.savez(tmp, x=np.arange(3))
    assert np.array_equal(np.load(target)["x"], np.arange(3))
    assert sorted(p.name for p in target.parent.iterdir()) == ["arrays.npz"]


def test_json_refuses_nan_and_converts_with_default(tmp_path):
    with pytest.raises(ValueError):
        write_json_atomic(tmp_path / "m.json", {"psnr": float("nan")})
    assert not (tmp_path / "m.json").exists()
    write_json_atomic(tmp_path / "m.json", {"n": np.int64(3)}, default=int)
    assert json.loads((tmp_path / "m.json").read_text()) == {"n": 3}


def test_ply_vertices_round_trip_every_type(tmp_path):
    dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("d", "<f8"), ("red", "u1"), ("label", "<i4")]
    data = np.zeros(4, dtype=dtype)
    data["x"] = [0, 1, 2, 3]
    data["d"] = [0.5, 1e-9, -2, 7]
    data["red"] = [0, 128, 255, 3]
    data["label"] = [-1, 5, 6, 7]
    path = write_ply_vertices(tmp_path / "v.ply", data, comment="two\nlines")
    cols = read_ply(path)
    assert np.array_equal(cols["points"][:, 0], data["x"])
    for name in ("d", "red", "label"):
        assert np.array_equal(cols[name], data[name]), name
    with pytest.raises(PlyError, match="structured"):
        write_ply_vertices(tmp_path / "bad.ply", np.zeros(3))


def test_atomic_files_get_the_mode_a_plain_open_would_give(tmp_path):
    """Not mkstemp's 0600: outputs are shared like any file the user writes (umask applies)."""
    import os
    import stat

    from image2sim.simulator.io.atomic import write_text_atomic

    old = os.umask(0o022)
    try:
        plain = tmp_path / "plain.txt"
        plain.write_text("x")
        atomic = write_text_atomic(tmp_path / "atomic.txt", "x")
        mode = stat.S_IMODE(atomic.stat().st_mode)
        assert mode == stat.S_IMODE(plain.stat().st_mode) == 0o644
        os.umask(0o077)
        assert stat.S_IMODE(write_text_atomic(tmp_path / "private.txt", "x").stat().st_mode) == 0o600
    finally:
        os.umask(old)


def _killed_mid_write(target) -> None:
    """A child process opens an atomic write of ``target`` and is SIGKILLed inside it."""
    import signal
    import subprocess
    import sys
    import time

    code = (
        "import sys, time\n"
        "from image2sim.simulator.io.atomic import atomic_open\n"
        "with atomic_open(sys.argv[1], 'wb') as f:\n"
        "    f.write(b'half'); f.flush(); print('ready', flush=True); time.sleep(60)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code, str(target)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    time.sleep(0.01)


def test_a_killed_writers_temp_is_swept_by_the_next_write_of_the_target(tmp_path):
    """SIGKILL cannot clean up (a stale `.navgraph.npz.<random>.npz` stayed forever, issue 23): the
    next write of the same target removes temps of writers that no longer run."""
    from image2sim.simulator.io.atomic import sweep_stale_temps, temp_sibling

    target = tmp_path / "navgraph.npz"
    _killed_mid_write(target)
    stale = [p for p in tmp_path.iterdir() if p.name.startswith(".navgraph.npz.")]
    assert len(stale) == 1 and not target.exists()
    live = temp_sibling(target, ".npz")  # this process's: a live writer, never touched
    live.write_bytes(b"in progress")
    other_host = tmp_path / ".navgraph.npz.00000000-1-deadbeef.npz"
    other_host.write_bytes(b"another machine's writer")
    unrelated = tmp_path / ".navgraph.npz.notes"
    unrelated.write_text("not a temp")
    write_text_atomic(target, "done")
    assert target.read_text() == "done" and not stale[0].exists()
    assert live.exists() and other_host.exists() and unrelated.exists()
    assert sweep_stale_temps(target) == []


def test_folder_writers_sweep_a_killed_writers_temp_folder(tmp_path):
    import os

    from image2sim.simulator.io.atomic import sweep_stale_temps, temp_sibling

    target = tmp_path / "scene"
    dead = temp_sibling(target, ".tmp")
    pid = int(dead.name.split("-")[1])
    assert pid == os.getpid()
    dead = dead.with_name(dead.name.replace(f"-{pid}-", "-999999999-"))  # no such process
    (dead / "frames").mkdir(parents=True)
    assert sweep_stale_temps(target) == [dead] and not dead.exists()


def test_atomic_dir_replaces_a_folder_whole_or_not_at_all(tmp_path):
    from image2sim.simulator.io.atomic import atomic_dir

    target = tmp_path / "export"
    with atomic_dir(target) as tmp:
        (tmp / "a.txt").write_text("old")
    with pytest.raises(RuntimeError), atomic_dir(target) as tmp:
        (tmp / "a.txt").write_text("half of the new")
        raise RuntimeError("killed mid-write")
    assert (target / "a.txt").read_text() == "old"
    with atomic_dir(target) as tmp:
        (tmp / "b.txt").write_text("new")
    assert sorted(p.name for p in target.iterdir()) == ["b.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["export"]
