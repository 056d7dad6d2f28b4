"""Frame-rate measurement: median over timed runs after warm-up, with the hardware string."""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any


def hardware_string() -> str:
    """CPU model, logical core count, torch threads and versions: enough to tell two machines apart."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    parts = [cpu, f"{os.cpu_count()} logical CPUs", f"python {platform.python_version()}"]
    try:
        import torch

        parts.append(f"torch {torch.__version__} ({torch.get_num_threads()} threads)")
        if torch.cuda.is_available():
            parts.append(f"cuda {torch.cuda.get_device_name(0)}")
    except ImportError:
        pass
    return ", ".join(parts)


@dataclass(frozen=True)
class FpsMeasurement:
    """Result of :func:`measure_fps`."""

    fps: float
    """frames_per_call / median seconds per timed call."""
    median_seconds: float
    """Median wall time of one timed call."""
    seconds: tuple[float, ...]
    """Every timed call's wall time (warm-up calls excluded)."""
    warmup: int
    """Untimed calls made first (JIT, caches, allocator)."""
    frames_per_call: int
    """Frames produced by one call (e.g. batch size)."""
    hardware: str
    """:func:`hardware_string` of the machine."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready record."""
        out = asdict(self)
        out["seconds"] = list(self.seconds)
        return out


def time_calls(
    fn: Callable[[], Any],
    *,
    warmup: int = 1,
    runs: int = 5,
    clock: Callable[[], float] = time.perf_counter,
    synchronize: Callable[[], None] | None = None,
) -> tuple[list[float], list[float]]:
    """Call ``fn`` ``warmup`` times untimed, then ``runs`` times timed.

    Returns the wall time (``clock``) and the process CPU time (all threads) of every timed call;
    the one timing loop shared by :func:`measure_fps` and the ``benchmarks/`` harness.
    """
    if warmup < 0 or runs < 1:
        raise ValueError(f"need warmup >= 0 and runs >= 1; got {warmup}, {runs}")
    sync = synchronize or (lambda: None)
    for _ in range(warmup):
        fn()
    sync()
    walls, cpus = [], []
    for _ in range(runs):
        start, cpu_start = clock(), time.process_time()
        fn()
        sync()
        walls.append(clock() - start)
        cpus.append(time.process_time() - cpu_start)
    return walls, cpus


def measure_fps(
    fn: Callable[[], Any],
    *,
    warmup: int = 3,
    runs: int = 10,
    frames_per_call: int = 1,
    clock: Callable[[], float] = time.perf_counter,
    synchronize: Callable[[], None] | None = None,
) -> FpsMeasurement:
    """Call ``fn`` ``warmup`` times untimed, then ``runs`` times timed; FPS from the median time.

    ``synchronize`` (e.g. ``torch.cuda.synchronize``) is called before reading the clock, so that
    asynchronous devices are timed to completion.
    """
    if warmup < 0 or runs < 1 or frames_per_call < 1:
        raise ValueError(
            f"need warmup >= 0, runs >= 1, frames_per_call >= 1; got {warmup}, {runs}, {frames_per_call}"
        )
    times, _ = time_calls(fn, warmup=warmup, runs=runs, clock=clock, synchronize=synchronize)
    med = statistics.median(times)
    if med <= 0:
        raise ValueError(f"median time per call is {med} s: the clock is too coarse for this workload")
    return FpsMeasurement(
        frames_per_call / med, med, tuple(times), warmup, frames_per_call, hardware_string()
    )
