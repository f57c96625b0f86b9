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

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from payload.design import (
    FINGER_JOINTS,
    FINGERS,
    MANIPULATION_JOINTS,
    Design,
    load_design,
)
from payload.envelope.vehicle import Vehicle
from payload.rotations import yaw_quat
from payload.schema import CONTROL_DT as SCHEMA_CONTROL_DT
from payload.schema import PHYSICS_DT
from payload.sim.astrobee import (
    ASTROBEE_INERTIA,
    ASTROBEE_MASS,
    ASTROBEE_SIZE,
    PAYLOAD_MOUNT,
    _add_astrobee,
    design_vehicle,
    payload_mount,
)
from payload.sim.cargo import CTB_MODELS, CTB_SIZES, DEFAULT_CTB, CtbSize, Handle, _add_ctb
from payload.sim.config import WorldConfig
from payload.sim.errors import SimError
from payload.sim.grasp import (
    PINCH_CLEARANCE,
    PINCH_TORQUE_FRACTION,
    PinchGrasp,
    ctb_offset,
    pinch_grasp,
)
from payload.sim.iss import _ISS_CONTYPE, IssLayout, IssModule, Zone, _add_iss
from payload.sim.pads import pad_contact

PAYLOAD_PREFIX = "payload/"
"""Prefix of every payload element name in the world (``payload/A_tip``)."""

CONTROL_DT = SCHEMA_CONTROL_DT
"""Control period [s] (50 Hz)."""

SUBSTEPS = round(CONTROL_DT / PHYSICS_DT)
"""Physics steps per control step at the default step (20; a world's own:
``WorldConfig.substeps``)."""


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
    spec.option.timestep = config.physics_dt
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
    start = layout.start()
    quat = yaw_quat(layout.start_yaw())
    vehicle = design_vehicle(design)
    astrobee = _add_astrobee(spec, vehicle, start, quat)

    child = mujoco.MjSpec.from_file(str(config.payload_mjcf))
    # the parent's options rule; match them so the attach reports no conflict
    child.option.timestep = config.physics_dt
    frame = astrobee.add_frame(pos=payload_mount(vehicle).tolist())
    frame.attach_body(child.body("base"), PAYLOAD_PREFIX, "")
    for key in list(spec.keys):
        spec.delete(key)

    size = config.ctb_size
    if config.pads == "silicone":
        contact = pad_contact(
            design,
            str(config.payload_mjcf),
            design.pinch.finger,
            size.mass if size is not None else None,
            config.physics_dt,
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


def _id(model: mujoco.MjModel, obj: mujoco.mjtObj, name: str) -> int:
    """Id of a named element of the compiled world; a missing one is a stale payload model."""
    i = mujoco.mj_name2id(model, obj, name)
    if i < 0:
        raise SimError(f"the payload model has no {obj.name[6:].lower()} {name!r}")
    return i


def _add_keyframes(spec: mujoco.MjSpec, model: mujoco.MjModel, design: Design) -> None:
    """Keyframes ``home`` and ``stowed``: the whole world at the route start, the payload
    deployed or stowed (``model`` is ``spec`` compiled without keyframes)."""
    act = mujoco.mjtObj.mjOBJ_ACTUATOR
    jnt = mujoco.mjtObj.mjOBJ_JOINT
    for key_name, posture in (("home", design.home), ("stowed", design.stowed)):
        qpos = model.qpos0.copy()
        ctrl_values = np.zeros(model.nu)
        values = {"rail": posture.rail, "stage": posture.stage}
        for f in FINGERS:
            for j, v in zip(FINGER_JOINTS, posture.finger):
                values[f"{f}_{j}"] = v
        for name, v in values.items():
            qpos[model.jnt_qposadr[_id(model, jnt, PAYLOAD_PREFIX + name)]] = v
            ctrl_values[_id(model, act, PAYLOAD_PREFIX + name)] = v
        spec.add_key(name=key_name, qpos=qpos.tolist(), ctrl=ctrl_values.tolist())


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
        return _id(model, obj, name)

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

    _add_keyframes(spec, model, design)
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
    "PINCH_TORQUE_FRACTION",
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
