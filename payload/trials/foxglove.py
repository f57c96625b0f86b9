"""Standard Foxglove channels in a trial recording, so Foxglove shows it with no custom panel.

Channels (all ``protobuf``, schemas from ``foxglove-schemas-protobuf``; times: the
message ``log_time`` and every ``timestamp`` are the recording's start time plus the
step time ``t``, so Foxglove plays a trial back in simulated time):

======================== ======================= ============================================
topic                    schema                  content
======================== ======================= ============================================
``/tf``                  foxglove.FrameTransforms ``world -> astrobee -> payload/...`` (every
                                                  payload link, relative to its parent link)
                                                  and ``world -> ctb``, at :data:`RATE_HZ`
``/scene``               foxglove.SceneUpdate    module walls (frame ``world``), Astrobee,
                                                  the payload's collision shapes and the CTB
                                                  box, each in its own frame; sent at the
                                                  start and every :data:`SCENE_PERIOD_S`
``/payload/joints/       foxglove.JointStates    the 17 manipulation coordinates and
commanded``                                       ``stage``, commanded [rad, m]
``/payload/joints/       foxglove.JointStates    the same, measured
measured``
``/trial/events``        foxglove.Log            one line per phase change and per change of
                                                  the opposing-contact indicator
======================== ======================= ============================================

Poses and joint values on these channels are rounded to :data:`VIEW_RESOLUTION`.
The contact indicator and the phase are also plottable from ``/trial/step`` (fields
``contact`` and ``phase``). Link poses come from forward kinematics of the simulator's
model on the recorded measured joints, so they are exactly what the step records.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.CylinderPrimitive_pb2 import CylinderPrimitive
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.JointState_pb2 import JointState
from foxglove_schemas_protobuf.JointStates_pb2 import JointStates
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from mcap_protobuf.schema import build_file_descriptor_set

from payload.design import MANIPULATION_JOINTS
from payload.schema import CONTROL_DT
from payload.trials.jointcodec import quantize_joints

RATE_HZ = 10.0
"""Rate of the transform and joint-state channels [Hz] (every fifth 50 Hz step)."""
SCENE_PERIOD_S = 10.0
"""Period at which the static scene is sent again [s] (for seeking in Foxglove)."""
JOINT_NAMES: tuple[str, ...] = (*MANIPULATION_JOINTS, "stage")
"""Joint names of the joint-state channels."""

TOPICS: dict[str, type] = {
    "/tf": FrameTransforms,
    "/scene": SceneUpdate,
    "/payload/joints/commanded": JointStates,
    "/payload/joints/measured": JointStates,
    "/trial/events": Log,
}
"""Every Foxglove channel this module writes, with its message class."""

_COLORS = {
    "world": (0.75, 0.75, 0.8, 0.25),
    "astrobee": (0.2, 0.4, 0.9, 0.9),
    "payload": (0.9, 0.6, 0.1, 1.0),
    "ctb": (0.9, 0.9, 0.85, 0.9),
}


VIEW_RESOLUTION = 2.0**-20
"""Resolution of the poses and joint values on these channels (about 1e-6 m or rad): they
are for viewing (``/trial/step`` holds the exact values), and the rounding leaves the low
mantissa bytes zero so the chunks compress well."""


def _view(x: np.ndarray) -> np.ndarray:
    """``x`` on the viewer's grid (:data:`VIEW_RESOLUTION`)."""
    return quantize_joints(x, VIEW_RESOLUTION)


def split_ns(ns: int) -> tuple[int, int]:
    """A log time [ns] as a protobuf ``Timestamp``'s (seconds, nanos)."""
    return ns // 1_000_000_000, ns % 1_000_000_000


def timestamp(ns: int) -> Timestamp:
    """A log time [ns] as a protobuf ``Timestamp``."""
    seconds, nanos = split_ns(ns)
    return Timestamp(seconds=seconds, nanos=nanos)


def _pose(pos: np.ndarray, quat_wxyz: np.ndarray) -> Pose:
    pos = _view(pos)
    w, x, y, z = (float(v) for v in _view(quat_wxyz))
    return Pose(
        position=Vector3(x=float(pos[0]), y=float(pos[1]), z=float(pos[2])),
        orientation=Quaternion(x=x, y=y, z=z, w=w),
    )


class FoxgloveScene:
    """Writes the Foxglove channels of a recording (see the module docstring).

    Args:
        world: The simulator's :class:`~payload.sim.world.World` (model and indices).
        modules: Optional module outlines (unused in the 3D scene; kept in metadata).
    """

    def __init__(self, world: Any, modules: Sequence[dict] | None = None) -> None:
        self.world = world
        self.model = world.model
        self.data = mujoco.MjData(self.model)
        mujoco.mj_kinematics(self.model, self.data)
        m = self.model
        self.bodies = [b for b in range(1, m.nbody) if m.body_rootid[b] == world.astrobee]
        self.names = {b: m.body(b).name for b in range(m.nbody)}
        self.names[0] = "world"
        # the /tf links: Astrobee's tree, then the CTB, each with its parent
        self._links = [*self.bodies, *([world.ctb] if world.ctb >= 0 else [])]
        self._parents = [int(m.body_parentid[b]) for b in self._links]
        self._link_names = [self.names[b] for b in self._links]
        self._parent_names = [self.names[p] for p in self._parents]
        self.every = max(1, round(1.0 / (CONTROL_DT * RATE_HZ)))  # control steps a scene
        self.channels: dict[str, int] = {}
        self._k = 0
        self._next_scene_ns = 0
        self._scene_drawn: SceneUpdate | None = None
        self._last_phase: str | None = None
        self._last_contact: bool | None = None
        self.modules = list(modules or [])

    def start(self, writer: Any) -> None:
        """Register the schemas and channels on an MCAP writer."""
        for topic, cls in TOPICS.items():
            schema = writer.register_schema(
                name=cls.DESCRIPTOR.full_name,
                encoding="protobuf",
                data=build_file_descriptor_set(cls).SerializeToString(),
            )
            self.channels[topic] = writer.register_channel(
                topic=topic, message_encoding="protobuf", schema_id=schema
            )

    def write(self, writer: Any, step: Any, ns: int) -> None:
        """Write the Foxglove messages due at this step (``ns``: its log time [ns])."""
        self._events(writer, step, ns)
        if ns >= self._next_scene_ns:
            self._emit(writer, "/scene", self.scene(ns), ns)
            self._next_scene_ns = ns + round(SCENE_PERIOD_S * 1e9)
        if self._k % self.every == 0:
            kernel = self._messages_kernel
            poses = self._poses(step)
            cmd = _view(np.append(step.q_cmd, step.deploy_cmd))
            meas = _view(np.append(step.q_meas, step.deploy_meas))
            stamp = split_ns(ns)
            for topic, data, message in (
                ("/tf", kernel and kernel.frame_transforms(poses, stamp),
                 lambda: self._frame_transforms(poses, ns)),
                ("/payload/joints/commanded", kernel and kernel.joint_states(cmd, stamp),
                 lambda: self.joint_states(cmd, ns)),
                ("/payload/joints/measured", kernel and kernel.joint_states(meas, stamp),
                 lambda: self.joint_states(meas, ns)),
            ):  # fmt: skip
                if data is None:  # the protobuf objects, serialised by the runtime
                    data = message().SerializeToString()
                self._emit_bytes(writer, topic, data, ns)
        self._k += 1

    def _emit(self, writer: Any, topic: str, msg: Any, ns: int) -> None:
        self._emit_bytes(writer, topic, msg.SerializeToString(), ns)

    def _emit_bytes(self, writer: Any, topic: str, data: bytes, ns: int) -> None:
        writer.add_message(channel_id=self.channels[topic], log_time=ns, publish_time=ns, data=data)

    @functools.cached_property
    def _messages_kernel(self) -> Any:
        """The ``/tf`` and joint-state messages serialised in C
        (:mod:`payload.trials.messages_c`, checked when built against the protobuf
        runtime's bytes), or None."""
        from payload.trials.messages_c import compiled_messages

        return compiled_messages(
            list(zip(self._parent_names, self._link_names)),
            list(JOINT_NAMES),
            lambda poses, ns: self._frame_transforms(poses, ns).SerializeToString(),
            lambda positions, ns: self.joint_states(positions, ns).SerializeToString(),
            split_ns,
        )

    def _events(self, writer: Any, step: Any, ns: int) -> None:
        lines = []
        if step.phase != self._last_phase:
            lines.append(f"phase: {step.phase}")
            self._last_phase = step.phase
        if step.contact != self._last_contact:
            lines.append(f"opposing contact: {'on' if step.contact else 'off'}")
            self._last_contact = step.contact
        for text in lines:
            msg = Log(timestamp=timestamp(ns), level=Log.INFO, message=text, name="trial")
            self._emit(writer, "/trial/events", msg, ns)

    # -- messages ----------------------------------------------------------------------
    def kinematics(self, step: Any) -> mujoco.MjData:
        """Forward kinematics of the model at a step's measured state."""
        w, d = self.world, self.data
        a = w.astrobee_qpos
        d.qpos[a : a + 3] = step.astrobee_pos
        d.qpos[a + 3 : a + 7] = step.astrobee_quat
        d.qpos[w.qpos] = step.q_meas
        d.qpos[w.stage_qpos] = step.deploy_meas
        if w.ctb >= 0:
            d.qpos[w.ctb_qpos : w.ctb_qpos + 3] = step.ctb_pos
            d.qpos[w.ctb_qpos + 3 : w.ctb_qpos + 7] = step.ctb_quat
        mujoco.mj_kinematics(self.model, d)
        return d

    def transforms(self, step: Any, ns: int) -> FrameTransforms:
        """``world -> astrobee -> payload links`` and ``world -> ctb`` at a step."""
        return self._frame_transforms(self._poses(step), ns)

    def _poses(self, step: Any) -> np.ndarray:
        """Each link's pose in its parent's frame at a step (:meth:`_poses_numpy`)."""
        self.kinematics(step)
        kernel = self._poses_kernel
        return kernel() if kernel is not None else self._poses_numpy()

    def _frame_transforms(self, poses: np.ndarray, ns: int) -> FrameTransforms:
        """The transforms message of ``poses`` (N, 7: position, quaternion w x y z)."""
        ts = timestamp(ns)
        out = FrameTransforms()
        for parent, child, (x, y, z, qw, qx, qy, qz) in zip(
            self._parent_names, self._link_names, poses.tolist()
        ):
            t = out.transforms.add()  # filled in place: no temporary messages to copy
            t.timestamp.CopyFrom(ts)
            t.parent_frame_id = parent
            t.child_frame_id = child
            v, q = t.translation, t.rotation
            v.x, v.y, v.z = x, y, z
            q.x, q.y, q.z, q.w = qx, qy, qz, qw
        return out

    def _poses_numpy(self) -> np.ndarray:
        """Each link's pose in its parent's frame now, rounded for viewing: (N, 7),
        position then quaternion (w x y z)."""
        d = self.data
        poses = np.zeros((len(self._links), 7))
        inv = np.zeros(4)
        xmat, xpos, xquat = d.xmat, d.xpos, d.xquat  # each access makes a new view
        for i, (b, p) in enumerate(zip(self._links, self._parents)):
            poses[i, :3] = xmat[p].reshape(3, 3).T @ (xpos[b] - xpos[p])
            mujoco.mju_negQuat(inv, xquat[p])
            mujoco.mju_mulQuat(poses[i, 3:], inv, xquat[b])
        return _view(poses)

    @property
    def _poses_kernel(self) -> Any:
        """:meth:`_poses_numpy` compiled for the scene's current data
        (:mod:`payload.trials.foxglove_c`, checked when built; made again for other data
        or another model), or None."""
        made = self.__dict__.get("_poses_made")
        if made is not None and made[0] is self.data and made[1] is self.model:
            return made[2]
        from payload.trials.foxglove_c import compiled_frame_poses

        kernel = compiled_frame_poses(
            self.model,
            self.data,
            np.array(self._links, dtype=np.int64),
            np.array(self._parents, dtype=np.int64),
            VIEW_RESOLUTION,
            self._poses_numpy,
        )
        self.__dict__["_poses_made"] = (self.data, self.model, kernel)
        return kernel

    @staticmethod
    def joint_states(positions: np.ndarray, ns: int) -> JointStates:
        """Named joint positions (17 manipulation coordinates and the stage), as they are
        (the caller puts them on the viewer's grid)."""
        return JointStates(
            timestamp=timestamp(ns),
            joints=[
                JointState(name=n, position=v) for n, v in zip(JOINT_NAMES, positions.tolist())
            ],
        )

    def scene(self, ns: int) -> SceneUpdate:
        """The module walls, Astrobee, the payload's collision shapes and the CTB, stamped
        ``ns`` (:meth:`_scene` drawn once: it depends on the model alone)."""
        if self._scene_drawn is None:
            self._scene_drawn = self._scene(0)
        out = SceneUpdate()
        out.CopyFrom(self._scene_drawn)
        stamp = timestamp(ns)
        for entity in out.entities:
            entity.timestamp.CopyFrom(stamp)
        return out

    def _scene(self, ns: int) -> SceneUpdate:
        """:meth:`scene` drawn from the model (at its reference configuration)."""
        m = self.model
        d = mujoco.MjData(m)
        mujoco.mj_kinematics(m, d)
        w = self.world
        entities: dict[int, SceneEntity] = {}
        for g in range(m.ngeom):
            b = int(m.geom_bodyid[g])
            if m.body_rootid[b] == w.astrobee and int(m.geom_group[g]) == 2:
                continue  # visual meshes: the collision shapes are drawn
            static = m.body_rootid[b] != w.astrobee and b != w.ctb
            frame_body = 0 if static else b
            kind = (
                "world"
                if static
                else "ctb"
                if b == w.ctb
                else "astrobee"
                if b == w.astrobee
                else "payload"
            )
            if frame_body not in entities:
                entities[frame_body] = SceneEntity(
                    timestamp=timestamp(ns),
                    frame_id=self.names[frame_body],
                    id=f"geoms/{self.names[frame_body]}",
                    frame_locked=True,
                )
            if static:
                pos, quat = d.geom_xpos[g], np.zeros(4)
                mujoco.mju_mat2Quat(quat, d.geom_xmat[g])
            else:
                pos, quat = m.geom_pos[g], m.geom_quat[g]
            _add_primitive(entities[frame_body], m, g, _pose(pos, quat), _COLORS[kind])
        return SceneUpdate(entities=list(entities.values()))


def _add_primitive(entity: SceneEntity, m: mujoco.MjModel, g: int, pose: Pose, rgba) -> None:
    size = m.geom_size[g]
    color = Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])
    kind = int(m.geom_type[g])
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        entity.cubes.append(
            CubePrimitive(
                pose=pose,
                size=Vector3(x=2 * size[0], y=2 * size[1], z=2 * size[2]),
                color=color,
            )
        )
    elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        s = 2 * float(size[0])
        entity.spheres.append(SpherePrimitive(pose=pose, size=Vector3(x=s, y=s, z=s), color=color))
    elif kind in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):
        r = 2 * float(size[0])
        length = 2 * float(size[1]) + (r if kind == mujoco.mjtGeom.mjGEOM_CAPSULE else 0.0)
        entity.cylinders.append(
            CylinderPrimitive(
                pose=pose,
                size=Vector3(x=r, y=r, z=length),
                bottom_scale=1.0,
                top_scale=1.0,
                color=color,
            )
        )
    else:  # meshes and the rest: their bounding box
        half = m.geom_rbound[g] / np.sqrt(3.0)
        entity.cubes.append(
            CubePrimitive(pose=pose, size=Vector3(x=2 * half, y=2 * half, z=2 * half), color=color)
        )


__all__ = ["JOINT_NAMES", "RATE_HZ", "SCENE_PERIOD_S", "TOPICS", "FoxgloveScene"]
