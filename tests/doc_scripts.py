"""The docs/make_*.py generators, imported by the tests that keep their docs honest."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def load_doc_script(name: str) -> ModuleType:
    """``docs/<name>.py`` as a module (registered in ``sys.modules``: dataclasses look their module up there)."""
    if str(ROOT / "docs") not in sys.path:  # the generators import docs/docgen.py as scripts do
        sys.path.insert(0, str(ROOT / "docs"))
    spec = importlib.util.spec_from_file_location(name, ROOT / "docs" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod
