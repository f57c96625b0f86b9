"""Mass properties of part solids, kept on disk by the hash of the solid's mesh.

Building the kinematic tree needs each part's mass, centre of mass and inertia, which
trimesh computes from the part's triangle mesh; importing trimesh alone costs about a
second of CPU on this machine, in every command. The figures depend only on the mesh,
the density and the trimesh version, so they are kept in the cache
(:func:`payload.cache.cache_dir`) under the SHA-256 of those, and trimesh is loaded only
for a part not seen before. A cached entry holds trimesh's own numbers, bit for bit.
"""

from __future__ import annotations

import functools
import hashlib
import io
from collections.abc import Callable
from pathlib import Path

import manifold3d as m3d
import numpy as np

from payload.cache import cache_dir, dist_version

_VERSION = b"mass-props-1"


@functools.cache
def _trimesh_version() -> str:
    return dist_version("trimesh")


def _path(solid: m3d.Manifold, density: float) -> Path:
    mesh = solid.to_mesh()
    h = hashlib.sha256(_VERSION + _trimesh_version().encode())
    h.update(np.ascontiguousarray(mesh.vert_properties).tobytes())
    h.update(np.ascontiguousarray(mesh.tri_verts).tobytes())
    h.update(np.float64(density).tobytes())
    return cache_dir() / "mass_props" / f"{h.hexdigest()[:32]}.npy"


def cached_mass_props(
    solid: m3d.Manifold,
    density: float,
    compute: Callable[[], tuple[float, np.ndarray, np.ndarray]],
) -> tuple[float, np.ndarray, np.ndarray]:
    """(mass [kg], centre of mass (3,) [m], inertia about it (3, 3) [kg m^2]) of a solid.

    Args:
        solid: The part's solid.
        density: Its density [kg/m^3].
        compute: Computes the figures when they are not cached (trimesh).
    """
    path = _path(solid, density)
    try:
        row = np.load(path, allow_pickle=False)
        if row.shape == (13,):
            return float(row[0]), row[1:4].copy(), row[4:].reshape(3, 3).copy()
    except (OSError, ValueError, EOFError):
        pass
    mass, com, inertia = compute()
    row = np.concatenate([[mass], np.asarray(com, float), np.asarray(inertia, float).ravel()])
    buf = io.BytesIO()
    np.save(buf, row, allow_pickle=False)
    try:
        from payload.safeio import replace_file

        path.parent.mkdir(parents=True, exist_ok=True)
        replace_file(path, buf.getvalue())
    except OSError:
        pass  # a read-only cache only costs the next computation
    return mass, com, inertia


__all__ = ["cached_mass_props"]
