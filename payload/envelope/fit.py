"""Stowed fit: containment in the bays, self-collision, posture search, deployment sweep.

Containment is a volume test: a part is inside the (convex) bay envelope when every
extreme point of the part is (closed form on the convex-hull vertices, exact for a
polyhedral solid), and the part's volume outside the envelope (manifold3d
difference) is nil. Clearance to the walls of an inside part is a python-fcl
distance between the part's triangle mesh and slabs standing on the six walls;
the protrusion of an outside part is the largest distance of a part point beyond
the envelope. Self-collision is a manifold3d intersection volume for every
non-adjacent link pair; penetration depths and clearances come from signed
distances (GJK/EPA) between the convex pieces of the links.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

from payload.envelope.containment import (
    INSIDE_TOL,
    box_clearance,
    box_solid,
    fit_parts,
    fit_solid,
    protrusion,
    wall_gaps,
    wall_slabs,
)
from payload.envelope.deployment import deployment_sweep, unfolding_check
from payload.envelope.fit_results import (
    VOLUME_TOL,
    EnvelopeAnalysis,
    PairContact,
    PartFit,
    PostureSearch,
    StowedCheck,
    SweepResult,
)
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.posture_search import (
    envelope_margin,
    finger_links,
    search_stowed_posture,
    with_finger_posture,
)
from payload.envelope.progress import Progress, quiet
from payload.envelope.self_collision import self_contacts
from payload.envelope.vehicle import Vehicle


def check_stowed(geom: PayloadGeometry, vehicle: Vehicle, q: Mapping[str, float]) -> StowedCheck:
    """Containment, self-collision and the deployment of one stowed configuration: the
    stage's sweep down, then the fingers and the rail to the design's home posture."""
    q = dict(q)
    q["stage"] = geom.tree.joint_map["stage"].lower
    poses = geom.poses(q)
    contacts = self_contacts(geom, poses)
    home = geom.tree.posture("home")
    return StowedCheck(
        q,
        fit_parts(geom, poses, vehicle),
        contacts,
        deployment_sweep(geom, vehicle, q, contacts),
        unfolding_check(geom, vehicle, q, home, contacts),
    )


def analyse_envelope(
    geom: PayloadGeometry,
    vehicle: Vehicle,
    search: bool | None = None,
    progress: Progress = quiet,
) -> EnvelopeAnalysis:
    """Check the design's stowed configuration; search a posture when it fails.

    Args:
        geom: Collision geometry of the design.
        vehicle: The vehicle.
        search: Run the stowed-posture search: ``None`` (default) when the given
            posture does not stow (outside the bays, colliding, or blocked as the stage
            goes down), ``True`` always, ``False`` never.
        progress: Progress callback.

    Returns:
        The :class:`EnvelopeAnalysis`.
    """
    t0 = time.perf_counter()
    progress("stowed fit", 0.0)
    given = check_stowed(geom, vehicle, geom.tree.posture("stowed"))
    progress("stowed fit", 1.0)
    found = suggested = None
    # the search maximises the stowed clearances: a design failing only as its fingers
    # unfold (its home posture's doing as much as the stowed one's) is not searched for
    if search or (search is None and not given.stows):
        found = search_stowed_posture(geom, vehicle, given.q, progress=progress)
        suggested = check_stowed(geom, vehicle, with_finger_posture(given.q, found.finger))
    approx = [(f"{p.link}/{p.name}", p.excess) for p in geom.approximate_pieces()]
    return EnvelopeAnalysis(
        vehicle,
        geom.tree.design.source,
        given,
        found,
        suggested,
        geom.excluded_pairs(),
        approx,
        time.perf_counter() - t0,
    )


__all__ = [
    "INSIDE_TOL",
    "VOLUME_TOL",
    "EnvelopeAnalysis",
    "PairContact",
    "PartFit",
    "PostureSearch",
    "StowedCheck",
    "SweepResult",
    "analyse_envelope",
    "box_clearance",
    "box_solid",
    "check_stowed",
    "deployment_sweep",
    "envelope_margin",
    "finger_links",
    "fit_parts",
    "fit_solid",
    "protrusion",
    "search_stowed_posture",
    "self_contacts",
    "wall_gaps",
    "wall_slabs",
    "with_finger_posture",
]
