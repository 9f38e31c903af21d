"""``spmc``: thin typer commands, each parsing arguments and calling one typed function.

Command modules register themselves on the shared ``app`` when imported here.
"""

from __future__ import annotations

import atexit
import os
import signal
import sys
import threading
from typing import NoReturn

import typer

from . import dynamics_cmd, inertia_cmd, observability_cmd, report_cmds, run_cmds, scenario_cmds  # noqa: F401
from . import export_cmd, sweep_cmd, tune_cmd  # noqa: F401  (each module registers its commands)
from .app import app

# OpenBLAS's idle worker threads spin for 2^28 CPU cycles (~0.1 s) after their pool starts or after a call before they
# sleep. The runs compute with BLAS single-threaded (``mc.engine``: ``threadpool_limits``), so that spin of numpy's and
# SciPy's pools, as they load, only takes a core from the start-up and the first chunks (~0.2 s of CPU per run). 2^4
# cycles: they sleep at once. Set before numpy is imported; a value in the environment is kept.
BLAS_THREAD_TIMEOUT = "4"


def main() -> None:  # console-script entry point
    """``spmc``; an unforeseen OS error (a file that vanished, a full disk) is one line and exit 2, not a traceback.

    The process then ends without tearing the interpreter down (``exit_now``).
    """
    os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", BLAS_THREAD_TIMEOUT)
    try:
        app()
    except SystemExit as exc:
        exit_now(exc.code)
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename else ""
        typer.echo(f"error: {where}{exc.strerror or exc}", err=True)
        exit_now(2)
    except MemoryError:
        typer.echo("error: out of memory (fewer trials or a smaller --chunk-size / --jobs may fit)", err=True)
        exit_now(2)
    exit_now(0)


def exit_now(code: int | str | None) -> NoReturn:
    """``sys.exit(code)`` without the interpreter's teardown, which costs 0.2-0.4 s once pandas, scipy and Numba are
    loaded (freeing every module and object one by one; the OS frees the process at once).

    What an exit must still do is done first: the ``atexit`` handlers run (logging, temporary files,
    worker pools), and stdout and stderr are flushed. Every file the commands write is closed by then
    (``rundir/store.py`` writes through temporary files and renames). While a non-daemon thread is
    still running, the ordinary exit is taken (it waits for the thread).
    """
    if code is None:
        code = 0
    elif not isinstance(code, int):  # sys.exit("message"): printed, status 1
        print(code, file=sys.stderr)
        code = 1
    figures = sys.modules.get("stereopose_mc.outputs.figures")
    if figures is not None:  # the report's drawing processes, and their executor's thread
        figures.stop_drawing()
    main_thread = threading.main_thread()
    if any(t is not main_thread and t.is_alive() and not t.daemon for t in threading.enumerate()):
        sys.exit(code)
    if threading.current_thread() is main_thread:  # a Ctrl-C now has nothing left to stop: no "Exception ignored"
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (spmc ... | head): status 120, as Python's own exit gives
            code = code or 120
    os._exit(code)


if __name__ == "__main__":
    main()
