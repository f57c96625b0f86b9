"""Generate every model of the payload from the design, and check committed files."""

from __future__ import annotations

import filecmp
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from payload.design.mjcf import scene_xml, to_mjcf
from payload.design.params import Design
from payload.design.solids import check_solid
from payload.design.tree import KinematicTree, build_tree
from payload.design.urdf import to_urdf

URDF_DIR = "urdf"
MESH_DIR = "cad/meshes"


def stl_bytes(mesh: trimesh.Trimesh, name: str) -> bytes:
    """Binary STL with a fixed header: the same mesh always gives the same bytes."""
    tris = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)]
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, norm, out=np.zeros_like(normals), where=norm > 0)
    header = f"payload build: {name}".encode()[:80].ljust(80, b" ")
    rec = np.zeros(
        len(tris),
        dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")],
    )
    rec["n"] = normals
    rec["v"] = tris
    return header + struct.pack("<I", len(tris)) + rec.tobytes()


@dataclass(frozen=True)
class BuildResult:
    """What a build wrote.

    Attributes:
        tree: The kinematic tree the files were generated from.
        files: Paths written, relative to the output root.
    """

    tree: KinematicTree
    files: tuple[str, ...]


def generate(design: Design) -> tuple[KinematicTree, dict[str, bytes]]:
    """All generated files as bytes, keyed by path relative to the project root."""
    tree = build_tree(design)
    files: dict[str, bytes] = {}
    seen = set()
    for link in tree.links:
        body = link.body
        if body is None or body.mesh in seen:
            continue
        seen.add(body.mesh)
        for part in body.parts:
            check_solid(f"{body.mesh}/{part.name}", part.solid)
        tm = check_solid(body.mesh, body.solid())
        files[f"{MESH_DIR}/{body.mesh}.stl"] = stl_bytes(tm, body.mesh)
    files[f"{URDF_DIR}/payload.urdf"] = to_urdf(tree).encode()
    mjcf, _ = to_mjcf(tree)
    files[f"{URDF_DIR}/payload.xml"] = mjcf.encode()
    files[f"{URDF_DIR}/scene.xml"] = scene_xml().encode()
    return tree, dict(sorted(files.items()))


def write(design: Design, root: Path) -> BuildResult:
    """Regenerate the models under ``root`` (a project folder, e.g. ``Project.root``);
    stale meshes no longer produced are removed."""
    tree, files = generate(design)
    mesh_dir = root / MESH_DIR
    mesh_dir.mkdir(parents=True, exist_ok=True)
    (root / URDF_DIR).mkdir(parents=True, exist_ok=True)
    for old in mesh_dir.glob("*.stl"):
        if f"{MESH_DIR}/{old.name}" not in files:
            old.unlink()
    for rel, data in files.items():
        path = root / rel
        if not path.exists() or path.read_bytes() != data:
            path.write_bytes(data)
    return BuildResult(tree, tuple(files))


def stale_files(design: Design, root: Path) -> list[str]:
    """Generated files under ``root`` that differ from a fresh build (missing, changed or
    no longer produced), as paths relative to ``root``."""
    with tempfile.TemporaryDirectory(prefix="payload-build-") as tmp:
        fresh = write(design, Path(tmp))
        stale = []
        for rel in fresh.files:
            mine = root / rel
            if not mine.exists() or not filecmp.cmp(mine, Path(tmp) / rel, shallow=False):
                stale.append(rel)
        mesh_dir = root / MESH_DIR
        if mesh_dir.exists():
            for extra in sorted(mesh_dir.glob("*.stl")):
                rel = f"{MESH_DIR}/{extra.name}"
                if rel not in fresh.files:
                    stale.append(rel)
    return stale
