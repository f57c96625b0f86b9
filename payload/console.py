"""Terminal output shared by the commands: rich consoles whose tables never wrap when piped."""

from __future__ import annotations

import sys

from rich.console import Console

PIPED_WIDTH = 200
"""Columns a console assumes when its stream is not a terminal (a file or a pipe)."""


def console(stderr: bool = False) -> Console:
    """A rich console on stdout (or stderr).

    On a terminal it takes the terminal's width. Piped or redirected, it takes
    :data:`PIPED_WIDTH` columns, so a table keeps one line per row instead of wrapping at
    rich's 80-column default.
    """
    stream = sys.stderr if stderr else sys.stdout
    width = None if stream.isatty() else PIPED_WIDTH
    return Console(stderr=stderr, width=width)
