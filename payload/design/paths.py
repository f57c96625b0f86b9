"""Where a design project keeps its generated models (relative to the project root)."""

from __future__ import annotations

URDF_DIR = "urdf"
"""Folder of the generated URDF and MJCF models, relative to the project root."""
MESH_DIR = "cad/meshes"
"""Folder of the generated link meshes (STL), relative to the project root."""

__all__ = ["MESH_DIR", "URDF_DIR"]
