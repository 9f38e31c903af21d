"""Studies built on runs: :func:`sweep` (a campaign per point of a grid) and :func:`tune` (Q from NEES/NIS)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ContextManager

import yaml

from ..config.loader import ScenarioError
from ..config.schema import Scenario
from ..mc import engine
from ..rundir.store import RunDirError
from .errors import SpmcError
from .runs import KERNELS, Run, _options, default_jobs
from .scenarios import _sweep, as_scenario

if TYPE_CHECKING:  # imported where used: studies.sweep and studies.tuning import pandas (~0.25 s)
    import pandas as pd

    from ..studies import tuning
    from ..studies.sweep import Point

Sets = Mapping[str, Sequence[Any]] | Sequence[str]


@dataclass
class Sweep:
    """A sweep directory: ``sweep.json``, one run directory per point, the stacked percentiles."""

    path: Path
    ran: list[str] = field(default_factory=list)  # points run (or resumed) by the call that returned this
    skipped: list[str] = field(default_factory=list)  # points already finished

    @classmethod
    def open(cls, path: str | Path) -> Sweep:
        s = cls(Path(path))
        s.spec  # noqa: B018  (raises for a directory that is not a sweep)
        return s

    @property
    def spec(self) -> dict[str, Any]:
        """``sweep.json``: the axes, the points (name and values), start and end."""
        sw = _sweep()
        try:
            return sw.load_sweep(self.path)
        except sw.SweepError as exc:
            raise SpmcError(str(exc)) from None

    @property
    def points(self) -> dict[str, Run]:
        """Point name -> its :class:`Run`, in sweep order."""
        return {p["name"]: Run(self.path / p["name"]) for p in self.spec["points"]}

    def summary(self) -> pd.DataFrame:
        """Per point and filter: the swept values, trials, divergence rate and quantiles of each error."""
        return _sweep().summary(self.path)

    @property
    def percentiles(self) -> pd.DataFrame:
        """The points' percentile tables stacked (filter = ``<point>/<filter>``)."""
        import pandas as pd

        return pd.read_csv(self.path / "percentiles.csv")

    def report(self) -> Path:
        """Write the sweep report (``report.html``, ``sweep.csv``, every point's report); return its path."""
        from ..outputs.report import ReportError
        from ..outputs.sweep_report import build_sweep_report

        sw = _sweep()
        try:
            return build_sweep_report(self.path, default_jobs())
        except sw.SweepError as exc:
            raise SpmcError(str(exc)) from None
        except ReportError as exc:
            raise SpmcError(exc.lines()) from None


def sweep(scenario: str | Path, sets: Sets | None = None, *, out: str | Path, zip: bool = False,
          trials: int | None = None, jobs: int | None = None, chunk_size: int | None = None, kernels: str | None = None,
          timeseries: str = "summary",
          report: bool = False, on_point: Callable[[int, int, Point, str], None] | None = None,
          progress_of: Callable[[Point], ContextManager] | None = None,
          command: list[str] | None = None) -> Sweep:  # fmt: skip
    """Run a campaign per point of a grid (``zip=True``: the lists side by side) into ``out``; resumable.

    ``scenario``: a scenario YAML file, or a sweep file (``configs/sweeps/*.yaml``) whose ``set``,
    ``zip`` and ``trials`` apply unless given here (a path in ``sets`` overrides the file's).
    ``sets``: ``{"camera.baseline_m": [0.5, 1, 2]}`` or ``["camera.baseline_m=0.5,1,2"]``.
    ``jobs``, ``chunk_size``, ``kernels``: as :func:`run`'s (a resumed point keeps its kernels unless
    given). Every point uses the scenario's root seed (paired trials). ``on_point(i, n, point, what)``
    is told of each point (``what``: run, resume or done); ``progress_of(point)`` gives a
    context manager yielding the point's progress callback.
    """
    sw = _sweep()
    if isinstance(sets, Mapping):
        sets = sw.set_strings({k: list(v) for k, v in sets.items()})
    sets = list(sets or [])
    scenario = Path(scenario)
    if sw.is_sweep_file(scenario):
        try:
            scenario, file_sets, file_zip, file_trials = sw.load_sweep_file(scenario)
        except sw.SweepError as exc:
            raise SpmcError(str(exc)) from None
        given = {s.split("=", 1)[0].strip() for s in sets}
        sets = [s for s in file_sets if s.split("=", 1)[0] not in given] + sets
        zip = zip or file_zip
        trials = trials if trials is not None else file_trials
    opts = _options(jobs, chunk_size, "auto", kernels, None, None, command, timeseries=timeseries)
    try:
        res = sw.run_sweep(scenario, sets, Path(out), zip, trials, opts, on_point, progress_of)
    except ScenarioError as exc:
        raise SpmcError([str(p) for p in exc.problems]) from None
    except (sw.SweepError, engine.RunError, RunDirError) as exc:
        raise SpmcError(str(exc)) from None
    s = Sweep(Path(out), res.ran, res.skipped)
    if report:
        s.report()
    return s


@dataclass(frozen=True)
class Tuning:
    """A tuned filter: before/after statistics on the tuning and the held-back trials, the tuned entry and the
    scenario that uses it."""

    filter: str
    result: tuning.TuneResult
    entry: dict[str, Any]  # the filter entry with the tuned process_noise (and measurement_noise), YAML-ready
    scenario: Scenario  # the input scenario with that filter's Q / R and (if tuned) the initial_covariance replaced

    @property
    def table(self) -> pd.DataFrame:
        """Before / after on the tuning trials: trials, lost, inconsistent, median NEES/dof per block, NIS/dof,
        median errors, cost."""
        from ..studies import tuning

        return tuning.comparison_table(self.result.before, self.result.after)

    @property
    def check(self) -> pd.DataFrame | None:
        """The same table on the held-back trials (None with ``check_trials=0``)."""
        from ..studies import tuning

        r = self.result
        return None if r.check_before is None else tuning.comparison_table(r.check_before, r.check_after)

    @property
    def yaml(self) -> str:
        """``filters: [entry]`` (and ``initial_covariance:`` when P0 was tuned) as YAML, to paste into a scenario."""
        from ..studies import tuning

        return yaml.safe_dump(tuning.tuned_yaml_data(self.filter, self.result), sort_keys=False)


def _kernels(kernels: str | None) -> str:
    if kernels not in (None, *KERNELS):
        raise SpmcError(f"--kernels must be numpy or compiled (got {kernels!r})")
    return kernels or engine.DEFAULT_KERNELS


def tune(scenario: Scenario | str | Path | Mapping[str, Any], filter: str, *, trials: int = 30,
         max_evaluations: int = 40, out: str | Path | None = None, kernels: str | None = None,
         space: str | Sequence[str] = "q", check_trials: int | None = None,
         progress: Callable[[int, tuning.Evaluation, str], None] | None = None,
         jobs: int | None = None) -> Tuning:  # fmt: skip
    """Tune the filter labelled ``filter`` (its Q blocks; with ``space`` also its R and the scenario's P0:
    ``"q,r,p0"``) so its NEES and NIS are consistent, on the trials ``spmc run`` would run.

    Every evaluation runs the same ``trials`` trials (at least 2), at most ``max_evaluations``
    of them; the start and the result are then compared on ``check_trials`` held-back trials
    (default ``trials``; trial indices ``trials … trials+check_trials-1``; 0: none) (docs/filters.md,
    ``spmc tune``). ``out``: also write the tuned entry there as YAML. ``progress(i, evaluation, what)``
    is called after each evaluation. ``kernels``, ``jobs``: as :func:`run`'s (default ``compiled``, the cores
    available: each evaluation's trials in chunks over them; the same results for any ``jobs``).
    """
    from ..studies import tuning

    scn = as_scenario(scenario)
    if trials < 2:
        raise SpmcError("--trials must be at least 2")
    if max_evaluations < 1:
        raise SpmcError("--max-evaluations must be at least 1")
    if jobs is not None and jobs < 1:
        raise SpmcError(f"--jobs must be at least 1 (got {jobs})")
    out = None if out is None else Path(out)
    if out is not None and (out.is_dir() or not out.parent.exists()):
        raise SpmcError(f"{out}: --out must be a file in an existing directory")
    try:
        res = tuning.tune(scn, filter, trials, max_evaluations, progress=progress, kernels=_kernels(kernels),
                          space=space, check_trials=check_trials,
                          jobs=default_jobs() if jobs is None else jobs)  # fmt: skip
    except tuning.TuneError as exc:
        where = scn.name if isinstance(scenario, (Scenario, Mapping)) else str(scenario)
        raise SpmcError(f"{where}: {exc}") from None
    t = Tuning(filter, res, tuning.tuned_entry(scn, filter, res), res.scenario)
    if out is not None:
        out.write_text(t.yaml)
    return t
