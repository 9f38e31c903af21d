"""The typer application and the helpers every command shares.

Errors in user input (scenario files, run directories) print one line per problem on
stderr and exit with code 2, writing nothing.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer


app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False, help="stereopose_mc: Monte Carlo runs of stereo-vision relative pose, motion and inertia estimation.")


JOBS_HELP = "parallel workers (default: the cores available to this process)"
CHUNK_HELP = ("trials stepped together per chunk (default: the trials split over the jobs, at most 250, at least 32 at "
              "case B's state size and fewer for larger states; numpy: 50)")
KERNELS_HELP = ("compiled (default: Numba) | numpy (the readable reference; the same results to round-off: "
                "docs/performance.md)")


def fail(lines: list[str] | str, code: int = 2) -> None:
    for line in [lines] if isinstance(lines, str) else lines:
        typer.echo(f"error: {line}", err=True)
    raise typer.Exit(code)


def load_or_exit(path: Path, overrides: dict | None = None):
    from ..config import ScenarioError, load_scenario  # here, not at import: `spmc --help` stays fast

    try:
        return load_scenario(path, overrides)
    except ScenarioError as exc:
        fail([str(p) for p in exc.problems])


def echo_json(obj: dict) -> None:
    """Print ``obj`` as one line of strict JSON (no NaN/inf)."""
    typer.echo(json.dumps(obj, allow_nan=False))


def emit(r: dict, lines, as_json: bool) -> None:
    """Print a study's result: one JSON object with ``--json``, else the text lines ``lines(r)``."""
    if as_json:
        echo_json(r)
        return
    for line in lines(r):
        typer.echo(line)
