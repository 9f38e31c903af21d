"""Progress between chunk ends: the chunks count trial-steps, the driver turns them into trials."""

from __future__ import annotations

import threading
from multiprocessing import Manager

import numpy as np
import pytest

from stereopose_mc.config import load_scenario
from stereopose_mc.mc import engine, progress

from scenarios import write_scenario

SHORT = {"dt_s": 1.0, "duration_s": 6.0, "error_window_start_s": 1.0}


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    return write_scenario(tmp_path_factory.mktemp("scn") / "s.yaml", trials=4, time=SHORT)


@pytest.mark.parametrize("kernels", ["numpy", "compiled"])
def test_a_chunk_ticks_every_trial_step_of_every_filter(scenario, kernels):
    scn = load_scenario(scenario)
    steps: dict = {}
    tick = progress.StepCounter.tick_of(steps, 0)
    co = engine.compute_chunk(scn.model_dump_json(), np.arange(3), "none", kernels, tick)
    n_filters = len(scn.filters)
    # 6 steps of 3 trials per filter, lost trials included (a lost trial's remaining steps count as done); per
    # filter the trials it lost, as the chunk's own count
    assert steps[0] == 6 * 3 * n_filters
    assert {k[1]: v for k, v in steps.items() if isinstance(k, tuple)} == co.diverged_by
    ref = engine.compute_chunk(scn.model_dump_json(), np.arange(3), "none", kernels)
    assert co.trials_table.equals(ref.trials_table)  # counting changes nothing


def test_a_worker_tick_through_a_manager_sends_at_most_every_interval_and_on_flush():
    with Manager() as m:
        d = m.dict()
        tick = progress.StepCounter.tick_of(d, 7, every_s=3600.0)
        for _ in range(5):
            tick(10)
        assert dict(d) == {}  # within the interval: nothing sent yet
        tick.flush()
        assert dict(d) == {7: 50}
        assert progress.StepCounter(d).total() == 50


def test_the_ticker_reports_trials_from_trial_steps_and_chunk_ends():
    calls: list[tuple[int, int, dict]] = []
    t = progress.Ticker(lambda done, total, div: calls.append((done, total, div)), start=10, total=110, per_trial=20,
                       diverged={"iekf": 1}, every_s=3600.0)
    c = t.counter(None)
    t.report()
    assert calls[-1] == (10, 110, {"iekf": 1})  # resumed: 10 trials done before
    tick_a, tick_b = (progress.StepCounter.tick_of(c.steps, k) for k in (10, 60))
    tick_a(20 * 30 + 5)  # 30 trials and a bit of chunk a
    tick_b(20 * 12)
    t.report()
    assert calls[-1][0] == 10 + 42
    t.chunk_done(50, {"iekf": 2})  # chunk a ends (its 50 trials) before its last ticks arrive: the chunks' count
    assert calls[-1] == (60, 110, {"iekf": 3})
    tick_a(20 * 20 - 5)  # a's last steps: a done (1,000), b at 12 of 50 trials
    t.report()
    assert calls[-1][0] == 10 + 62
    tick_b(20 * 38)
    t.report()
    assert calls[-1][0] == 110


def test_the_ticker_polls_from_its_thread():
    seen = threading.Event()
    t = progress.Ticker(lambda *a: seen.set(), 0, 1, 1, {}, every_s=0.01)
    with t:
        assert seen.wait(5)


def test_the_plain_progress_line_at_100_percent_is_printed_again_when_the_lost_counts_arrive(capsys):
    """All trial-steps are counted before the last chunks return their lost counts: the 100 % line is repeated with
    the complete counts (once), so the last line a log shows is the run's (mission-debris: 230 then 465 lost)."""
    from stereopose_mc.cli.progress import _Plain

    line = _Plain("debris", every_s=0.0)
    line(250, 500, {"ekf": 100})
    line(500, 500, {"ekf": 230})
    line(500, 500, {"ekf": 230})
    line(500, 500, {"ekf": 465})
    line(500, 500, {"ekf": 465})
    out = capsys.readouterr().err.strip().splitlines()
    assert len(out) == 3
    assert out[1].startswith("debris: 500/500 trials (100%)") and out[1].endswith("lost ekf 230")
    assert out[2].endswith("lost ekf 465")


def test_the_ticker_counts_the_trials_lost_by_chunks_in_flight_once():
    """Lost trials show as the chunks lose them, not only when a chunk ends; a finished chunk's own count replaces
    its in-flight one (never both), through a plain dict (threads) and a Manager's proxy (processes)."""
    calls: list[tuple[int, int, dict]] = []
    t = progress.Ticker(lambda done, total, div: calls.append((done, total, div)), start=0, total=100, per_trial=10,
                       diverged={}, every_s=3600.0)
    with Manager() as m:
        for steps in ({}, m.dict()):
            t.finished.clear()
            c = t.counter(steps)
            tick_a, tick_b = (progress.StepCounter.tick_of(c.steps, k) for k in (0, 50))
            tick_a(5, "ekf", 2)
            tick_a(5, "ekf", 1)  # (increments: a dispersed chunk runs a filter in several calls)
            tick_a(5, "iekf", 0)
            tick_b(5, "ekf", 1)
            t.report()
            assert calls[-1][2] == {"ekf": 4, "iekf": 0}
            t.chunk_done(50, {"ekf": 7, "iekf": 1}, key=0)  # chunk a ends: its own count
            assert calls[-1][2] == {"ekf": 8, "iekf": 1}
            tick_b(5, "ekf", 1)
            t.report()
            assert calls[-1][2] == {"ekf": 9, "iekf": 1}
            t.diverged.clear()


@pytest.mark.parametrize("width", [80, 132])
def test_the_bar_keeps_the_counts_eta_and_lost_whole_on_a_narrow_terminal(width):
    """A sweep point's label is long; at 80 columns the label is cut and the bar shrinks, never the counts."""
    import io

    from rich.console import Console
    from rich.progress import Progress

    from stereopose_mc.cli.progress import bar_columns

    label = "p000-baseline_m=0.5"
    buf = io.StringIO()
    console = Console(file=buf, width=width, force_terminal=True, color_system=None)
    bar = Progress(*bar_columns(label, width), console=console, auto_refresh=False)
    task = bar.add_task(label, total=200, rate="51.0/s", div="iekf 0, ekf 41")
    bar.update(task, completed=135)
    console.print(bar.make_tasks_table(bar.tasks))
    line = buf.getvalue().rstrip("\n")
    assert "\n" not in line and len(line) <= width
    for whole in ("135/200 trials", "51.0/s", "ETA -:--:--", "lost iekf 0, ekf 41"):
        assert whole in line
    assert (label in line) == (width >= 132)  # cut with an ellipsis at 80 columns, whole at 132
    assert "━" in line  # some bar is left


def test_the_eta_of_tune_and_sweep_is_the_mean_step_times_the_steps_left():
    from stereopose_mc.cli.progress import duration_text, eta_text

    assert eta_text(12.0, 4, 40, at_most=True) == "12 s elapsed, at most 1 min 48 s left"  # 12 / 4 x 36 = 108 s
    assert eta_text(40.0, 1, 9) == "40 s elapsed, about 5 min 20 s left"  # a sweep: 8 points of 40 s left
    assert eta_text(75.0, 40, 40, at_most=True) == "1 min 15 s elapsed"  # all done: no estimate
    assert eta_text(3.0, 0, 9) == ""  # nothing done yet: nothing to say
    assert duration_text(3600 + 5 * 60 + 29) == "1 h 05 min" and duration_text(59.6) == "1 min 00 s"
