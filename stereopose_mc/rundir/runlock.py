"""One writer per run directory: an ``fcntl`` advisory lock on ``<run>/.lock``.

The lock is held for the whole run, resume, report or overwrite and released by the
kernel when the holder exits or dies (even by SIGKILL), so a stale lock file never
blocks anyone. The file holds the holder's pid, host and start time, which a refused
second writer names in its error.
"""

from __future__ import annotations

import fcntl
import json
import os
import platform
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

from .store import RunDirError, build_dir, check_replaceable, now_iso

LOCK_NAME = ".lock"
_HELD: set[int] = set()  # this process's lock descriptors (a forked child closes its copies: forget_inherited)


def _holder(fd: int) -> str:
    try:
        info = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        info = {}
    if not info:
        return "another process"
    return f"pid {info.get('pid', '?')} on {info.get('host', '?')}, started {info.get('start', '?')}"


def acquire(run_dir: Path, what: str) -> int:
    """Lock ``run_dir`` (which must exist) and return the lock's file descriptor.

    Raises :class:`RunDirError` naming the holder when another process has it.
    """
    path = Path(run_dir) / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as exc:
        raise RunDirError(f"{run_dir}: cannot create its lock file ({exc.strerror})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = _holder(fd)
        os.close(fd)
        raise RunDirError(f"{run_dir} is in use by {holder}; wait for it to finish (or stop it) and retry") from None
    info = {"pid": os.getpid(), "host": platform.node(), "start": now_iso(), "what": what}
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps(info).encode(), 0)
    _HELD.add(fd)
    return fd


def release(fd: int | None) -> None:
    if fd is not None:
        _HELD.discard(fd)
        os.close(fd)  # closing the descriptor releases the flock


def forget_inherited() -> None:
    """In a child forked from a lock holder: close its copies of the holder's lock descriptors.

    A ``flock`` belongs to the open file, which a fork shares: the lock would outlive the holder
    as long as a child lives. Closed in the child, it stays the holder's alone (closing a copy
    does not release it)."""
    for fd in list(_HELD):
        try:
            os.close(fd)
        except OSError:
            pass
    _HELD.clear()


@contextmanager
def locked(run_dir: Path, what: str) -> Iterator[int]:
    """``with locked(dir, "report"):`` hold the run directory's lock for the block."""
    fd = acquire(run_dir, what)
    try:
        yield fd
    finally:
        release(fd)


def create_locked(out: Path, overwrite: bool, populate: Callable[[Path], None], what: str) -> int:
    """Create run directory ``out`` complete or not at all, and return its lock.

    ``populate(d)`` writes the first files into a hidden staging directory next to
    ``out``, which is locked and then renamed to ``out`` in one step: a crash leaves either
    no ``out`` or a complete one. ``--overwrite`` takes the old directory's lock first (a
    busy run is never replaced) and swaps the old directory out by renames.
    """
    out = Path(out)
    old_fd = acquire(out, what) if check_replaceable(out, overwrite) else None
    fd = None

    def fill(stage: Path) -> None:
        nonlocal fd
        fd = acquire(stage, what)
        populate(stage)

    try:
        build_dir(out, overwrite, fill)
    except BaseException:
        release(fd)
        raise
    finally:
        release(old_fd)
    return fd
