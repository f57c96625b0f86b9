"""Native kernels: C loaded by ctypes, checked against the numpy code, and the check stamps.

The retargeting solvers (:mod:`payload.retarget.compiled`) and the 50 Hz loop's compiled
kernels (:mod:`payload.sim.allocation_c`, :mod:`payload.sim.vehicle_c`,
:mod:`payload.sim.station_c`, :mod:`payload.sim.facet_c`, :mod:`payload.sim.readout_c`,
:mod:`payload.sim.contacts_c`, :mod:`payload.sim.period_c`, :mod:`payload.teleop.hand_c`,
:mod:`payload.teleop.filter_c`, :mod:`payload.teleop.limiter_c`,
:mod:`payload.teleop.safety_c`, :mod:`payload.teleop.base_c`, :mod:`payload.teleop.pair_c`,
:mod:`payload.teleop.handmodel_c`, :mod:`payload.teleop.intake_c`,
:mod:`payload.teleop.operator_c`, :mod:`payload.teleop.barrier_c`,
:mod:`payload.retarget.targets_c`,
:mod:`payload.trials.foxglove_c`, :mod:`payload.trials.messages_c`,
:mod:`payload.trials.codec_c`) build their shared
libraries through here: compiled and cached by :mod:`payload.native_build` (named by the
hash of their code, the compiler, the flags, the machine and whatever else their caller
says they depend on), calling numpy's CBLAS and MuJoCo's functions at the addresses
:mod:`payload.native_symbols` finds. Both modules' names are importable from here too.

Each kernel checks itself against the numpy code when built: in full the first time
(:func:`probes`), and on a short prefix of its probes once a full check passed, in this
process or in an earlier one that left a stamp beside the library (:func:`check_stamp`:
named by the library file, the check's key, the workbench's sources, the versions and the
processor).
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
from collections.abc import Callable, Hashable, Sequence
from pathlib import Path
from typing import Any

from payload.cache import dist_version, sources_digest
from payload.native_build import (
    CFLAGS,
    CHECK_SUFFIX,
    OPTIONAL_CFLAGS,
    build_library,
    find_compiler,
    flags,
    prune,
)
from payload.native_symbols import (
    CBLAS_COL_MAJOR,
    CBLAS_NO_TRANS,
    CBLAS_ROW_MAJOR,
    NUMPY_BLAS_CORE,
    NUMPY_DDOT,
    NUMPY_DGEMV,
    gemv_layout,
    loaded_symbol,
    mujoco_function,
    mujoco_headers,
    numpy_blas,
    numpy_dgemv,
)

NATIVE_ENV = "PAYLOAD_NATIVE"
"""Set to ``0`` to run the numpy code of every kernel loaded by :func:`load_kernel` (the
50 Hz loop's; the same results). The retargeting solvers' generated C is not affected."""


BLAS_C = f"""#include <math.h>
#include <stdint.h>

/* numpy's CBLAS functions, as the kernels call them through their addresses */
typedef void (*dgemv_fn)(int, int, int64_t, int64_t, double, const double *, int64_t,
                         const double *, int64_t, double, double *, int64_t);
typedef double (*ddot_fn)(int64_t, const double *, int64_t, const double *, int64_t);
enum {{
    ROW_MAJOR = {CBLAS_ROW_MAJOR},
    COL_MAJOR = {CBLAS_COL_MAJOR},
    NO_TRANS = {CBLAS_NO_TRANS},
}};

"""
"""What every kernel's C starts with (:func:`load_kernel` puts it first): the headers,
the types of numpy's ``dgemv`` and ``ddot`` and CBLAS's layout codes."""


PYMOD_C = """
/* Python's float % (float_rem): fmod, moved to the divisor's sign; a zero takes it too */
static double pymod(double x, double y)
{
    double m = fmod(x, y);
    if (m != 0.0) {
        if ((y < 0) != (m < 0)) m += y;
    } else {
        m = copysign(0.0, y);
    }
    return m;
}
"""
"""Python's ``%`` of two floats in C (``pymod``), for the kernels whose numpy code uses it
(a kernel's source puts it before its own)."""


def load_kernel(
    name: str,
    source: str,
    what: str,
    logger: logging.Logger,
    *,
    prelude: str = "",
    key_parts: Sequence[str] = (),
    include_dirs: Sequence[str] = (),
    link: Sequence[str] = (),
) -> ctypes.CDLL | None:
    """A compiled kernel's library (``source`` built by
    :func:`~payload.native_build.build_library` as ``name``), or None when the numpy code
    is to run: :data:`NATIVE_ENV` is ``0``, there is no C compiler, or the build fails
    (said on ``logger``, the compiler's log kept). The kernel's caller still checks it
    against the numpy code before using it."""
    if os.environ.get(NATIVE_ENV, "1") == "0":
        return None
    compiler = find_compiler()
    if compiler is None:
        logger.info("%s: numpy (no C compiler)", what)
        return None
    try:
        path = build_library(
            name,
            {f"{name}.c": source},
            compiler,
            prelude=BLAS_C + prelude,
            key_parts=(*key_parts, _numpy_version()),
            what=what,
            include_dirs=include_dirs,
            link=link,
        )
        return ctypes.CDLL(str(path))
    except (RuntimeError, OSError) as exc:
        logger.warning("%s: numpy (%s)", what, exc)
        return None


def load_blas_kernel(
    name: str,
    source: str,
    what: str,
    logger: logging.Logger,
    *functions: str,
    prelude: str = "",
    include_dirs: Sequence[str] = (),
    link: Sequence[str] = (),
) -> tuple[Any, ...] | None:
    """:func:`load_kernel` for a kernel that calls numpy's CBLAS (or LAPACK) ``functions``
    (e.g. :data:`NUMPY_DDOT`, :data:`NUMPY_DGEMV`): ``(library, *their addresses)``, or
    None when one of them or the library is not there (the numpy code runs)."""
    addresses = [numpy_blas(f) for f in functions]
    if any(a is None for a in addresses):
        return None
    lib = load_kernel(
        name, source, what, logger, prelude=prelude, include_dirs=include_dirs, link=link
    )
    return None if lib is None else (lib, *addresses)


_KERNELS: dict[str, bool] = {}


def reported(name: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorate a kernel's factory (it returns the kernel, or None for the numpy code):
    :func:`kernel_status` then says which way its last call went, as ``name``."""

    def wrap(factory: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(factory)
        def made(*args: Any, **kwargs: Any) -> Any:
            kernel = factory(*args, **kwargs)
            _KERNELS[name] = kernel is not None
            return kernel

        return made

    return wrap


_CHECKED: set[tuple[str, Hashable]] = set()

_FULL_CHECKS: list[str] = []
"""The libraries (their names' stems, the hash left off) whose kernels were given a full
self-check in this process, one entry a check (:func:`full_checks`)."""


def full_checks() -> tuple[str, ...]:
    """The full self-checks this process has run so far, in order, each named by its
    kernel's library (the hash left off; a library checked for two keys, or checked again
    after a failure, is named twice): those with no check stamp yet (:func:`probes`), as
    on the first use after a change to their C, the workbench's sources or the
    environment. Once a check passes and its stamp is written, later processes run the
    short check instead; ``payload bench trial`` says which a run included."""
    return tuple(_FULL_CHECKS)


SHORT_SHARE = 10
"""A short self-check runs the first 1/SHORT_SHARE of a full check's probes (unless the
kernel says otherwise: :func:`probes`'s ``again``)."""


def probes(lib: ctypes.CDLL, key: Hashable, full: int, again: int | None = None) -> int:
    """How many probes a kernel's self-check against the numpy code runs: ``full`` the
    first time the library ``lib`` is checked for ``key`` (what shapes the kernel's code
    paths: counts, sizes, which parts are made), and ``again`` once such a check passed
    (:func:`passed`) in this process or, with the same code, in an earlier one
    (:func:`check_stamp`): the first ``again`` of the same probes, which show that a new
    build (a campaign worker's next trial, a driver's reset, the next command) reads its
    own data and settings (by default the first :data:`SHORT_SHARE`-th). Another library
    (changed C, another cache) is checked in full."""
    short = max(1, full // SHORT_SHARE) if again is None else again
    if (str(lib._name), key) in _CHECKED:
        return short
    if check_stamp(lib, key).is_file():
        _CHECKED.add((str(lib._name), key))
        return short
    _FULL_CHECKS.append(Path(lib._name).stem.rsplit("_", 1)[0])  # a full check to run
    return full


def checked_blas_kernel(
    name: str,
    source: str,
    what: str,
    logger: logging.Logger,
    make: Callable[..., Any],
    check: Callable[[Any, int], bool],
    key: Callable[[Any], Hashable],
    full: int,
    *functions: str,
    prelude: str = "",
) -> Any | None:
    """A kernel built by ``make(library, *addresses)`` (:func:`load_blas_kernel` of
    ``functions``) and checked by ``check(kernel, n)`` against the numpy code on ``n``
    probes (:func:`probes`: ``full``, or the short check's once a full one passed for
    ``key(kernel)``, which a full pass records: :func:`passed`); or None, logged as ``what``:
    nothing to load, ``make`` refused the data (``ValueError``), or the check failed."""
    loaded = load_blas_kernel(name, source, what, logger, *functions, prelude=prelude)
    if loaded is None:
        return None
    try:
        kernel = make(*loaded)
    except ValueError as exc:
        logger.warning("%s: numpy (%s)", what, exc)
        return None
    if not self_checked(loaded[0], key(kernel), full, lambda n: check(kernel, n)):
        logger.warning("%s: numpy (the compiled kernel differs)", what)
        return None
    return kernel


def self_checked(
    lib: ctypes.CDLL,
    key: Hashable,
    full: int,
    check: Callable[[int], bool],
    again: int | None = None,
) -> bool:
    """Whether ``lib``'s kernel passes ``check(n)``, its self-check against the numpy code
    on ``n`` probes (:func:`probes` of ``full`` and ``again``); a full pass is recorded
    (:func:`passed`)."""
    n = probes(lib, key, full, again)
    if not check(n):
        return False
    if n == full:
        passed(lib, key)
    return True


def passed(lib: ctypes.CDLL, key: Hashable) -> None:
    """Record that ``lib``'s kernel passed its full self-check for ``key`` (:func:`probes`),
    for this process and, as a stamp file beside the library, for later ones."""
    if (str(lib._name), key) in _CHECKED:
        return
    _CHECKED.add((str(lib._name), key))
    stamp = check_stamp(lib, key)
    try:
        stamp.touch()
        library, key_part = stamp.name.split(".")[:2]
        for old in stamp.parent.glob(f"{library}.{key_part}.*{CHECK_SUFFIX}"):
            if old != stamp:  # the same check in an earlier environment
                old.unlink(missing_ok=True)
    except OSError as exc:  # a read-only cache: later processes check in full again
        logging.getLogger(__name__).info("no check stamp %s (%s)", stamp, exc)


def check_stamp(lib: ctypes.CDLL, key: Hashable) -> Path:
    """The file that says ``lib``'s kernel passed its full self-check for ``key`` (it
    exists then): beside the library, named by the library, ``key`` and what the check's
    answer depends on besides the C source (:func:`_checked_with`, the library file's size
    and time), so a change to any of them asks for a full check again. :func:`passed`
    deletes the stamps of the same library and key it replaces,
    :func:`~payload.native_build.prune` all of a library's with it."""
    import hashlib

    path = Path(lib._name)
    try:
        seen = path.stat()
        built = f"{seen.st_size}:{seen.st_mtime_ns}"
    except OSError:
        built = "?"
    key_part = hashlib.sha256(repr(key).encode()).hexdigest()[:12]
    env_part = hashlib.sha256(f"{_checked_with()}\n{built}".encode()).hexdigest()[:16]
    return path.with_name(f"{path.stem}.{key_part}.{env_part}{CHECK_SUFFIX}")


_SOURCES = sources_digest()
"""The workbench's sources as this process imported them (the numpy code its kernels are
checked against): taken at import, so a source edited while the process runs is not
stamped as checked."""

CHECK_ENVIRONMENT = ("NPY_DISABLE_CPU_FEATURES", "NPY_ENABLE_CPU_FEATURES", "OPENBLAS_CORETYPE")
"""Environment variables that choose numpy's or OpenBLAS's machine code (part of a check
stamp's name)."""


@functools.cache
def _checked_with() -> str:
    """What a kernel's self-check answer depends on besides its C: the workbench's own
    Python (the numpy code it is checked against: every module's text), Python's build,
    what a result's bits depend on (:func:`environment`: the packages' versions, the
    machine, OpenBLAS's kernels), and the processor and the variables that pick numpy's
    and OpenBLAS's machine code for it."""
    import sys

    return "\n".join(
        [
            _SOURCES,
            sys.version,
            *(f"{name}={value}" for name, value in environment().items()),
            _processor(),
            *(f"{name}={os.environ.get(name, '')}" for name in CHECK_ENVIRONMENT),
        ]
    )


def result_environment() -> str:
    """What a computed answer's bits depend on besides its own code and inputs: the text
    :func:`check_stamp` names a kernel's check by (the workbench's sources, Python's build,
    :func:`environment`, the processor and the variables that pick numpy's and OpenBLAS's
    machine code), for the disk cache's keys of other derived answers."""
    return _checked_with()


def _processor() -> str:
    """The processor's model and feature flags (``/proc/cpuinfo``), else the platform's
    name for it."""
    import platform

    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return platform.processor()
    wanted = ("model name", "flags", "Features", "CPU part")
    return "\n".join(dict.fromkeys(line for line in lines if line.split(":")[0].strip() in wanted))


def kernel_status() -> dict[str, str]:
    """Each kernel built in this process so far: ``compiled``, or ``numpy`` (why is in the
    log: no compiler, no numpy OpenBLAS, :data:`NATIVE_ENV`, a failed build or check)."""
    return {name: "compiled" if ok else "numpy" for name, ok in sorted(_KERNELS.items())}


def _numpy_version() -> str:
    import numpy

    return numpy.__version__


RESULT_PACKAGES: tuple[tuple[str, str], ...] = (
    ("numpy", "numpy"),
    ("scipy", "scipy"),
    ("mujoco", "mujoco"),
    ("casadi", "casadi"),
    ("pinocchio", "pin"),
)
"""The packages a simulated result's bits depend on (name, distribution), the versions
:func:`environment` reports (``constraints.txt`` pins them for ``make``)."""


def environment() -> dict[str, str | None]:
    """What a simulated result's bits depend on besides the workbench's code and the design,
    for its provenance: Python's version and :data:`RESULT_PACKAGES`' (``"?"`` when not
    installed), the machine and the kernels numpy's OpenBLAS picked (:data:`NUMPY_BLAS_CORE`;
    None when numpy links another BLAS or not on Linux). Trials that differ in any of these
    may differ in their last bits, and a sensitive trial in its outcome (docs/results.md)."""
    import platform

    address = numpy_blas(NUMPY_BLAS_CORE)
    core = ctypes.CFUNCTYPE(ctypes.c_char_p)(address)() if address is not None else None
    return {
        "python": platform.python_version(),
        **{package: dist_version(dist) for package, dist in RESULT_PACKAGES},
        "machine": platform.machine(),
        "openblas_core": core.decode() if core else None,
    }


__all__ = [
    "BLAS_C",
    "CBLAS_COL_MAJOR",
    "CBLAS_NO_TRANS",
    "CBLAS_ROW_MAJOR",
    "CFLAGS",
    "CHECK_ENVIRONMENT",
    "CHECK_SUFFIX",
    "NATIVE_ENV",
    "NUMPY_BLAS_CORE",
    "NUMPY_DDOT",
    "NUMPY_DGEMV",
    "OPTIONAL_CFLAGS",
    "PYMOD_C",
    "RESULT_PACKAGES",
    "SHORT_SHARE",
    "build_library",
    "check_stamp",
    "checked_blas_kernel",
    "environment",
    "find_compiler",
    "flags",
    "full_checks",
    "gemv_layout",
    "kernel_status",
    "load_blas_kernel",
    "load_kernel",
    "loaded_symbol",
    "mujoco_function",
    "mujoco_headers",
    "numpy_blas",
    "numpy_dgemv",
    "passed",
    "probes",
    "prune",
    "reported",
    "result_environment",
    "self_checked",
]
