"""``image2sim eval``: navigation and rendering benchmarks, reports."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(help="Evaluation: navigation metrics, rendering benchmark, reports.", no_args_is_help=True)


@app.command("protocols")
def protocols_cmd(
    name: Annotated[
        str | None, typer.Argument(help="Print one protocol as JSON (image2sim, vlnce, rxr-habitat).")
    ] = None,
) -> None:
    """List the built-in evaluation protocols (or print one in full)."""
    from image2sim.eval.protocols import PROTOCOLS, get_protocol
    from image2sim.eval.report import describe_protocol

    if name:
        typer.echo(json.dumps(get_protocol(name).to_dict(), indent=2))
        return
    for p in PROTOCOLS.values():
        typer.echo(f"{p.name:14s} {describe_protocol(p)}")


@app.command("aggregate")
def aggregate_cmd(
    log: Annotated[Path, typer.Argument(exists=True, dir_okay=False, help="Per-episode JSONL log of a run.")],
    out: Annotated[
        Path | None, typer.Option(help="Directory for aggregate.json, metrics.json, table.md.")
    ] = None,
    label: Annotated[str | None, typer.Option(help="Row label (default: the log's stem).")] = None,
) -> None:
    """Aggregate a per-episode log (one protocol) into means with episode counts."""
    from image2sim.eval.metrics.nav import aggregate
    from image2sim.eval.report import nav_table_markdown, write_nav_report
    from image2sim.eval.results import read_episode_log

    _, results = read_episode_log(log)
    report = aggregate(results)
    name = label or log.stem
    typer.echo(nav_table_markdown([(name, report)]))
    if out is not None:
        paths = write_nav_report(out, name, report, {"source": str(log)})
        typer.echo("wrote " + ", ".join(str(p) for p in paths.values()))


@app.command("report")
def report_cmd(
    aggregates: Annotated[
        list[Path], typer.Argument(exists=True, dir_okay=False, help="aggregate.json files.")
    ],
    out: Annotated[
        Path | None, typer.Option(help="Write the Markdown table here (atomically).")
    ] = None,
) -> None:
    """Collect aggregate result files into one table laid out like the paper's Table 2."""
    from image2sim.eval.report import nav_table_markdown, read_aggregate

    table = nav_table_markdown([read_aggregate(p) for p in aggregates])
    typer.echo(table)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_name(f".{out.name}.tmp")
        tmp.write_text(table, encoding="utf-8")
        tmp.replace(out)
