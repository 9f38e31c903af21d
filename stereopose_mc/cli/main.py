"""``spmc``: thin typer commands, each parsing arguments and calling one typed function.

Command modules register themselves on the shared ``app`` when imported here.
"""

from __future__ import annotations

from . import analysis_cmds, dynamics_cmd, report_cmds, run_cmds, scenario_cmds, tune_cmd  # noqa: F401  (registers commands)
from .app import app


def main() -> None:  # console-script entry point
    app()


if __name__ == "__main__":
    main()
