"""The collision model's geometry (:mod:`payload.retarget.collision`): a link's collision
geometry read from the URDF (meshes and primitives), the capsule enclosing it, and the
structure's boxes (the design's collision boxes, else the URDF's)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from payload.retarget.errors import RetargetError


@dataclass(frozen=True)
class Capsule:
    """A capsule fixed in a link frame.

    Attributes:
        link: The URDF link.
        a: First end of the axis in the link frame [m], shape (3,).
        b: Second end [m], shape (3,).
        radius: [m].
    """

    link: str
    a: np.ndarray
    b: np.ndarray
    radius: float


@dataclass(frozen=True)
class Box:
    """A box fixed in the pair's base frame.

    Attributes:
        link: The structure link it belongs to.
        centre: [m], shape (3,).
        rotation: Box axes in the base frame (columns), shape (3, 3).
        half: Half sizes [m], shape (3,).
    """

    link: str
    centre: np.ndarray
    rotation: np.ndarray
    half: np.ndarray


def _origin(el: ET.Element | None) -> np.ndarray:
    pose = np.eye(4)
    if el is not None:
        xyz = [float(v) for v in el.get("xyz", "0 0 0").split()]
        rpy = [float(v) for v in el.get("rpy", "0 0 0").split()]
        pose[:3, :3] = pin.rpy.rpyToMatrix(*rpy)
        pose[:3, 3] = xyz
    return pose


def _circle(radius: float, z: float, n: int = 48) -> np.ndarray:
    # a polygon circumscribing the circle, so the points enclose it
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    r = radius / np.cos(np.pi / n)
    return np.column_stack([r * np.cos(t), r * np.sin(t), np.full(n, z)])


def _sphere_points(radius: float, n: int = 24) -> np.ndarray:
    pts = [np.array([[0.0, 0.0, radius], [0.0, 0.0, -radius]])]
    for phi in np.linspace(0.0, np.pi, n // 2 + 1)[1:-1]:
        pts.append(_circle(radius * np.sin(phi), radius * np.cos(phi), n))
    return np.vstack(pts) * (1.0 / np.cos(np.pi / n))


def mesh_path(name: str, urdf_dir: Path) -> Path:
    """The file a URDF ``<mesh filename=...>`` names (relative to the URDF's folder,
    ``package://`` and ``file://`` stripped)."""
    if name.startswith("package://") or name.startswith("file://"):
        name = name.split("://", 1)[1]
    return Path(name) if Path(name).is_absolute() else urdf_dir / name


def load_collision_mesh(filename: str, urdf_dir: Path) -> Any:
    """The trimesh mesh a URDF ``<mesh filename=...>`` names (relative to the URDF's folder,
    ``package://`` and ``file://`` stripped), unscaled.

    Raises:
        RetargetError: The file is missing or unreadable: one line naming it.
    """
    import trimesh

    path = mesh_path(filename, urdf_dir)
    if not path.is_file():
        raise RetargetError(
            f"collision mesh not found: {path} (the self-collision model and the mesh check "
            "need the URDF's collision meshes; without them, retarget without the model)"
        )
    try:
        return trimesh.load(str(path), force="mesh")
    except (ValueError, OSError) as exc:
        raise RetargetError(f"collision mesh unreadable: {path} ({exc})") from None


def link_geometry(urdf: Path) -> dict[str, list[tuple[str, object, np.ndarray]]]:
    """Per link, its collision elements ``(kind, data, origin 4x4)`` from a URDF.

    ``kind`` is ``mesh`` (data: a trimesh mesh, scaled), ``box`` (size (3,)),
    ``cylinder`` ((radius, length)) or ``sphere`` (radius).
    """
    import trimesh

    root = ET.parse(urdf).getroot()
    out: dict[str, list[tuple[str, object, np.ndarray]]] = {}
    for link in root.findall("link"):
        for col in link.findall("collision"):
            geo = col.find("geometry")
            if geo is None:
                continue
            pose = _origin(col.find("origin"))
            item: tuple[str, object] | None = None
            if (m := geo.find("mesh")) is not None:
                tm = load_collision_mesh(m.get("filename", ""), urdf.parent)
                scale = np.array([float(v) for v in m.get("scale", "1 1 1").split()])
                tm = trimesh.Trimesh(np.asarray(tm.vertices) * scale, tm.faces, process=False)
                item = ("mesh", tm)
            elif (b := geo.find("box")) is not None:
                item = ("box", np.array([float(v) for v in b.get("size", "0 0 0").split()]))
            elif (c := geo.find("cylinder")) is not None:
                item = ("cylinder", (float(c.get("radius", 0)), float(c.get("length", 0))))
            elif (s := geo.find("sphere")) is not None:
                item = ("sphere", float(s.get("radius", 0)))
            if item is not None:
                out.setdefault(link.get("name", ""), []).append((item[0], item[1], pose))
    return out


def _points(kind: str, data: object, pose: np.ndarray) -> np.ndarray:
    """Points whose convex hull contains the element, in the link frame."""
    if kind == "mesh":
        local = np.asarray(data.vertices, dtype=float)  # type: ignore[attr-defined]
    elif kind == "box":
        h = 0.5 * np.asarray(data)
        local = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
    elif kind == "cylinder":
        r, length = data  # type: ignore[misc]
        local = np.vstack([_circle(r, -length / 2), _circle(r, length / 2)])
    else:
        local = _sphere_points(float(data))  # type: ignore[arg-type]
    return local @ pose[:3, :3].T + pose[:3, 3]


def enclosing_capsule(link: str, pts: np.ndarray) -> Capsule:
    """A capsule containing every point (shape (k, 3)): see the module docstring."""
    from scipy.optimize import minimize  # here, not at import (a trial needs no SciPy)

    pts = np.asarray(pts, dtype=float)
    centred = pts - pts.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    best: Capsule | None = None
    best_vol = np.inf
    for axis in (np.eye(3)[0], np.eye(3)[1], np.eye(3)[2], vt[0]):
        u = axis / np.linalg.norm(axis)
        e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        xy = np.column_stack([pts @ e1, pts @ e2])
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        res = minimize(
            lambda c, xy=xy: float(np.max(np.sum((xy - c) ** 2, axis=1))),
            0.5 * (lo + hi),
            method="Nelder-Mead",
            options={"xatol": 1e-7, "fatol": 1e-12},
        )
        c2 = res.x
        rho = np.sqrt(np.sum((xy - c2) ** 2, axis=1))
        r = float(rho.max()) * (1.0 + 1e-9) + 1e-9
        t = pts @ u
        cap = np.sqrt(np.maximum(r * r - rho * rho, 0.0))
        a, b = float(np.min(t + cap)), float(np.max(t - cap))
        base = c2[0] * e1 + c2[1] * e2
        if a > b:  # a sphere
            m = 0.5 * (a + b)
            centre = base + m * u
            r = float(np.max(np.linalg.norm(pts - centre, axis=1))) * (1.0 + 1e-9) + 1e-9
            a = b = m
        b = max(b, a + 1e-6)
        cand = Capsule(link, base + a * u, base + b * u, r)
        vol = np.pi * r * r * (b - a) + 4.0 / 3.0 * np.pi * r**3
        if vol < best_vol:
            best, best_vol = cand, vol
    assert best is not None
    return best


def _oriented_boxes(link: str, kind: str, data: object, pose: np.ndarray) -> list[tuple]:
    """``(centre, rotation, half)`` boxes enclosing one URDF element, in the link frame."""
    if kind == "box":
        return [(pose[:3, 3], pose[:3, :3], 0.5 * np.asarray(data))]
    if kind == "cylinder":
        r, length = data  # type: ignore[misc]
        return [(pose[:3, 3], pose[:3, :3], np.array([r, r, length / 2]))]
    if kind == "sphere":
        r = float(data)  # type: ignore[arg-type]
        return [(pose[:3, 3], pose[:3, :3], np.full(3, r))]
    out = []
    for piece in data.split(only_watertight=False) or [data]:  # type: ignore[attr-defined]
        obb = piece.bounding_box_oriented
        tf = pose @ np.asarray(obb.primitive.transform)
        out.append((tf[:3, 3], tf[:3, :3], 0.5 * np.asarray(obb.primitive.extents)))
    return out


def _design_boxes(design_path: Path) -> dict[str, list[tuple]]:
    """The design's structure collision boxes and guide columns, per link frame."""
    from payload.design.params import load_design
    from payload.design.solids import structure_bodies

    out: dict[str, list[tuple]] = {}
    for name, body in structure_bodies(load_design(design_path)).items():
        items = [(np.array(c), np.eye(3), np.array(h)) for c, h in body.boxes]
        for c, axis, r, half_len in body.cylinders:
            half = np.full(3, r)
            half["xyz".index(axis)] = half_len
            items.append((np.array(c), np.eye(3), half))
        out[name] = items
    return out


def structure_boxes(
    design: Path | None, geometry: dict[str, list], links: list[str]
) -> dict[str, list[Box]]:
    """The structure's boxes per link, in that link's frame: the design's collision boxes
    and guide columns when the hand names a design, else the URDF's primitives and, for a
    mesh, the oriented bounding box of each connected piece (``geometry``:
    :func:`link_geometry`)."""
    designed = _design_boxes(design) if design is not None else {}
    out: dict[str, list[Box]] = {}
    for n in links:
        items = designed.get(n)
        if items is None:
            items = [b for k, g, o in geometry[n] for b in _oriented_boxes(n, k, g, o)]
        out[n] = [Box(n, np.asarray(c, float), np.asarray(r, float), np.asarray(h, float))
                  for c, r, h in items]  # fmt: skip
    return out
