"""``spmc observability``, ``inertia``, ``dynamics`` (the rest of the thesis)."""

from __future__ import annotations

from .app import app, fail, load_or_exit  # noqa: F401
