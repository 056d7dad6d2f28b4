"""Pool workers end with their parent: a SIGKILLed driver leaves no worker computing for nobody; a
process sharing its cores runs its own torch ops on the threads it is given."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux")

_DRIVER = textwrap.dedent(
    """
    import multiprocessing as mp, os, sys, time
    from concurrent.futures import ProcessPoolExecutor
    from image2sim.simulator.lifetime import die_with_parent

    def work(_):
        print(os.getpid(), flush=True)
        time.sleep(120)

    if __name__ == "__main__":
        init = die_with_parent if sys.argv[1] == "armed" else None
        args = (os.getpid(),) if init else ()
        with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"), initializer=init, initargs=args) as p:
            list(p.map(work, [0]))
    """
)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as fh:  # a zombie is gone for our purpose
        return fh.read().split()[2] != "Z"


def _orphaned_worker(tmp_path, mode: str, wait: float) -> int:
    script = tmp_path / "driver.py"
    script.write_text(_DRIVER)
    driver = subprocess.Popen([sys.executable, str(script), mode], stdout=subprocess.PIPE, text=True)
    worker = int(driver.stdout.readline())
    driver.send_signal(signal.SIGKILL)
    driver.wait()
    deadline = time.monotonic() + wait
    while _alive(worker) and time.monotonic() < deadline:
        time.sleep(0.1)
    return worker


@linux_only
def test_an_armed_worker_dies_with_its_killed_parent(tmp_path):
    assert not _alive(_orphaned_worker(tmp_path, "armed", wait=10.0))


@linux_only
def test_an_unarmed_worker_outlives_it(tmp_path):
    """The default this guards against (and proof the test can fail)."""
    worker = _orphaned_worker(tmp_path, "plain", wait=2.0)
    try:
        assert _alive(worker)
    finally:
        os.kill(worker, signal.SIGKILL)


def test_torch_threads_sets_the_count_inside_and_restores_it_after_an_error():
    import torch
    from image2sim.simulator.lifetime import torch_threads

    before = torch.get_num_threads()
    other = 3 if before != 3 else 2
    try:
        with pytest.raises(RuntimeError, match="inside"):
            with torch_threads(other):
                assert torch.get_num_threads() == other
                raise RuntimeError("inside")
        assert torch.get_num_threads() == before
        with torch_threads(0):  # 0 leaves the count alone
            assert torch.get_num_threads() == before
    finally:
        torch.set_num_threads(before)
