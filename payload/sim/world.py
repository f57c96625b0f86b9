"""The zero-gravity ISS world: Kibo, the hatch vestibule, Node 2, Astrobee, the payload, a CTB.

World frame (REP-103 style, ISS analysis axes turned to y-left): origin at the centre of
Node 2 (Harmony), x forward along Node 2's axis, y to port, z to zenith. Kibo berths on
Node 2's port side, so Kibo's long axis runs along +y.

Every interior is an axis-aligned box of open space bounded by rack faces (thin collision
boxes) with handrails standing off them; the hatch vestibule is a square tube joining
Node 2's port rack face to Kibo's forward rack face. Figures come from
``docs/sources.md``; where a figure is not published the default is marked ASSUMPTION.

The payload MJCF (``urdf/payload.xml``, generated from ``cad/design.toml``) is attached
under the Astrobee body with the name prefix :data:`PAYLOAD_PREFIX`, so its names stay
recognisable (``payload/A_tip``, ``payload/rail``). Its actuators keep the force limits of
the generated model (XC330 torque at the hardware current cap); :func:`build_world`
refuses a model whose limits disagree with the design.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import mujoco
import numpy as np

from payload.design import (
    FINGER_JOINTS,
    FINGERS,
    MANIPULATION_JOINTS,
    SIDE_OF,
    Design,
    load_design,
)
from payload.envelope.vehicle import Vehicle, vehicle_from_dict
from payload.errors import PayloadError
from payload.project import Project, current_project, project_of
from payload.rotations import yaw_quat
from payload.schema import CONTROL_DT as SCHEMA_CONTROL_DT
from payload.sim.pads import pad_contact

PAYLOAD_PREFIX = "payload/"
"""Prefix of every payload element name in the world (``payload/A_tip``)."""

PHYSICS_DT = 0.001
"""Physics time step [s] (1 kHz)."""

CONTROL_DT = SCHEMA_CONTROL_DT
"""Control period [s] (50 Hz)."""

SUBSTEPS = round(CONTROL_DT / PHYSICS_DT)
"""Physics steps per control step (20)."""

ASTROBEE_MASS = 9.5838
"""Astrobee mass without payloads, four batteries [kg] (docs/sources.md)."""

ASTROBEE_INERTIA = (0.15343, 0.14271, 0.16230)
"""Astrobee principal inertia about its centre of mass [kg m^2] (docs/sources.md)."""


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

# Collision bits. The payload MJCF uses contype 1 (fingers) and 2 (structure), conaffinity 1.
_ISS_CONTYPE, _ISS_CONAFFINITY = 4, 1 | 2
_ASTROBEE_CONTYPE, _ASTROBEE_CONAFFINITY = 8, 4  # walls only: the payload sits inside it
_CTB_CONTYPE, _CTB_CONAFFINITY = 16, 1 | 2 | 4 | 8


class SimError(PayloadError):
    """The simulated world cannot be built or driven as asked."""


class IssModule(str, enum.Enum):
    """Where a point is: one of the modules along the cargo route."""

    KIBO = "kibo"
    VESTIBULE = "vestibule"
    NODE2 = "node2"


class Zone(NamedTuple):
    """An axis-aligned box of open interior, world frame [m]."""

    module: IssModule
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def contains(self, point: Sequence[float]) -> bool:
        """True when ``point`` (3,) [m] lies inside the box (boundary included)."""
        return all(self.lo[i] <= float(point[i]) <= self.hi[i] for i in range(3))

    @property
    def centre(self) -> np.ndarray:
        """Centre of the box, shape (3,) [m]."""
        return (np.asarray(self.lo) + np.asarray(self.hi)) / 2.0

    @property
    def size(self) -> np.ndarray:
        """Extent along x, y, z, shape (3,) [m]."""
        return np.asarray(self.hi) - np.asarray(self.lo)


@dataclass(frozen=True)
class IssLayout:
    """Dimensions of the route's three volumes (world frame, metres).

    Attributes:
        kibo_width: Kibo open interior across its axis, along x (docs/sources.md: 1.7 m).
        kibo_height: Kibo open interior, along z (docs/sources.md: 2.0 m).
        kibo_length: Kibo open interior along its axis, y (docs/sources.md: 7.3 m).
        node2_length: Node 2 open interior along its axis, x. ASSUMPTION: 6.0 m of the
            7.2 m module (end cones excluded).
        node2_width: Node 2 open interior between rack faces, along y and z. ASSUMPTION:
            2.0 m, Kibo's figure (rack depth is common to the pressurised modules).
        module_diameter: Outer diameter of Node 2 (docs/sources.md: 4.4 m); sets how far the port
            rack face stands from the hull.
        hatch: Edge of the square common hatch (docs/sources.md: 1.3 m).
        vestibule_length: Length of the berthing vestibule (docs/sources.md: 0.4 m).
        kibo_endcone: Kibo's forward bulkhead to its first rack face. ASSUMPTION: 0.6 m.
        hatch_x: x of the Kibo hatch centre on Node 2. ASSUMPTION: 1.5 m (radial ports
            toward the forward end of Node 2).
        wall: Thickness of the rack-face collision slabs.
        handrail_section: Square section of a handrail.
        handrail_length: Length of a handrail.
        handrail_standoff: Rack face to handrail centre line.
        handrail_pitch: Spacing of handrails along a module (about one rack bay).
        route_height: z of the Astrobee centre along the route: puts the vehicle, payload
            and CTB stack (+0.16 m to about -0.65 m) in the middle of the 1.3 m hatch.
        route_start_depth: How far into Kibo (from its forward rack face) the route starts.
        route_aft: Distance travelled aft along Node 2 after the turn.
    """

    kibo_width: float = 1.7
    kibo_height: float = 2.0
    kibo_length: float = 7.3
    node2_length: float = 6.0
    node2_width: float = 2.0
    module_diameter: float = 4.4
    hatch: float = 1.3
    vestibule_length: float = 0.4
    kibo_endcone: float = 0.6
    hatch_x: float = 1.5
    wall: float = 0.1
    handrail_section: float = 0.025
    handrail_length: float = 0.5
    handrail_standoff: float = 0.06
    handrail_pitch: float = 1.2
    route_height: float = 0.25
    route_start_depth: float = 3.8
    route_aft: float = 2.0

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if name == "hatch_x":
                continue
            if not (math.isfinite(value) and value > 0.0):
                raise SimError(f"IssLayout.{name}: must be a positive number, got {value!r}")
        half = self.hatch / 2.0
        if half > min(self.kibo_width, self.kibo_height, self.node2_width) / 2.0:
            raise SimError("IssLayout.hatch: the hatch is larger than a module cross-section")
        if abs(self.hatch_x) + half > self.node2_length / 2.0:
            raise SimError("IssLayout.hatch_x: the hatch does not fit on Node 2's port face")
        if not self.route_start_depth < self.kibo_length:
            raise SimError("IssLayout.route_start_depth: the start lies beyond Kibo's end")
        if self.route_aft > self.node2_length / 2.0 + self.hatch_x:
            raise SimError("IssLayout.route_aft: the route ends beyond Node 2's aft end")

    # -- volumes -------------------------------------------------------------------------
    @property
    def node2(self) -> Zone:
        """Node 2 open interior."""
        hx, hw = self.node2_length / 2.0, self.node2_width / 2.0
        return Zone(IssModule.NODE2, (-hx, -hw, -hw), (hx, hw, hw))

    @property
    def vestibule(self) -> Zone:
        """The passage from Node 2's port rack face through the hatch and vestibule to Kibo."""
        half = self.hatch / 2.0
        y0 = self.node2_width / 2.0
        y1 = self.module_diameter / 2.0 + self.vestibule_length + self.kibo_endcone
        return Zone(
            IssModule.VESTIBULE, (self.hatch_x - half, y0, -half), (self.hatch_x + half, y1, half)
        )

    @property
    def kibo(self) -> Zone:
        """Kibo (JEM pressurised module) open interior between its racks."""
        y0 = self.vestibule.hi[1]
        hw, hh = self.kibo_width / 2.0, self.kibo_height / 2.0
        return Zone(
            IssModule.KIBO,
            (self.hatch_x - hw, y0, -hh),
            (self.hatch_x + hw, y0 + self.kibo_length, hh),
        )

    def zones(self) -> tuple[Zone, Zone, Zone]:
        """Kibo, vestibule, Node 2, in route order."""
        return (self.kibo, self.vestibule, self.node2)

    def module_at(self, point: Sequence[float]) -> IssModule | None:
        """The module containing ``point`` (3,) [m, world frame], or None outside all three.

        The vestibule wins on its shared faces with the modules (a point on the hatch
        plane counts as in the hatch).
        """
        kibo, vest, node2 = self.zones()
        for zone in (vest, kibo, node2):
            if zone.contains(point):
                return zone.module
        return None

    # -- route ----------------------------------------------------------------------------
    def route(self) -> np.ndarray:
        """Waypoints of the cargo route, shape (3, 3) [m]: start in Kibo, the turn on
        Node 2's axis in front of the hatch, the end aft in Node 2."""
        z = self.route_height
        start = (self.hatch_x, self.kibo.lo[1] + self.route_start_depth, z)
        turn = (self.hatch_x, 0.0, z)
        end = (self.hatch_x - self.route_aft, 0.0, z)
        return np.array([start, turn, end], dtype=float)

    def route_length(self) -> float:
        """Length of the route polyline [m]."""
        return float(np.sum(np.linalg.norm(np.diff(self.route(), axis=0), axis=1)))

    def start_yaw(self) -> float:
        """Heading of the first route leg [rad] (Astrobee's x along the route)."""
        d = np.diff(self.route()[:2], axis=0)[0]
        return float(math.atan2(d[1], d[0]))


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


PINCH_OPEN = (-0.30, 0.0, 0.0, 0.90)
"""Finger pre-shape for the handle pinch (mcp_flex, mcp_abd, pip, dip) [rad]: MCP flexion
opened near its lower limit, the distal link curled toward the handle so the fingertip pad
faces it; the handle is centred on the four fingertips of this posture."""

PINCH_CLEARANCE = 0.005
"""Least gap between the pads and the handle at the pre-shape [m]; a design that leaves
less makes :func:`pinch_grasp` refuse."""

PINCH_SQUEEZE = 0.05
"""MCP flexion commanded past first contact for the pinch [rad]: with kp = 3 N m/rad this
asks 0.15 N m, 83 % of the current-capped torque. Unsaturated fingers act as springs, which
lets the handle settle under the yaw couple of the staggered opposing fingers (A/C and B/D
are offset along x); saturated fingers push equally and the handle keeps yawing."""


class PinchGrasp(NamedTuple):
    """The scripted handle pinch, derived from the design and the handle.

    Attributes:
        open: Pre-shape (mcp_flex, mcp_abd, pip, dip) for every finger [rad].
        closed: Closing command for every finger [rad].
        contact_mcp: MCP flexion at which the pads first touch the handle [rad].
        rail: Rail position of the grasp [m].
        stage: Deployment of the grasp [m].
    """

    open: tuple[float, float, float, float]
    closed: tuple[float, float, float, float]
    contact_mcp: float
    rail: float
    stage: float

    def command_q(self, closed: bool) -> np.ndarray:
        """The 17 manipulation coordinates (paper order) for the open or closed pinch."""
        finger = self.closed if closed else self.open
        return np.array([*finger * len(FINGERS), self.rail])


@dataclass(frozen=True)
class WorldConfig:
    """What to put in the world.

    Attributes:
        ctb: CTB size name (``half``, ``single``, ``double``) or None for no CTB.
        ctb_mass: Override of the CTB mass [kg]; None keeps the size's loaded mass.
        handle: CTB handle geometry.
        layout: ISS volumes and route.
        payload_mjcf: The payload MJCF to attach (its meshdir is relative to the file).
            ``None``: the ``urdf/payload.xml`` of the project holding ``design``, or of
            the current project.
        design: The design file the payload was generated from. ``None``: the design of
            the project holding ``payload_mjcf``, or of the current project. Both are
            concrete paths once the config is made; :meth:`for_project` sets both.
        cone: Friction cone, ``elliptic`` or ``pyramidal``.
        impratio: Ratio of frictional to normal impedance (elliptic cones).
        pads: ``silicone`` (default: the pad contact's solref/solimp derived from the
            design's pad material, :mod:`payload.sim.pads`) or ``mujoco`` (MuJoCo's
            default contact parameters, the earlier model, for comparison).
    """

    ctb: str | None = "single"
    ctb_mass: float | None = None
    handle: Handle = field(default_factory=Handle)
    layout: IssLayout = field(default_factory=IssLayout)
    payload_mjcf: Path | None = None
    design: Path | None = None
    cone: str = "elliptic"
    impratio: float = 10.0
    pads: str = "silicone"

    @classmethod
    def for_project(cls, project: Project, **kwargs: Any) -> WorldConfig:
        """The world of ``project``: its generated MJCF and its design file."""
        return cls(payload_mjcf=project.mjcf, design=project.design_path, **kwargs)

    def __post_init__(self) -> None:
        if self.payload_mjcf is None or self.design is None:
            known = self.design if self.design is not None else self.payload_mjcf
            project = (project_of(known) if known is not None else None) or current_project()
            if self.payload_mjcf is None:
                object.__setattr__(self, "payload_mjcf", project.mjcf)
            if self.design is None:
                object.__setattr__(self, "design", project.design_path)
        if self.pads not in ("silicone", "mujoco"):
            raise SimError(f"WorldConfig.pads: {self.pads!r} is not 'silicone' or 'mujoco'")
        if self.ctb is not None and self.ctb not in CTB_SIZES:
            raise SimError(
                f"WorldConfig.ctb: unknown CTB size {self.ctb!r} "
                f"(expected one of {', '.join(CTB_SIZES)} or None)"
            )
        if self.ctb_mass is not None and not (math.isfinite(self.ctb_mass) and self.ctb_mass > 0.0):
            raise SimError(f"WorldConfig.ctb_mass: must be a positive mass, got {self.ctb_mass}")
        if self.cone not in ("elliptic", "pyramidal"):
            raise SimError(f"WorldConfig.cone: {self.cone!r} is not 'elliptic' or 'pyramidal'")
        if not (math.isfinite(self.impratio) and self.impratio >= 1.0):
            raise SimError(f"WorldConfig.impratio: must be >= 1, got {self.impratio}")

    @property
    def ctb_size(self) -> CtbSize | None:
        """The CTB size with the mass override applied, or None."""
        if self.ctb is None:
            return None
        size = CTB_SIZES[self.ctb]
        if self.ctb_mass is None:
            return size
        return CtbSize(size.name, size.length, size.width, size.height, float(self.ctb_mass))


@dataclass(frozen=True)
class World:
    """A compiled world and the indices everything else needs.

    Attributes:
        model: The compiled MuJoCo model.
        spec: The MjSpec it was compiled from (``spec.to_xml()`` gives the MJCF).
        config: What was built.
        design: The payload design.
        ctrl: Actuator ids of the 17 manipulation coordinates in the paper's order, (17,).
        stage_ctrl: Actuator id of the stage.
        qpos: qpos addresses of the 17 manipulation joints, (17,).
        stage_qpos: qpos address of the stage joint.
        dof: dof addresses of the 17 manipulation joints, (17,).
        stage_dof: dof address of the stage joint.
        astrobee: Body id of Astrobee.
        astrobee_qpos: qpos address of Astrobee's free joint (7 values: pos, quat wxyz).
        astrobee_dof: dof address of Astrobee's free joint (6 values).
        ctb: Body id of the CTB, -1 without one.
        ctb_qpos: qpos address of the CTB free joint, -1 without one.
        ctb_dof: dof address of the CTB free joint, -1 without one.
        pad_geoms: Fingertip pad geom id per finger.
        distal_geoms: Every collision geom of each finger's distal link.
        ctb_geoms: Collision geoms of the CTB.
        iss_geoms: Collision geoms of the ISS interior.
        force_limit: Actuator force bound of the 18 payload actuators (17 + stage) [N m, N].
        slew_rate: Servo speed bound of the 18 payload actuators (17 + stage) [rad/s, m/s].
        pinch: The scripted handle pinch for this design and handle.
        vehicle: Astrobee's body and bays, from the design's ``[vehicle]`` table.
    """

    model: mujoco.MjModel
    spec: mujoco.MjSpec
    config: WorldConfig
    design: Design
    ctrl: np.ndarray
    stage_ctrl: int
    qpos: np.ndarray
    stage_qpos: int
    dof: np.ndarray
    stage_dof: int
    astrobee: int
    astrobee_qpos: int
    astrobee_dof: int
    ctb: int
    ctb_qpos: int
    ctb_dof: int
    pad_geoms: dict[str, int]
    distal_geoms: dict[str, tuple[int, ...]]
    ctb_geoms: tuple[int, ...]
    iss_geoms: tuple[int, ...]
    force_limit: np.ndarray
    slew_rate: np.ndarray
    pinch: PinchGrasp
    vehicle: Vehicle = field(default_factory=Vehicle)

    @property
    def mount(self) -> np.ndarray:
        """Payload frame origin in the Astrobee body frame, shape (3,) [m]."""
        return payload_mount(self.vehicle)

    @property
    def layout(self) -> IssLayout:
        """The ISS layout."""
        return self.config.layout

    @property
    def ctrl_all(self) -> np.ndarray:
        """Actuator ids of the 17 coordinates then the stage, (18,)."""
        return np.append(self.ctrl, self.stage_ctrl)

    @property
    def qpos_all(self) -> np.ndarray:
        """qpos addresses of the 17 coordinates then the stage, (18,)."""
        return np.append(self.qpos, self.stage_qpos)

    def name(self, obj: mujoco.mjtObj, index: int) -> str:
        """Name of a model element (``mujoco.mjtObj.mjOBJ_GEOM``, id) or ``#id`` if unnamed."""
        return mujoco.mj_id2name(self.model, obj, index) or f"#{index}"

    def module_at(self, point: Sequence[float]) -> IssModule | None:
        """Which ISS module contains ``point`` (3,) [m, world frame]; see IssLayout."""
        return self.layout.module_at(point)

    def make_data(self, keyframe: str = "home") -> mujoco.MjData:
        """Fresh data reset to a keyframe (``home``: deployed, ``stowed``)."""
        key = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_KEY, keyframe)
        if key < 0:
            raise SimError(f"unknown keyframe {keyframe!r} (expected 'home' or 'stowed')")
        data = mujoco.MjData(self.model)
        mujoco.mj_resetDataKeyframe(self.model, data, key)
        mujoco.mj_forward(self.model, data)
        return data


def servo_limits(design: Design) -> tuple[np.ndarray, np.ndarray]:
    """Force and speed bounds of the 18 payload servos from the design.

    Finger joints: the XC330 torque at the hardware current cap and its no-load speed.
    Rail and stage: the same through their pinions (force = torque / r, speed = omega r).

    Args:
        design: The payload design.

    Returns:
        ``(force, speed)``, each shape (18,) in the order of MANIPULATION_JOINTS then stage
        [N m or N; rad/s or m/s].
    """
    servo = design.servo
    torque, omega = servo.torque_limit, servo.no_load_speed
    force, speed = [], []
    for name in (*MANIPULATION_JOINTS, "stage"):
        if name in ("rail", "stage"):
            r = design.rail.drive_radius if name == "rail" else design.stage.drive_radius
            force.append(torque / r)
            speed.append(omega * r)
        else:
            force.append(torque)
            speed.append(omega)
    return np.array(force), np.array(speed)


# -- building ---------------------------------------------------------------------------------
def _box(body: mujoco.MjsBody, default: mujoco.MjsDefault, name: str, lo, hi) -> None:
    """A box ``lo``..``hi`` [m, world frame] in a static body at the world origin."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    body.add_geom(
        default=default,
        name=name,
        type=mujoco.mjtGeom.mjGEOM_BOX,
        pos=((lo + hi) / 2.0).tolist(),
        size=((hi - lo) / 2.0).tolist(),
    )


def _face_slabs(zone: Zone, axis: int, side: int, wall: float, hole: Zone | None):
    """Slabs closing one face of ``zone`` (axis 0..2, side 0 = lo, 1 = hi), minus a hole."""
    lo = np.array(zone.lo, float) - wall
    hi = np.array(zone.hi, float) + wall
    if side == 0:
        lo[axis], hi[axis] = zone.lo[axis] - wall, zone.lo[axis]
    else:
        lo[axis], hi[axis] = zone.hi[axis], zone.hi[axis] + wall
    if hole is None:
        return [(lo, hi)]
    u, v = [a for a in range(3) if a != axis]
    slabs = []
    # strips below and above the hole along u (full v extent), then left/right along v
    for a, b in ((lo[u], hole.lo[u]), (hole.hi[u], hi[u])):
        if b - a > 1e-9:
            s_lo, s_hi = lo.copy(), hi.copy()
            s_lo[u], s_hi[u] = a, b
            slabs.append((s_lo, s_hi))
    for a, b in ((lo[v], hole.lo[v]), (hole.hi[v], hi[v])):
        if b - a > 1e-9:
            s_lo, s_hi = lo.copy(), hi.copy()
            s_lo[u], s_hi[u] = hole.lo[u], hole.hi[u]
            s_lo[v], s_hi[v] = a, b
            slabs.append((s_lo, s_hi))
    return slabs


def _handrails(zone: Zone, along: int, layout: IssLayout, hole: Zone | None):
    """Handrails on the four long faces of ``zone``, running along axis ``along``."""
    rails = []
    half_len = layout.handrail_length / 2.0
    half_sec = layout.handrail_section / 2.0
    n = max(1, int(zone.size[along] // layout.handrail_pitch))
    first = zone.lo[along] + (zone.size[along] - (n - 1) * layout.handrail_pitch) / 2.0
    for axis in (a for a in range(3) if a != along):
        other = 3 - along - axis
        for side in (0, 1):
            face = zone.lo[axis] if side == 0 else zone.hi[axis]
            offset = layout.handrail_standoff if side == 0 else -layout.handrail_standoff
            for k in range(n):
                c = np.zeros(3)
                c[along] = first + k * layout.handrail_pitch
                c[axis] = face + offset
                c[other] = zone.centre[other]
                half = np.full(3, half_sec)
                half[along] = half_len
                if hole is not None and axis == 1 and side == 1:
                    # the port face: no handrail across the hatch opening
                    margin = 0.05
                    if (
                        c[along] + half_len > hole.lo[along] - margin
                        and c[along] - half_len < hole.hi[along] + margin
                    ):
                        continue
                rails.append((axis, side, c - half, c + half))
    return rails


def _add_iss(spec: mujoco.MjSpec, layout: IssLayout) -> None:
    wall = spec.add_default("iss_wall", spec.default)
    wall.geom.contype, wall.geom.conaffinity = _ISS_CONTYPE, _ISS_CONAFFINITY
    wall.geom.rgba = [0.82, 0.82, 0.78, 0.25]
    wall.geom.group = 1
    wall.geom.density = 0.0  # static: mass would only pollute whole-world mass totals
    rail = spec.add_default("iss_handrail", spec.default)
    rail.geom.contype, rail.geom.conaffinity = _ISS_CONTYPE, _ISS_CONAFFINITY
    rail.geom.rgba = [0.9, 0.75, 0.2, 1.0]
    rail.geom.group = 1
    rail.geom.density = 0.0
    world = spec.worldbody
    kibo, vest, node2 = layout.zones()
    t = layout.wall
    # One static body per module face (rack-face slabs and their handrails): each gets its
    # own bounding box in the broad phase, so a vehicle in mid-module is tested against no
    # ISS geom at all (a single world body would cost about a third of the step time).
    faces: dict[str, mujoco.MjsBody] = {}

    def face(name: str) -> mujoco.MjsBody:
        if name not in faces:
            faces[name] = world.add_body(name=name)
        return faces[name]

    openings = {("kibo", 1, 0): vest, ("node2", 1, 1): vest}  # the hatch passage
    for zone, key in ((kibo, "kibo"), (node2, "node2")):
        for axis in range(3):
            for side in (0, 1):
                body = face(f"{key}_{'xyz'[axis]}{side}")
                hole = openings.get((key, axis, side))
                for i, (lo, hi) in enumerate(_face_slabs(zone, axis, side, t, hole)):
                    _box(body, wall, f"{key}_wall_{'xyz'[axis]}{side}_{i}", lo, hi)
    # Vestibule: a square tube along y (faces x and z only), ending flush with the rack
    # faces of the two modules (whose slabs frame the opening).
    for axis in (0, 2):
        for side in (0, 1):
            (lo, hi) = _face_slabs(vest, axis, side, t, None)[0]
            lo[1], hi[1] = vest.lo[1], vest.hi[1]
            name = f"vestibule_{'xyz'[axis]}{side}"
            _box(face(name), wall, f"vestibule_wall_{'xyz'[axis]}{side}", lo, hi)
    for zone, key, along, hole in ((kibo, "kibo", 1, None), (node2, "node2", 0, vest)):
        for i, (axis, side, lo, hi) in enumerate(_handrails(zone, along, layout, hole)):
            _box(face(f"{key}_{'xyz'[axis]}{side}"), rail, f"{key}_handrail_{i}", lo, hi)
    world.add_light(pos=[layout.hatch_x, 0.0, 0.9], dir=[0, 0, -1])
    world.add_light(pos=[layout.hatch_x, layout.kibo.centre[1], 0.9], dir=[0, 0, -1])


def _add_astrobee(spec: mujoco.MjSpec, vehicle: Vehicle, pos, quat) -> mujoco.MjsBody:
    body = spec.worldbody.add_body(name="astrobee", pos=list(pos), quat=list(quat))
    body.add_freejoint(name="astrobee")
    body.explicitinertial = True
    body.mass = ASTROBEE_MASS
    body.inertia = list(ASTROBEE_INERTIA)
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


class _PayloadKinematics:
    """Forward kinematics of the payload model alone (payload frame)."""

    def __init__(self, payload_mjcf: Path) -> None:
        self.model = mujoco.MjModel.from_xml_path(str(payload_mjcf))
        self.data = mujoco.MjData(self.model)

    def tips(self, finger: Sequence[float], rail: float, stage: float) -> np.ndarray:
        """Fingertip points of A, B, C, D, shape (4, 3) [m], all fingers at ``finger``."""
        m, d = self.model, self.data
        values = {"rail": rail, "stage": stage}
        for f in FINGERS:
            for j, v in zip(FINGER_JOINTS, finger):
                values[f"{f}_{j}"] = v
        for name, v in values.items():
            d.qpos[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)]] = v
        mujoco.mj_kinematics(m, d)
        return np.array(
            [
                d.site_xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{f}_tip")]
                for f in FINGERS
            ]
        )


def pinch_grasp(design: Design, config: WorldConfig) -> PinchGrasp:
    """The handle pinch for this design and handle.

    The first-contact MCP flexion solves ``|y_tip| - r_pad = w_handle / 2`` (pad sphere on
    the handle's side face) by bisection on the payload model's kinematics; the closing
    command adds :data:`PINCH_SQUEEZE`.

    Raises:
        SimError: The pads cannot reach the handle from the pre-shape.
    """
    kin = _PayloadKinematics(config.payload_mjcf)
    rail, stage = design.home.rail, design.home.stage
    face = config.handle.width / 2.0 + design.finger.pad.radius

    side = np.array([1.0 if SIDE_OF[f] == 1 else -1.0 for f in FINGERS])  # +y is side 1

    def gap(mcp: float) -> float:
        tips = kin.tips((mcp, *PINCH_OPEN[1:]), rail, stage)
        return float(np.min(side * tips[:, 1])) - face

    # search the first 0.6 rad of closing: the pads cross the array's mid-plane within it
    lo = PINCH_OPEN[0]
    hi = min(lo + 0.6, design.finger.limits.mcp_flex.upper)
    if gap(lo) < PINCH_CLEARANCE:
        raise SimError(
            f"pinch_grasp: the pre-shape leaves {gap(lo) * 1e3:.1f} mm between the pads and "
            f"the handle, less than {PINCH_CLEARANCE * 1e3:.0f} mm (handle too wide?)"
        )
    if gap(hi) > 0.0:
        raise SimError("pinch_grasp: the fingertips cannot reach the handle")
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if gap(mid) > 0.0 else (lo, mid)
    contact = 0.5 * (lo + hi)
    closed = (contact + PINCH_SQUEEZE, *PINCH_OPEN[1:])
    return PinchGrasp(PINCH_OPEN, closed, contact, rail, stage)


def ctb_offset(design: Design, config: WorldConfig) -> np.ndarray:
    """Where the CTB centre starts in the Astrobee body frame, shape (3,) [m].

    The handle bar is centred on the four fingertips at the pinch pre-shape (deployed stage,
    home rail), so closing the fingers pinches it from both sides of the array.
    """
    size = config.ctb_size
    if size is None:
        raise SimError("ctb_offset: the world has no CTB")
    kin = _PayloadKinematics(config.payload_mjcf)
    tips = kin.tips(PINCH_OPEN, design.home.rail, design.home.stage)
    tips = tips + payload_mount(design_vehicle(design))
    centre = tips.mean(axis=0)
    h = config.handle
    drop = h.height / 2.0 + h.standoff + size.height / 2.0
    return np.array([centre[0], centre[1], centre[2] - drop])


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


def build_spec(config: WorldConfig | None = None, design: Design | None = None) -> mujoco.MjSpec:
    """The world as an MjSpec (not compiled, no keyframes).

    Args:
        config: What to build (default: single CTB, default layout).
        design: The payload design (default: loaded from ``config.design``).

    Returns:
        The spec; ``build_world`` compiles it and adds the keyframes.
    """
    config = config or WorldConfig()
    design = design or load_design(config.design)
    if not Path(config.payload_mjcf).is_file():
        raise SimError(f"payload model {config.payload_mjcf} not found; run `payload build`")
    spec = mujoco.MjSpec()
    spec.modelname = "iss_astrobee_payload"
    spec.option.timestep = PHYSICS_DT
    spec.option.gravity = [0.0, 0.0, 0.0]
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = (
        mujoco.mjtCone.mjCONE_ELLIPTIC
        if config.cone == "elliptic"
        else mujoco.mjtCone.mjCONE_PYRAMIDAL
    )
    spec.option.impratio = config.impratio
    spec.compiler.autolimits = True
    spec.stat.extent = 3.0
    spec.stat.center = [config.layout.hatch_x, 2.0, 0.0]

    layout = config.layout
    _add_iss(spec, layout)
    start = layout.route()[0]
    quat = yaw_quat(layout.start_yaw())
    vehicle = design_vehicle(design)
    astrobee = _add_astrobee(spec, vehicle, start, quat)

    child = mujoco.MjSpec.from_file(str(config.payload_mjcf))
    # the parent's options rule; match them so the attach reports no conflict
    frame = astrobee.add_frame(pos=payload_mount(vehicle).tolist())
    frame.attach_body(child.body("base"), PAYLOAD_PREFIX, "")
    for key in list(spec.keys):
        spec.delete(key)

    size = config.ctb_size
    if config.pads == "silicone":
        contact = pad_contact(
            design,
            str(config.payload_mjcf),
            PINCH_OPEN,
            size.mass if size is not None else None,
            PHYSICS_DT,
        )
        for f in FINGERS:
            geom = spec.geom(f"{PAYLOAD_PREFIX}{f}_distal_pad")
            geom.solref = list(contact.solref)
            geom.solimp = list(contact.solimp)
    if size is not None:
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, quat)
        pos = start + rot.reshape(3, 3) @ ctb_offset(design, config)
        _add_ctb(spec, size, config.handle, design.finger.pad.friction, pos, quat)
    return spec


def _check_servo_limits(world_model: mujoco.MjModel, ctrl: np.ndarray, design: Design) -> None:
    force, _ = servo_limits(design)
    got = world_model.actuator_forcerange[ctrl]
    names = (*MANIPULATION_JOINTS, "stage")
    for i, name in enumerate(names):
        if not world_model.actuator_forcelimited[ctrl[i]]:
            raise SimError(f"actuator {name}: not force-limited in the payload MJCF")
        if not np.allclose(got[i], (-force[i], force[i]), rtol=1e-6, atol=1e-9):
            raise SimError(
                f"actuator {name}: force range {got[i].tolist()} differs from the servo limit "
                f"+-{force[i]:.6g} of the design; run `payload build`"
            )


def build_world(config: WorldConfig | None = None, design: Design | None = None) -> World:
    """Build and compile the world, with keyframes ``home`` (deployed) and ``stowed``.

    Args:
        config: What to build (default: single CTB, default layout).
        design: The payload design (default: loaded from ``config.design``).

    Returns:
        The compiled :class:`World`.

    Raises:
        SimError: Bad configuration, missing or stale payload model.
    """
    config = config or WorldConfig()
    design = design or load_design(config.design)
    spec = build_spec(config, design)
    try:
        model = spec.compile()
    except ValueError as exc:  # MuJoCo reports compile errors as ValueError
        raise SimError(f"the world does not compile: {exc}") from exc

    def idx(obj: mujoco.mjtObj, name: str) -> int:
        i = mujoco.mj_name2id(model, obj, name)
        if i < 0:
            raise SimError(f"the payload model has no {obj.name[6:].lower()} {name!r}")
        return i

    act = mujoco.mjtObj.mjOBJ_ACTUATOR
    jnt = mujoco.mjtObj.mjOBJ_JOINT
    ctrl = np.array([idx(act, PAYLOAD_PREFIX + n) for n in MANIPULATION_JOINTS])
    stage_ctrl = idx(act, PAYLOAD_PREFIX + "stage")
    joints = [idx(jnt, PAYLOAD_PREFIX + n) for n in MANIPULATION_JOINTS]
    stage_joint = idx(jnt, PAYLOAD_PREFIX + "stage")
    _check_servo_limits(model, np.append(ctrl, stage_ctrl), design)
    body = mujoco.mjtObj.mjOBJ_BODY
    geom = mujoco.mjtObj.mjOBJ_GEOM
    astrobee = idx(body, "astrobee")
    ctb = mujoco.mj_name2id(model, body, "ctb")
    pad_geoms = {f: idx(geom, f"{PAYLOAD_PREFIX}{f}_distal_pad") for f in FINGERS}
    distal_geoms = {}
    for f in FINGERS:
        b = idx(body, f"{PAYLOAD_PREFIX}{f}_distal")
        distal_geoms[f] = tuple(
            g
            for g in range(model.ngeom)
            if model.geom_bodyid[g] == b and (model.geom_contype[g] or model.geom_conaffinity[g])
        )
    ctb_geoms = tuple(g for g in range(model.ngeom) if ctb >= 0 and model.geom_bodyid[g] == ctb)
    iss_geoms = tuple(
        g
        for g in range(model.ngeom)
        if model.body_weldid[model.geom_bodyid[g]] == 0 and model.geom_contype[g] == _ISS_CONTYPE
    )
    astrobee_jnt = idx(jnt, "astrobee")
    ctb_jnt = mujoco.mj_name2id(model, jnt, "ctb")
    force, speed = servo_limits(design)

    # keyframes: the whole world at the route start, payload deployed (home) or stowed
    for key_name, posture in (("home", design.home), ("stowed", design.stowed)):
        qpos = model.qpos0.copy()
        ctrl_values = np.zeros(model.nu)
        values = {"rail": posture.rail, "stage": posture.stage}
        for f in FINGERS:
            for j, v in zip(FINGER_JOINTS, posture.finger):
                values[f"{f}_{j}"] = v
        for name, v in values.items():
            qpos[model.jnt_qposadr[idx(jnt, PAYLOAD_PREFIX + name)]] = v
            ctrl_values[idx(act, PAYLOAD_PREFIX + name)] = v
        spec.add_key(name=key_name, qpos=qpos.tolist(), ctrl=ctrl_values.tolist())
    model = spec.compile()

    return World(
        model=model,
        spec=spec,
        config=config,
        design=design,
        ctrl=ctrl,
        stage_ctrl=stage_ctrl,
        qpos=model.jnt_qposadr[joints].copy(),
        stage_qpos=int(model.jnt_qposadr[stage_joint]),
        dof=model.jnt_dofadr[joints].copy(),
        stage_dof=int(model.jnt_dofadr[stage_joint]),
        astrobee=astrobee,
        astrobee_qpos=int(model.jnt_qposadr[astrobee_jnt]),
        astrobee_dof=int(model.jnt_dofadr[astrobee_jnt]),
        ctb=ctb,
        ctb_qpos=int(model.jnt_qposadr[ctb_jnt]) if ctb_jnt >= 0 else -1,
        ctb_dof=int(model.jnt_dofadr[ctb_jnt]) if ctb_jnt >= 0 else -1,
        pad_geoms=pad_geoms,
        distal_geoms=distal_geoms,
        ctb_geoms=ctb_geoms,
        iss_geoms=iss_geoms,
        force_limit=force,
        slew_rate=speed,
        pinch=pinch_grasp(design, config),
        vehicle=design_vehicle(design),
    )


__all__ = [
    "ASTROBEE_INERTIA",
    "ASTROBEE_MASS",
    "ASTROBEE_SIZE",
    "CONTROL_DT",
    "CTB_MODELS",
    "CTB_SIZES",
    "DEFAULT_CTB",
    "PAYLOAD_MOUNT",
    "PAYLOAD_PREFIX",
    "PHYSICS_DT",
    "PINCH_CLEARANCE",
    "PINCH_OPEN",
    "PINCH_SQUEEZE",
    "SUBSTEPS",
    "CtbSize",
    "Handle",
    "IssLayout",
    "IssModule",
    "PinchGrasp",
    "SimError",
    "World",
    "WorldConfig",
    "Zone",
    "build_spec",
    "build_world",
    "ctb_offset",
    "design_vehicle",
    "payload_mount",
    "pinch_grasp",
    "servo_limits",
]
