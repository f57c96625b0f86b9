"""Fingertip pads that land like silicone: MuJoCo contact parameters from the pad design.

The pad is a silicone skin of thickness ``h`` and Young's modulus ``E`` over a sphere of
radius ``R`` (``[finger.pad]`` in the design file; the values are ASSUMPTIONs until
measured), pressed by ``delta`` against the flat handle face. Its force law is Hertz's
for an elastic sphere on a rigid flat (Hertz 1882; K. L. Johnson, *Contact Mechanics*,
1985, eqs. 4.22-4.23):

    F = (4/3) E* sqrt(R) delta^(3/2),   E* = E / (1 - nu^2),   contact radius a = sqrt(R delta)

with silicone incompressible (``nu = 0.5``). Linearised at the design's pad load ``F0``:
``delta0 = (3 F0 / (4 E* sqrt(R)))^(2/3)`` and tangent stiffness ``k = 1.5 F0 / delta0``.
Hertz treats the skin as a half-space, which holds while the contact radius is small
beside the skin (``a < h``: at the design values a = 1.8 mm under a 3 mm skin). The former
thin-layer law ``F = E (pi a^2) delta / h`` with ``a^2 = 2 R delta`` assumed the opposite
(``a >> h``; it gave a = 2.1 mm, not thin) and was twice the Winkler layer's own integral
``int (E / h)(delta - r^2 / 2R) 2 pi r dr = pi E R delta^2 / h``.

MuJoCo's contact is a mass-normalised spring-damper: ``solref = (timeconst, dampratio)``
sets ``K = 1 / (dmax^2 timeconst^2 dampratio^2)`` and the damping ``2 / (dmax
timeconst)``, and the impedance ``d(r)`` of ``solimp`` enters twice (the reference
acceleration is ``-b v - K d r`` and the constrained acceleration blends it in with
weight ``d``: ``a1 = (1 - d) a0 + d a_ref``). So a contact of effective mass ``m``
pressed with force ``F`` settles at the penetration ``r`` with
``F / r = m d^2 / (1 - d) K`` (a secant law, checked against MuJoCo in the tests; at
``d = dmax`` it is the resting penetration ``a (1 - d) timeconst^2 dampratio^2`` of the
MuJoCo documentation), and ``dampratio = 1`` damps it critically. The effective
mass of a pad contact along the closing direction is the finger's (``1 / (n J M^-1 J^T
n)`` from the payload model at the pinch pre-shape, with its reflected servo inertia) in
series with the CTB's. The pad's secant ``F0 / delta0`` at the design load (with
``d = dmax``) gives ``timeconst = sqrt(m / (1 - dmax) * delta0 / F0) / dampratio``,
``dampratio`` the design's damping ratio (at least 1).

``solimp`` follows Hertz's progressive stiffening: the impedance rises from ``dmin`` at
first touch to ``dmax`` at the design-load indentation ``delta0`` (the transition width),
with ``dmin`` chosen so that half-way in the secant ``F / delta`` is ``0.5^(1/2)`` of the
design load's, as ``F ~ delta^(3/2)`` gives (midpoint of MuJoCo's sigmoid:
``d = (dmin + dmax) / 2`` there, where the secant goes as ``d^2 / (1 - d)``). MuJoCo needs
``timeconst >= 2 dt``; a stiffer pad is clamped there (and said so).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import mujoco
import numpy as np

from payload.design import FINGER_JOINTS, FINGERS, SIDE_OF, Design
from payload.errors import PayloadError

SOLIMP_DMAX = 0.95
"""Impedance at the design-load indentation (MuJoCo's default dmax)."""
POISSON = 0.5
"""Poisson's ratio of the pad silicone (an elastomer: incompressible)."""
HERTZ_EXPONENT = 1.5
"""``F ~ delta^HERTZ_EXPONENT`` (Hertz, sphere on a flat)."""


def _secant_factor(d: float) -> float:
    """How MuJoCo's resting secant stiffness ``F / r`` scales with the impedance ``d``:
    ``d^2 / (1 - d)`` (module docstring)."""
    return d * d / (1.0 - d)


def _midpoint_dmin(dmax: float) -> float:
    """``dmin`` with ``s((dmin + dmax) / 2) = s(dmax) 0.5^(n - 1)``, ``s`` the
    :func:`_secant_factor` and n the Hertz exponent: half-way to the design indentation
    the secant stiffness is that share."""
    target = 0.5 ** (HERTZ_EXPONENT - 1.0) * _secant_factor(dmax)
    mid = 0.5 * (math.sqrt(target * target + 4.0 * target) - target)  # d^2 = t (1 - d)
    return 2.0 * mid - dmax


class PadContact(NamedTuple):
    """The pad contact derived from the design.

    Attributes:
        stiffness: Linearised (tangent) contact stiffness ``k`` at the design load [N/m].
        indentation: Indentation at the design load [m].
        effective_mass: Effective mass of the contact along the closing direction [kg].
        timeconst: MuJoCo solref time constant [s].
        dampratio: MuJoCo solref damping ratio.
        solref: ``(timeconst, dampratio)``.
        solimp: ``(dmin, dmax, width, midpoint, power)``.
        clamped: The time constant was raised to MuJoCo's least stable value.
    """

    stiffness: float
    indentation: float
    effective_mass: float
    timeconst: float
    dampratio: float
    solref: tuple[float, float]
    solimp: tuple[float, float, float, float, float]
    clamped: bool


def pad_stiffness(design: Design) -> tuple[float, float]:
    """Hertz pad stiffness at the design load: ``(k [N/m], delta0 [m])`` (module docstring)."""
    p = design.finger.pad
    e_star = p.modulus / (1.0 - POISSON**2)
    delta0 = (3.0 * p.load / (4.0 * e_star * math.sqrt(p.radius))) ** (2.0 / 3.0)
    return HERTZ_EXPONENT * p.load / delta0, delta0


def patch_radius(design: Design) -> float:
    """Hertz contact radius at the design load ``a = sqrt(R delta0)`` [m]: the model holds
    while it is below the skin thickness."""
    return math.sqrt(design.finger.pad.radius * pad_stiffness(design)[1])


def pose_payload(
    m: mujoco.MjModel, d: mujoco.MjData, finger: Sequence[float], rail: float, stage: float
) -> None:
    """Set the payload model's joints in ``d.qpos``: every finger at ``finger`` (mcp_flex,
    mcp_abd, pip, dip) [rad], the rail and the stage [m]."""
    values = {"rail": rail, "stage": stage}
    for f in FINGERS:
        for j, v in zip(FINGER_JOINTS, finger):
            values[f"{f}_{j}"] = v
    for name, v in values.items():
        d.qpos[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)]] = v


def finger_effective_mass(
    payload_mjcf: str, design: Design, finger: tuple[float, float, float, float]
) -> float:
    """Smallest effective mass of a fingertip pad along its closing direction (+-y) [kg],
    over the four fingers, at the finger posture ``finger`` (fixed base, home rail and
    stage)."""
    m = mujoco.MjModel.from_xml_path(str(payload_mjcf))
    d = mujoco.MjData(m)
    pose_payload(m, d, finger, design.home.rail, design.home.stage)
    mujoco.mj_forward(m, d)
    masses = []
    for f in FINGERS:
        geom = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{f}_distal_pad")
        if geom < 0:
            raise PayloadError(f"the payload model has no pad geom {f}_distal_pad")
        jac = np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, jac, None, d.geom_xpos[geom], m.geom_bodyid[geom])
        n = np.array([0.0, 1.0 if SIDE_OF[f] == 2 else -1.0, 0.0])  # toward the other side
        row = n @ jac
        minv_row = np.zeros(m.nv)
        mujoco.mj_solveM(m, d, minv_row.reshape(1, -1), row.reshape(1, -1))
        masses.append(1.0 / float(row @ minv_row))
    return min(masses)


def pad_contact(
    design: Design,
    payload_mjcf: str,
    finger: tuple[float, float, float, float],
    cargo_mass: float | None,
    timestep: float,
) -> PadContact:
    """The pad's MuJoCo contact parameters (module docstring for the derivation).

    Args:
        design: The payload design (``finger.pad``).
        payload_mjcf: The generated payload model.
        finger: The finger posture the effective mass is taken at (the pinch pre-shape).
        cargo_mass: Mass of the body the pad lands on [kg] (None: immovable).
        timestep: Physics step [s].
    """
    k, delta0 = pad_stiffness(design)
    m_finger = finger_effective_mass(payload_mjcf, design, finger)
    inv = 1.0 / m_finger + (1.0 / cargo_mass if cargo_mass else 0.0)
    m_eff = 1.0 / inv
    zeta = float(design.finger.pad.damping_ratio)
    dmax = SOLIMP_DMAX
    secant = design.finger.pad.load / delta0  # = k / HERTZ_EXPONENT
    tc = math.sqrt(m_eff / ((1.0 - dmax) * secant)) / zeta
    least = 2.0 * timestep
    clamped = tc < least
    tc = max(tc, least)
    solimp = (_midpoint_dmin(dmax), dmax, delta0, 0.5, 2.0)
    return PadContact(k, delta0, m_eff, tc, zeta, (tc, zeta), solimp, clamped)


__all__ = [
    "HERTZ_EXPONENT",
    "POISSON",
    "SOLIMP_DMAX",
    "PadContact",
    "finger_effective_mass",
    "pad_contact",
    "pad_stiffness",
    "patch_radius",
    "pose_payload",
]
