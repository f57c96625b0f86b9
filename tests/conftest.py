"""Shared fixtures: the project paths and the default design's models."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest
import tomllib

ROOT = Path(__file__).resolve().parents[1]
URDF = ROOT / "urdf" / "payload.urdf"
MJCF = ROOT / "urdf" / "payload.xml"
SCENE = ROOT / "urdf" / "scene.xml"
DESIGN = ROOT / "cad" / "design.toml"

if sys.version_info < (3, 11):  # pragma: no cover
    import tomli as tomllib


@pytest.fixture(scope="session")
def design_dict() -> dict[str, Any]:
    """The default design file as plain data (copy before editing)."""
    return tomllib.loads(DESIGN.read_text())


@pytest.fixture(scope="session")
def design():
    from payload.design import load_design

    return load_design(DESIGN)
