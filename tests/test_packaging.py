"""Wheels carry what the code reads at run time: every non-Python file under a package's ``src``
is declared as package data (a wheel install of the simulator once lacked the CPU kernel's source)."""

from __future__ import annotations

import fnmatch
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11 (the project supports 3.10)

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = sorted(p.parent for p in (ROOT / "packages").glob("*/pyproject.toml"))


@pytest.mark.parametrize("package", PACKAGES, ids=lambda p: p.name)
def test_every_data_file_is_declared_package_data(package):
    data = tomllib.loads((package / "pyproject.toml").read_text())
    declared = data.get("tool", {}).get("setuptools", {}).get("package-data", {})
    src = package / "src"
    files = [
        f
        for f in src.rglob("*")
        if f.is_file() and f.suffix not in {".py", ".pyc"} and ".egg-info" not in str(f)
    ]
    for f in files:
        rel = f.relative_to(src)
        covered = False
        for owner, patterns in declared.items():
            parts = tuple(owner.split("."))
            if rel.parts[: len(parts)] == parts:
                inner = str(rel.relative_to(Path(*parts)))
                covered |= any(fnmatch.fnmatch(inner, pattern) for pattern in patterns)
        assert covered, f"{package.name}/src/{rel} is not in [tool.setuptools.package-data]"
