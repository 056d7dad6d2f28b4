"""The code a DVC stage runs, derived from its command: every repository source file it may import.

For each ``image2sim <group> <command>`` in a stage's ``cmd`` the Typer app names the callback; the
callback's module (its module-level imports and the imports inside the callback) is the entry. Every
``image2sim.*`` import reached from there is followed through whole modules, lazy imports inside
functions included, with the parent packages' ``__init__.py`` files that importing runs. Scripts run
as ``python scripts/X.py`` are followed the same way. The result is a superset of what runs: a stage
whose declared deps miss a file of it would not rerun when that file changes (``dvc status`` would
say "up to date"), which ``tests/test_dvc_deps.py`` forbids.

    python scripts/stage_deps.py dvc.yaml            # per stage: the directories that cover its code
"""

from __future__ import annotations

import ast
import re
import shlex
import sys
from functools import cache
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SRC_ROOTS = sorted((REPO / "packages").glob("*/src"))


def module_file(name: str) -> Path | None:
    """The source file of an ``image2sim.*`` module or package, or None."""
    parts = name.split(".")
    for root in SRC_ROOTS:
        base = root.joinpath(*parts)
        if base.with_suffix(".py").is_file():
            return base.with_suffix(".py")
        if (base / "__init__.py").is_file():
            return base / "__init__.py"
    return None


def _imports_of(tree: ast.AST) -> set[str]:
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)  # submodules imported by name
    return {m for m in out if m == "image2sim" or m.startswith("image2sim.")}


def _with_parents(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[: i + 1]) for i in range(1, len(parts))]


@cache
def _module_imports(path: Path) -> frozenset[str]:
    return frozenset(_imports_of(ast.parse(path.read_text(encoding="utf-8"))))


def closure(modules: set[str]) -> set[Path]:
    """Source files of ``modules`` and of everything they import (transitively)."""
    files: set[Path] = set()
    todo = [p for m in modules for p in _with_parents(m)]
    seen: set[str] = set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        path = module_file(name)
        if path is None:
            continue  # a name imported from a module (a function, a class), not a module
        files.add(path)
        for m in _module_imports(path):
            todo += [p for p in _with_parents(m) if p not in seen]
    return files


@cache
def _root_command():
    import typer
    from image2sim.simulator.cli import build_app

    return typer.main.get_command(build_app())


def callback_entry(group: str, command: str) -> set[str]:
    """Modules an ``image2sim <group> <command>`` call starts from (see the module docstring)."""
    import inspect
    import textwrap

    cmd = _root_command().commands[group]
    cmd = cmd.commands[command] if hasattr(cmd, "commands") else cmd
    fn = cmd.callback
    module = fn.__module__
    mod_tree = ast.parse(Path(sys.modules[module].__file__).read_text(encoding="utf-8"))
    top = ast.Module(
        body=[n for n in mod_tree.body if isinstance(n, (ast.Import, ast.ImportFrom))], type_ignores=[]
    )
    body = ast.parse(textwrap.dedent(inspect.getsource(fn)))
    return {module} | _imports_of(top) | _imports_of(body)


def stage_code(cmd: str) -> set[Path]:
    """Repository files a stage command may run."""
    files: set[Path] = set()
    text = re.sub(r"\$\(.*?\)", " ", cmd).replace("'", " ").replace('"', " ").replace("\\\n", " ")
    words = shlex.split(text, comments=True)
    for i, w in enumerate(words):
        if w == "image2sim" and i + 2 < len(words):
            files |= closure(callback_entry(words[i + 1], words[i + 2]))
        if w.endswith(".sh") and (REPO / w).is_file():  # a shell script: the commands in it
            files |= stage_code((REPO / w).read_text(encoding="utf-8"))
        if w.startswith("scripts/") and w.endswith(".py"):
            script = REPO / w
            files.add(script)
            files |= closure(set(_imports_of(ast.parse(script.read_text(encoding="utf-8")))))
    return files


def covering_dirs(files: set[Path]) -> list[str]:
    """Repository-relative deps that cover ``files``: ``packages/<p>/src/image2sim`` of each package
    touched (not ``src``: pip writes its egg-info there), and
    each script file.

    Package level, not module level: the CLI groups import every command module when they register
    them, so a stage's closure reaches most of each package it touches anyway, and whole ``src``
    folders keep dvc.yaml readable while staying complete (the test checks completeness)."""
    out: set[str] = set()
    for f in files:
        rel = f.relative_to(REPO)
        out.add(str(Path(*rel.parts[:4])) if rel.parts[0] == "packages" else str(rel))
    return sorted(out)


def code_deps(deps: list[str]) -> list[str]:
    """The entries of a stage's deps that name code (package sources or scripts)."""
    return [d for d in deps if d.startswith("packages/") or (d.startswith("scripts/") and d.endswith(".py"))]


def uncovered(files: set[Path], deps: list[str]) -> list[str]:
    """Files of ``files`` that no dep (a file or a folder above it) covers."""
    rels = [str(f.relative_to(REPO)) for f in files]
    return sorted(r for r in rels if not any(r == d or r.startswith(d.rstrip("/") + "/") for d in deps))


def stage_commands(dvc_file: Path) -> dict[str, tuple[str, list[str]]]:
    """stage name -> (command, deps) of a dvc.yaml (``foreach`` stages: their ``do`` block, once)."""
    import yaml

    doc = yaml.safe_load(dvc_file.read_text())
    out = {}
    for name, stage in doc["stages"].items():
        body = stage.get("do", stage)
        cmd = body.get("cmd", "")
        out[name] = (cmd if isinstance(cmd, str) else " ".join(cmd), list(body.get("deps", [])))
    return out


def main(argv: list[str]) -> int:
    """Print the covering code deps of every stage of the given dvc.yaml files (default dvc.yaml)."""
    if {"-h", "--help"} & set(argv):
        print(__doc__)
        return 0
    missing = [f for f in argv if not Path(f).is_file()]
    if missing:
        print(f"error: {missing[0]}: no such dvc.yaml (usage: python scripts/stage_deps.py [DVC_YAML ...])")
        return 2
    for dvc_file in argv or ["dvc.yaml"]:
        for name, (cmd, _) in stage_commands(Path(dvc_file)).items():
            print(f"{dvc_file}:{name}")
            for d in covering_dirs(stage_code(cmd)):
                print(f"  - {d}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
