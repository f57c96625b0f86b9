"""The generated model as the review draws it: URDF visuals, Pinocchio link placements."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from payload.kinematics import Kinematics, KinematicsError
from payload.review.errors import ReviewError


@dataclass(frozen=True)
class Visual:
    """One visual of a URDF link.

    Attributes:
        mesh: The mesh file (resolved against the URDF's folder).
        origin: Mesh placement in the link frame, shape (4, 4).
        scale: Per-axis mesh scale, shape (3,).
    """

    mesh: Path
    origin: np.ndarray
    scale: np.ndarray


class PayloadModel:
    """The generated URDF: its links, their mesh visuals and their placements (Pinocchio).

    Args:
        urdf: The generated ``payload.urdf``.

    Raises:
        ReviewError: The URDF cannot be read, or a mesh it names is missing.
    """

    def __init__(self, urdf: Path) -> None:
        import yourdfpy

        try:
            self.kinematics = Kinematics(urdf)
            robot = yourdfpy.URDF.load(str(urdf), build_scene_graph=False, load_meshes=False)
        except (KinematicsError, OSError, ValueError) as exc:
            raise ReviewError(f"cannot read the generated model {urdf}: {exc}") from exc
        self.urdf = Path(urdf)
        self.links: tuple[str, ...] = tuple(link.name for link in robot.robot.links)
        self.visuals: dict[str, list[Visual]] = {}
        for link in robot.robot.links:
            out = []
            for v in link.visuals:
                if v.geometry is None or v.geometry.mesh is None:
                    continue
                mesh = (self.urdf.parent / v.geometry.mesh.filename).resolve()
                if not mesh.is_file():
                    raise ReviewError(
                        f"mesh {mesh} of link {link.name} not found; run `payload build`"
                    )
                origin = np.eye(4) if v.origin is None else np.asarray(v.origin, dtype=float)
                scale = np.ones(3) if v.geometry.mesh.scale is None else v.geometry.mesh.scale
                out.append(Visual(mesh, origin, np.broadcast_to(np.asarray(scale, float), (3,))))
            self.visuals[link.name] = out
        model = self.kinematics.model
        self._frames = {n: model.getFrameId(n, pin.FrameType.BODY) for n in self.links}

    def configuration(self, values: Mapping[str, float]) -> np.ndarray:
        """Pinocchio configuration from joint values by name (others neutral), shape (nq,)."""
        return self.kinematics.configuration(dict(values))

    def placements(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """Every link's placement in the payload frame at configuration ``q``, shape (4, 4)."""
        kin = self.kinematics
        q = np.asarray(q, dtype=float)
        if q.shape != (kin.nq,):
            raise ReviewError(f"configuration: expected shape ({kin.nq},), got {q.shape}")
        pin.forwardKinematics(kin.model, kin.data, q)
        pin.updateFramePlacements(kin.model, kin.data)
        return {n: np.array(kin.data.oMf[f].homogeneous) for n, f in self._frames.items()}


__all__ = ["PayloadModel", "Visual"]
