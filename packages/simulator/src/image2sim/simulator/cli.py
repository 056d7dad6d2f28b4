"""The single ``image2sim`` command. Packages contribute subcommand groups through the
``image2sim.cli`` entry-point group (``data``, ``sim``, ``nav``, ``eval``); nothing is imported
until the command runs.

One error boundary (:func:`main`): an error that escapes a command is one line on stderr naming
its class and message, and the exit status says which class it is: 2 = bad input (``ValueError``,
``OSError`` and errors that declare ``cli_exit_code = 2``: a missing file, a bad capture, config or
episode file), 1 = a failure while running, 130 = interrupted. ``--debug`` (or ``IMAGE2SIM_DEBUG=1``)
shows the traceback instead. Usage errors keep click's own message and status 2.
"""

from __future__ import annotations

import os
import sys
from importlib.metadata import entry_points

import typer

sim_app = typer.Typer(help="Simulator tools: scenes, rendering, navigation.", no_args_is_help=True)


@sim_app.command("cameras")
def sim_cameras() -> None:
    """Print the camera and frame conventions in force."""
    from image2sim.simulator import conventions

    typer.echo(conventions.__doc__)


def _register_renderer_commands() -> None:
    # Lazy: the renderer (torch, lightning) is imported only when its command runs.
    from image2sim.simulator.renderer import cli as renderer_cli

    sim_app.command("train")(renderer_cli.train_command)
    sim_app.command("renderer-eval")(renderer_cli.eval_command)
    sim_app.command("export-renderer")(renderer_cli.export_command)


_register_renderer_commands()


def _register_navigation_commands() -> None:
    # The navigation CLI module imports only typer; numpy/scipy load when a command runs.
    from image2sim.simulator.navigation import cli as navigation_cli

    sim_app.command("navmap")(navigation_cli.navmap_command)
    sim_app.command("plan")(navigation_cli.plan_command)


_register_navigation_commands()


def _register_gaussian_commands() -> None:
    # The gaussians CLI module imports only typer; torch loads when a command runs.
    from image2sim.simulator.gaussians import cli as gaussians_cli

    sim_app.command("build-scene")(gaussians_cli.build_scene_command)
    sim_app.command("render")(gaussians_cli.render_command)
    sim_app.command("train-geometry")(gaussians_cli.train_geometry_command)


_register_gaussian_commands()


def build_app() -> typer.Typer:
    app = typer.Typer(
        help="Image2Sim: posed RGB-D captures -> neural simulators -> navigation data and policies.",
        no_args_is_help=True,
        add_completion=False,
    )
    for ep in sorted(entry_points(group="image2sim.cli"), key=lambda e: e.name):
        app.add_typer(ep.load(), name=ep.name)

    def _print_versions(value: bool) -> None:
        if value:
            typer.echo(versions_text())
            raise typer.Exit(0)

    @app.callback()
    def _root(
        version: bool = typer.Option(  # noqa: B008 (typer's declaration style)
            False,
            "--version",
            is_eager=True,
            callback=_print_versions,
            help="Print the installed image2sim packages and their versions, then exit.",
        ),
    ) -> None:
        """Image2Sim: posed RGB-D captures -> neural simulators -> navigation data and policies."""

    return app


def versions_text() -> str:
    """One line per installed image2sim package (``image2sim-simulator 0.1.0``), and torch's."""
    from importlib.metadata import PackageNotFoundError, version

    lines = []
    packages = ("simulator", "dataengine", "navpolicy", "eval")
    for name in [f"image2sim-{p}" for p in packages] + ["torch"]:
        try:
            lines.append(f"{name} {version(name)}")
        except PackageNotFoundError:
            lines.append(f"{name} (not installed)")
    return "\n".join(lines)


EXIT_BAD_INPUT = 2
EXIT_RUNTIME = 1
EXIT_INTERRUPTED = 130


def exit_code_of(err: BaseException) -> int:
    """The exit status of an error that escaped a command (see the module docstring)."""
    declared = getattr(err, "cli_exit_code", None)
    if isinstance(declared, int):
        return declared
    return EXIT_BAD_INPUT if isinstance(err, (ValueError, OSError)) else EXIT_RUNTIME


def main(argv: list[str] | None = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in args or os.environ.get("IMAGE2SIM_DEBUG", "") not in ("", "0")
    args = [a for a in args if a != "--debug"]
    app = build_app()
    if debug:
        app(args=args, prog_name="image2sim")
        return
    try:
        app(args=args, prog_name="image2sim", standalone_mode=True)
    except SystemExit:
        raise
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)
    except Exception as err:  # the boundary: one line, a status by class
        code = exit_code_of(err)
        kind = "bad input" if code == EXIT_BAD_INPUT else "failed"
        print(f"error ({kind}, {type(err).__name__}): {err}", file=sys.stderr)
        print("(image2sim --debug ... shows the traceback)", file=sys.stderr)
        sys.exit(code)
