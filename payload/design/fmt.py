"""Deterministic number formatting shared by the exporters."""

from __future__ import annotations

from collections.abc import Iterable

from payload.rotations import matrix_to_quat as quat_from_matrix

__all__ = ["num", "quat_from_matrix", "vec"]


def num(x: float) -> str:
    """Format a float with 12 significant digits; tiny values and -0 become 0."""
    v = float(x)
    if abs(v) < 1e-15:
        return "0"
    return f"{v:.12g}"


def vec(xs: Iterable[float]) -> str:
    return " ".join(num(x) for x in xs)
