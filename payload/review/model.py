"""The generated model as the review draws it: URDF visuals, Pinocchio link placements."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pinocchio as pin

from payload.design.tree import rpy_matrix
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
        try:
            self.kinematics = Kinematics(urdf)
            links = _link_visuals(Path(urdf))
        except (KinematicsError, OSError, ValueError, ElementTree.ParseError) as exc:
            raise ReviewError(f"cannot read the generated model {urdf}: {exc}") from exc
        self.urdf = Path(urdf)
        self.links: tuple[str, ...] = tuple(links)
        self.visuals: dict[str, list[Visual]] = {}
        for name, visuals in links.items():
            out = []
            for filename, origin, scale in visuals:
                mesh = (self.urdf.parent / filename).resolve()
                if not mesh.is_file():
                    raise ReviewError(f"mesh {mesh} of link {name} not found; run `payload build`")
                out.append(Visual(mesh, origin, scale))
            self.visuals[name] = out
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


def _numbers(text: str | None, default: tuple[float, ...]) -> np.ndarray:
    return np.array(default if text is None else [float(v) for v in text.split()], dtype=float)


def _link_visuals(urdf: Path) -> dict[str, list[tuple[str, np.ndarray, np.ndarray]]]:
    """Each link of a URDF (in file order) -> its mesh visuals: (file name as written,
    placement in the link frame (4, 4), per-axis scale (3,)). Read with the standard
    library: a URDF parser (yourdfpy) would load trimesh, about a second of imports."""
    out: dict[str, list[tuple[str, np.ndarray, np.ndarray]]] = {}
    for link in ElementTree.parse(urdf).getroot().iter("link"):
        visuals = []
        for v in link.findall("visual"):
            mesh = v.find("geometry/mesh")
            if mesh is None or mesh.get("filename") is None:
                continue
            origin = np.eye(4)
            o = v.find("origin")
            if o is not None:
                origin[:3, :3] = rpy_matrix(tuple(_numbers(o.get("rpy"), (0.0, 0.0, 0.0))))
                origin[:3, 3] = _numbers(o.get("xyz"), (0.0, 0.0, 0.0))
            scale = np.broadcast_to(_numbers(mesh.get("scale"), (1.0,)), (3,))
            visuals.append((str(mesh.get("filename")), origin, scale))
        out[str(link.get("name"))] = visuals
    return out


__all__ = ["PayloadModel", "Visual"]
