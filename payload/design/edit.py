"""Editing a design file's text in place: one key's value, every other byte kept.

Used where a command writes into a design (``payload sweep`` makes its point designs,
``payload report envelope --write-stowed`` writes the proposed stowed posture): the
designer's comments, order and layout stay as they were.
"""

from __future__ import annotations

import re
from typing import Any

_HEADER = re.compile(r"^\s*\[\s*([A-Za-z0-9_.\- ]+?)\s*\]\s*(#.*)?$")


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
    assign = re.compile(rf"^(\s*{re.escape(leaf)}\s*=\s*)([^#\n]*?)(\s*(#.*)?)(\r?\n?)$")
    written = toml_value(value)
    current: list[str] = []
    end_of_table = None
    for i, line in enumerate(lines):
        m = _HEADER.match(line)
        if m and not line.lstrip().startswith("[["):
            if current == table and end_of_table is None:
                end_of_table = i
            current = [p.strip() for p in m.group(1).split(".")]
            continue
        if current == table:
            a = assign.match(line)
            if a:
                tail = a.group(3) if comment is None else f"  # {comment}"
                lines[i] = f"{a.group(1)}{written}{tail}{a.group(5)}"
                return "".join(lines)
    addition = f"{leaf} = {written}" + ("" if comment is None else f"  # {comment}") + "\n"
    if current == table and end_of_table is None:  # the table is the last one
        sep = "" if not lines or lines[-1].endswith("\n") else "\n"
        return "".join(lines) + sep + addition
    if end_of_table is not None:
        lines.insert(end_of_table, addition)
        return "".join(lines)
    sep = "" if not lines or lines[-1].endswith("\n") else "\n"
    return "".join(lines) + sep + f"\n[{'.'.join(table)}]\n" + addition


__all__ = ["set_in_text", "toml_value"]
