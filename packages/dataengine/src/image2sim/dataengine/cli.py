"""``image2sim data``: capture inspection, fusion, ingest, procedural synthesis and the data engine.

Each command module keeps its own small Typer registry; this module gathers their commands into one
group. The command modules never import this one, so there is no import cycle.
"""

from __future__ import annotations

import typer
from image2sim.dataengine import capture_cli, engine_cli
from image2sim.dataengine.procedural import cli as procedural_cli

app = typer.Typer(
    help="Data: inspect, fuse and ingest captures; synthesise procedural scenes.", no_args_is_help=True
)
for _module in (capture_cli, engine_cli, procedural_cli):
    app.registered_commands.extend(_module.app.registered_commands)
