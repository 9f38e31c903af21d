"""The benchmark suite of ``stereopose_mc`` (``make bench``; entry point ``benchmarks/run.py``).

Modules: ``common`` (rows, timing, scenario copies, table/CSV/JSON output), ``machine``
(what the numbers were measured on), ``procmem`` (peak memory of a process tree),
``filterpy_baseline`` (the per-trial FilterPy EKF), ``sections`` (one function per table
section). See docs/performance.md.
"""
