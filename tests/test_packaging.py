"""Wheels carry what the code reads at run time: every non-Python file under a package's ``src``
is declared as package data (a wheel install of the simulator once lacked the CPU kernel's source)."""

from __future__ import annotations

import fnmatch
import tomllib
from pathlib import Path

import pytest

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
        owners = {k: v for k, v in declared.items() if rel.parts[: len(k.split("."))] == tuple(k.split("."))}
        inner = [str(rel.relative_to(Path(*k.split(".")))) for k in owners]
        assert any(
            fnmatch.fnmatch(path, pattern) for path, patterns in zip(inner, owners.values()) for pattern in patterns
        ), f"{package.name}/src/{rel} is not in [tool.setuptools.package-data]: a wheel would leave it out"
