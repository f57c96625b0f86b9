"""Validation of one decoded recording step, whatever the storage format.

:func:`check_step` looks at a step as the reader decoded it (a mapping of field name to
plain values: numbers, bools, strings, nested lists, ``None``) and raises
:class:`StepError` naming the step, the field and what was expected. The field table is
passed in (``recorder.FIELD_SPECS``), so this module depends on no storage format.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from payload.errors import PayloadError


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_)
    )


class StepError(PayloadError):
    """A decoded step is malformed; the message names the step, field and expectation."""


def _shape_text(shape: tuple[int, ...]) -> str:
    return " x ".join(str(n) for n in shape)


def _describe(value: Any) -> str:
    if isinstance(value, list):
        return f"a list of {len(value)}"
    if value is None:
        return "null"
    text = repr(value)
    return f"{type(value).__name__} {text[:40]}"


def _check_array(value: Any, shape: tuple[int, ...], nullable: bool) -> str | None:
    """What is wrong with a nested list (or array) of numbers, or ``None`` if nothing."""
    if isinstance(value, np.ndarray):
        return _check_ndarray(value, shape, nullable)
    if len(shape) == 0:
        if value is None and nullable:
            return None
        if not _is_number(value):
            return f"expected a number{' or null' if nullable else ''}, got {_describe(value)}"
        if not math.isfinite(value) and not (nullable and math.isnan(value)):
            return f"expected a finite number, got {value}"
        return None
    if not isinstance(value, list) or len(value) != shape[0]:
        return f"expected {_shape_text(shape)} numbers, got {_describe(value)}"
    for i, item in enumerate(value):
        problem = _check_array(item, shape[1:], nullable)
        if problem is not None:
            return f"[{i}]{'' if problem.startswith('[') else ': '}{problem}"
    return None


def _check_ndarray(value: np.ndarray, shape: tuple[int, ...], nullable: bool) -> str | None:
    """The array form of :func:`_check_array` (what a typed decoder returns)."""
    if value.shape != shape:
        got = _shape_text(value.shape) if value.shape else "a scalar"
        return f"expected {_shape_text(shape) or 'a'} number(s), got an array of {got}"
    if value.dtype.kind not in "fiu":
        return f"expected numbers, got an array of {value.dtype}"
    bad = np.isinf(value) if nullable else ~np.isfinite(value)
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        index = "".join(f"[{i}]" for i in where)
        return f"{index}{': ' if index else ''}expected a finite number, got {value[where]}"
    return None


def field_problem(value: Any, shape: tuple[int, ...], kind: Any) -> str | None:
    """What is wrong with one field's value (``None`` if it is valid).

    Args:
        value: The decoded value.
        shape: The field's shape (``()`` for a scalar).
        kind: ``"float"``, ``"float_nan"`` (null allowed), ``"bool"`` or a tuple of the
            allowed strings.
    """
    if isinstance(kind, tuple):
        if not isinstance(value, str) or value not in kind:
            return f"expected one of {list(kind)}, got {_describe(value)}"
        return None
    if kind == "bool":
        if not isinstance(value, (bool, np.bool_)):
            return f"expected true or false, got {_describe(value)}"
        return None
    return _check_array(value, shape, kind == "float_nan")


def check_step(
    step: Mapping[str, Any],
    specs: Mapping[str, tuple[tuple[int, ...], Any]],
    index: int,
    where: str = "",
) -> None:
    """Check one decoded step against the field table.

    Args:
        step: The decoded step.
        specs: Field name -> (shape, kind) (``recorder.FIELD_SPECS``).
        index: The step's position in the recording (from 0), for the message.
        where: The file, for the message.

    Raises:
        StepError: ``"<file>: step <index>: <field>: <what was expected>"``.
    """
    prefix = f"{where}: " if where else ""
    if not isinstance(step, Mapping):
        raise StepError(f"{prefix}step {index}: expected a JSON object, got {_describe(step)}")
    for name, (shape, kind) in specs.items():
        if name not in step:
            raise StepError(f"{prefix}step {index}: {name}: missing")
        problem = field_problem(step[name], shape, kind)
        if problem is not None:
            raise StepError(f"{prefix}step {index}: {name}: {problem}")


__all__ = ["StepError", "check_step", "field_problem"]
