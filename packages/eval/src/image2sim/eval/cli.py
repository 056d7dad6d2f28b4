"""``image2sim eval``: navigation and rendering benchmarks, reports."""

from __future__ import annotations

import typer

app = typer.Typer(help="Evaluation: navigation metrics, rendering benchmark, reports.", no_args_is_help=True)
