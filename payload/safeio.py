"""Writing results without losing or silently replacing any.

- :func:`replace_file` writes through a temporary file beside the target and an atomic
  rename, so a reader (or a crash) sees either the old file or the new one, never half.
- :func:`write_unless_changed` refuses to replace a file whose content differs unless
  asked to (``force``), and leaves an identical file untouched.
- Files written here get the mode a plain ``open()`` would give (0666 less the umask:
  0644 at umask 022), so colleagues on a shared disk can read them; the temporary file
  ``mkstemp`` makes is 0600 until it is given that mode.
- :func:`new_folder` claims a fresh numbered folder (``runs/trial-0000``,
  ``runs/trial-0000-2``, ...) atomically, so two runs never share one.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from payload.errors import PayloadError


def cannot_write_in(folder: Path) -> str | None:
    """Why a file could not be written in the existing ``folder`` (None: it can): the file
    system's own answer (permissions, a read-only mount) to making and removing an empty
    file there, asked before the work whose results go there."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".payload-write-probe-", dir=folder)
    except OSError as exc:
        return exc.strerror or str(exc)
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)
    return None


def umask_mode() -> int:
    """The mode a new file gets from ``open()`` under the current umask (0o644 at 022).

    The umask can only be read by setting it, so it is set back at once (process-wide,
    not thread-safe for a concurrent ``os.umask`` caller; nothing here calls it elsewhere).
    """
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


class OverwriteError(PayloadError):
    """Writing would replace an existing result (pass ``--force`` to allow it)."""


@contextlib.contextmanager
def replacing(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` (same suffix); renamed onto ``path`` on success.

    On an exception the temporary file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.chmod(tmp, umask_mode())  # mkstemp's 0600 -> what open() would have given
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def replace_file(path: str | Path, data: bytes | str) -> None:
    """Write ``data`` to ``path`` through a temporary file and an atomic rename."""
    raw = data.encode("utf-8") if isinstance(data, str) else data
    with replacing(path) as tmp:
        tmp.write_bytes(raw)


def write_unless_changed(path: str | Path, data: bytes | str, *, force: bool = False) -> bool:
    """Write ``data`` unless ``path`` already holds exactly it.

    Returns:
        Whether the file was written.

    Raises:
        OverwriteError: ``path`` holds different content and ``force`` is false.
    """
    path = Path(path)
    raw = data.encode("utf-8") if isinstance(data, str) else data
    if path.exists():
        if path.read_bytes() == raw:
            return False
        if not force:
            raise OverwriteError(f"{path}: exists with different content (pass --force to replace)")
    replace_file(path, raw)
    return True


def check_new(paths: list[Path], *, force: bool = False, what: str = "result") -> None:
    """Refuse (without ``force``) if any of ``paths`` exists; one line names them.

    Raises:
        OverwriteError: One of the paths exists and ``force`` is false.
    """
    existing = [p for p in paths if p.exists()]
    if existing and not force:
        names = ", ".join(p.name for p in existing)
        raise OverwriteError(
            f"{existing[0].parent}: already holds a {what} ({names}); pass --force to "
            "replace it or choose another --out"
        )


def new_folder(parent: str | Path, stem: str) -> Path:
    """Create and return the first free folder of ``parent/stem``, ``stem-2``, ``stem-3``..."""
    parent = Path(parent)
    parent.mkdir(parents=True, exist_ok=True)
    n = 1
    while True:
        candidate = parent / (stem if n == 1 else f"{stem}-{n}")
        try:
            candidate.mkdir()
        except FileExistsError:
            n += 1
            continue
        return candidate


def numbered_folder(parent: str | Path, prefix: str) -> Path:
    """Create and return ``parent/<prefix>-NNNN``, the number one above the highest taken
    (``campaign-0001``, ``campaign-0002``, ...), claimed atomically like :func:`new_folder`."""
    parent = Path(parent)
    parent.mkdir(parents=True, exist_ok=True)
    taken = [p.name.removeprefix(f"{prefix}-") for p in parent.glob(f"{prefix}-*")]
    n = max((int(t) for t in taken if t.isdigit()), default=0) + 1
    while True:
        candidate = parent / f"{prefix}-{n:04d}"
        try:
            candidate.mkdir()
        except FileExistsError:
            n += 1
            continue
        return candidate


__all__ = [
    "OverwriteError",
    "cannot_write_in",
    "check_new",
    "new_folder",
    "numbered_folder",
    "replace_file",
    "replacing",
    "umask_mode",
    "write_unless_changed",
]
