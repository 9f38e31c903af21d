"""The run-directory modules the API uses, imported in one place (they are moving to their own layer)."""

from __future__ import annotations

from ..outputs.rundir import RunDirError
from ..outputs.runlock import locked

__all__ = ["RunDirError", "locked"]
