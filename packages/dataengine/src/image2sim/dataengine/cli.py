"""``image2sim data``: capture inspection, fusion, ingest and procedural synthesis."""

from __future__ import annotations

import typer

app = typer.Typer(
    help="Data: inspect, fuse and ingest captures; synthesise procedural scenes.", no_args_is_help=True
)

# Capture commands (inspect, fuse, ingest) register themselves on `app`; imported last to avoid a cycle.
from image2sim.dataengine import capture_cli  # noqa: E402,F401
from image2sim.dataengine import engine_cli as _engine_cli  # noqa: E402,F401
from image2sim.dataengine.procedural import cli as _procedural_cli  # noqa: E402,F401
