"""Envelope and reach reports: does the stowed payload fit the bays, what can it reach.

``payload report envelope`` checks the stowed configuration against the combined
envelope of Astrobee's two lower 1-U bays (containment, clearance, self-collision,
a stowed-posture search, the deployment sweep); ``payload report reach`` samples
the deployed joint space (workspaces, pair spans, rail spacing, collision-free
fraction, CTB grasp check). The bay size is an assumption (not public); every
report names it.
"""

from payload.envelope.fit import (
    EnvelopeAnalysis,
    PairContact,
    PartFit,
    PostureSearch,
    StowedCheck,
    SweepResult,
    analyse_envelope,
    check_stowed,
    deployment_sweep,
    fit_parts,
    search_stowed_posture,
    self_contacts,
)
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.reach import (
    CTB_FEATURES,
    PAIRS,
    GraspFeature,
    ReachAnalysis,
    ReachError,
    analyse_reach,
    design_kinematics,
    span_range,
)
from payload.envelope.vehicle import (
    BAY_ASSUMPTION,
    VEHICLE_TOML,
    Vehicle,
    VehicleError,
    load_design_and_vehicle,
    vehicle_from_dict,
    with_bay_size,
)

__all__ = [
    "BAY_ASSUMPTION",
    "CTB_FEATURES",
    "PAIRS",
    "VEHICLE_TOML",
    "EnvelopeAnalysis",
    "GraspFeature",
    "PairContact",
    "PartFit",
    "PayloadGeometry",
    "PostureSearch",
    "ReachAnalysis",
    "ReachError",
    "StowedCheck",
    "SweepResult",
    "Vehicle",
    "VehicleError",
    "analyse_envelope",
    "analyse_reach",
    "check_stowed",
    "deployment_sweep",
    "design_kinematics",
    "fit_parts",
    "load_design_and_vehicle",
    "search_stowed_posture",
    "self_contacts",
    "span_range",
    "vehicle_from_dict",
    "with_bay_size",
]
