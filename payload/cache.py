"""The workbench's disk cache: derived data kept outside the project, keyed by its source.

Compiled retargeting solvers and kernels, span ranges, the pairs' self-collision
geometry, the generated models' fingerprints, the kernels' check stamps and the
propulsion's linear programmes live here, each named by a hash of what it was derived
from, so a stale entry is never read.
"""

from __future__ import annotations

import functools
import hashlib
import os
from collections.abc import Iterable
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def cache_dir() -> Path:
    """Directory of the cache: ``$PAYLOAD_CACHE_DIR``, else the user cache dir."""
    env = os.environ.get("PAYLOAD_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "astrobee-payload" / "retarget"


@functools.cache
def sources_digest(package: Path = _PACKAGE) -> str:
    """SHA-256 (hex) of the workbench's Python sources and packaged data: every module's
    path in the package and its bytes, and every file under ``data/`` (the packaged
    default design fills what a project's design leaves out, so it shapes answers too).
    What names a cached answer that the workbench's own code shapes."""
    h = hashlib.sha256()
    data = sorted(p for p in (package / "data").rglob("*") if p.is_file())
    for path in [*sorted(package.rglob("*.py")), *data]:
        h.update(str(path.relative_to(package)).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


@functools.cache
def dist_version(name: str) -> str:
    """The installed version of the distribution ``name`` (what a cached answer may depend
    on), ``"?"`` when it is not installed. Read once a process (``importlib.metadata``
    parses the distribution's metadata file each time, about 2 ms: a trial asks for a
    dozen); a package installed over it while the process runs is not the one it
    imported either."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return "?"


def code_key(tag: str, libraries: Iterable[str], *parts: bytes) -> str:
    """A cache entry's name (32 hex digits): a hash of ``tag`` (the entry's kind and
    format), ``parts`` (what it is derived from: a design file's path and bytes, say), the
    workbench's sources (:func:`sources_digest`) and the versions of ``libraries``."""
    h = hashlib.sha256(tag.encode())
    for part in parts:
        h.update(b"\0" + part)
    h.update(b"\0" + sources_digest().encode())
    for lib in libraries:
        h.update(f"\0{lib}={dist_version(lib)}".encode())
    return h.hexdigest()[:32]


__all__ = ["cache_dir", "code_key", "dist_version", "sources_digest"]
