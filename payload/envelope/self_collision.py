"""Self-collision of a posed payload: signed distances and shared volumes of link pairs."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from payload.envelope.fit_results import (
    PairContact,
)
from payload.envelope.geometry import PayloadGeometry


def self_contacts(
    geom: PayloadGeometry, poses: Mapping[str, np.ndarray], near: float = 1e-4
) -> list[PairContact]:
    """Signed distance of every non-adjacent link pair, with the exact overlap volume.

    Args:
        geom: Collision geometry of the payload.
        poses: Link poses in the payload frame.
        near: Pairs closer than this (convex pieces) get a manifold3d intersection
            volume; farther pairs share no volume [m].

    Returns:
        Every pair, closest first.
    """
    out = []
    for a, b in geom.pairs:
        d = geom.link_distance(a, b, poses)
        vol = geom.overlap_volume(a, b, poses) if d < near else 0.0
        out.append(PairContact(a, b, d, vol))
    # closest first; equal distances (to 10 nm) keep the tree's pair order
    order = sorted(range(len(out)), key=lambda i: (round(out[i].distance, 8), i))
    return [out[i] for i in order]


__all__ = [
    "self_contacts",
]
