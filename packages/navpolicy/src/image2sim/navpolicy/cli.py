"""``image2sim nav``: Image2Nav training and inference."""

from __future__ import annotations

import typer

app = typer.Typer(help="Navigation policy (Image2Nav): train, DAgger, run.", no_args_is_help=True)
