"""The payload's kinematic tree: links, joints, frames and inertias.

Built once from a :class:`~payload.design.params.Design`; both exporters (URDF and
MJCF) and every summary read this one object, so the models cannot disagree.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Any

import numpy as np

from payload.design.params import FINGER_JOINTS, FINGERS, SIDE_OF, Design, posture_values
from payload.design.servo import joint_servo, kind_of
from payload.design.solids import LinkBody, MassProps, all_bodies, carriage_origin_x, finger_mount

MANIPULATION_JOINTS: tuple[str, ...] = (
    *tuple(f"{f}_{j}" for f in FINGERS for j in FINGER_JOINTS),
    "rail",
)
"""The 17 manipulation coordinates in the paper's order (A, B, C, D joints, then rail)."""

ALL_JOINTS: tuple[str, ...] = (*MANIPULATION_JOINTS, "stage")
"""The 17 manipulation coordinates followed by the deployment coordinate."""


@dataclass(frozen=True)
class Link:
    """A rigid link.

    Attributes:
        name: Link name.
        body: Geometry and mass sources; ``None`` for a massless frame link.
        mass: Mass properties in the link frame.
    """

    name: str
    body: LinkBody | None
    mass: MassProps


@dataclass(frozen=True)
class Joint:
    """A joint between two links.

    Attributes:
        name: Joint name.
        kind: ``revolute``, ``prismatic`` or ``fixed``.
        parent: Parent link name.
        child: Child link name.
        xyz: Joint origin in the parent frame [m].
        rpy: Joint origin rotation (roll, pitch, yaw) [rad].
        axis: Unit axis in the joint (child) frame.
        lower: Lower limit [rad or m].
        upper: Upper limit [rad or m].
        effort: Force or torque limit [N or N m].
        velocity: Speed limit [rad/s or m/s].
        damping: Viscous damping.
        frictionloss: Dry friction.
        armature: Reflected rotor inertia.
        kp: Position-servo stiffness for the actuator.
        kv: Velocity feedback of the actuator (inside its force clamp, unlike ``damping``).
        group: Actuator class: the servo's joint kind (``finger``, ``abduction``, ``rail``,
            ``stage``; :data:`payload.design.servo.JOINT_KINDS`).
    """

    name: str
    kind: str
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    lower: float = 0.0
    upper: float = 0.0
    effort: float = 0.0
    velocity: float = 0.0
    damping: float = 0.0
    frictionloss: float = 0.0
    armature: float = 0.0
    kp: float = 0.0
    kv: float = 0.0
    group: str = ""

    def origin(self) -> np.ndarray:
        """Homogeneous transform parent -> joint frame at q = 0, shape (4, 4) (made once a
        joint: read-only)."""
        return _origin(tuple(self.xyz), tuple(self.rpy))

    def motion(self, q: float) -> np.ndarray:
        """Homogeneous transform of the joint motion by ``q``, shape (4, 4)."""
        ax = np.asarray(self.axis, dtype=float)
        if self.kind == "revolute":
            return homogeneous(axis_angle(ax, q), np.zeros(3))
        if self.kind == "prismatic":
            return homogeneous(np.eye(3), ax * q)
        return np.eye(4)


@dataclass(frozen=True)
class Frame:
    """A named point frame rigidly attached to a link (a fixed child link in URDF, a site in
    MJCF)."""

    name: str
    parent: str
    xyz: tuple[float, float, float]


def rpy_matrix(rpy: tuple[float, float, float]) -> np.ndarray:
    """Rotation matrix of URDF roll-pitch-yaw (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation matrix about the unit ``axis``."""
    k = np.asarray(axis, dtype=float)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


@lru_cache(maxsize=256)
def _origin(xyz: tuple[float, ...], rpy: tuple[float, ...]) -> np.ndarray:
    out = homogeneous(rpy_matrix(rpy), np.asarray(xyz))
    out.setflags(write=False)
    return out


def homogeneous(rot: np.ndarray, pos: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = pos
    return t


@dataclass(frozen=True)
class KinematicTree:
    """Links, joints (parents before children) and named frames of the payload."""

    design: Design
    links: tuple[Link, ...]
    joints: tuple[Joint, ...]
    frames: tuple[Frame, ...]
    root: str = "base"

    @cached_property
    def link_map(self) -> dict[str, Link]:
        return {link.name: link for link in self.links}

    @cached_property
    def joint_map(self) -> dict[str, Joint]:
        return {j.name: j for j in self.joints}

    @property
    def actuated(self) -> tuple[Joint, ...]:
        """The 18 actuated joints: the 17 manipulation joints, then the stage."""
        return tuple(self.joint_map[n] for n in ALL_JOINTS)

    def children(self, link: str) -> list[Joint]:
        return [j for j in self.joints if j.parent == link]

    def total_mass(self) -> float:
        return float(sum(link.mass.mass for link in self.links))

    def link_poses(self, q: Mapping[str, float] | None = None) -> dict[str, np.ndarray]:
        """World (payload-frame) pose of every link for joint values ``q`` (missing = 0).

        Returns:
            Link name -> homogeneous transform, shape (4, 4).
        """
        q = q or {}
        poses = {self.root: np.eye(4)}
        for j in self.joints:
            poses[j.child] = poses[j.parent] @ j.origin() @ j.motion(float(q.get(j.name, 0.0)))
        return poses

    def frame_positions(self, q: Mapping[str, float] | None = None) -> dict[str, np.ndarray]:
        """Payload-frame position of every named frame, shape (3,) each [m]."""
        poses = self.link_poses(q)
        out = {}
        for fr in self.frames:
            out[fr.name] = (poses[fr.parent] @ np.array([*fr.xyz, 1.0]))[:3]
        return out

    def posture(self, name: str) -> dict[str, float]:
        """Joint values of a named design posture (``stowed`` or ``home``)."""
        return posture_values(self.design, name)


def _servo_fields(design: Design, kind: str) -> dict[str, Any]:
    """A joint's servo parameters from the one servo model (:mod:`payload.design.servo`)."""
    js = joint_servo(design, kind)
    return {
        "effort": js.torque_cap,
        "damping": js.damping,
        "frictionloss": js.frictionloss,
        "armature": js.armature,
        "kp": js.kp,
        "kv": js.kv,
        "group": kind,
    }


def build_tree(design: Design) -> KinematicTree:
    """The kinematic tree of ``design`` with inertias from its solids and servos."""
    bodies = all_bodies(design)
    props = {name: body.mass_props() for name, body in bodies.items()}
    f, s, rl, st, mnt = design.finger, design.servo, design.rail, design.stage, design.mounting

    links = [
        Link("base", bodies["base"], props["base"]),
        Link("stage", bodies["stage"], props["stage"]),
        Link("carriage", bodies["carriage"], props["carriage"]),
    ]
    joints = [
        Joint(
            "stage",
            "prismatic",
            "base",
            "stage",
            (0.0, 0.0, -(mnt.plate_thickness + st.stowed_gap + st.plate_thickness)),
            axis=(0.0, 0.0, -1.0),
            lower=0.0,
            upper=st.travel,
            velocity=s.no_load_speed * st.drive_radius,
            **_servo_fields(design, "stage"),
        ),
        Joint(
            "rail",
            "prismatic",
            "stage",
            "carriage",
            (carriage_origin_x(design), 0.0, -rl.height),
            axis=(1.0, 0.0, 0.0),
            lower=0.0,
            upper=rl.travel,
            velocity=s.no_load_speed * rl.drive_radius,
            **_servo_fields(design, "rail"),
        ),
    ]
    frames = []
    L, o = f.lengths, f.offsets
    # child link origin, axis, in the parent finger link frame
    chain = (
        ("mcp_flex", None, (1.0, 0.0, 0.0), "knuckle"),
        ("mcp_abd", (0.0, o.mcp_abd, -L.knuckle), (0.0, 1.0, 0.0), "proximal"),
        ("pip", (0.0, o.pip, -L.proximal), (1.0, 0.0, 0.0), "middle"),
        ("dip", (0.0, o.dip, -L.middle), (1.0, 0.0, 0.0), "distal"),
    )
    for finger in FINGERS:
        parent = "stage" if finger in ("A", "C") else "carriage"
        yaw = np.pi if SIDE_OF[finger] == 1 else 0.0
        for jname, xyz, axis, lname in chain:
            rpy = (0.0, 0.0, 0.0)
            if xyz is None:
                xyz, rpy = finger_mount(design, finger), (0.0, 0.0, yaw)
            lim = f.limit(jname)
            child = f"{finger}_{lname}"
            joints.append(
                Joint(
                    f"{finger}_{jname}",
                    "revolute",
                    parent,
                    child,
                    tuple(float(v) for v in xyz),
                    rpy=rpy,
                    axis=axis,
                    lower=lim.lower,
                    upper=lim.upper,
                    velocity=s.no_load_speed,
                    **_servo_fields(design, kind_of(jname)),
                )
            )
            mesh = f"finger_{lname}"
            links.append(Link(child, bodies[mesh], props[mesh]))
            parent = child
        frames.append(Frame(f"{finger}_distal", f"{finger}_distal", (0.0, 0.0, 0.0)))
        frames.append(Frame(f"{finger}_tip", f"{finger}_distal", (0.0, o.tip, -L.distal)))
    return KinematicTree(design, tuple(links), tuple(joints), tuple(frames))


def load_inertia(tree: KinematicTree, kind: str) -> float:
    """What a servo of ``kind`` moves besides itself at the home posture, in joint units.

    Finger flexion: the finger's links below its MCP flexion about that axis; abduction:
    the links below MCP abduction about its axis [kg m^2]; rail: the carriage and the
    fingers it carries; stage: everything below the mounting plate [kg]. Finger A is
    taken (the four fingers are alike).
    """
    joint = {"finger": "A_mcp_flex", "abduction": "A_mcp_abd"}.get(kind, kind)
    j = tree.joint_map[joint]
    poses = tree.link_poses(tree.posture("home"))
    below = _subtree(tree, j.child)
    if kind in ("rail", "stage"):
        return float(sum(tree.link_map[n].mass.mass for n in below))
    frame = poses[j.child]
    axis = frame[:3, :3] @ np.asarray(j.axis, dtype=float)
    point = frame[:3, 3]
    total = 0.0
    for name in below:
        mp = tree.link_map[name].mass
        if mp.mass <= 0:
            continue
        rot, pos = poses[name][:3, :3], poses[name][:3, 3]
        com = rot @ mp.com + pos
        arm = np.cross(com - point, axis)
        total += float(axis @ (rot @ mp.inertia @ rot.T) @ axis + mp.mass * arm @ arm)
    return total


def _subtree(tree: KinematicTree, link: str) -> list[str]:
    out, stack = [], [link]
    while stack:
        name = stack.pop()
        out.append(name)
        stack += [c.child for c in tree.children(name)]
    return out
