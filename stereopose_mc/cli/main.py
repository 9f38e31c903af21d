"""``spmc``: thin typer commands, each parsing arguments and calling one typed function.

Command modules register themselves on the shared ``app`` when imported here.
"""

from __future__ import annotations

import sys

import typer

from . import dynamics_cmd, inertia_cmd, observability_cmd, report_cmds, run_cmds, scenario_cmds  # noqa: F401
from . import sweep_cmd, tune_cmd  # noqa: F401  (each module registers its commands)
from .app import app


def main() -> None:  # console-script entry point
    """``spmc``; an unforeseen OS error (a file that vanished, a full disk) is one line and exit 2, not a traceback."""
    try:
        app()
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename else ""
        typer.echo(f"error: {where}{exc.strerror or exc}", err=True)
        sys.exit(2)
    except MemoryError:
        typer.echo("error: out of memory (fewer trials or a smaller --chunk-size / --jobs may fit)", err=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
