"""The on-disk cache of :func:`payload.retarget.span_range.pair_range` results.

A range is kept beside the compiled solvers (:func:`payload.cache.cache_dir`),
keyed by the URDF, the pair, the seed, the margin, the design and the source of the code
that computes it; an unreadable or torn file is computed again and rewritten.
"""

from __future__ import annotations

import hashlib
import inspect
import os
import threading
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import Protocol, TypeVar

import numpy as np

from payload.retarget.features import PairKinematics


class _Range(Protocol):
    spans: np.ndarray
    postures: np.ndarray
    span_min: float
    span_max: float
    span_min_kinematic: float


R = TypeVar("R", bound=_Range)

_CACHE_VERSION = "pair-range-1"


def disk_key(pk: PairKinematics, seed: int, collisions: bool, sources: Sequence[ModuleType]) -> str:
    """The cache key of one range: the model, the settings and the computing code."""
    from payload import kinematics
    from payload.retarget import (
        collision,
        collision_distance,
        collision_geometry,
        features,
        symbolic,
    )

    parts = [
        _CACHE_VERSION,
        Path(pk.kin.urdf).read_text(),
        repr(pk.desc),
        repr(seed),
        repr(collisions),
        repr(pk.hand.collision_margin),
        # the code that computes it: a change of it or of the collision model is a new key
        *(inspect.getsource(m) for m in sources),
        inspect.getsource(collision),
        inspect.getsource(collision_distance),
        inspect.getsource(collision_geometry),
        # and the features and forward kinematics it is measured with
        inspect.getsource(features),
        inspect.getsource(symbolic),
        inspect.getsource(kinematics),
    ]
    if pk.hand.design is not None:
        parts.append(Path(pk.hand.design).read_text())
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:24]


def load_or_compute(
    pk: PairKinematics,
    seed: int,
    collisions: bool,
    compute: Callable[[PairKinematics, int, bool], R],
    restore: Callable[..., R],
    sources: Sequence[ModuleType],
) -> R:
    """The range from the on-disk cache (next to the compiled solvers), else ``compute``d
    and stored.

    Args:
        pk: The pair's kinematics.
        seed: Seed of the computation.
        collisions: Whether the range keeps the self-collision margin.
        compute: ``(pk, seed, collisions) -> range``.
        restore: ``(pair, span_min, span_max, span_min_kinematic, spans, postures,
            pinch, open) -> range``, from the stored arrays.
        sources: The modules whose code the key covers.
    """
    from payload.cache import cache_dir

    try:
        key = disk_key(pk, seed, collisions, sources)
    except OSError:  # the model's files are gone (a temporary URDF): no key, no cache
        return compute(pk, seed, collisions)
    path = cache_dir() / f"pair_range_{key}.npz"
    try:
        with np.load(path) as z:
            spans, postures = z["spans"], z["postures"]
            lo, hi, kmin = (float(v) for v in z["scalars"])
        return restore(
            pk.name,
            lo,
            hi,
            kmin,
            spans,
            postures,
            pk.features(postures[0]),
            pk.features(postures[-1]),
        )
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        pass  # missing or unreadable (a torn write): computed again and rewritten
    rg = compute(pk, seed, collisions)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # one writer per process and thread (campaign workers run a retargeter per thread)
        tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp.npz")
        np.savez(
            tmp,
            spans=rg.spans,
            postures=rg.postures,
            scalars=np.array([rg.span_min, rg.span_max, rg.span_min_kinematic]),
        )
        os.replace(tmp, path)
    except OSError:  # pragma: no cover - a read-only cache only costs the recomputation
        pass
    return rg
