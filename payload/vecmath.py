"""Small-vector helpers for the 50 Hz loops: numpy's own formulas without its per-call
overhead (tens of microseconds per ``np.cross``, several per ``np.linalg.norm``), so the
results are the same to the last bit."""

from __future__ import annotations

import math

import numpy as np


def norm(v: np.ndarray) -> float:
    """``np.linalg.norm(v)`` of a vector (no ``axis``): the square root of the flattened
    array's dot product with itself, as numpy computes it."""
    x = np.asarray(v)
    if x.dtype != np.float64:
        return float(np.linalg.norm(x))  # other types: numpy's own handling
    x = x.ravel(order="K")
    return math.sqrt(x.dot(x))


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of two 3-vectors: the same products and differences."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


__all__ = ["cross", "norm"]
