"""The compiled kernel's build folder: keyed by the source's path, and a killed build's lock cleared
(``extensions.build_guard``, which DeepSpeed's op build goes through too)."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("torch")
from image2sim.simulator.extensions import build_guard  # noqa: E402
from image2sim.simulator.splatting.backends import cpu_kernel  # noqa: E402


def test_build_folder_depends_on_the_source_path(tmp_path, monkeypatch):
    """Two checkouts with the same source must not share a folder: torch's ninja file names the
    source path, so they would rebuild the library in place under each other's processes."""
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    copy = tmp_path / "other_checkout" / "splat_cpu.cpp"
    copy.parent.mkdir()
    copy.write_bytes(cpu_kernel._SOURCE.read_bytes())
    here = cpu_kernel._build_dir()
    assert here == cpu_kernel._build_dir()  # stable
    monkeypatch.setattr(cpu_kernel, "_SOURCE", copy)
    assert cpu_kernel._build_dir() != here


def test_the_guard_clears_a_lock_left_by_a_killed_build(tmp_path):
    (tmp_path / "lock").write_text("")  # torch's FileBaton file of a build that was killed
    with build_guard(tmp_path):
        assert not (tmp_path / "lock").exists()


def test_the_guard_serialises_builders_and_dies_with_its_holder(tmp_path):
    """A second builder waits while another process holds the guard; when that process is killed
    (no clean exit), the OS releases the lock and the waiting builder goes on."""
    src = str(Path(cpu_kernel.__file__).resolve().parents[4])  # the folder holding image2sim
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; sys.path.insert(0, sys.argv[1]); from pathlib import Path; "
            "from image2sim.simulator.extensions import build_guard\n"
            "with build_guard(Path(sys.argv[2])):\n"
            "    Path(sys.argv[2], 'lock').write_text(''); print('held', flush=True); time.sleep(60)",
            src,
            str(tmp_path),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        entered = threading.Event()

        def second_builder():
            with build_guard(tmp_path):
                entered.set()

        t = threading.Thread(target=second_builder, daemon=True)
        t.start()
        time.sleep(0.5)
        assert not entered.is_set()  # the holder's build is still running: wait
        assert (tmp_path / "lock").exists()  # and its lock is not touched meanwhile
        holder.kill()  # a killed build: no release, no clean-up
        holder.wait(timeout=10)
        assert entered.wait(timeout=10)
        t.join(timeout=10)
        assert not (tmp_path / "lock").exists()  # the killed build's lock was cleared
    finally:
        holder.kill()
