"""The public Python API of stereopose_mc: scenarios, runs, sweeps, tuning and exports.

::

    from stereopose_mc import api
    run = api.run(api.load("configs/caseB.yaml"), trials=100, out="runs/caseB-py")
    print(run.percentiles)

Everything here raises :class:`SpmcError` (``.lines``: one line per problem) for bad input.
The ``spmc`` commands are thin wrappers over these functions (docs/api.md).
"""

from ..config.schema import Scenario
from .errors import SpmcError
from .runs import Rerun, ReportOutcome, Run, default_jobs, export, report, resume, run
from .scenarios import edit, from_dict, load, to_yaml
from .studies import Sweep, Tuning, sweep, tune

__all__ = [
    "Rerun", "ReportOutcome", "Run", "Scenario", "SpmcError", "Sweep", "Tuning", "default_jobs", "edit", "export",
    "from_dict", "load", "report", "resume", "run", "sweep", "to_yaml", "tune",
]  # fmt: skip
