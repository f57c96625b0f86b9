"""Forward kinematics and frame Jacobians of any URDF, with Pinocchio.

:class:`Kinematics` wraps a Pinocchio model built from a URDF (ours,
``urdf/payload.urdf``, by default). It gives the positions of named frames
(fingertips ``<finger>_tip``, distal joints ``<finger>_distal``) and their
translational Jacobians in the ``LOCAL_WORLD_ALIGNED`` convention (the frame's
origin velocity expressed in the root frame), for one configuration or batched
over many.

Configurations are Pinocchio configuration vectors, shape ``(nq,)``; Jacobian
columns follow the tangent space, shape ``(nv,)``. For our payload ``nq = nv = 18``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np
import pinocchio as pin

from payload.errors import PayloadError
from payload.project import current_project

__all__ = ["Kinematics", "KinematicsError"]


class KinematicsError(PayloadError):
    """A URDF cannot be loaded, or a frame, joint or configuration is invalid."""


class Kinematics:
    """Pinocchio model of a URDF with frame positions and Jacobians.

    Args:
        urdf: Path of the URDF file; ``None`` loads the current project's
            ``urdf/payload.urdf`` (:func:`payload.project.current_project`).

    Attributes:
        model: The Pinocchio model (kinematics only, no geometry).
        data: Its scratch data (not thread-safe: one :class:`Kinematics` per thread).
        urdf: Absolute path of the loaded URDF.
    """

    def __init__(self, urdf: str | Path | None = None) -> None:
        path = Path(urdf) if urdf is not None else current_project().urdf
        if not path.is_file():
            raise KinematicsError(f"URDF not found: {path}")
        try:
            self.model: pin.Model = pin.buildModelFromUrdf(str(path))
        except (RuntimeError, ValueError) as exc:
            raise KinematicsError(f"cannot load URDF {path}: {exc}") from exc
        self.data: pin.Data = self.model.createData()
        self.urdf: Path = path.resolve()

    # ----------------------------------------------------------------- names
    @property
    def nq(self) -> int:
        """Size of a configuration vector."""
        return int(self.model.nq)

    @property
    def nv(self) -> int:
        """Size of a tangent (velocity) vector: the number of Jacobian columns."""
        return int(self.model.nv)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Names of the moving joints in Pinocchio's order (the universe excluded)."""
        return tuple(self.model.names[i] for i in range(1, self.model.njoints))

    @property
    def lower(self) -> np.ndarray:
        """Lower configuration limits, shape (nq,) [rad or m]."""
        return np.array(self.model.lowerPositionLimit, dtype=float)

    @property
    def upper(self) -> np.ndarray:
        """Upper configuration limits, shape (nq,) [rad or m]."""
        return np.array(self.model.upperPositionLimit, dtype=float)

    def joint_id(self, name: str) -> int:
        """Pinocchio index of the joint ``name``.

        Raises:
            KinematicsError: No joint of that name in the model.
        """
        if not self.model.existJointName(name):
            raise KinematicsError(
                f"no joint {name!r} in {self.urdf.name} (joints: {', '.join(self.joint_names)})"
            )
        return int(self.model.getJointId(name))

    def frame_id(self, name: str) -> int:
        """Pinocchio index of the frame ``name`` (a URDF link or joint).

        A name shared by a link and a joint (URDF allows it) means the link.

        Raises:
            KinematicsError: No frame of that name in the model.
        """
        if not self.model.existFrame(name):
            raise KinematicsError(f"no frame {name!r} in {self.urdf.name}")
        for kind in (pin.FrameType.BODY, pin.FrameType.FIXED_JOINT, pin.FrameType.OP_FRAME):
            if self.model.existFrame(name, kind):
                return int(self.model.getFrameId(name, kind))
        return int(self.model.getFrameId(name, pin.FrameType.JOINT))

    def q_indices(self, joints: Sequence[str]) -> np.ndarray:
        """Configuration indices of one-coordinate joints, shape (len(joints),).

        Raises:
            KinematicsError: An unknown joint, or one with more than one coordinate.
        """
        out = []
        for name in joints:
            jm = self.model.joints[self.joint_id(name)]
            if jm.nq != 1 or jm.nv != 1:
                raise KinematicsError(
                    f"joint {name!r} has {jm.nq} coordinates ({jm.shortname()}); "
                    "only one-coordinate revolute or prismatic joints are supported here"
                )
            out.append(jm.idx_q)
        return np.array(out, dtype=int)

    def v_indices(self, joints: Sequence[str]) -> np.ndarray:
        """Tangent (Jacobian column) indices of one-coordinate joints, shape (len(joints),)."""
        self.q_indices(joints)
        return np.array([self.model.joints[self.joint_id(n)].idx_v for n in joints], dtype=int)

    # --------------------------------------------------------- configurations
    def neutral(self) -> np.ndarray:
        """Pinocchio's neutral configuration, shape (nq,)."""
        return np.array(pin.neutral(self.model), dtype=float)

    def configuration(self, values: Mapping[str, float] | None = None) -> np.ndarray:
        """A configuration from joint values by name (others neutral), shape (nq,).

        Args:
            values: Joint name -> value [rad or m] for one-coordinate joints.
        """
        q = self.neutral()
        values = values or {}
        if values:
            idx = self.q_indices(list(values))
            q[idx] = np.array(list(values.values()), dtype=float)
        return q

    def random_configurations(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Configurations drawn uniformly within the joint limits, shape (n, nq).

        Joints without finite limits (continuous joints) take their neutral value.
        """
        lo, hi = self.lower, self.upper
        finite = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
        q = np.tile(self.neutral(), (n, 1))
        u = rng.random((n, int(finite.sum())))
        q[:, finite] = lo[finite] + u * (hi[finite] - lo[finite])
        return q

    def _check_q(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if q.shape != (self.nq,):
            raise KinematicsError(f"configuration: expected shape ({self.nq},), got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise KinematicsError("configuration: non-finite value")
        return q

    def _frame_ids(self, frames: Iterable[str | int]) -> list[int]:
        return [f if isinstance(f, int) else self.frame_id(f) for f in frames]

    # ------------------------------------------------------------ kinematics
    def frame_positions(self, q: np.ndarray, frames: Sequence[str | int]) -> np.ndarray:
        """Root-frame positions of ``frames`` at configuration ``q``.

        Args:
            q: Configuration, shape (nq,).
            frames: Frame names or Pinocchio frame indices, k of them.

        Returns:
            Positions, shape (k, 3) [m].
        """
        ids = self._frame_ids(frames)
        q = self._check_q(q)
        pin.forwardKinematics(self.model, self.data, q)
        out = np.empty((len(ids), 3))
        for k, fid in enumerate(ids):
            out[k] = pin.updateFramePlacement(self.model, self.data, fid).translation
        return out

    def frame_placement(self, q: np.ndarray, frame: str | int) -> pin.SE3:
        """Root-frame placement of one frame at ``q`` (a copy)."""
        (fid,) = self._frame_ids([frame])
        q = self._check_q(q)
        pin.forwardKinematics(self.model, self.data, q)
        return pin.SE3(pin.updateFramePlacement(self.model, self.data, fid))

    def frame_jacobians(
        self, q: np.ndarray, frames: Sequence[str | int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Positions and translational Jacobians (``LOCAL_WORLD_ALIGNED``) of ``frames``.

        Args:
            q: Configuration, shape (nq,).
            frames: Frame names or Pinocchio frame indices, k of them.

        Returns:
            ``(positions, jacobians)``: shape (k, 3) [m] and (k, 3, nv) [m/rad or m/m];
            ``jacobians[i] @ dq`` is the velocity of frame i's origin in the root frame.
        """
        ids = self._frame_ids(frames)
        q = self._check_q(q)
        pin.computeJointJacobians(self.model, self.data, q)
        pos = np.empty((len(ids), 3))
        jac = np.empty((len(ids), 3, self.nv))
        for k, fid in enumerate(ids):
            pos[k] = pin.updateFramePlacement(self.model, self.data, fid).translation
            jac[k] = pin.getFrameJacobian(self.model, self.data, fid, pin.LOCAL_WORLD_ALIGNED)[:3]
        return pos, jac

    def frame_positions_batch(self, qs: np.ndarray, frames: Sequence[str | int]) -> np.ndarray:
        """Frame positions for many configurations.

        Args:
            qs: Configurations, shape (m, nq).
            frames: Frame names or indices, k of them.

        Returns:
            Positions, shape (m, k, 3) [m].
        """
        qs = self._check_batch(qs)
        ids = self._frame_ids(frames)
        out = np.empty((qs.shape[0], len(ids), 3))
        model, data = self.model, self.data
        for i, q in enumerate(qs):
            pin.forwardKinematics(model, data, q)
            for k, fid in enumerate(ids):
                out[i, k] = pin.updateFramePlacement(model, data, fid).translation
        return out

    def frame_jacobians_batch(
        self, qs: np.ndarray, frames: Sequence[str | int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Positions and translational Jacobians for many configurations.

        Args:
            qs: Configurations, shape (m, nq).
            frames: Frame names or indices, k of them.

        Returns:
            ``(positions, jacobians)``: shape (m, k, 3) [m] and (m, k, 3, nv).
        """
        qs = self._check_batch(qs)
        ids = self._frame_ids(frames)
        m = qs.shape[0]
        pos = np.empty((m, len(ids), 3))
        jac = np.empty((m, len(ids), 3, self.nv))
        model, data, lwa = self.model, self.data, pin.LOCAL_WORLD_ALIGNED
        for i, q in enumerate(qs):
            pin.computeJointJacobians(model, data, q)
            for k, fid in enumerate(ids):
                pos[i, k] = pin.updateFramePlacement(model, data, fid).translation
                jac[i, k] = pin.getFrameJacobian(model, data, fid, lwa)[:3]
        return pos, jac

    def _check_batch(self, qs: np.ndarray) -> np.ndarray:
        qs = np.asarray(qs, dtype=float)
        if qs.ndim != 2 or qs.shape[1] != self.nq:
            raise KinematicsError(f"configurations: expected shape (m, {self.nq}), got {qs.shape}")
        if not np.all(np.isfinite(qs)):
            raise KinematicsError("configurations: non-finite value")
        return qs

    # ------------------------------------------------------- chain structure
    def chain(self, base: str, frame: str) -> list[int]:
        """Joints between frame ``base`` and frame ``frame``, from base outward.

        Raises:
            KinematicsError: ``base`` is not an ancestor of ``frame``.
        """
        fb = self.model.frames[self.frame_id(base)]
        ff = self.model.frames[self.frame_id(frame)]
        jb = int(fb.parentJoint)
        path = []
        j = int(ff.parentJoint)
        while j != jb:
            if j == 0:
                raise KinematicsError(f"frame {base!r} is not an ancestor of frame {frame!r}")
            path.append(j)
            j = int(self.model.parents[j])
        return path[::-1]

    def joint_motion(self, joint: int) -> tuple[str, np.ndarray]:
        """Kind and unit axis (in the joint frame) of a one-coordinate joint.

        Returns:
            ``("revolute" | "prismatic", axis)`` with ``axis`` of shape (3,).

        Raises:
            KinematicsError: The joint is not a one-coordinate revolute or prismatic joint.
        """
        jm = self.model.joints[joint]
        name = self.model.names[joint]
        if jm.nq != 1 or jm.nv != 1:
            raise KinematicsError(
                f"joint {name!r} ({jm.shortname()}) is not a one-coordinate joint"
            )
        jd = jm.createData()
        jm.calc(jd, np.zeros(1))
        s = np.asarray(jd.S, dtype=float).reshape(6)
        lin, ang = s[:3], s[3:]
        if np.linalg.norm(lin) < 1e-12 and abs(np.linalg.norm(ang) - 1.0) < 1e-9:
            return "revolute", ang.copy()
        if np.linalg.norm(ang) < 1e-12 and abs(np.linalg.norm(lin) - 1.0) < 1e-9:
            return "prismatic", lin.copy()
        raise KinematicsError(
            f"joint {name!r} ({jm.shortname()}) is neither revolute nor prismatic"
        )
