"""``spmc run``, ``rerun``, ``report``, ``compare`` (Monte Carlo engine and outputs)."""

from __future__ import annotations

from .app import app, fail, load_or_exit  # noqa: F401
