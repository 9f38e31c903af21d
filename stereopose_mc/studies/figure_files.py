"""How every figure of the project is saved: ``stem.png`` (150 dpi) and a reproducible ``stem.svg``.

The SVG is made reproducible (fixed hash salt, text as paths, no date or creator), and each
file is written atomically. ``studies/`` saves its figures through this module and so do
the report modules of ``outputs/`` above it.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING

from ..rundir import store

if TYPE_CHECKING:
    from matplotlib.figure import Figure

DPI = 150
SVG_RC = {"svg.hashsalt": "stereopose_mc", "svg.fonttype": "path"}


def save_figure(fig: Figure, out_dir: Path, stem: str) -> tuple[Path, Path]:
    """Save ``fig`` as ``stem.png`` (150 dpi) and ``stem.svg``, each written atomically."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    paths = []
    for ext in ("png", "svg"):
        buf = io.BytesIO()
        with matplotlib.rc_context(SVG_RC):
            meta = {"Software": None} if ext == "png" else {"Date": None, "Creator": None}
            fig.savefig(buf, format=ext, dpi=DPI, metadata=meta)
        path = Path(out_dir) / f"{stem}.{ext}"
        store.atomic_write_bytes(path, buf.getvalue())
        paths.append(path)
    return paths[0], paths[1]
