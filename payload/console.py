"""Terminal output shared by the commands: rich consoles whose tables never wrap when piped."""

from __future__ import annotations

import sys

from rich.console import Console

PIPED_WIDTH = 200
"""Columns a console assumes when its stream is not a terminal (a file or a pipe)."""


class _Console(Console):
    """rich's console, but a reader that went away (``payload ... | head``) ends the
    command as any other output does: rich's own answer is ``SystemExit(1)``, the exit
    code of a failed check; :func:`payload.cli.run` ends it as SIGPIPE would (141)."""

    def on_broken_pipe(self) -> None:
        self.quiet = True
        raise BrokenPipeError(32, "the reader of the console's stream went away")


def console(stderr: bool = False) -> Console:
    """A rich console on stdout (or stderr).

    On a terminal it takes the terminal's width. Piped or redirected, it takes
    :data:`PIPED_WIDTH` columns, so a table keeps one line per row instead of wrapping at
    rich's 80-column default.
    """
    stream = sys.stderr if stderr else sys.stdout
    width = None if stream.isatty() else PIPED_WIDTH
    return _Console(stderr=stderr, width=width)
