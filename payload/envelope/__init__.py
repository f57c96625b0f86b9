"""Envelope and reach reports: does the stowed payload fit the bays, what can it reach.

``payload report envelope`` checks the stowed configuration against the combined
envelope of Astrobee's two lower 1-U bays (containment, clearance, self-collision,
a stowed-posture search, the deployment sweep); ``payload report reach`` samples
the deployed joint space (workspaces, pair spans, rail spacing, collision-free
fraction, CTB grasp check). The bay size is an assumption (not public); every
report names it.


Names load on first use (module ``__getattr__``), so importing the package (or
a command module inside it) costs no numerical library.
"""

from __future__ import annotations

from payload.lazy import lazy_exports

REACH_SAMPLES = 100_000
"""The reach report's sampled configurations by default (what the committed report uses):
with fewer, a pair's thinnest grasp can be missed, and its verdict says so."""
MIN_SAMPLES = 1000
"""The fewest sampled configurations a reach analysis takes."""

_LAZY: dict[str, str] = {
    "EnvelopeAnalysis": "payload.envelope.fit",
    "PairContact": "payload.envelope.fit",
    "PartFit": "payload.envelope.fit",
    "PostureSearch": "payload.envelope.fit",
    "StowedCheck": "payload.envelope.fit",
    "SweepResult": "payload.envelope.fit",
    "analyse_envelope": "payload.envelope.fit",
    "check_stowed": "payload.envelope.fit",
    "deployment_sweep": "payload.envelope.fit",
    "fit_parts": "payload.envelope.fit",
    "search_stowed_posture": "payload.envelope.fit",
    "self_contacts": "payload.envelope.fit",
    "PayloadGeometry": "payload.envelope.geometry",
    "CTB_FEATURES": "payload.envelope.reach",
    "PAIRS": "payload.envelope.reach",
    "GraspFeature": "payload.envelope.reach",
    "ReachAnalysis": "payload.envelope.reach",
    "ReachError": "payload.envelope.reach",
    "analyse_reach": "payload.envelope.reach",
    "design_kinematics": "payload.envelope.reach",
    "span_range": "payload.envelope.reach",
    "BAY_ASSUMPTION": "payload.envelope.vehicle",
    "Vehicle": "payload.envelope.vehicle",
    "VehicleError": "payload.envelope.vehicle",
    "load_design_and_vehicle": "payload.envelope.vehicle",
    "vehicle_from_dict": "payload.envelope.vehicle",
    "with_bay_size": "payload.envelope.vehicle",
}
"""Each public name and the module defining it."""

__all__ = sorted([*_LAZY, "MIN_SAMPLES", "REACH_SAMPLES"])


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
