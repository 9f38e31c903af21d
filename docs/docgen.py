"""Shared pieces of the docs/make_*.py generators: generated blocks between markers, lost reasons by kind."""

from __future__ import annotations

from pathlib import Path

REASON_KINDS = (("mean NIS", "NIS test"), ("gate rejected", "gate lock-out"), ("no feature", "no features"),
                ("non-finite", "numerical"), ("not positive definite", "numerical"), ("linear algebra", "numerical"))


def reason_kind(reason: str) -> str:
    """A lost reason by kind: ``filter lost: mean NIS over 10 steps = 300 ...`` -> ``NIS test``."""
    return next((kind for text, kind in REASON_KINDS if text in (reason or "")), reason or "(none)")


def markers(name: str) -> tuple[str, str]:
    return f"<!-- {name}:begin -->", f"<!-- {name}:end -->"


def splice(text: str, name: str, body: str, doc: Path) -> str:
    """Replace the text between the markers of ``name`` (each present once in ``doc``'s ``text``) by ``body``."""
    begin, end = markers(name)
    if text.count(begin) != 1 or text.count(end) != 1:
        raise SystemExit(f"{doc}: markers of {name!r} missing or repeated")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{begin}\n{body}\n{end}{tail}"
