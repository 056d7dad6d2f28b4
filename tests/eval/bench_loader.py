"""Load a ``benchmarks/`` script as a module for its smoke test (its ``from harness import ...``
needs ``benchmarks/`` on the path; both are removed again afterwards)."""

from __future__ import annotations

import contextlib
import importlib.util
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


@contextlib.contextmanager
def benchmark_module(script: str) -> Iterator[ModuleType]:
    """``benchmarks/<script>`` imported under a private name for the duration of the block."""
    name = f"bench_{Path(script).stem}_under_test"
    had_harness = "harness" in sys.modules
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location(name, BENCH / script)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # dataclasses resolve their module through sys.modules
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(name, None)
        if not had_harness:
            sys.modules.pop("harness", None)
        sys.path.remove(str(BENCH))
