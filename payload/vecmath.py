"""Small-vector helpers for the 50 Hz loops: numpy's own formulas without its per-call
overhead (tens of microseconds per ``np.cross``, several per ``np.linalg.norm``), so the
results are the same to the last bit."""

from __future__ import annotations

import math

import numpy as np

try:  # numpy 2
    from numpy._core.umath import clip as _clip_ufunc
except ImportError:  # numpy 1.26
    from numpy.core.umath import clip as _clip_ufunc  # type: ignore[no-redef]

F64 = np.dtype(np.float64)
"""The loop's number type, to compare an array's ``dtype`` with (no new dtype per test)."""

add_reduce = np.add.reduce
"""What ``ndarray.sum`` runs: ``add_reduce(a)`` is ``a.sum()`` of a 1-D array, the same
pairwise sum, without the method's Python wrappers."""

max_reduce = np.maximum.reduce
"""What ``ndarray.max`` runs: ``max_reduce(a, axis=None)`` is ``a.max()`` (a NaN wins)."""

all_reduce = np.logical_and.reduce
"""What ``ndarray.all`` runs: ``all_reduce(a, axis=None)`` is ``a.all()`` of a boolean array."""


def all_finite(a: np.ndarray) -> bool:
    """Whether every value of the float array ``a`` is finite: a finite sum says so at
    once (NaN and infinities propagate); only otherwise are the values checked one by one
    (a sum of finite values that overflows)."""
    return math.isfinite(add_reduce(a, axis=None)) or bool(np.isfinite(a).all())


clip: np.ufunc = _clip_ufunc
"""``np.clip(a, lo, hi)`` of arrays or floats: the ufunc ``np.clip`` ends in, without the
1.4 us of its wrappers (the same bits: NaN, signed zeros and all)."""


def read_only(a: object) -> np.ndarray:
    """A read-only float64 copy of ``a``: a setting a compiled kernel copies or reads in
    place when it is built, which must therefore stay as it was (numpy's code would take a
    change the kernel did not, or the other way round)."""
    out = np.array(a, dtype=np.float64)
    out.setflags(write=False)
    return out


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


__all__ = [
    "F64",
    "add_reduce",
    "all_finite",
    "all_reduce",
    "clip",
    "cross",
    "max_reduce",
    "norm",
    "read_only",
]
