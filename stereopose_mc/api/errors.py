"""The one exception the API raises for bad input or a run that cannot go on."""

from __future__ import annotations


class SpmcError(Exception):
    """Bad input (a scenario, a run directory, an option) or a run that cannot go on.

    ``lines``: one line per problem, each naming the file, key or option and what is wrong
    (``spmc`` prints them as ``error: ...`` and exits with code 2).
    """

    def __init__(self, lines: list[str] | str):
        self.lines = [lines] if isinstance(lines, str) else list(lines)
        super().__init__("\n".join(self.lines))
