"""Editing a design file's text in place: one key's value, every other byte kept.

Used where a command writes into a design (``payload sweep`` makes its point designs,
``payload report envelope --write-stowed`` writes the proposed stowed posture): the
designer's comments, order and layout stay as they were.
"""

from __future__ import annotations

import re
from typing import Any

_HEADER = re.compile(r"^\s*\[\s*([A-Za-z0-9_.\- ]+?)\s*\]\s*(#.*)?$")
_REST = r"([^#\r\n]*?)([ \t]*(?:#[^\r\n]*)?)(\r?\n?)$"
"""The rest of a line after ``key =``: the value's text, its blanks and comment, its end."""
_LINE = re.compile(_REST)
_ANY_KEY = re.compile(r"^([ \t]*[A-Za-z0-9_\-\"'.]+[ \t]*=[ \t]*)" + _REST)
"""Any ``key = value`` line (bare, quoted or dotted key)."""


def toml_value(value: Any) -> str:
    """A number or a list of numbers as TOML text (``0.045``, ``[1.66, 0.0]``)."""
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return repr(float(value)) if isinstance(value, float) else repr(value)


def set_in_text(text: str, key: str, value: Any, comment: str | None = None) -> str:
    """``text`` with ``key = value`` in its table, keeping every other line as it is.

    Args:
        text: A design file's text.
        key: Dotted key, e.g. ``stowed.finger``.
        value: A number or a list of numbers.
        comment: Replaces the line's comment (``# ...`` after the value); ``None`` keeps
            the line's own.

    Returns:
        The edited text; a key the table lacks is added at the table's end (the table at
        the file's end when it is missing).
    """
    *table, leaf = key.split(".")
    lines = text.splitlines(keepends=True)
    eol = "\r\n" if "\r\n" in text else "\n"  # a key added ends its line as the file does
    # within one line: blanks are spaces and tabs, never the line's end (which is kept)
    assign = re.compile(rf"^([ \t]*{re.escape(leaf)}[ \t]*=[ \t]*)" + _REST)
    written = toml_value(value)
    current: list[str] = []
    end_of_table = None
    i = 0
    while i < len(lines):
        line = lines[i]
        m = _HEADER.match(line)
        if m and not line.lstrip().startswith("[["):
            if current == table and end_of_table is None:
                end_of_table = i
            current = [p.strip() for p in m.group(1).split(".")]
            i += 1
            continue
        a = assign.match(line) if current == table else None
        if a:
            last, tail, end = _value_end(lines, i, a)
            tail = tail if comment is None else f"  # {comment}"
            lines[i : last + 1] = [f"{a.group(1)}{written}{tail}{end}"]
            return "".join(lines)
        other = _ANY_KEY.match(line)  # another key's value: its lines are not headers
        i = (_value_end(lines, i, other)[0] if other else i) + 1
    addition = f"{leaf} = {written}" + ("" if comment is None else f"  # {comment}") + eol
    if current == table and end_of_table is None:  # the table is the last one
        sep = "" if not lines or lines[-1].endswith("\n") else eol
        return "".join(lines) + sep + addition
    if end_of_table is not None:
        lines.insert(end_of_table, addition)
        return "".join(lines)
    sep = "" if not lines or lines[-1].endswith("\n") else eol
    return "".join(lines) + sep + f"{eol}[{'.'.join(table)}]{eol}" + addition


def _value_end(lines: list[str], i: int, assign: re.Match[str]) -> tuple[int, str, str]:
    """Where the value assigned on line ``i`` ends (an array may run over several lines,
    with comments among its items): its last line, and that line's blanks and comment
    and its line end, which follow the new value."""
    depth, j, rest = _depth(assign.group(2)), i, assign
    while depth > 0 and j + 1 < len(lines):
        j += 1
        rest = _LINE.match(lines[j])  # matches any one line
        assert rest is not None
        depth += _depth(rest.group(1))
    *_, tail, end = rest.groups()
    return j, tail, end


def _depth(value: str) -> int:
    """How many more brackets ``value`` opens than it closes, outside quoted text."""
    depth, quote = 0, ""
    for ch in value:
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch == "[":
            depth += 1
        elif ch == "]":
            depth -= 1
    return depth


__all__ = ["set_in_text", "toml_value"]
