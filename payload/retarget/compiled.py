"""Generated C for CasADi functions: compiled once, cached on disk, called through ctypes.

A function's C code (``casadi.CodeGenerator``) is compiled with the system C compiler
into a shared library under :func:`payload.cache.cache_dir`, named by the hash of its code, the
compiler, the flags, the machine and CasADi's version, and loaded with ``ctypes`` on
preallocated buffers: a call costs a few microseconds of Python instead of about 20 us
for a ``casadi.Function`` call. A failed compilation leaves its log beside the cache.
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path

import casadi as ca
import numpy as np

from payload import native
from payload.retarget.errors import RetargetError

_CFLAGS = native.CFLAGS
_OPTIONAL_CFLAGS = native.OPTIONAL_CFLAGS
_flags = native.flags


PRELUDE = r"""/* ---- payload.retarget.compiled: prepended to every C source it compiles ---- */
#include <math.h>
/* fmax and fmin inline, with glibc's x86-64 results for every quiet input (maxsd/minsd
   after a NaN check: on equal operands, +0 and -0 included, the second; a NaN operand
   gives the other one), instead of a call into libm for each (a solve with collisions
   takes 0.91 to 0.97 of the time). Other machines' libm may order signed zeros otherwise. */
static inline double payload_fmax(double x, double y) { return (x > y || y != y) ? x : y; }
static inline double payload_fmin(double x, double y) { return (x < y || y != y) ? x : y; }
#define fmax payload_fmax
#define fmin payload_fmin
/* ---- end of prelude ---- */
"""


def _compiler() -> str | None:
    return native.find_compiler()


def code_generator(name: str) -> ca.CodeGenerator:
    """CasADi's code generator for the C file ``name`` of a library this module loads: no
    header, and ``casadi_int`` is ``long long``, as :class:`_CompiledSolve` passes it."""
    return ca.CodeGenerator(name, {"with_header": False, "casadi_int": "long long int"})


def c_ints(values: list[int]) -> str:
    """Integers as the body of a C array initialiser."""
    return ", ".join(str(int(v)) for v in values)


def c_reals(values: list[float]) -> str:
    """Doubles as the body of a C array initialiser (exact; infinities as ``INFINITY``)."""
    names = {float("inf"): "INFINITY", -float("inf"): "-INFINITY"}
    return ", ".join(names.get(float(v), repr(float(v))) for v in values)


def work_sizes(functions: list[ca.Function]) -> dict[str, int]:
    """The largest ``w``, ``iw``, ``arg`` and ``res`` work sizes of generated functions a
    C caller calls with one shared set of buffers (at least 1 each)."""
    sizes = {"w": 1, "iw": 1, "arg": 1, "res": 1}
    for fn in functions:
        sizes["w"] = max(sizes["w"], int(fn.sz_w()))
        sizes["iw"] = max(sizes["iw"], int(fn.sz_iw()))
        sizes["arg"] = max(sizes["arg"], int(fn.sz_arg()))
        sizes["res"] = max(sizes["res"], int(fn.sz_res()))
    return sizes


def build_library(
    name: str, sources: dict[str, str], compiler: str, what: str = "the retargeting solver"
) -> Path:
    """C ``sources`` (file name -> code) compiled into one shared library, cached.

    The library is named by ``name`` and the hash of the code (with :data:`PRELUDE`), the
    compiler, the flags, the machine and CasADi's version; an existing one is reused. A
    failed compilation leaves its log beside the cache and raises :class:`RetargetError`
    naming ``what`` (:func:`payload.native.build_library`).
    """
    return native.build_library(
        name,
        sources,
        compiler,
        prelude=PRELUDE,
        key_parts=(ca.__version__,),
        error=RetargetError,
        what=what,
    )


class _CompiledSolve:
    """A generated CasADi function in a shared library, called through ctypes.

    ``extra``: further C sources (file name -> code) compiled into the same library,
    e.g. the definitions of external functions the generated code calls. ``code``: the
    C of ``fn`` when it is not CasADi's own generation of it (the same symbol, inputs,
    outputs and calling convention, e.g. :func:`payload.retarget.lm_c.driver_source`)."""

    def __init__(
        self,
        fn: ca.Function,
        compiler: str,
        extra: dict[str, str] | None = None,
        code: str | None = None,
    ) -> None:
        name = fn.name()
        if code is None:
            cg = code_generator(f"{name}.c")
            cg.add(fn)
            code = cg.dump()
        lib_path = build_library(name, {f"{name}.c": code, **(extra or {})}, compiler)
        sizes_in = [fn.nnz_in(i) for i in range(fn.n_in())]
        self._load(name, lib_path, sizes_in, [fn.nnz_out(i) for i in range(fn.n_out())])

    @classmethod
    def loaded(
        cls, name: str, path: Path, sizes_in: list[int], sizes_out: list[int]
    ) -> _CompiledSolve:
        """The function ``name`` of a library built before (its inputs' and outputs'
        sizes as its function gave them), loaded without its CasADi function."""
        made = cls.__new__(cls)
        made._load(name, path, sizes_in, sizes_out)
        return made

    @property
    def sizes(self) -> tuple[list[int], list[int]]:
        """The inputs' and outputs' sizes."""
        return [a.size for a in self.inputs], [a.size for a in self.outputs]

    def _load(self, name: str, lib_path: Path, sizes_in: list[int], sizes_out: list[int]) -> None:
        self.path = lib_path
        self._lib = ctypes.CDLL(str(lib_path))
        ll = ctypes.c_longlong
        work = getattr(self._lib, f"{name}_work")
        work.argtypes = [ctypes.POINTER(ll)] * 4
        sizes = [ll() for _ in range(4)]
        if work(*[ctypes.byref(s) for s in sizes]) != 0:
            raise RetargetError("the compiled retargeting solver did not report its work sizes")
        sz_arg, sz_res, sz_iw, sz_w = (s.value for s in sizes)
        self.input = np.zeros(sum(sizes_in))  # all inputs: one finiteness check covers them
        ends = np.cumsum(sizes_in)
        self.inputs = [self.input[e - k : e] for e, k in zip(ends, sizes_in)]
        self.outputs = [np.zeros(k) for k in sizes_out]
        dp = ctypes.POINTER(ctypes.c_double)
        self._arg = (dp * max(sz_arg, len(self.inputs)))(
            *[a.ctypes.data_as(dp) for a in self.inputs]
        )
        self._res = (dp * max(sz_res, len(self.outputs)))(
            *[a.ctypes.data_as(dp) for a in self.outputs]
        )
        self._iw = (ll * max(sz_iw, 1))()
        self._w = (ctypes.c_double * max(sz_w, 1))()
        self._fn = getattr(self._lib, name)
        self._fn.argtypes = [
            ctypes.POINTER(dp),
            ctypes.POINTER(dp),
            ctypes.POINTER(ll),
            ctypes.POINTER(ctypes.c_double),
            ctypes.c_int,
        ]
        self._fn.restype = ctypes.c_int
        checkout = getattr(self._lib, f"{name}_checkout", None)
        self._mem = int(checkout()) if checkout is not None else 0
        # A teleoperation step's entry (payload.retarget.lm_c), when the library has one:
        # the inputs' finiteness checked and the anchor inputs updated in C.
        step = getattr(self._lib, f"{name}_step", None)
        self._step_call = None
        if step is not None:
            step.argtypes = self._fn.argtypes
            step.restype = ctypes.c_int
            self._step_call = functools.partial(
                step, self._arg, self._res, self._iw, self._w, self._mem
            )

    def step_entry(self) -> tuple[int, ...] | None:
        """The step entry's address and its arguments (argument and result pointer
        arrays, integer and real work, memory slot), for C that calls it (:meth:`step`
        returns its codes' meaning), or None (no step entry)."""
        if self._step_call is None:
            return None
        fn = self._step_call.func
        return (
            ctypes.cast(fn, ctypes.c_void_p).value,
            *(ctypes.addressof(a) for a in (self._arg, self._res, self._iw, self._w)),
            self._mem,
        )

    def __call__(self) -> None:
        if self._fn(self._arg, self._res, self._iw, self._w, self._mem) != 0:
            raise RetargetError("the compiled retargeting solver reported an error")

    def step(self) -> bool:
        """One solve through the library's step entry (``<name>_step``, the driver's of
        :mod:`payload.retarget.lm_c`): the first three inputs checked finite (``False``,
        nothing solved, when one is not), then the command and bounds outputs copied into
        the fourth and fifth inputs (the next solve's anchor)."""
        if self._step_call is None:
            raise RetargetError(f"{self.path.name} has no step entry")
        code = self._step_call()
        if code == 2:
            return False
        if code != 0:
            raise RetargetError("the compiled retargeting solver reported an error")
        return True


def _compiled_or_none(fn: ca.Function) -> _CompiledSolve | None:
    """``fn`` compiled and loaded, or ``None`` without a working C compiler."""
    compiler = _compiler()
    if compiler is None:
        return None
    try:
        return _CompiledSolve(fn, compiler)
    except (RetargetError, OSError):
        return None


_prune = native.prune


def _slug(s: str) -> str:
    return "".join(ch if ch.isalnum() else "_" for ch in s)
