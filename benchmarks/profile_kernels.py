"""Where a chunk's time goes, by function, the compiled kernels' own functions named (``perf``, Linux).

    .venv/bin/python benchmarks/profile_kernels.py configs/mission-mesh-dispersed.yaml --trials 100
    .venv/bin/python benchmarks/profile_kernels.py configs/caseB.yaml --trials 250 --top 40
    .venv/bin/python benchmarks/profile_kernels.py configs/caseB.yaml --map-only   # the symbol map, no perf

Runs one engine chunk of ``--trials`` trials in this process on one thread (after a 2-trial chunk that loads the
kernels), with ``perf record`` attached to this process for that chunk only, then prints ``perf report``'s
functions by self time. ``perf`` names the machine code of Python's and the libraries' functions by itself, but
not Numba's: its kernels are loaded from Numba's cache into anonymous memory. This script reads each loaded
kernel's object code (the ELF that Numba's cache holds: every function of the kernel, its callees inlined or not,
with its offset and size), places it where the JIT engine loaded it (a global symbol's address, less its offset)
and writes ``/tmp/perf-<pid>.map``, perf's map of JIT code (``start size name``), so that ``perf report`` names
them (``stereopose_mc::core::kernels::whiten::_whiten_information``; a function that appears in several kernels'
objects appears once per copy).

Needs ``perf`` (Debian's linux-perf) and permission to record (``perf_event_paranoid``); ``--map-only`` needs
neither. The profile is of one thread without the engine's threads and files: the kernels' shares, not a run's.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

_OBJECTS: dict[int, bytes] = {}  # id(library) -> the object code Numba's cache loaded it from


def record_objects() -> None:
    """Keep the object code of every library Numba loads from its cache from now on (before the kernels load)."""
    from numba.core import codegen

    lib_cls = codegen.CPUCodeLibrary
    if getattr(lib_cls, "_spmc_profile", False):
        return
    numba_set = lib_cls._set_compiled_object

    def _set_compiled_object(self, value):
        _OBJECTS[id(self)] = value
        return numba_set(self, value)

    lib_cls._set_compiled_object = _set_compiled_object
    lib_cls._spmc_profile = True


def _demangled(names: list[str]) -> list[str]:
    """Numba's mangled names as ``module::function`` (c++filt, without its ABI tags and arguments)."""
    if not names or shutil.which("c++filt") is None:
        return names
    out = subprocess.run(["c++filt"], input="\n".join(names), capture_output=True, text=True, check=True).stdout
    return [d.split("(")[0].split("[abi")[0] for d in out.splitlines()]


def kernel_symbols() -> list[tuple[int, int, str]]:
    """``(address, size, name)`` of every function in the loaded kernels' object code (``record_objects``)."""
    from numba.core.registry import CPUDispatcher

    from stereopose_mc.core import kernels

    libraries = {}
    for m in pkgutil.iter_modules(kernels.__path__):
        module = importlib.import_module(f"{kernels.__name__}.{m.name}")
        for obj in vars(module).values():
            if isinstance(obj, CPUDispatcher):
                for cres in obj.overloads.values():
                    libraries[id(cres.library)] = cres.library
    symbols = []
    with tempfile.TemporaryDirectory() as tmp:
        for key, lib in libraries.items():
            code = _OBJECTS.get(key)
            if code is None:
                continue
            path = Path(tmp) / "kernel.o"
            path.write_bytes(code)
            nm = subprocess.run(["nm", "-S", "--defined-only", str(path)], capture_output=True, text=True).stdout
            funcs = [(int(p[0], 16), int(p[1], 16), p[2], p[3]) for p in (ln.split() for ln in nm.splitlines())
                     if len(p) == 4 and p[2] in "TtWw"]  # fmt: skip
            engine = lib._codegen._engine
            base = next((a - off for off, _, kind, name in funcs if kind == "T"
                         and (a := engine.get_function_address(name))), None)  # fmt: skip
            if base is None:
                continue
            names = _demangled([name for *_, name in funcs])
            symbols += [(base + off, size, name) for (off, size, _, _), name in zip(funcs, names)]
    return sorted(symbols)


def write_map(symbols: list[tuple[int, int, str]], pid: int | None = None) -> Path:
    """``/tmp/perf-<pid>.map``: perf's map of this process's JIT code."""
    path = Path(f"/tmp/perf-{pid or os.getpid()}.map")
    path.write_text("".join(f"{a:x} {s:x} {n}\n" for a, s, n in symbols))
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="benchmarks/profile_kernels.py", description=__doc__.split("\n\n")[0])
    p.add_argument("scenario", type=Path)
    p.add_argument("--trials", type=int, default=100, help="trials of the profiled chunk (default 100)")
    p.add_argument("--top", type=int, default=30, help="functions printed (default 30)")
    p.add_argument("--map-only", action="store_true", help="write the symbol map after the 2-trial chunk, no perf")
    args = p.parse_args(argv)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    record_objects()
    from stereopose_mc.config.loader import load_scenario
    from stereopose_mc.mc import engine

    scenario = load_scenario(args.scenario).model_dump_json()
    engine.compute_chunk(scenario, np.arange(2), "summary")  # loads the kernels (and compiles what is not cached)
    path = write_map(kernel_symbols())
    print(f"symbol map: {path} ({len(path.read_text().splitlines())} functions)", file=sys.stderr)
    if args.map_only:
        return 0
    if shutil.which("perf") is None:
        print("error: perf not found (Debian: apt-get install linux-perf); --map-only writes the map alone",
              file=sys.stderr)  # fmt: skip
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "perf.data"
        rec = subprocess.Popen(["perf", "record", "-q", "-o", str(data), "-p", str(os.getpid())])
        time.sleep(0.5)  # (perf attached)
        t0 = time.perf_counter()
        engine.compute_chunk(scenario, np.arange(100, 100 + args.trials), "summary")
        wall = time.perf_counter() - t0
        rec.send_signal(signal.SIGINT)
        rec.wait()
        report = subprocess.run(["perf", "report", "-i", str(data), "--stdio", "--no-children", "--sort", "symbol"],
                                capture_output=True, text=True).stdout  # fmt: skip
    rows = [ln for ln in report.splitlines() if ln.strip() and not ln.startswith("#") and "%" in ln]
    print(f"{args.scenario.name}: one chunk of {args.trials} trials on one thread, {wall:.2f} s; self time by function")
    for ln in rows[: args.top]:
        print(ln.rstrip()[:140])
    return 0


if __name__ == "__main__":
    sys.exit(main())
