"""Self-collision of a posed payload: signed distances and shared volumes of link pairs."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from payload.envelope.fit_results import (
    PairContact,
)
from payload.envelope.geometry import PayloadGeometry, aabb_gap

NEAR = 1e-4
"""Pairs closer than this (convex pieces) get a manifold3d intersection volume; farther
pairs share no volume [m]."""


def _contact(
    geom: PayloadGeometry, a: str, b: str, poses: Mapping[str, np.ndarray], near: float = NEAR
) -> PairContact:
    """Two links' signed distance, with their shared volume when closer than ``near``."""
    d = geom.link_distance(a, b, poses)
    return PairContact(a, b, d, geom.overlap_volume(a, b, poses) if d < near else 0.0)


def self_contacts(
    geom: PayloadGeometry, poses: Mapping[str, np.ndarray], near: float = NEAR
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
    out = [_contact(geom, a, b, poses, near) for a, b in geom.pairs]
    # closest first; equal distances (to 10 nm) keep the tree's pair order
    order = sorted(range(len(out)), key=lambda i: (round(out[i].distance, 8), i))
    return [out[i] for i in order]


def colliding_pairs(
    geom: PayloadGeometry,
    poses: Mapping[str, np.ndarray],
    boxes: Mapping[str, tuple[np.ndarray, np.ndarray]],
    pairs: Iterable[tuple[str, str]],
) -> list[PairContact]:
    """The pairs of ``pairs`` that collide (:attr:`PairContact.colliding`) posed at
    ``poses``; ``boxes``: each link's bounding box there (:func:`aabb` of its pieces'
    vertices), so apart boxes are apart links, sharing no volume, and are not measured."""
    out = []
    for a, b in pairs:
        if aabb_gap(boxes[a], boxes[b]) > 0.0:
            continue
        c = _contact(geom, a, b, poses)
        if c.colliding:
            out.append(c)
    return out


__all__ = [
    "colliding_pairs",
    "self_contacts",
]
