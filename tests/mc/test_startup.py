"""The collector during a run's start-up (mc/startup.py): paused, then frozen and resumed, once per process."""

from __future__ import annotations

import gc

import pytest

from stereopose_mc.mc import startup


@pytest.fixture
def fresh(monkeypatch):
    """A process whose start-up has not been settled yet; the collector and the freeze restored after."""
    monkeypatch.setattr(startup, "_settled", False)
    was_on = gc.isenabled()
    frozen = gc.get_freeze_count()
    yield
    if gc.get_freeze_count() > frozen:
        gc.unfreeze()
    (gc.enable if was_on else gc.disable)()


def test_the_collector_is_off_until_settled_then_on_with_the_start_ups_objects_frozen(fresh):
    gc.enable()
    before = gc.get_freeze_count()
    with startup.paused() as settle:
        assert not gc.isenabled()
        made = [[i] for i in range(1000)]  # objects of the start-up
        settle()
        assert gc.isenabled()
        assert gc.get_freeze_count() >= before + len(made)
        settle()  # a second call does nothing
        assert gc.isenabled()
    assert gc.isenabled()
    assert startup._settled


def test_later_runs_of_the_process_leave_the_collector_alone(fresh):
    gc.enable()
    with startup.paused() as settle:
        settle()
    frozen = gc.get_freeze_count()
    with startup.paused() as settle:
        assert gc.isenabled()  # not paused again
        kept = [[i] for i in range(100)]
        settle()
    assert gc.get_freeze_count() <= frozen  # nothing frozen the second time (frozen objects freed since leave it)
    assert len(kept) == 100


def test_an_error_during_the_start_up_resumes_the_collector_without_freezing(fresh):
    gc.enable()
    frozen = gc.get_freeze_count()
    with pytest.raises(RuntimeError):
        with startup.paused():
            assert not gc.isenabled()
            raise RuntimeError("bad scenario")
    assert gc.isenabled()
    assert gc.get_freeze_count() <= frozen
    assert not startup._settled  # the next run pauses again


def test_a_collector_turned_off_by_the_caller_stays_off(fresh):
    gc.disable()
    frozen = gc.get_freeze_count()
    with startup.paused() as settle:
        settle()
        assert not gc.isenabled()
    assert not gc.isenabled()
    assert gc.get_freeze_count() <= frozen
