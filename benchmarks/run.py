"""``make bench``: the benchmark suite of stereopose_mc (see docs/performance.md).

    .venv/bin/python benchmarks/run.py              # what `make bench` runs: e2e, realistic, steps (full sizes)
    .venv/bin/python benchmarks/run.py --quick      # reduced sizes (100-trial campaigns, 1,000-trial memory run)
    .venv/bin/python benchmarks/run.py --only latency --only scaling
    .venv/bin/python benchmarks/run.py --all        # every section

Prints the machine, then one table (section, filter, measure, value, unit, target,
status, note); writes it to ``runs/bench/results-<mode>[-<sections>].csv`` and ``.json``
(the JSON adds the machine and the sizes). Progress goes to stderr.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SECTIONS = ("campaign", "chunk", "latency", "scaling", "memory", "baseline", "dispersed", "e2e", "realistic", "steps")
DEFAULT_SECTIONS = ("e2e", "realistic", "steps")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="benchmarks/run.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="reduced sizes: 100-trial campaigns, 1,000-trial memory run")
    p.add_argument("--only", action="append", choices=SECTIONS, metavar="NAME",
                   help=f"run only this section (repeatable): {', '.join(SECTIONS)}; default "
                        f"{', '.join(DEFAULT_SECTIONS)}")  # fmt: skip
    p.add_argument("--all", action="store_true", help="every section")
    p.add_argument("--scenario", type=Path, default=ROOT / "configs" / "caseB.yaml", help="scenario (default case B)")
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "bench", help="output directory (default runs/bench)")
    p.add_argument("--blas-threads", type=int, default=None, metavar="N",
                   help="set OPENBLAS/OMP/MKL_NUM_THREADS=N for this process and the spmc subprocesses "
                        "(default: leave the environment as it is)")  # fmt: skip
    p.add_argument("--keep", action="store_true", help="keep the temporary scenario copies and run directories")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.blas_threads:  # before numpy is imported
        for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[k] = str(args.blas_threads)
    sys.path.insert(0, str(ROOT))
    from benchmarks.common import BenchConfig, format_table, log, write_outputs
    from benchmarks.machine import format_machine, machine_info
    from benchmarks.sections import SECTION_FUNCS

    kw = dict(scenario=args.scenario.resolve(), out=args.out.resolve(), keep_runs=args.keep,
              blas_threads=args.blas_threads)  # fmt: skip
    cfg = BenchConfig.quick(**kw) if args.quick else BenchConfig.full(**kw)
    names = [s for s in SECTIONS if (s in args.only if args.only else (args.all or s in DEFAULT_SECTIONS))]
    info = machine_info()
    cfg.out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="tmp-", dir=cfg.out))
    started = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    t0 = time.perf_counter()
    rows, ctx, timings = [], {}, {}
    log(f"{cfg.mode} run of sections {', '.join(names)}; scratch {tmp}")
    try:
        for name in names:
            t1 = time.perf_counter()
            rows.extend(SECTION_FUNCS[name](cfg, tmp, ctx))
            timings[name] = round(time.perf_counter() - t1, 1)
            log(f"{name} done in {timings[name]:.0f} s")
    finally:
        if not cfg.keep_runs:
            import shutil

            shutil.rmtree(tmp, ignore_errors=True)
    info["loadavg_end"] = os.getloadavg()
    total = time.perf_counter() - t0
    print(format_machine(info))
    print(f"bench   : {cfg.mode} run, scenario {cfg.scenario.name}, sections {', '.join(names)}; {total / 60:.1f} min; "
          f"{started}\n")  # fmt: skip
    print(format_table(rows))
    stem = f"results-{cfg.mode}" + ("" if not args.only else "-" + "-".join(names))
    sizes = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(cfg).items()}
    sizes["chunk_trials"] = {str(k): v for k, v in cfg.chunk_trials.items()}
    meta = {"mode": cfg.mode, "sections": names, "started": started, "duration_s": round(total, 1),
            "section_seconds": timings, "command": sys.argv, "machine": info, "sizes": sizes}  # fmt: skip
    csv_path, json_path = write_outputs(rows, meta, cfg.out, stem)
    print(f"\n* = measured at reduced size (or projected from it); see the note. Written: {csv_path}, {json_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
