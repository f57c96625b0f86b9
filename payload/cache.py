"""The workbench's disk cache: derived data kept outside the project, keyed by its source.

Compiled retargeting solvers, span ranges and the generated models' fingerprints live
here, each named by a hash of what it was derived from, so a stale entry is never read.
"""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """Directory of the cache: ``$PAYLOAD_CACHE_DIR``, else the user cache dir."""
    env = os.environ.get("PAYLOAD_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "astrobee-payload" / "retarget"


__all__ = ["cache_dir"]
