"""Paths stored in files are relative to the file that holds them (issue 22: relocatable outputs).

A manifest or list written into an output folder names its neighbours relative to itself, so the
folder can be moved, copied to another machine or restored by ``dvc pull`` elsewhere and still read.
:func:`relative_to_file` makes the stored form; :func:`resolve_from_file` reads it back and also
accepts the absolute paths that older files hold.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["relative_to_file", "resolve_from_file"]


def relative_to_file(target: str | Path, holder: str | Path) -> str:
    """``target`` relative to the folder of ``holder`` (the file that will store it), POSIX style.

    ``..`` steps are used when ``target`` lies outside that folder; both are made absolute first, so
    either may be given relative to the working directory.
    """
    start = Path(holder).absolute().parent
    return Path(os.path.relpath(Path(target).absolute(), start)).as_posix()


def resolve_from_file(value: str | Path, holder: str | Path) -> Path:
    """A path read from ``holder``: an absolute one as it is (files written before paths were
    relative), a relative one joined to ``holder``'s folder."""
    path = Path(value)
    return path if path.is_absolute() else Path(holder).parent / path
