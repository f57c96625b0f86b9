"""Self-collision of a posed payload: signed distances and shared volumes of link pairs."""

from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping

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


def path_collisions(
    geom: PayloadGeometry,
    postures: Iterable[Mapping[str, float]],
    skip: Collection[frozenset[str]] = (),
) -> list[PairContact]:
    """The link pairs that collide (:attr:`PairContact.colliding`) in any of ``postures``
    (the samples of a motion), each once at its deepest, deepest first; the pairs in
    ``skip`` (``frozenset((a, b))``) left out.

    Args:
        geom: Collision geometry of the payload.
        postures: Joint values of each sample [rad, m].
        skip: Pairs already known to collide (a stowed check's).
    """
    deepest: dict[frozenset[str], PairContact] = {}
    for q in postures:
        for c in self_contacts(geom, geom.poses(q)):
            key = frozenset((c.a, c.b))
            if c.colliding and key not in skip:
                if key not in deepest or c.distance < deepest[key].distance:
                    deepest[key] = c
    return sorted(deepest.values(), key=lambda c: c.distance)


__all__ = [
    "path_collisions",
    "self_contacts",
]
