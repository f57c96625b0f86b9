"""Generate every model of the payload from the design, and check committed files."""

from __future__ import annotations

import struct
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from payload.design.mjcf import scene_xml, to_mjcf
from payload.design.params import Design
from payload.design.paths import MESH_DIR, URDF_DIR
from payload.design.solids import check_solid
from payload.design.tree import KinematicTree, build_tree
from payload.design.urdf import to_urdf
from payload.errors import BuildError
from payload.safeio import cannot_write_in, replace_file


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
        files: Every generated path, relative to the output root (what the root now
            holds from the design).
        removed: Meshes removed from ``cad/meshes/`` that no part of the design makes
            (a renamed or dropped part's), relative to the output root.
        written: The paths of ``files`` written, those that were missing or differed (a
            file that already held its bytes is left as it is).
    """

    tree: KinematicTree
    files: tuple[str, ...]
    removed: tuple[str, ...] = ()
    written: tuple[str, ...] = ()


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
    written, removed = _write_files(files, root)
    return BuildResult(tree, tuple(files), removed, written)


def _write_files(files: dict[str, bytes], root: Path) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Write the stale ``files`` under ``root``; returns the paths written and the meshes
    removed that no part makes any more."""
    mesh_dir = root / MESH_DIR
    stale = [root / rel for rel, data in files.items() if not _holds(root / rel, data)]
    extra = [old for old in sorted(mesh_dir.glob("*.stl")) if f"{MESH_DIR}/{old.name}" not in files]
    # every folder written in (or made, or removed from) must take it before anything is
    # written: a build that stopped half-way would leave meshes that no longer match the URDF
    for folder in sorted({path.parent for path in (*stale, *extra)}):
        where = folder
        while not where.exists() and where != where.parent:  # made: its first existing parent
            where = where.parent
        problem = cannot_write_in(where)
        if problem is not None:
            raise BuildError(
                f"{where}: cannot write the generated models there ({problem}); nothing written"
            )
    mesh_dir.mkdir(parents=True, exist_ok=True)
    (root / URDF_DIR).mkdir(parents=True, exist_ok=True)
    removed = []
    for old in extra:
        old.unlink()
        removed.append(f"{MESH_DIR}/{old.name}")
    written = []
    for rel, data in files.items():
        path = root / rel
        if not _holds(path, data):
            replace_file(path, data)  # atomic: a command reading the models sees old or new
            written.append(rel)
    return tuple(written), tuple(removed)


def _stale(files: dict[str, bytes], root: Path) -> list[str]:
    """Paths of ``files`` (a fresh :func:`generate`) that differ on disk under ``root``
    (missing or changed), then meshes under ``root`` no longer produced."""
    stale = [rel for rel, data in files.items() if not _holds(root / rel, data)]
    mesh_dir = root / MESH_DIR
    if mesh_dir.exists():
        for extra in sorted(mesh_dir.glob("*.stl")):
            if f"{MESH_DIR}/{extra.name}" not in files:
                stale.append(f"{MESH_DIR}/{extra.name}")
    return stale


def _holds(path: Path, data: bytes) -> bool:
    return path.is_file() and path.stat().st_size == len(data) and path.read_bytes() == data


def stale_files(design: Design, root: Path) -> list[str]:
    """Generated files under ``root`` that differ from a fresh build (missing, changed or
    no longer produced), as paths relative to ``root``."""
    return _stale(generate(design)[1], root)


MODELS_LINE = "models: rebuilt {files} from {design} (the models follow the design)"
"""What every command that reads the generated models prints after rebuilding stale ones."""

REMOVED_LINE = (
    "models: removed {files} (no part of {design} makes it; {mesh_dir}/ holds the "
    "generated meshes only)"
)
"""Printed after :data:`MODELS_LINE` (or alone) for meshes no part makes any more, a
file put there by hand among them."""


def _shown(paths: Sequence[str]) -> str:
    return ", ".join(paths[:3]) + (f" and {len(paths) - 3} more" if len(paths) > 3 else "")


def follow_design(
    design_path: Path, root: Path, *, json: bool = False
) -> tuple[list[str], dict[str, bytes]]:
    """The work of :func:`payload.design.follow.models_follow_design`: generate every model
    from the design, rewrite the stale ones under ``root`` and print :data:`MODELS_LINE`.

    Returns:
        The rebuilt files relative to ``root`` (empty: the models matched), and every
        generated file's bytes by path relative to ``root``.

    Raises:
        DesignError: The design file is invalid (nothing is written).
    """
    from payload.design.params import load_design

    _, files = generate(load_design(design_path))
    stale = _stale(files, root)
    if stale:
        rebuilt, removed = _write_files(files, root)
        lines = []
        if rebuilt:
            lines.append(MODELS_LINE.format(files=_shown(rebuilt), design=design_path))
        if removed:
            lines.append(
                REMOVED_LINE.format(files=_shown(removed), mesh_dir=MESH_DIR, design=design_path)
            )
        print("\n".join(lines), file=sys.stderr if json else sys.stdout, flush=True)
    return stale, files
