"""Reach of the deployed fingers: workspaces, pair spans, rail spacing, grasp check.

The joint space is sampled uniformly inside the limits (the 17 manipulation
coordinates, stage deployed) and every configuration goes through the shared
forward kinematics (the design's tree, the URDF's source, numpy over the samples:
:mod:`payload.envelope.batch_fk`, checked against Pinocchio on the URDF as the retargeter
uses it; see :mod:`payload.envelope.kinematics`). Self-collision of
every sample is checked by MuJoCo on a model built from the convex pieces of the
link solids (the same pieces python-fcl uses for the stowed checks), with the
vehicle body beside it.

A pair's span is eq. 2's fingertip separation l = |p2 - p1|; its range is the
retargeter's (:func:`payload.retarget.pair_range`: the fingertips kept in front of
their fingers' first joints), so the report and the calibration agree.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from payload.design.params import FINGER_JOINTS, FINGERS
from payload.design.tree import ALL_JOINTS, KinematicTree
from payload.envelope import REACH_SAMPLES
from payload.envelope.batch_fk import fingertips_batch
from payload.envelope.collisions import CollisionModel, Contacts
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.grasp import (
    CTB_FEATURES,
    GraspFeature,
    GraspResult,
    grasp_check,
    opposition,
    symmetric_samples,
)
from payload.envelope.kinematics import DesignKinematics, design_kinematics
from payload.envelope.pairs import (
    OPPOSITION_CONE,
    PAIRS,
    ReachError,
    finger_link_names,
    grasp_base,
    pair_joints,
    pair_side,
)
from payload.envelope.progress import Progress, quiet
from payload.envelope.reach_start import StartedCheck, check_samples, start_check
from payload.envelope.sampling import fingertips, sample_configurations
from payload.envelope.spans import SpanRange, span_range
from payload.envelope.vehicle import Vehicle
from payload.envelope.workspace import Workspace, rail_spacing, value_range, workspace

_TIPS = [f"{f}_tip" for f in FINGERS]

# ----------------------------------------------------------------- the analysis


@dataclass
class PairReach:
    """Everything reported for one pair.

    Attributes:
        name: ``L`` or ``R``.
        fingers: The two fingers.
        span: Range of eq. 2's separation: the retargeter's (:func:`payload.retarget.pair_range`).
        pad_contact: Separation at which the two pads touch (twice the pad radius) [m].
        free_fraction: Samples in which the pair's links touch nothing (the other pair's
            fingers aside, whose posture is independent).
        free_span: (min, max) separation over those samples [m].
        opposed_span: (min, max) over those samples with opposing pads below the
            vehicle [m] (NaN when none).
        grasps: Grasp-check results.
        free: Per-sample flags of the pair touching nothing, shape (n,).
    """

    name: str
    fingers: tuple[str, str]
    span: SpanRange
    pad_contact: float
    free_fraction: float
    free_span: tuple[float, float]
    opposed_span: tuple[float, float]
    grasps: list[GraspResult]
    free: np.ndarray

    @property
    def span_min(self) -> float:
        """Smallest separation with the pads not interpenetrating [m]."""
        return max(self.span.minimum, self.pad_contact)


@dataclass
class ReachAnalysis:
    """The reach report's content.

    Attributes:
        vehicle: The vehicle.
        design_source: The design file.
        samples: Number of sampled configurations.
        seed: Random seed.
        workspaces: Per finger.
        pairs: Per pair.
        rail_spacing: (min, max) pair spacing over the rail [m].
        contacts: Every contact of every sample.
        tips: Fingertips of every sample, shape (n, 4, 3) [m].
        home_below_vehicle: Fingertip depth below the bottom face in the home posture [m].
        timings: Stage -> seconds.
        seconds: Wall time of the analysis [s].
    """

    vehicle: Vehicle
    design_source: str
    samples: int
    seed: int
    workspaces: list[Workspace]
    pairs: list[PairReach]
    rail_spacing: tuple[float, float]
    contacts: Contacts
    tips: np.ndarray
    home_below_vehicle: float
    timings: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def collision_free_fraction(self) -> float:
        """Fraction of samples in which no two payload links touch."""
        return float(1.0 - self.contacts.self_collision().mean())

    @property
    def below_vehicle(self) -> float:
        """Largest fingertip depth below the vehicle's bottom face over all reachable
        samples [m] (NaN when no finger reached in any)."""
        depths = [w.below_vehicle for w in self.workspaces if np.isfinite(w.below_vehicle)]
        return max(depths, default=float("nan"))

    def assumptions(self) -> list[str]:
        v = self.vehicle
        size = " x ".join(f"{s * 1e3:.0f}" for s in v.bay_size)
        return [
            f"ASSUMPTION (bay size): {v.assumption}",
            f"bay envelope {size} mm from {v.source}; the vehicle's bottom face is at "
            f"z = {v.bottom_z * 1e3:.0f} mm (payload frame)",
            "joints sampled uniformly inside their limits, stage fully deployed",
            "collisions use the convex hull of every part of the link solids (MuJoCo); "
            "parent/child links are never checked",
            f"opposing pads: pinch axis within {np.degrees(OPPOSITION_CONE):.0f} deg of the "
            "across-array (y) axis, both pads wholly below the vehicle's bottom face",
            "grasp witnesses: rail at its home position, stage fully deployed",
            "CTB strap and edge thicknesses marked ASSUMPTION are not measured values",
        ]


def analyse_reach(
    geom: PayloadGeometry,
    vehicle: Vehicle,
    samples: int = REACH_SAMPLES,
    seed: int = 0,
    features: Sequence[GraspFeature] = CTB_FEATURES,
    workers: int | None = None,
    progress: Progress = quiet,
    started: StartedCheck | None = None,
) -> ReachAnalysis:
    """Sample the deployed joint space and measure reach, spans and collisions.

    Args:
        geom: Collision geometry of the design.
        vehicle: The vehicle.
        samples: Number of configurations (at least 1,000).
        seed: Random seed.
        features: Thicknesses for the grasp check.
        workers: Processes for the collision checks (default: up to 2, the CPUs there are).
        progress: Progress callback.
        started: The check already started by
            :func:`payload.envelope.reach_start.start_check` with these ``samples``,
            ``seed`` and ``workers`` (default: started here).

    Returns:
        The :class:`ReachAnalysis`.

    Raises:
        ReachError: Too few samples, or a negative thickness.
    """
    _check_inputs(samples, features)
    if started is None:
        started = start_check(geom, vehicle, samples, seed, workers, progress)
    elif len(started.samples) != samples:
        raise ReachError(f"the started check has {len(started.samples)} samples, not {samples}")
    tree = geom.tree
    t0, q, rng, model = started.t_start, started.samples, started.rng, started.model
    timings: dict[str, float] = {}

    t1 = time.perf_counter()
    _load_scipy()
    model_kin = design_kinematics(tree)
    tips = fingertips_batch(tree, q)
    spans = {name: span_range(model_kin.pairs[name]) for name in PAIRS}
    timings["batched FK"] = time.perf_counter() - t1

    contacts = started.contacts(progress)
    timings["collisions"] = time.perf_counter() - started.t_model

    t = time.perf_counter()
    spaces = _workspaces(tree, tips, contacts, vehicle, progress)
    timings["workspaces"] = time.perf_counter() - t

    t = time.perf_counter()
    pairs = []
    for name in PAIRS:
        pairs.append(
            _pair_reach(
                tree, model_kin, name, spans[name], q, tips, contacts, model, vehicle, features, rng
            )
        )
        progress("spans and grasps", len(pairs) / len(PAIRS))
    timings["spans and grasps"] = time.perf_counter() - t

    kin = model_kin.kin
    home_tips = kin.frame_positions(kin.configuration(tree.posture("home")), _TIPS)
    home_depth = max(vehicle.bottom_z - home_tips[:, 2])
    out = ReachAnalysis(
        vehicle,
        tree.design.source,
        int(samples),
        seed,
        spaces,
        pairs,
        rail_spacing(kin),
        contacts,
        tips,
        float(home_depth),
        timings,
    )
    out.seconds = time.perf_counter() - t0
    return out


def _load_scipy() -> None:
    """Import the SciPy modules the workspaces and the grasp check use (each imports its
    own when first used): here, while the collision check's workers run, instead of
    after them (0.2 to 0.4 s on this machine)."""
    import scipy.optimize
    import scipy.spatial  # noqa: F401


def _check_inputs(samples: int, features: Sequence[GraspFeature]) -> None:
    """Raise :class:`ReachError` on a bad sample count or a negative thickness."""
    check_samples(samples)
    for f in features:
        if not (np.isfinite(f.thickness) and f.thickness >= 0):
            raise ReachError(f"thickness of {f.name!r} must be >= 0 m (got {f.thickness})")


def _workspaces(
    tree: KinematicTree,
    tips: np.ndarray,
    contacts: Contacts,
    vehicle: Vehicle,
    progress: Progress,
) -> list[Workspace]:
    """Each finger's workspace over the samples in which its links touch nothing."""
    spaces = []
    links = {f: finger_link_names(tree, f) for f in FINGERS}
    for i, f in enumerate(FINGERS):
        others = [n for g in FINGERS if g != f for n in links[g]]
        keep = ~contacts.involving(links[f], ignore=others)
        spaces.append(workspace(f, tips[:, i], vehicle.bottom_z, keep))
        progress("workspaces", (i + 1) / len(FINGERS))
    return spaces


def _pair_reach(
    tree: KinematicTree,
    model_kin: DesignKinematics,
    name: str,
    span: SpanRange,
    q: np.ndarray,
    tips: np.ndarray,
    contacts: Contacts,
    model: CollisionModel,
    vehicle: Vehicle,
    features: Sequence[GraspFeature],
    rng: np.random.Generator,
) -> PairReach:
    """Span range, collision-free spans and grasp check of one pair."""
    f1, f2 = PAIRS[name]
    r = tree.design.finger.pad.radius
    c1 = [ALL_JOINTS.index(f"{f1}_{j}") for j in FINGER_JOINTS]
    c2 = [ALL_JOINTS.index(f"{f2}_{j}") for j in FINGER_JOINTS]
    own = finger_link_names(tree, f1) + finger_link_names(tree, f2)
    others = [n for g in FINGERS if g not in (f1, f2) for n in finger_link_names(tree, g)]
    free = ~contacts.involving(own, ignore=others)
    i1, i2 = FINGERS.index(f1), FINGERS.index(f2)
    ell = np.linalg.norm(tips[:, i2] - tips[:, i1], axis=1)
    ang = opposition(tips[:, i1], tips[:, i2], pair_side(tree, name))
    top = np.maximum(tips[:, i1, 2], tips[:, i2, 2]) + r
    opp = free & (ang <= OPPOSITION_CONE) & (top <= vehicle.bottom_z)
    base = q[0].copy()
    for j, v in grasp_base(tree).items():
        base[ALL_JOINTS.index(j)] = v
    cols = c1 + c2

    def pair_free(q8: np.ndarray) -> bool:
        row = base.copy()
        row[cols] = q8
        return model.pair_free(row, own, others)

    candidates = np.vstack([q[opp][:, cols], symmetric_samples(tree, name, 20_000, rng)])
    grasps = grasp_check(
        model_kin.kin, tree, name, candidates, vehicle, features, is_free=pair_free
    )
    return PairReach(
        name,
        (f1, f2),
        span,
        2 * r,
        float(free.mean()),
        value_range(ell[free]),
        value_range(ell[opp]),
        grasps,
        free,
    )


__all__ = [
    "CTB_FEATURES",
    "OPPOSITION_CONE",
    "PAIRS",
    "CollisionModel",
    "Contacts",
    "GraspFeature",
    "GraspResult",
    "PairReach",
    "ReachAnalysis",
    "ReachError",
    "SpanRange",
    "Workspace",
    "analyse_reach",
    "design_kinematics",
    "finger_link_names",
    "fingertips",
    "grasp_base",
    "grasp_check",
    "opposition",
    "pair_joints",
    "rail_spacing",
    "sample_configurations",
    "span_range",
    "symmetric_samples",
    "workspace",
]
