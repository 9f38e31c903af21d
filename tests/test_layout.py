"""Layout rules: the layers point one way, and ``stereopose_mc/core`` is pure numerics.

The layers, lowest first (README, "Layout"): core, data, config, sim, filters, rundir, mc,
studies, outputs, api, cli. A module imports only from its own layer and the layers below
it. Every module under ``core/`` may import only numpy, scipy, numba, the standard library,
``__future__`` and (relatively) other modules of ``core``. Both are checked on the source
with ``ast``, so imports inside functions and ``if TYPE_CHECKING`` blocks count too.
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
ORDER = ("core", "data", "config", "sim", "filters", "rundir", "mc", "studies", "outputs", "api", "cli")  # lowest first
LAYERS = set(ORDER)


def _imported(node: ast.Import | ast.ImportFrom, module: str, is_package: bool) -> list[str]:
    """The absolute names ``node`` imports, in ``module`` (dotted; ``is_package``: an ``__init__``)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if not node.level:
        return [node.module or ""]
    parts = module.split(".") if is_package else module.split(".")[:-1]
    base = ".".join(parts[: len(parts) - (node.level - 1)])
    if node.module:
        return [f"{base}.{node.module}"]
    return [f"{base}.{a.name}" for a in node.names]  # from .. import rundir: the names are modules


def layer_violations(source: str, module: str, is_package: bool = False) -> list[str]:
    """Imports of ``source`` (the module ``stereopose_mc.<layer>...``) from a layer above its own."""
    layer = module.split(".")[1]
    bad = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        for name in _imported(node, module, is_package):
            parts = name.split(".")
            if parts[0] != "stereopose_mc" or len(parts) < 2 or parts[1] == "__version__":
                continue
            if parts[1] not in LAYERS or ORDER.index(parts[1]) > ORDER.index(layer):
                bad.append(f"line {node.lineno}: {layer} imports {name}")
    return bad


def test_layer_rule_flags_what_it_should():
    src = (
        "from __future__ import annotations\nimport numpy as np\nfrom .. import __version__\n"
        "from ..rundir import store, tables\nfrom . import trial\nfrom .trial import run_chunk\n"
        "from stereopose_mc.core import state\nfrom ..outputs import tables\nimport stereopose_mc.cli.main\n"
        "from .. import studies, sim\nif TYPE_CHECKING:\n    from ..api import Run\n"
        "def f():\n    from ..studies.sweep import summary\n"
        "class C:\n    def g(self):\n        from ..outputs.report import page\n"
    )
    assert layer_violations(src, "stereopose_mc.mc.engine") == [
        "line 8: mc imports stereopose_mc.outputs",
        "line 9: mc imports stereopose_mc.cli.main",
        "line 10: mc imports stereopose_mc.studies",
        "line 12: mc imports stereopose_mc.api",
        "line 14: mc imports stereopose_mc.studies.sweep",
        "line 17: mc imports stereopose_mc.outputs.report",
    ]
    # a package's __init__ resolves ``.`` to itself; a sub-package's module one level further down
    assert layer_violations("from .store import x\nfrom ..mc import engine\n", "stereopose_mc.rundir", True) == [
        "line 2: rundir imports stereopose_mc.mc"]
    assert layer_violations("from ..mc import engine\n", "stereopose_mc.rundir.store") == [
        "line 1: rundir imports stereopose_mc.mc"]
    assert layer_violations("from ...mc import x\n", "stereopose_mc.core.kernels.model") == [
        "line 1: core imports stereopose_mc.mc"]


MODULES = sorted(p for p in PACKAGE.rglob("*.py") if p.parent != PACKAGE)


@pytest.mark.parametrize("path", MODULES, ids=[str(p.relative_to(PACKAGE)) for p in MODULES])
def test_each_layer_imports_only_the_layers_below(path):
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    is_package = rel.name == "__init__"
    module = ".".join(rel.parts[:-1] if is_package else rel.parts)
    assert layer_violations(path.read_text(encoding="utf-8"), module, is_package) == [], path


def test_no_module_at_the_package_root():
    """Every module sits in the folder of its layer; only ``__init__`` is at the root."""
    assert sorted(p.name for p in PACKAGE.glob("*.py")) == ["__init__.py"]
    assert {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()} <= LAYERS


@pytest.mark.parametrize("path", sorted((PACKAGE / "cli").glob("*.py")), ids=lambda p: p.name)
def test_cli_files_stay_thin(path):
    """One small file per command group: parse, call one typed function, print."""
    assert len(path.read_text(encoding="utf-8").splitlines()) <= 200, path
