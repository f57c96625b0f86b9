"""The envelope report's figure: cross-sections of the stowed payload, the deployment sweep."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import manifold3d as m3d
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from payload.envelope.drawing import (
    AXES,
    AXIS_LABEL,
    COLLISION_COLOUR,
    FAIL_COLOUR,
    FINGER_COLOURS,
    PASS_COLOUR,
    STRUCTURE_COLOUR,
    TIGHT_COLOUR,
    draw_vehicle,
    legend_box,
    part_colour,
    polygon_patch,
    polygons,
    posed_solids,
    to_view,
    vehicle_legend,
)
from payload.envelope.fit_results import (
    COLLIDES_MEANING,
    OUTSIDE_MEANING,
    TIGHT_CLEARANCE,
    EnvelopeAnalysis,
    StowedCheck,
    clearance_text,
    tight_meaning,
)
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.vehicle import Vehicle


def _section_panel(
    ax: Any,
    solids: Mapping[str, m3d.Manifold],
    vehicle: Vehicle,
    axis: int,
    value: float,
    parts_by_name: Mapping[str, Any],
    title: str,
    colliding: frozenset[str] = frozenset(),
    tight: frozenset[str] = frozenset(),
) -> None:
    """One section of the stowed parts, their silhouettes shaded; a part outside the bays
    edged red and hatched, a colliding one (``colliding``) edged magenta
    (``COLLISION_COLOUR``), a tight one (``tight``, names of links) filled amber, section
    and silhouette, in the colours the design review fills such parts with."""
    h, v = AXES[axis]
    draw_vehicle(ax, vehicle, axis)
    for name, solid in solids.items():
        view = to_view(solid, axis)
        colour = TIGHT_COLOUR if name in tight else part_colour(name)
        sil = polygon_patch(
            polygons(view.project(), axis),
            facecolor=colour,
            alpha=0.25 if name in tight else 0.12,  # a faint amber reads as the body's beige
            edgecolor="none",
            zorder=1,
        )
        if sil is not None:
            ax.add_patch(sil)
        sec = polygons(view.slice(value), axis)
        fit = parts_by_name.get(name)
        outside = fit is not None and not fit.inside
        edge = FAIL_COLOUR if outside else (COLLISION_COLOUR if name in colliding else "black")
        patch = polygon_patch(
            sec,
            facecolor=colour,
            alpha=0.85,
            edgecolor=edge,
            lw=0.4 if edge == "black" else 1.6,
            hatch="///" if outside else None,
            zorder=2,
        )
        if patch is not None:
            ax.add_patch(patch)
    lo, hi = vehicle.bay_lower * 1e3, vehicle.bay_upper * 1e3
    pad = 25.0
    ax.set_xlim(lo[h] - pad, hi[h] + pad)
    ax.set_ylim(lo[v] - pad, hi[v] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel(f"{AXIS_LABEL[h]} [mm]")
    ax.set_ylabel(f"{AXIS_LABEL[v]} [mm]")
    ax.set_title(
        f"{title}\nsection {AXIS_LABEL[axis]} = {value * 1e3:.1f} mm (shaded: silhouettes)",
        fontsize=9,
    )


def _annotate_clearances(ax: Any, check: StowedCheck, vehicle: Vehicle, axis: int) -> None:
    """Mark, for each wall seen in this view, the part sticking out farthest beyond it (of
    every part crossing it, :meth:`StowedCheck.beyond_wall`), else the smallest clearance to
    it over every part (inside the bays or not) and its part."""
    h, v = AXES[axis]
    lo, hi = vehicle.bay_lower * 1e3, vehicle.bay_upper * 1e3
    for w in range(len(vehicle.walls)):
        ax_i = w // 2
        if ax_i not in (h, v):
            continue
        out, near = check.beyond_wall(w), check.nearest_to_wall(w)
        if out:  # a wall a part crosses: no clearance (0 there) said of it
            text, colour = (
                f"{out[0].name}: {out[0].wall_protrusion[w] * 1e3:.1f} mm out",
                FAIL_COLOUR,
            )
        elif near is not None:
            text, colour = f"{clearance_text(near.wall_clearance[w])} ({near.name})", "black"
        else:
            continue
        side = w % 2
        # labels stand just outside their wall, on a white box, so they never cover the
        # parts (or the hatching of a part that protrudes)
        box = {"facecolor": "white", "alpha": 0.85, "edgecolor": "none", "pad": 0.6}
        gap = 1.5  # [mm] between the wall and its label
        if ax_i == h:
            x = hi[h] + gap if side else lo[h] - gap
            ax.annotate(
                text,
                (x, (lo[v] + hi[v]) / 2),
                fontsize=6.5,
                color=colour,
                rotation=90,
                ha="left" if side else "right",
                va="center",
                bbox=box,
                zorder=5,
            )
        else:
            y = hi[v] + gap if side else lo[v] - gap
            ax.annotate(
                text,
                ((lo[h] + hi[h]) / 2, y),
                fontsize=6.5,
                color=colour,
                ha="center",
                va="bottom" if side else "top",
                bbox=box,
                zorder=5,
            )


def envelope_figure(geom: PayloadGeometry, a: EnvelopeAnalysis, path: Path, dpi: int = 130) -> Path:
    """Cross-sections of the stowed payload in the bays, and the deployment sweep."""
    check = a.given
    solids = posed_solids(geom, check.q)
    fits = {p.name: p for p in check.parts}
    tree = geom.tree
    xa = tree.joint_map["A_mcp_flex"].xyz[0]
    ya = tree.joint_map["A_mcp_flex"].xyz[1]
    poses = geom.poses(check.q)
    z_mcp = float(poses["A_knuckle"][2, 3])
    fig = Figure(figsize=(13, 10), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 2)
    hit = frozenset(n for c in check.collisions for n in (c.a, c.b))
    # amber for the tight links that do not fail (a failing one is drawn failing)
    tight = frozenset(n for n in solids if check.link_role(n) == "tight")
    panels = (
        (axes[0, 0], 0, xa, "front view (y-z), through finger A"),
        (axes[0, 1], 1, ya, "side view (x-z), through fingers A, B"),
        (axes[1, 0], 2, z_mcp, "top view (x-y), through the MCP axes"),
    )
    for ax, axis, value, title in panels:
        _section_panel(ax, solids, a.vehicle, axis, value, fits, title, hit, tight)
        _annotate_clearances(ax, check, a.vehicle, axis)
    _deployment_panel(axes[1, 1], geom, a.vehicle, check)
    handles = [
        *vehicle_legend(),
        legend_box("structure", facecolor=STRUCTURE_COLOUR),
        *[legend_box(f"finger {f}", facecolor=c) for f, c in FINGER_COLOURS.items()],
        legend_box(OUTSIDE_MEANING, facecolor="white", edgecolor=FAIL_COLOUR, hatch="///"),
        legend_box(COLLIDES_MEANING, facecolor="white", edgecolor=COLLISION_COLOUR, lw=1.6),
    ]
    if tight:  # said only when something is: a fit with room to spare keeps its legend
        walls = any(p.name in tight for p in check.tight_parts)
        links = any(c.a in tight or c.b in tight for c in check.tight_pairs)
        said = tight_meaning(walls=walls, links=links)
        handles.append(legend_box(said, facecolor=TIGHT_COLOUR))
    ncol = 9 if len(handles) <= 9 else (len(handles) + 1) // 2
    fig.legend(handles=handles, loc="outside lower center", ncol=ncol, fontsize=8, frameon=False)
    # the verdict in its colour, as the review's and the reach figure's
    fig.suptitle(
        figure_title(check), fontsize=11, color=PASS_COLOUR if check.passed else FAIL_COLOUR
    )
    fig.savefig(path, dpi=dpi)
    return path


def figure_title(check: StowedCheck) -> str:
    """The figure's title: whether the parts fit the bays, the least clearance and the
    self-collision; a design whose parts fit but collide, or whose deployment path is
    not clear, is said to fail, as its verdict says."""
    status = "fits" if check.fits else "DOES NOT FIT"
    if check.passed and check.tight:
        status = f"{check.fits_words}: under {clearance_text(TIGHT_CLEARANCE)}"
    if check.fits and not check.passed:
        why = ["collide"] if check.self_collision else []
        if not check.deploy_clear:
            why.append("the deployment path is not clear")
        status = "FAILS: the parts fit the bays but " + " and ".join(why)
    # a tight pair is named by its distance (the min clearance above is the walls')
    close = check.min_self_clearance if check.passed and check.tight_pairs else None
    return (
        f"Stowed payload in the two lower bays ({status}; min clearance "
        f"{clearance_text(check.min_clearance)}; self-collision: "
        f"{'yes' if check.self_collision else 'none'}"
        + (f", closest {clearance_text(close.distance)}" if close is not None else "")
        + ")"
    )


def _deployment_panel(ax: Any, geom: PayloadGeometry, vehicle: Vehicle, check: StowedCheck) -> None:
    """Silhouettes at stowed (dashed) and deployed, with the vehicle body (front view)."""
    tree = geom.tree
    draw_vehicle(ax, vehicle, 0)
    stage = tree.joint_map["stage"]
    for s, deployed in ((stage.lower, False), (stage.upper, True)):
        q = dict(check.q)
        q["stage"] = s
        for name, solid in posed_solids(geom, q).items():
            polys = polygons(to_view(solid, 0).project(), 0)
            if deployed:
                patch = polygon_patch(
                    polys, facecolor=part_colour(name), alpha=0.6, edgecolor="none", zorder=2
                )
            else:
                patch = polygon_patch(
                    polys, fill=False, edgecolor=part_colour(name), lw=0.6, ls="--", zorder=3
                )
            if patch is not None:
                ax.add_patch(patch)
    sweep = check.sweep
    ax.axhline(vehicle.bottom_z * 1e3, color="#6b6b6b", lw=0.8)
    blo, bhi = vehicle.body_lower * 1e3, vehicle.body_upper * 1e3
    ax.set_xlim(blo[1] - 10, bhi[1] + 10)
    ax.set_ylim((vehicle.bottom_z - stage.upper) * 1e3 - 50, 60)
    ax.set_aspect("equal")
    ax.set_xlabel("y [mm]")
    ax.set_ylabel("z [mm]")
    verdict = (
        "clear"
        if sweep.clear
        else ("carried parts collide" if sweep.vehicle_clear else "BLOCKED by the vehicle")
    )
    if not check.unfolding.clear:
        u = check.unfolding
        verdict += "; the fingers unfolding: " + (
            "hit the vehicle" if u.hits else "links collide" if u.collisions else "not proved clear"
        )
    ax.set_title(
        f"deployment sweep, stage 0 -> {stage.upper * 1e3:.0f} mm (dashed: stowed): {verdict}\n"
        f"closest {clearance_text(sweep.min_distance)}, {sweep.between[0]} / {sweep.between[1]}",
        fontsize=9,
    )


__all__ = [
    "envelope_figure",
]
