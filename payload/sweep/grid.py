"""The grid of a design sweep: ``--set KEY=...`` values and the edited design files.

A sweep key is a dotted design key (``finger.lengths.distal``) naming a number of the
design. ``KEY=V1,V2,...`` lists values; ``KEY=A:B:N`` gives ``N`` evenly spaced values
from ``A`` to ``B``. The grid is every combination, in the order the keys were given
(the last key varies fastest).
"""

from __future__ import annotations

import itertools
import math
import sys
from dataclasses import dataclass
from typing import Any

import numpy as np

from payload.design.edit import set_in_text
from payload.design.params import Design, design_from_dict, design_to_dict
from payload.errors import PayloadError, closest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

MAX_POINTS = 10_000
"""Refuse grids larger than this (a typo in ``N`` should not start a week of work)."""


class SweepError(PayloadError):
    """A bad ``--set`` or sweep setting (exit 2)."""


@dataclass(frozen=True)
class Axis:
    """One swept key and its values.

    Attributes:
        key: Dotted design key, e.g. ``finger.lengths.distal``.
        values: The values, in the given order [SI units of the key].
    """

    key: str
    values: tuple[float, ...]


def _number(key: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise SweepError(f"--set {key}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise SweepError(f"--set {key}: {text!r} is not finite")
    return value


def _tidy(value: float) -> float:
    """Drop the last-bit noise of ``linspace`` (0.045000000000000005 -> 0.045)."""
    return float(f"{value:.12g}")


def parse_set(text: str) -> Axis:
    """Parse one ``KEY=V1,V2,...`` or ``KEY=A:B:N``.

    Raises:
        SweepError: No ``=``, an empty key or value, a non-number, or a bad ``N``.
    """
    key, sep, spec = text.partition("=")
    key, spec = key.strip(), spec.strip()
    if not sep or not key or not spec:
        raise SweepError(f"--set {text!r}: expected KEY=V1,V2,... or KEY=A:B:N")
    if ":" in spec:
        parts = spec.split(":")
        if len(parts) != 3:
            raise SweepError(f"--set {key}: expected A:B:N, got {spec!r}")
        a, b = _number(key, parts[0]), _number(key, parts[1])
        try:
            n = int(parts[2])
        except ValueError:
            raise SweepError(f"--set {key}: N must be an integer, got {parts[2]!r}") from None
        if n < 1:
            raise SweepError(f"--set {key}: N must be >= 1, got {n}")
        if n == 1 and a != b:  # B would be dropped without a word
            raise SweepError(
                f"--set {key}: {spec} is {parts[0]} alone (N = 1): give N >= 2 to reach "
                f"{parts[1]}, or {key}={parts[0]}"
            )
        values = [a] if n == 1 else [_tidy(v) for v in np.linspace(a, b, n)]
    else:
        values = [_number(key, v.strip()) for v in spec.split(",")]
    if len(set(values)) != len(values):
        raise SweepError(f"--set {key}: a value is listed twice")
    return Axis(key, tuple(values))


def _lookup(data: dict[str, Any], key: str) -> Any:
    node: Any = data
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(key)
        node = node[part]
    return node


def _number_keys(node: Any, prefix: str = "") -> list[str]:
    """The dotted keys of the numbers in a design's plain dict (what can be swept)."""
    if isinstance(node, dict):
        return [k for name, v in node.items() for k in _number_keys(v, f"{prefix}{name}.")]
    if isinstance(node, (int, float)) and not isinstance(node, bool):
        return [prefix[:-1]]
    return []


def check_axes(axes: list[Axis], base: Design) -> None:
    """Every key names a number of the design, once.

    Raises:
        SweepError: No axes, a repeated key, an unknown key, a key that is not a
            number (a table, a list, a string), or a grid larger than :data:`MAX_POINTS`.
    """
    if not axes:
        raise SweepError("nothing to sweep: give at least one --set KEY=...")
    plain = design_to_dict(base)
    seen: set[str] = set()
    for axis in axes:
        if axis.key in seen:
            raise SweepError(f"--set {axis.key}: given twice")
        seen.add(axis.key)
        try:
            value = _lookup(plain, axis.key)
        except KeyError:
            near = closest(axis.key, _number_keys(plain))
            hint = f" (did you mean {near}?)" if near else ""
            raise SweepError(f"--set {axis.key}: not a design key{hint}") from None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SweepError(f"--set {axis.key}: not a number in the design (it is {value!r})")
    total = math.prod(len(a.values) for a in axes)
    if total > MAX_POINTS:
        raise SweepError(f"the grid has {total:,} points, more than {MAX_POINTS:,}")


def key_unit(key: str) -> str | None:
    """The unit of design key ``key`` (``finger.lengths.distal``: ``m``), from the design's
    own field and table docs (the ``[unit]`` each states), or None (not a design key, or
    none stated)."""
    import dataclasses
    import re
    import typing

    table: Any = Design
    for part in key.split("."):
        if not dataclasses.is_dataclass(table):
            return None
        fields = {f.name: f for f in dataclasses.fields(table)}
        if part not in fields:
            return None
        kind = typing.get_type_hints(table).get(part)
        if dataclasses.is_dataclass(kind):
            table = kind
            continue
        docs = (fields[part].metadata.get("doc", ""), (table.__doc__ or "").split("\n")[0])
        for doc in docs:
            found = re.search(r"\[([^\]]+)\]", doc)
            if found:
                return found.group(1)
        return None
    return None


def grid(axes: list[Axis]) -> list[dict[str, float]]:
    """Every combination of the axes' values, as ``{key: value}`` (last key fastest)."""
    keys = [a.key for a in axes]
    return [dict(zip(keys, combo)) for combo in itertools.product(*(a.values for a in axes))]


def edit_design(text: str, params: dict[str, float]) -> str:
    """The design TOML ``text`` with each dotted key of ``params`` set to its value.

    Comments and every other line stay as they are. The result is parsed again and
    compared with the intended document, so an edit the line editor cannot make
    (e.g. a key inside an inline table) is an error rather than a wrong design.

    Raises:
        SweepError: The edit did not give the intended document.
    """
    want = tomllib.loads(text)
    out = text
    for key, value in params.items():
        node = want
        *table, leaf = key.split(".")
        for part in table:
            node = node.setdefault(part, {})
        node[leaf] = value
        out = set_in_text(out, key, value)
    if tomllib.loads(out) != want:
        raise SweepError(f"cannot write {', '.join(params)} into the design file text")
    return out


def validate_point(text: str) -> Design:
    """The design of a point's TOML text (raises :class:`DesignError` when invalid)."""
    return design_from_dict(tomllib.loads(text), source="<sweep point>")


__all__ = [
    "MAX_POINTS",
    "Axis",
    "SweepError",
    "check_axes",
    "edit_design",
    "grid",
    "parse_set",
    "validate_point",
]
