"""Astrobee's body and bays for the envelope and reach reports: the design's ``[vehicle]``
table (:mod:`payload.design.vehicle`, re-exported here) loaded with the design, and
report paths relative to their project."""

from __future__ import annotations

from pathlib import Path

from payload.design.params import Design, load_design
from payload.design.vehicle import (
    BAY_ASSUMPTION,
    Vehicle,
    VehicleError,
    vehicle_from_dict,
    with_bay_size,
)
from payload.project import current_project, project_of


def display_path(path: str | Path) -> str:
    """``path`` relative to the root of the design project holding it (for committed
    reports), or as given when it lies in no project."""
    project = project_of(path)
    return project.relative(path) if project is not None else str(path)


def load_design_and_vehicle(path: str | Path | None = None) -> tuple[Design, Vehicle]:
    """Load a design file that may hold a ``[vehicle]`` table.

    Args:
        path: Design TOML (default: the current project's ``cad/design.toml``).

    Returns:
        The validated design and the vehicle (defaults where the table is absent).

    Raises:
        DesignError: The file or a design parameter is invalid.
        VehicleError: The ``[vehicle]`` table is invalid.
    """
    p = Path(path) if path is not None else current_project().design_path
    design = load_design(p)
    vehicle = (
        Vehicle() if not design.vehicle else vehicle_from_dict(design.vehicle, display_path(p))
    )
    return design, vehicle


__all__ = [
    "BAY_ASSUMPTION",
    "Vehicle",
    "VehicleError",
    "display_path",
    "load_design_and_vehicle",
    "vehicle_from_dict",
    "with_bay_size",
]
