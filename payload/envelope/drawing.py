"""Shared pieces of the envelope and reach figures: colours, views, sections, the vehicle."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import manifold3d as m3d
import numpy as np

from payload.envelope.geometry import PayloadGeometry
from payload.envelope.vehicle import Vehicle

if TYPE_CHECKING:  # matplotlib loads with the first drawing: the colours below need none
    from matplotlib.patches import PathPatch, Rectangle

FINGER_COLOURS = {"A": "#1f77b4", "B": "#9467bd", "C": "#2ca02c", "D": "#e377c2"}
"""One colour per finger, none of them the pass/fail colours below."""
STRUCTURE_COLOUR = "#8c8c8c"
FAIL_COLOUR = "#e00000"
"""A part that protrudes from the bays (in the design review, or hits the vehicle as the
stage deploys): red, and nothing else is (but the review's verdict on a design that fails,
the trial replay's keep-out boxes, where the vehicle must not be, and reach.png's crosses,
a grasp feature a finger pair does not close on)."""
COLLISION_COLOUR = "#ff00ff"
"""A part that collides with another link (and is not outside the bays): magenta, and
nothing else is; the envelope figure edges it in it, the design review fills it. Apart from
the fingers' colours (CIE76 difference over 60 from finger D's pink, the nearest) and
from the red, so the links that collide show among the parts that stick out; on white
about 3:1, as a line or a fill."""
PASS_COLOUR = "#1a7f37"
"""The review's verdict on a design that passes: dark green, on white as legible as the
red (contrast about 5:1); no part is drawn in it."""
TIGHT_COLOUR = "#ffb000"
"""A link that does not fail but is under ``fit_results.TIGHT_CLEARANCE`` to a bay wall or to
another link: amber, and nothing else is."""

# a view: (name, section axis, (horizontal axis, vertical axis))
AXES = {0: (1, 2), 1: (0, 2), 2: (0, 1)}
AXIS_LABEL = "xyz"


def posed_solids(geom: PayloadGeometry, q: Mapping[str, float]) -> dict[str, m3d.Manifold]:
    poses = geom.poses(q)
    return {name: geom.posed_solid(name, poses[name]) for name in geom.links}


def to_view(solid: m3d.Manifold, axis: int) -> m3d.Manifold:
    """Rotate so that ``axis`` becomes z and the view axes become x, y (in AXES order)."""
    if axis == 2:
        return solid
    if axis == 0:  # (x, y, z) -> (y, z, x)
        return solid.transform([[0, 1, 0, 0], [0, 0, 1, 0], [1, 0, 0, 0]])
    # axis == 1: (x, y, z) -> (z, x, y), then swap the plotted axes
    return solid.transform([[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0]])


def polygons(section: m3d.CrossSection, axis: int) -> list[np.ndarray]:
    polys = [np.asarray(p, dtype=float) for p in section.to_polygons()]
    if axis == 1:
        polys = [p[:, ::-1] for p in polys]
    return [p for p in polys if len(p) >= 3]


def polygon_patch(polys: Sequence[np.ndarray], **kw: Any) -> PathPatch | None:
    from matplotlib.patches import PathPatch
    from matplotlib.path import Path as MplPath

    if not polys:
        return None
    verts, codes = [], []
    for p in polys:
        p = p * 1e3
        verts += [*p.tolist(), p[0].tolist()]
        codes += [MplPath.MOVETO] + [MplPath.LINETO] * (len(p) - 1) + [MplPath.CLOSEPOLY]
    return PathPatch(MplPath(verts, codes), **kw)


def part_colour(name: str) -> str:
    return FINGER_COLOURS.get(name[0], STRUCTURE_COLOUR) if name[1:2] == "_" else STRUCTURE_COLOUR


VEHICLE_STYLE: dict[str, Any] = {"facecolor": "#f2efe6", "edgecolor": "#6b6b6b"}
"""Fill and edge of the Astrobee body, in the figures and their legends."""

BAY_STYLE: dict[str, Any] = {"facecolor": "white", "edgecolor": "black", "ls": "--"}
"""Fill, edge and line of the (assumed) bay envelope, in the figures and their legends."""


def legend_box(label: str, **style: Any) -> Rectangle:
    """A legend handle: a box in ``style`` (matplotlib patch properties) named ``label``."""
    from matplotlib.patches import Rectangle

    return Rectangle((0, 0), 1, 1, label=label, **style)


def _box(lower: np.ndarray, upper: np.ndarray, h: int, v: int, **style: Any) -> Rectangle:
    """The (h, v) view of the axis-aligned box from ``lower`` to ``upper`` [mm]."""
    from matplotlib.patches import Rectangle

    size = (upper[h] - lower[h], upper[v] - lower[v])
    return Rectangle((lower[h], lower[v]), *size, fill=True, **style)


def draw_vehicle(ax: Any, vehicle: Vehicle, axis: int, full_body: bool = True) -> None:
    """The vehicle body (``full_body``) and the bay envelope, seen along ``axis``."""
    h, v = AXES[axis]
    if full_body:
        body = (vehicle.body_lower * 1e3, vehicle.body_upper * 1e3)
        ax.add_patch(_box(*body, h, v, lw=1.0, zorder=0, label="Astrobee body", **VEHICLE_STYLE))
    bay = (vehicle.bay_lower * 1e3, vehicle.bay_upper * 1e3)
    label = "bay envelope (assumed)"
    ax.add_patch(_box(*bay, h, v, lw=1.2, zorder=0.5, label=label, **BAY_STYLE))


def vehicle_legend() -> list[Rectangle]:
    """Legend handles of the vehicle body and the bay envelope."""
    return [
        legend_box("Astrobee body", **VEHICLE_STYLE),
        legend_box("bay envelope (ASSUMED size)", **BAY_STYLE),
    ]


__all__ = [
    "AXES",
    "AXIS_LABEL",
    "BAY_STYLE",
    "COLLISION_COLOUR",
    "FAIL_COLOUR",
    "FINGER_COLOURS",
    "PASS_COLOUR",
    "STRUCTURE_COLOUR",
    "TIGHT_COLOUR",
    "VEHICLE_STYLE",
    "draw_vehicle",
    "legend_box",
    "part_colour",
    "polygon_patch",
    "polygons",
    "posed_solids",
    "to_view",
    "vehicle_legend",
]
