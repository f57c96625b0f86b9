"""The Cargo Transfer Bag: its sizes, its handle and its MJCF body."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco

from payload.sim.iss import _CTB_CONAFFINITY, _CTB_CONTYPE


@dataclass(frozen=True)
class CtbSize:
    """A Cargo Transfer Bag size: outer box and loaded mass (docs/sources.md).

    Attributes:
        name: Size name.
        length: Along the vehicle's x [m].
        width: Along the vehicle's y [m].
        height: Along the vehicle's z [m].
        mass: Loaded mass [kg].
    """

    name: str
    length: float
    width: float
    height: float
    mass: float


CTB_SIZES: dict[str, CtbSize] = {
    "half": CtbSize("half", 0.425, 0.248, 0.235, 7.3),
    "single": CtbSize("single", 0.502, 0.425, 0.248, 15.4),
    "double": CtbSize("double", 0.502, 0.425, 0.502, 31.0),
    "rigid": CtbSize("rigid", 0.50, 0.42, 0.25, 5.0),
}
"""The CTB models, in one place: NASA's standard loaded CTB sizes (packing challenge
figures, docs/sources.md) and ``rigid``, the rigid CTB model of Morton et al. 2025 (pyastrobee
config/bag_properties.py: a 50 x 25 x 42 cm compartment of about 5 kg). The rigid bag is
mounted with its 25 cm edge vertical, so its handle face (normal to that edge, like
pyastrobee's front handle) is on top under the fingers, as the single bag's is. Both are
uniform boxes: the inertia is a solid box's of that mass (ASSUMPTION: loaded evenly)."""

CTB_MODELS: tuple[str, ...] = ("single", "rigid")
"""The CTB models the trials choose between (``--ctb``): NASA's loaded single CTB and the
rigid CTB of the cited work; which one the paper used is not stated."""

DEFAULT_CTB = "single"
"""The trials' default CTB model."""


@dataclass(frozen=True)
class Handle:
    """The CTB's carry handle: a bar along x on two posts standing off the top face.

    Stands in for the soft strap handle (a stiffened strap the fingertips pinch from both
    sides of the array). All [m].
    """

    length: float = 0.24
    width: float = 0.02
    height: float = 0.03
    standoff: float = 0.03
    post: float = 0.02


def _add_ctb(spec: mujoco.MjSpec, size: CtbSize, handle: Handle, friction: float, pos, quat):
    body = spec.worldbody.add_body(name="ctb", pos=list(pos), quat=list(quat))
    body.add_freejoint(name="ctb")
    body.explicitinertial = True
    body.mass = size.mass
    a, b, c = size.length, size.width, size.height
    body.inertia = [
        size.mass * (b * b + c * c) / 12.0,
        size.mass * (a * a + c * c) / 12.0,
        size.mass * (a * a + b * b) / 12.0,
    ]
    body.ipos = [0.0, 0.0, 0.0]
    common = dict(
        type=mujoco.mjtGeom.mjGEOM_BOX,
        contype=_CTB_CONTYPE,
        conaffinity=_CTB_CONAFFINITY,
        friction=[friction, 0.005, 0.0001],
        density=0.0,
    )
    body.add_geom(name="ctb_bag", size=[a / 2, b / 2, c / 2], rgba=[0.9, 0.9, 0.82, 1.0], **common)
    top = c / 2.0
    bar_z = top + handle.standoff + handle.height / 2.0
    body.add_geom(
        name="ctb_handle",
        pos=[0.0, 0.0, bar_z],
        size=[handle.length / 2, handle.width / 2, handle.height / 2],
        rgba=[0.25, 0.3, 0.45, 1.0],
        **common,
    )
    for i, sx in enumerate((-1.0, 1.0)):
        body.add_geom(
            name=f"ctb_handle_post{i}",
            pos=[sx * (handle.length - handle.post) / 2, 0.0, top + handle.standoff / 2],
            size=[handle.post / 2, handle.width / 2, handle.standoff / 2],
            rgba=[0.25, 0.3, 0.45, 1.0],
            **common,
        )
    body.add_site(name="ctb", size=[0.01, 0.01, 0.01])
    body.add_site(name="ctb_handle", pos=[0.0, 0.0, bar_z], size=[0.005, 0.005, 0.005])
    return body
