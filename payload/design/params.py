"""Typed design parameters loaded from ``cad/design.toml``, with validation.

Every field is SI (m, rad, kg, s, N, A). Loading is strict: an unknown key, a
missing key, a value of the wrong type or out of range raises
:class:`~payload.errors.DesignError` naming the dotted parameter path.

The types, their cross-field checks and :func:`design_to_dict` are
:mod:`payload.design.param_types` (the names other modules import from here are
re-exported); this module reads a design file into them.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import sys
import types
import typing
import warnings
from pathlib import Path
from typing import Any

from payload.design.param_types import (
    FINGER_JOINTS,
    FINGERS,
    SIDE_OF,
    Design,
    Pinch,
    Range,
    design_to_dict,
)
from payload.errors import DesignError, as_toml, closest, is_number, not_text
from payload.project import current_project, default_design_text

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

_LEGACY_KEYS = {
    "finger": ("damping", "frictionloss", "armature", "kp", "kv"),
    "rail": ("damping", "kp"),
    "stage": ("damping", "kp"),
}
"""Keys of design files written before the servo model: now derived from ``[servo]``."""


def _upgrade(data: dict[str, Any]) -> dict[str, Any]:
    """A design document from before the servo model, brought to today's keys.

    The per-joint servo keys of ``[finger]``, ``[rail]`` and ``[stage]`` are dropped with a
    warning (the servo model derives them); missing ``[servo]`` keys take the packaged
    default's values.
    """
    data = copy.deepcopy(data)
    dropped = []
    for table, keys in _LEGACY_KEYS.items():
        sub = data.get(table)
        if isinstance(sub, dict):
            dropped += [f"{table}.{k}" for k in keys if sub.pop(k, None) is not None]
    if dropped:
        warnings.warn(
            f"design: {', '.join(dropped)} ignored; the servo model derives them from "
            "[servo] (docs/servo.md)",
            DeprecationWarning,
            stacklevel=3,
        )
    servo = data.get("servo")
    if isinstance(servo, dict):
        for key, value in _default_servo().items():
            servo.setdefault(key, copy.deepcopy(value))
    return data


@functools.cache
def _default_servo() -> dict[str, Any]:
    return dict(tomllib.loads(default_design_text())["servo"])


def _build(cls: type, data: Any, path: str) -> Any:
    """Build dataclass ``cls`` from a TOML table, strictly."""
    if not isinstance(data, dict):
        raise DesignError(path or "<root>", f"expected a table, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = [f for f in dataclasses.fields(cls) if not f.metadata.get("internal")]
    known = {f.name for f in fields}
    for key in data:
        if key not in known:
            where = f"{path}.{key}" if path else key
            near = closest(key, known)  # a typo: the key it was
            hint = f"did you mean {near}? " if near else ""
            raise DesignError(
                where, f"unknown key ({hint}expected one of: {', '.join(sorted(known))})"
            )
    kwargs: dict[str, Any] = {}
    for f in fields:
        where = f"{path}.{f.name}" if path else f.name
        if f.metadata.get("optional_table"):
            table = data.get(f.name, {})
            if not isinstance(table, dict):
                raise DesignError(where, f"expected a table, got {type(table).__name__}")
            kwargs[f.name] = copy.deepcopy(table)
            continue
        if f.name not in data:
            if f.metadata.get("optional"):
                continue
            table = dataclasses.is_dataclass(hints[f.name]) and hints[f.name] is not Range
            raise DesignError(where, f"missing table [{where}]" if table else "missing key")
        kwargs[f.name] = _value(hints[f.name], data[f.name], where, f.metadata)
    return cls(**kwargs)


def _value(tp: Any, v: Any, where: str, meta: Any) -> Any:
    if dataclasses.is_dataclass(tp) and tp is not Range:
        return _build(tp, v, where)
    if tp is Range:
        if not (isinstance(v, list) and len(v) == 2 and all(is_number(x) for x in v)):
            raise DesignError(where, f"expected [lower, upper] numbers, got {as_toml(v)}")
        lo, hi = float(v[0]), float(v[1])
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise DesignError(where, "limits must be finite")
        return Range(lo, hi)
    origin = typing.get_origin(tp)
    if origin is tuple:
        args = typing.get_args(tp)
        if not (isinstance(v, list) and len(v) == len(args) and all(is_number(x) for x in v)):
            raise DesignError(where, f"expected {len(args)} numbers, got {as_toml(v)}")
        return tuple(float(x) for x in v)
    if tp is str:
        if not isinstance(v, str):
            raise DesignError(where, f"expected a string, got {as_toml(v)}")
        return v
    if tp is float:
        if not is_number(v):
            raise DesignError(where, f"expected a number, got {as_toml(v)}")
        x = float(v)
        if not math.isfinite(x):
            raise DesignError(where, "must be finite")
        if meta.get("positive") and not x > 0:
            raise DesignError(where, f"must be positive (got {x})")
        if meta.get("nonneg") and x < 0:
            raise DesignError(where, f"must not be negative (got {x})")
        return x
    if isinstance(tp, types.UnionType):  # pragma: no cover - not used yet
        raise DesignError(where, "unsupported union type")
    raise DesignError(where, f"unsupported parameter type {tp!r}")  # pragma: no cover


def design_from_dict(data: dict[str, Any], source: str = "<memory>") -> Design:
    """Build and validate a :class:`Design` from a parsed TOML document."""
    if not data:
        raise DesignError(
            source,
            "the design file is empty (no tables, no parameters); `payload new DIR` makes a "
            "project whose cad/design.toml holds every parameter",
        )
    design = _build(Design, _upgrade(data), "")
    defaulted = design.pinch is None
    if defaulted:
        # a design file written before [pinch] existed takes the packaged default's
        design = dataclasses.replace(design, pinch=_default_pinch())
    try:
        return dataclasses.replace(design, source=source).validate()
    except DesignError as exc:
        if not (defaulted and exc.parameter == "pinch.finger"):
            raise
        raise DesignError(
            "pinch",
            f"missing, and the packaged default pre-shape {list(design.pinch.finger)} does "
            f"not fit this design ({exc.reason}); add a [pinch] table with "
            "finger = [mcp_flex, mcp_abd, pip, dip]",
        ) from None


@functools.cache
def _default_pinch() -> Pinch:
    return _build(Pinch, tomllib.loads(default_design_text())["pinch"], "pinch")


def load_design(path: str | Path | None = None) -> Design:
    """Load and validate a design file.

    Args:
        path: The design TOML; ``None``: the current project's ``cad/design.toml``
            (:func:`payload.project.current_project`).

    Raises:
        DesignError: The file is missing, is not valid TOML, or a parameter is invalid.
        ProjectError: ``path`` is ``None`` and there is no current project.
    """
    if path is None:
        path = current_project().design_path
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise DesignError(str(p), f"cannot read design file ({exc.strerror})") from exc
    except UnicodeDecodeError as exc:
        raise DesignError(str(p), not_text(exc, "TOML")) from None
    if text.startswith("\ufeff"):  # TOML has no byte-order mark; tomllib's line 1 error
        raise DesignError(
            str(p),
            "starts with a byte-order mark (U+FEFF, which some Windows editors add): save it "
            "as UTF-8 without one",
        )
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise DesignError(str(p), f"not valid TOML: {exc}") from exc
    return design_from_dict(data, source=str(p))


def posture_values(design: Design, name: str) -> dict[str, float]:
    """Joint values of a named design posture (``stowed`` or ``home``), joint -> value."""
    p = getattr(design, name)
    q = {f"{f}_{j}": v for f in FINGERS for j, v in zip(FINGER_JOINTS, p.finger)}
    q["rail"] = p.rail
    q["stage"] = p.stage
    return q


__all__ = [
    "FINGERS",
    "FINGER_JOINTS",
    "SIDE_OF",
    "Design",
    "DesignError",
    "Pinch",
    "Range",
    "design_from_dict",
    "design_to_dict",
    "load_design",
    "posture_values",
]
