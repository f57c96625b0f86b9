"""The addresses of native functions this process has loaded: numpy's own CBLAS in the
OpenBLAS it links (:func:`numpy_blas`), MuJoCo's C functions in ``libmujoco``
(:func:`mujoco_function`), and MuJoCo's headers; the compiled kernels call them through
these addresses (:mod:`payload.native`), so they compute with the very code numpy and
MuJoCo run.
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path
from typing import Any

CBLAS_ROW_MAJOR = 101
"""CBLAS's ``CblasRowMajor``."""
CBLAS_COL_MAJOR = 102
"""CBLAS's ``CblasColMajor``."""
CBLAS_NO_TRANS = 111
"""CBLAS's ``CblasNoTrans``."""

NUMPY_DGEMV = "scipy_cblas_dgemv64_"
"""The CBLAS ``dgemv`` of the OpenBLAS numpy's wheels bundle (64-bit integers), the kernel
numpy's ``matmul`` runs for a contiguous matrix times a vector (numpy 2's wheels; numpy
1.26's name it without the ``scipy_`` prefix, :func:`numpy_blas` tries both)."""

NUMPY_DDOT = "scipy_cblas_ddot64_"
"""Its CBLAS ``ddot``, what numpy's ``dot`` of two float64 vectors runs."""


NUMPY_BLAS_CORE = "scipy_openblas_get_corename64_"
"""OpenBLAS's name for the kernels it picked for this processor (``SkylakeX``, ``Haswell``,
...; ``OPENBLAS_CORETYPE`` forces others): numpy's ``dot`` and ``matmul`` run them, so a
trial's last bits differ between processors that get different kernels."""


def loaded_symbol(library: str, symbol: str) -> int | None:
    """The address of ``symbol`` in a shared library this process has loaded whose path
    contains ``library`` (the very code the Python package calls), or None: not loaded,
    no such symbol, or no ``/proc/self/maps`` (not Linux)."""
    try:
        maps = Path("/proc/self/maps").read_text().splitlines()
    except OSError:
        return None
    seen: set[str] = set()
    for line in maps:
        fields = line.split(maxsplit=5)  # the path, the sixth field, may hold spaces
        path = fields[5].strip() if len(fields) == 6 else ""
        if library not in Path(path).name or path in seen or not path.startswith("/"):
            continue
        seen.add(path)
        try:
            fn = getattr(ctypes.CDLL(path), symbol)
        except (OSError, AttributeError):
            continue
        return ctypes.cast(fn, ctypes.c_void_p).value
    return None


@functools.cache
def numpy_blas(symbol: str) -> int | None:
    """The address of one of numpy's own CBLAS functions (:data:`NUMPY_DGEMV`,
    :data:`NUMPY_DDOT`), or of OpenBLAS's :data:`NUMPY_BLAS_CORE`, in the OpenBLAS numpy
    loaded on import, or None (numpy built against another BLAS, or not on Linux). Calling
    it as numpy does gives numpy's bits on every machine (OpenBLAS picks its kernel by the
    processor, for both alike)."""
    import numpy  # noqa: F401 - loads the OpenBLAS numpy links

    found = loaded_symbol("openblas", symbol)
    if found is None and symbol.startswith("scipy_"):  # numpy 1.26's wheels
        found = loaded_symbol("openblas", symbol.removeprefix("scipy_"))
    return found


def numpy_dgemv() -> int | None:
    """:func:`numpy_blas` of :data:`NUMPY_DGEMV`."""
    return numpy_blas(NUMPY_DGEMV)


def gemv_layout(a: Any) -> tuple[int, int] | None:
    """How numpy's ``matmul`` hands the float64 matrix ``a`` (m, n) to ``dgemv``: (CBLAS
    order, leading dimension), row-major for C order and column-major for Fortran order
    (numpy passes the memory as it lies), or None for other layouts."""
    if a.dtype != "float64" or a.ndim != 2:
        return None
    if a.flags.c_contiguous:
        return CBLAS_ROW_MAJOR, a.shape[1]
    if a.flags.f_contiguous:
        return CBLAS_COL_MAJOR, a.shape[0]
    return None


def mujoco_headers() -> tuple[str, str] | None:
    """MuJoCo's C headers as its Python package ships them (the directory to include
    ``<mujoco/mujoco.h>`` from) and the package's version (what they describe), or None."""
    import mujoco

    include = Path(mujoco.__file__).parent / "include"
    if not (include / "mujoco" / "mujoco.h").is_file():
        return None
    return str(include), mujoco.__version__


@functools.cache
def mujoco_function(name: str) -> int | None:
    """The address of MuJoCo's C function ``name`` in the library its Python bindings
    loaded (``libmujoco``), or None."""
    import mujoco  # noqa: F401 - loads libmujoco

    return loaded_symbol("libmujoco", name)


__all__ = [
    "CBLAS_COL_MAJOR",
    "CBLAS_NO_TRANS",
    "CBLAS_ROW_MAJOR",
    "NUMPY_BLAS_CORE",
    "NUMPY_DDOT",
    "NUMPY_DGEMV",
    "gemv_layout",
    "loaded_symbol",
    "mujoco_function",
    "mujoco_headers",
    "numpy_blas",
    "numpy_dgemv",
]
