"""Layout rule: ``stereopose_mc/core`` is pure numerics.

Every module under ``core/`` may import only numpy, scipy, numba, the standard library,
``__future__`` and (relatively) other modules of ``core``. Checked on the source with
``ast``, so imports inside functions and ``if TYPE_CHECKING`` blocks count too.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parents[1] / "stereopose_mc" / "core"
ALLOWED_TOP = {"numpy", "scipy", "numba", "__future__"}  # numba: core/kernels (the layer rule: numpy/scipy/numba only)


def _core_modules() -> set[str]:
    return {p.stem for p in CORE.glob("*.py")} | {p.name for p in CORE.iterdir() if (p / "__init__.py").exists()}


def forbidden_imports(source: str, depth: int = 1) -> list[str]:
    """Imports of ``source`` that break the rule; ``depth`` is the module's package depth below ``core``.

    ``depth`` = 1 for ``core/x.py``: ``from . import y`` (level 1) stays in core, level 2 leaves it.
    """
    bad = []
    stdlib = set(sys.stdlib_module_names)
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                if node.level > depth:
                    bad.append(f"line {node.lineno}: from {'.' * node.level}{node.module or ''} leaves core")
                continue
            names = [node.module or ""]
        else:
            continue
        for name in names:
            top = name.split(".")[0]
            if top not in ALLOWED_TOP and top not in stdlib:
                bad.append(f"line {node.lineno}: import {name}")
    return bad


def test_rule_flags_what_it_should():
    src = (
        "from __future__ import annotations\nimport numpy as np\nfrom scipy.linalg import expm\n"
        "import math, dataclasses\nfrom . import quaternion\nfrom .orbit import Orbit\n"
        "import pandas\nfrom ..config import schema\nimport stereopose_mc.sim\nfrom pydantic import BaseModel\n"
        "def f():\n    import matplotlib.pyplot as plt\n"
    )
    assert forbidden_imports(src) == [
        "line 7: import pandas",
        "line 8: from ..config leaves core",
        "line 9: import stereopose_mc.sim",
        "line 10: import pydantic",
        "line 12: import matplotlib.pyplot",
    ]


FILES = sorted(CORE.rglob("*.py"))


def test_core_has_modules():
    assert {"quaternion", "orbit", "state", "dynamics", "camera", "inertia"} <= _core_modules()


@pytest.mark.parametrize("path", FILES, ids=[str(p.relative_to(CORE)) for p in FILES])
def test_core_imports_only_numpy_scipy_stdlib(path):
    depth = len(path.relative_to(CORE).parts)  # core/x.py -> 1, core/sub/x.py -> 2
    assert forbidden_imports(path.read_text(encoding="utf-8"), depth) == [], path


PACKAGE = CORE.parent
LAYERS = {"cli", "api", "outputs", "studies", "mc", "filters", "sim", "config", "core", "data"}


def test_no_module_at_the_package_root():
    """Every module sits in the folder of its layer; only ``__init__`` is at the root."""
    assert sorted(p.name for p in PACKAGE.glob("*.py")) == ["__init__.py"]
    assert {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()} <= LAYERS


@pytest.mark.parametrize("path", sorted((PACKAGE / "cli").glob("*.py")), ids=lambda p: p.name)
def test_cli_files_stay_thin(path):
    """One small file per command group: parse, call one typed function, print."""
    assert len(path.read_text(encoding="utf-8").splitlines()) <= 200, path
