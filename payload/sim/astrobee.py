"""Astrobee in the world: its mass properties, its collision box and the payload mount."""

from __future__ import annotations

import mujoco
import numpy as np

from payload.design import Design
from payload.envelope.vehicle import Vehicle, vehicle_from_dict
from payload.sim.iss import _ASTROBEE_CONAFFINITY, _ASTROBEE_CONTYPE

ASTROBEE_MASS = Vehicle().mass
"""Fallback only: the default vehicle's mass [kg]; the world takes the design's
``vehicle.mass`` (:func:`design_vehicle`)."""

ASTROBEE_INERTIA = Vehicle().inertia
"""Fallback only: the default vehicle's principal inertia [kg m^2]; the world takes the
design's ``vehicle.inertia``."""


def payload_mount(vehicle: Vehicle) -> np.ndarray:
    """Payload frame origin in the Astrobee body frame, shape (3,) [m].

    The payload frame's origin is the top centre of the two lower bays, which reach down to
    the vehicle's bottom face; the Astrobee body frame's origin is the body box's centre. So
    the mount is ``(-body_offset_x, -body_offset_y, -body_size_z / 2 + bay_size_z)``.
    """
    ox, oy = vehicle.body_offset
    return np.array([0.0 - ox, 0.0 - oy, vehicle.bay_size[2] - vehicle.body_size[2] / 2.0])


def design_vehicle(design: Design) -> Vehicle:
    """Astrobee's body and bays from the design's ``[vehicle]`` table (defaults if absent)."""
    return vehicle_from_dict(design.vehicle, source=design.source)


ASTROBEE_SIZE = float(Vehicle().body_size[0])
"""Fallback only: edge of the collision cube of the default vehicle (0.32 m, docs/sources.md). The
world sizes Astrobee's collision box from the design's ``vehicle.body_size``."""

PAYLOAD_MOUNT = tuple(float(v) for v in payload_mount(Vehicle()))
"""Fallback only: :func:`payload_mount` of the default vehicle, (0, 0, -0.06) [m] (the bays
fill the lower 0.10 m of the 0.32 m cube, so -0.16 + 0.10). The world places the payload at
:func:`payload_mount` of the design's ``[vehicle]`` table (:attr:`World.mount`)."""


def _add_astrobee(spec: mujoco.MjSpec, vehicle: Vehicle, pos, quat) -> mujoco.MjsBody:
    body = spec.worldbody.add_body(name="astrobee", pos=list(pos), quat=list(quat))
    body.add_freejoint(name="astrobee")
    body.explicitinertial = True
    body.mass = vehicle.mass
    body.inertia = list(vehicle.inertia)
    body.ipos = [0.0, 0.0, 0.0]
    half = [float(v) / 2.0 for v in vehicle.body_size]
    body.add_geom(
        name="astrobee_collision",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=half,
        contype=_ASTROBEE_CONTYPE,
        conaffinity=_ASTROBEE_CONAFFINITY,
        group=3,
        density=0.0,
        rgba=[0.2, 0.35, 0.8, 0.4],
    )
    body.add_geom(
        name="astrobee_visual",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=[h * 0.98 for h in half],
        contype=0,
        conaffinity=0,
        group=2,
        density=0.0,
        rgba=[0.85, 0.85, 0.88, 1.0],
    )
    body.add_site(name="astrobee", size=[0.01, 0.01, 0.01])
    return body
