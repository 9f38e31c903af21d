"""Pure numerical core: numpy/scipy only, SI units, trial axis first, no I/O.

Nothing in this package may import pydantic, pandas, pyarrow, matplotlib, typer or
any other part of ``stereopose_mc`` outside ``core`` (checked by
``tests/test_layout.py``).
"""
