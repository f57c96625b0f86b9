"""Native code: C sources compiled with the system compiler, cached on disk, loaded by ctypes.

The retargeting solvers (:mod:`payload.retarget.compiled`) and the 50 Hz loop's compiled
kernels (:mod:`payload.sim.allocation_c`, :mod:`payload.sim.vehicle_c`,
:mod:`payload.sim.station_c`, :mod:`payload.sim.facet_c`, :mod:`payload.sim.readout_c`,
:mod:`payload.sim.contacts_c`, :mod:`payload.sim.period_c`, :mod:`payload.teleop.hand_c`,
:mod:`payload.teleop.filter_c`, :mod:`payload.teleop.limiter_c`,
:mod:`payload.teleop.safety_c`, :mod:`payload.teleop.base_c`, :mod:`payload.teleop.pair_c`,
:mod:`payload.teleop.handmodel_c`, :mod:`payload.teleop.intake_c`,
:mod:`payload.teleop.operator_c`, :mod:`payload.retarget.targets_c`,
:mod:`payload.trials.foxglove_c`, :mod:`payload.trials.messages_c`,
:mod:`payload.trials.codec_c`) build their shared
libraries here. A library is named by the hash of its code, the compiler, the flags, the
machine and whatever else its caller says it depends on (``key_parts``; a kernel compiled
against MuJoCo's headers, MuJoCo's version), so a stale one is never loaded; a failed
compilation leaves its log beside the cache.

Each kernel checks itself against the numpy code when built: in full the first time
(:func:`probes`), and on a short prefix of its probes once a full check passed, in this
process or in an earlier one that left a stamp beside the library (:func:`check_stamp`:
named by the library file, the check's key, the workbench's sources, the versions and the
processor).

The flags keep IEEE arithmetic (no ``-ffast-math``, no contraction into fused
multiply-adds), so compiled code that does the same operations in the same order as
numpy gives numpy's bits.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
from collections.abc import Callable, Hashable, Sequence
from pathlib import Path
from typing import Any

from payload.cache import cache_dir, dist_version, sources_digest
from payload.safeio import replace_file

CFLAGS: tuple[str, ...] = ("-O3", "-ffp-contract=off", "-fPIC", "-shared")
"""No -ffast-math and no contraction: IEEE arithmetic, so -O3 gives the bits -O1 gave."""

OPTIONAL_CFLAGS: tuple[str, ...] = ("-fno-semantic-interposition",)
"""Added when the compiler accepts them (:func:`flags`). ``-fno-semantic-interposition``:
generated code's helpers (``casadi_sq``, ...) are global functions; without it,
position-independent code calls every one of them through the PLT instead of inlining it
(a paper-budget solve with collisions took about 1.2 to 1.3 times as long)."""


@functools.cache
def flags(compiler: str) -> tuple[str, ...]:
    """The compile flags for ``compiler``: :data:`CFLAGS` and those of
    :data:`OPTIONAL_CFLAGS` it accepts (an older compiler without one still builds);
    the answer is kept in the cache, named by the compiler's file and the flags tried."""
    import hashlib

    try:
        seen = Path(compiler).resolve().stat()
    except OSError:
        seen = None
    known = None
    if seen is not None:
        key = hashlib.sha256(
            "\n".join(
                [str(Path(compiler).resolve()), str(seen.st_size), str(seen.st_mtime_ns),
                 *CFLAGS, "--", *OPTIONAL_CFLAGS]
            ).encode()
        ).hexdigest()[:20]  # fmt: skip
        known = cache_dir() / f"flags_{key}.txt"
        try:
            kept = tuple(known.read_text().split("\n"))
            if kept[: len(CFLAGS)] == CFLAGS and set(kept[len(CFLAGS) :]) <= set(OPTIONAL_CFLAGS):
                return kept
        except OSError:
            pass
    import subprocess
    import tempfile

    out = list(CFLAGS)
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "probe.c"
        src.write_text("int payload_probe(void) { return 0; }\n")
        for flag in OPTIONAL_CFLAGS:
            proc = subprocess.run(
                [compiler, *out, flag, "-o", str(Path(tmp) / "probe.so"), str(src)],
                capture_output=True,
                check=False,
            )
            if proc.returncode == 0:
                out.append(flag)
    if known is not None:
        try:
            known.parent.mkdir(parents=True, exist_ok=True)
            replace_file(known, "\n".join(out))
        except OSError:  # a read-only cache: asked again in the next process
            pass
    return tuple(out)


def find_compiler() -> str | None:
    """The C compiler: ``$CC``, else ``cc``, ``gcc`` or ``clang`` on the path (None: none)."""
    import shutil

    cc = os.environ.get("CC") or "cc"
    return shutil.which(cc) or shutil.which("gcc") or shutil.which("clang")


def build_library(
    name: str,
    sources: dict[str, str],
    compiler: str,
    *,
    prelude: str = "",
    key_parts: Sequence[str] = (),
    error: Callable[[str], Exception] = RuntimeError,
    what: str = "native code",
    include_dirs: Sequence[str] = (),
    link: Sequence[str] = (),
) -> Path:
    """C ``sources`` (file name -> code, each prefixed with ``prelude``) compiled into one
    shared library under :func:`~payload.cache.cache_dir`, or the cached one. Headers
    are searched in ``include_dirs`` too, and the static libraries ``link`` (paths) are
    linked in (what they hold belongs in ``key_parts``: a version).

    Raises:
        ``error(message)``: The compiler failed; the message names ``what`` and the log.
    """
    import hashlib
    import platform
    import subprocess
    import tempfile

    key = hashlib.sha256(
        "\n".join(
            [
                prelude,
                *(f"{k}\n{v}" for k, v in sorted(sources.items())),
                compiler,
                *flags(compiler),
                platform.machine(),
                *include_dirs,
                *link,
                *key_parts,
            ]
        ).encode()
    ).hexdigest()[:20]
    directory = cache_dir()
    lib_path = directory / f"{name}_{key}.so"
    if lib_path.is_file():
        return lib_path
    directory.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=directory) as tmp:
        paths = []
        for file_name, code in sources.items():
            paths.append(Path(tmp) / file_name)
            paths[-1].write_text(prelude + code)
        out = Path(tmp) / "lib.so"
        proc = subprocess.run(
            [
                compiler,
                *flags(compiler),
                *(f"-I{d}" for d in include_dirs),
                "-o",
                str(out),
                *map(str, paths),
                *link,
                "-lm",
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        if proc.returncode != 0:
            log = directory / f"{name}_{key}.log"
            log.write_text(
                f"$ {' '.join(proc.args)}\nexit {proc.returncode}\n"
                f"--- stdout\n{proc.stdout}--- stderr\n{proc.stderr}"
            )
            raise error(
                f"compiling {what} failed ({Path(compiler).name} "
                f"exit {proc.returncode}); log: {log}"
            )
        os.replace(out, lib_path)
    (directory / f"{name}_{key}.log").unlink(missing_ok=True)  # an older failure's
    prune(directory, name)
    return lib_path


def prune(directory: Path, name: str, keep: int = 8) -> None:
    """Delete all but the ``keep`` newest libraries of one name (older designs)."""
    libs = sorted(directory.glob(f"{name}_*.so"), key=lambda p: p.stat().st_mtime, reverse=True)
    for old in libs[keep:]:
        for path in (old, *directory.glob(f"{old.stem}.*{CHECK_SUFFIX}")):
            try:
                path.unlink()
            except OSError:  # pragma: no cover - another process may have removed it
                pass


NATIVE_ENV = "PAYLOAD_NATIVE"
"""Set to ``0`` to run the numpy code of every kernel loaded by :func:`load_kernel` (the
50 Hz loop's; the same results). The retargeting solvers' generated C is not affected."""


CBLAS_ROW_MAJOR = 101
"""CBLAS's ``CblasRowMajor``."""
CBLAS_COL_MAJOR = 102
"""CBLAS's ``CblasColMajor``."""
CBLAS_NO_TRANS = 111
"""CBLAS's ``CblasNoTrans``."""

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
    """A compiled kernel's library (``source`` built by :func:`build_library` as
    ``name``), or None when the numpy code is to run: :data:`NATIVE_ENV` is ``0``, there
    is no C compiler, or the build fails (said on ``logger``, the compiler's log kept).
    The kernel's caller still checks it against the numpy code before using it."""
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
    deletes the stamps of the same library and key it replaces, :func:`prune` all of a
    library's with it."""
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


CHECK_SUFFIX = ".checked"

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
    "self_checked",
]
