"""Compiling C for the workbench: the system compiler, its flags, and the shared libraries
cached on disk (:func:`build_library`, which :mod:`payload.native` loads kernels through).

A library is named by the hash of its code, the compiler, the flags, the machine and
whatever else its caller says it depends on (``key_parts``; a kernel compiled against
MuJoCo's headers, MuJoCo's version), so a stale one is never loaded; a failed compilation
leaves its log beside the cache. :func:`prune` keeps a few of each name, and deletes a
library's check stamps (:data:`CHECK_SUFFIX`) with it.

The flags keep IEEE arithmetic (no ``-ffast-math``, no contraction into fused
multiply-adds), so compiled code that does the same operations in the same order as
numpy gives numpy's bits.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Sequence
from pathlib import Path

from payload.cache import cache_dir
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


CHECK_SUFFIX = ".checked"
"""The suffix of a library's check stamps (:func:`payload.native.check_stamp`), files
beside it that :func:`prune` deletes with it."""


__all__ = [
    "CFLAGS",
    "CHECK_SUFFIX",
    "OPTIONAL_CFLAGS",
    "build_library",
    "find_compiler",
    "flags",
    "prune",
]
