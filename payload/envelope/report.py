"""Envelope and reach reports: Markdown, PNG figures (matplotlib) and JSON in ``analyses/``."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import manifold3d as m3d
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import PathPatch, Rectangle
from matplotlib.path import Path as MplPath

from payload.design.params import FINGERS
from payload.envelope.fit import EnvelopeAnalysis, StowedCheck
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.reach import OPPOSITION_CONE, ReachAnalysis, reach_json
from payload.envelope.vehicle import Vehicle, display_path
from payload.safeio import OverwriteError, replace_file, replacing

FINGER_COLOURS = {"A": "#1f77b4", "B": "#ff7f0e", "C": "#2ca02c", "D": "#d62728"}
STRUCTURE_COLOUR = "#8c8c8c"

# a view: (name, section axis, (horizontal axis, vertical axis))
_AXES = {0: (1, 2), 1: (0, 2), 2: (0, 1)}
_LABEL = "xyz"


def _round_mm(x: float) -> float | None:
    return round(float(x) * 1e3, 2) if np.isfinite(x) else None


# ----------------------------------------------------------------- JSON


def _check_json(check: StowedCheck) -> dict[str, Any]:
    sweep = check.sweep
    closest = check.min_self_clearance
    return {
        "fits": check.fits,
        "min_clearance_mm": _round_mm(check.min_clearance),
        "tightest": {"part": check.tightest.name, "wall": check.tightest.wall},
        "parts": [
            {
                "name": p.name,
                "inside": p.inside,
                "clearance_mm": _round_mm(p.clearance),
                "protrusion_mm": _round_mm(p.protrusion),
                "wall": p.wall,
                "outside_volume_mm3": round(p.outside_volume * 1e9, 3),
                "mounted": p.mounted,
                "wall_clearance_mm": [_round_mm(w) for w in p.wall_clearance],
            }
            for p in check.parts
        ],
        "self_collision": check.self_collision,
        "self_collisions": [
            {
                "links": [c.a, c.b],
                "depth_mm": _round_mm(-c.distance),
                "overlap_mm3": round(c.overlap_volume * 1e9, 1),
            }
            for c in check.collisions
        ],
        "min_self_clearance_mm": _round_mm(closest.distance),
        "min_self_clearance_links": [closest.a, closest.b],
        "deploy_path_clear": sweep.clear,
        "deploy_path": {
            "vehicle_clear": sweep.vehicle_clear,
            "carried_parts_clear": not any(
                c.colliding and "base" not in (c.a, c.b) for c in check.self_contacts
            ),
            "min_distance_mm": _round_mm(sweep.min_distance),
            "at_stage_mm": _round_mm(sweep.at_stage),
            "between": list(sweep.between),
            "samples": sweep.samples,
            "certified": sweep.certified,
            "first_contact_mm": _round_mm(sweep.first_contact),
        },
        "passed": check.passed,
        "failures": check.failures(),
    }


def envelope_json(a: EnvelopeAnalysis) -> dict[str, Any]:
    """The JSON object of ``payload report envelope --json`` (lengths in mm)."""
    given = _check_json(a.given)
    q = a.given.q
    posture = {
        "finger": [q[f"A_{j}"] for j in ("mcp_flex", "mcp_abd", "pip", "dip")],
        "rail": q["rail"],
        "stage": q["stage"],
    }
    search = None
    if a.search is not None and a.suggested is not None:
        search = {
            "finger": [round(v, 4) for v in a.search.finger],
            "min_clearance_mm": _round_mm(a.search.clearance),
            "limited_by": a.search.limited_by,
            "evaluations": a.search.evaluations,
            "seconds": round(a.search.seconds, 2),
            "check": {k: v for k, v in _check_json(a.suggested).items() if k != "parts"},
        }
    return {
        "design": display_path(a.design_source),
        **given,
        "posture": posture,
        "excluded_pairs": [list(p) for p in a.excluded_pairs],
        "approximate_pieces": [
            {"piece": name, "hull_excess": round(ex, 4)} for name, ex in a.approximate
        ],
        "stowed_search": search,
        "vehicle": {**a.vehicle.to_dict(), "source": a.vehicle.source},
        "assumptions": a.assumptions(),
        "seconds": round(a.seconds, 2),
    }


# ----------------------------------------------------------------- figures


def _posed(geom: PayloadGeometry, q: Mapping[str, float]) -> dict[str, m3d.Manifold]:
    poses = geom.poses(q)
    return {name: geom.posed_solid(name, poses[name]) for name in geom.links}


def _to_view(solid: m3d.Manifold, axis: int) -> m3d.Manifold:
    """Rotate so that ``axis`` becomes z and the view axes become x, y (in _AXES order)."""
    if axis == 2:
        return solid
    if axis == 0:  # (x, y, z) -> (y, z, x)
        return solid.transform([[0, 1, 0, 0], [0, 0, 1, 0], [1, 0, 0, 0]])
    # axis == 1: (x, y, z) -> (z, x, y), then swap the plotted axes
    return solid.transform([[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0]])


def _polygons(section: m3d.CrossSection, axis: int) -> list[np.ndarray]:
    polys = [np.asarray(p, dtype=float) for p in section.to_polygons()]
    if axis == 1:
        polys = [p[:, ::-1] for p in polys]
    return [p for p in polys if len(p) >= 3]


def _patch(polys: Sequence[np.ndarray], **kw: Any) -> PathPatch | None:
    if not polys:
        return None
    verts, codes = [], []
    for p in polys:
        p = p * 1e3
        verts += [*p.tolist(), p[0].tolist()]
        codes += [MplPath.MOVETO] + [MplPath.LINETO] * (len(p) - 1) + [MplPath.CLOSEPOLY]
    return PathPatch(MplPath(verts, codes), **kw)


def _colour(name: str) -> str:
    return FINGER_COLOURS.get(name[0], STRUCTURE_COLOUR) if name[1:2] == "_" else STRUCTURE_COLOUR


def _draw_vehicle(ax: Any, vehicle: Vehicle, axis: int, full_body: bool = True) -> None:
    h, v = _AXES[axis]
    blo, bhi = vehicle.body_lower * 1e3, vehicle.body_upper * 1e3
    lo, hi = vehicle.bay_lower * 1e3, vehicle.bay_upper * 1e3
    if full_body:
        ax.add_patch(
            Rectangle(
                (blo[h], blo[v]),
                bhi[h] - blo[h],
                bhi[v] - blo[v],
                fill=True,
                facecolor="#f2efe6",
                edgecolor="#6b6b6b",
                lw=1.0,
                zorder=0,
                label="Astrobee body",
            )
        )
    ax.add_patch(
        Rectangle(
            (lo[h], lo[v]),
            hi[h] - lo[h],
            hi[v] - lo[v],
            fill=True,
            facecolor="white",
            edgecolor="black",
            lw=1.2,
            ls="--",
            zorder=0.5,
            label="bay envelope (assumed)",
        )
    )


def _section_panel(
    ax: Any,
    solids: Mapping[str, m3d.Manifold],
    vehicle: Vehicle,
    axis: int,
    value: float,
    parts_by_name: Mapping[str, Any],
    title: str,
    colliding: frozenset[str] = frozenset(),
) -> None:
    h, v = _AXES[axis]
    _draw_vehicle(ax, vehicle, axis)
    for name, solid in solids.items():
        view = _to_view(solid, axis)
        sil = _patch(
            _polygons(view.project(), axis),
            facecolor=_colour(name),
            alpha=0.12,
            edgecolor="none",
            zorder=1,
        )
        if sil is not None:
            ax.add_patch(sil)
        sec = _polygons(view.slice(value), axis)
        fit = parts_by_name.get(name)
        outside = fit is not None and not fit.inside
        edge = "red" if outside else ("magenta" if name in colliding else "black")
        patch = _patch(
            sec,
            facecolor=_colour(name),
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
    ax.set_xlabel(f"{_LABEL[h]} [mm]")
    ax.set_ylabel(f"{_LABEL[v]} [mm]")
    ax.set_title(
        f"{title}\nsection {_LABEL[axis]} = {value * 1e3:.1f} mm (shaded: silhouettes)", fontsize=9
    )


def _annotate_clearances(ax: Any, check: StowedCheck, vehicle: Vehicle, axis: int) -> None:
    """Mark, for each wall seen in this view, the smallest clearance and its part."""
    h, v = _AXES[axis]
    lo, hi = vehicle.bay_lower * 1e3, vehicle.bay_upper * 1e3
    for w, wall in enumerate(vehicle.walls):
        ax_i = w // 2
        if ax_i not in (h, v):
            continue
        vals = [
            (p.wall_clearance[w], p.name)
            for p in check.parts
            if p.inside and np.isfinite(p.wall_clearance[w])
        ]
        outs = [(p.protrusion, p.name) for p in check.parts if not p.inside and p.wall == wall]
        if outs:
            d, name = max(outs)
            text, colour = f"{name}: {d * 1e3:.1f} mm out", "red"
        elif vals:
            d, name = min(vals)
            text, colour = f"{d * 1e3:.1f} mm ({name})", "black"
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
    solids = _posed(geom, check.q)
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
    panels = (
        (axes[0, 0], 0, xa, "front view (y-z), through finger A"),
        (axes[0, 1], 1, ya, "side view (x-z), through fingers A, B"),
        (axes[1, 0], 2, z_mcp, "top view (x-y), through the MCP axes"),
    )
    for ax, axis, value, title in panels:
        _section_panel(ax, solids, a.vehicle, axis, value, fits, title, hit)
        _annotate_clearances(ax, check, a.vehicle, axis)
    # deployment: silhouettes at stowed and deployed, with the vehicle body
    ax = axes[1, 1]
    _draw_vehicle(ax, a.vehicle, 0)
    stage = tree.joint_map["stage"]
    for s, deployed in ((stage.lower, False), (stage.upper, True)):
        q = dict(check.q)
        q["stage"] = s
        for name, solid in _posed(geom, q).items():
            polys = _polygons(_to_view(solid, 0).project(), 0)
            if deployed:
                patch = _patch(
                    polys, facecolor=_colour(name), alpha=0.6, edgecolor="none", zorder=2
                )
            else:
                patch = _patch(
                    polys, fill=False, edgecolor=_colour(name), lw=0.6, ls="--", zorder=3
                )
            if patch is not None:
                ax.add_patch(patch)
    sweep = check.sweep
    ax.axhline(a.vehicle.bottom_z * 1e3, color="#6b6b6b", lw=0.8)
    blo, bhi = a.vehicle.body_lower * 1e3, a.vehicle.body_upper * 1e3
    ax.set_xlim(blo[1] - 10, bhi[1] + 10)
    ax.set_ylim((a.vehicle.bottom_z - stage.upper) * 1e3 - 50, 60)
    ax.set_aspect("equal")
    ax.set_xlabel("y [mm]")
    ax.set_ylabel("z [mm]")
    verdict = (
        "clear"
        if sweep.clear
        else ("carried parts collide" if sweep.vehicle_clear else "BLOCKED by the vehicle")
    )
    ax.set_title(
        f"deployment sweep, stage 0 -> {stage.upper * 1e3:.0f} mm (dashed: stowed): {verdict}\n"
        f"closest {sweep.min_distance * 1e3:.1f} mm, {sweep.between[0]} / {sweep.between[1]}",
        fontsize=9,
    )
    handles = [
        Rectangle((0, 0), 1, 1, facecolor="#f2efe6", edgecolor="#6b6b6b", label="Astrobee body"),
        Rectangle(
            (0, 0),
            1,
            1,
            facecolor="white",
            edgecolor="black",
            ls="--",
            label="bay envelope (ASSUMED size)",
        ),
        Rectangle((0, 0), 1, 1, facecolor=STRUCTURE_COLOUR, label="structure"),
        *[
            Rectangle((0, 0), 1, 1, facecolor=c, label=f"finger {f}")
            for f, c in FINGER_COLOURS.items()
        ],
        Rectangle(
            (0, 0),
            1,
            1,
            facecolor="white",
            edgecolor="red",
            hatch="///",
            label="outside the envelope",
        ),
        Rectangle(
            (0, 0), 1, 1, facecolor="white", edgecolor="magenta", lw=1.6, label="self-collision"
        ),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=9, fontsize=8, frameon=False)
    status = "fits" if check.fits else "DOES NOT FIT"
    fig.suptitle(
        f"Stowed payload in the two lower bays ({status}; min clearance "
        f"{check.min_clearance * 1e3:.1f} mm; self-collision: "
        f"{'yes' if check.self_collision else 'none'})",
        fontsize=11,
    )
    fig.savefig(path, dpi=dpi)
    return path


def reach_figure(
    geom: PayloadGeometry, a: ReachAnalysis, path: Path, dpi: int = 100, points: int = 2500
) -> Path:
    """Fingertip clouds with the vehicle outline in three views, and the span histograms."""
    rng = np.random.default_rng(0)
    fig = Figure(figsize=(13, 10), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 2)
    home = _posed(geom, geom.tree.posture("home"))
    views = (
        (axes[0, 0], 1, "side view (x-z)"),
        (axes[0, 1], 0, "front view (y-z)"),
        (axes[1, 0], 2, "top view (x-y)"),
    )
    for ax, axis, title in views:
        h, v = _AXES[axis]
        _draw_vehicle(ax, a.vehicle, axis, full_body=True)
        if axis != 2:
            ax.axhline(a.vehicle.bottom_z * 1e3, color="#6b6b6b", lw=0.8)
        for name, solid in home.items():
            patch = _patch(
                _polygons(_to_view(solid, axis).project(), axis),
                facecolor=_colour(name),
                alpha=0.5,
                edgecolor="none",
                zorder=2,
            )
            if patch is not None:
                ax.add_patch(patch)
        for w in a.workspaces:
            k = rng.choice(len(w.points), size=min(points, len(w.points)), replace=False)
            pts = w.points[k] * 1e3
            ax.scatter(
                pts[:, h],
                pts[:, v],
                s=0.6,
                alpha=0.25,
                color=FINGER_COLOURS[w.finger],
                zorder=3,
                rasterized=True,
            )
        allp = np.vstack([w.points for w in a.workspaces]) * 1e3
        blo, bhi = a.vehicle.body_lower * 1e3, a.vehicle.body_upper * 1e3
        lo = np.minimum(allp.min(axis=0), blo) - 15
        hi = np.maximum(allp.max(axis=0), bhi) + 15
        if axis != 2:
            hi[2] = min(hi[2], a.vehicle.bottom_z * 1e3 + 80)
        ax.set_xlim(lo[h], hi[h])
        ax.set_ylim(lo[v], hi[v])
        ax.set_aspect("equal")
        ax.set_xlabel(f"{_LABEL[h]} [mm]")
        ax.set_ylabel(f"{_LABEL[v]} [mm]")
        ax.set_title(f"{title}: reachable fingertip samples, home posture shaded", fontsize=9)
    ax = axes[1, 1]
    r = geom.tree.design.finger.pad.radius
    bins = np.linspace(0, max(p.span.maximum for p in a.pairs) * 1e3, 80)
    for p, colour in zip(a.pairs, ("#1f77b4", "#ff7f0e")):
        f1, f2 = p.fingers
        i1, i2 = FINGERS.index(f1), FINGERS.index(f2)
        ell = np.linalg.norm(a.tips[:, i2] - a.tips[:, i1], axis=1) * 1e3
        ax.hist(ell, bins=bins, histtype="step", color=colour, label=f"pair {p.name}: all samples")
        ax.hist(
            ell[p.free],
            bins=bins,
            histtype="stepfilled",
            color=colour,
            alpha=0.3,
            label=f"pair {p.name}: pair touching nothing",
        )
        # pair L wide and dashed under pair R thin and dotted: equal ranges stay visible
        style = {"ls": "--", "lw": 2.4} if p.name == "L" else {"ls": ":", "lw": 1.2}
        ax.axvline(p.span_min * 1e3, color=colour, label=f"pair {p.name}: span range", **style)
        ax.axvline(p.span.maximum * 1e3, color=colour, **style)
        for g in p.grasps:
            x = (g.feature.thickness + 2 * r) * 1e3
            ax.plot(
                [x],
                [0],
                marker="^" if g.closes else "x",
                color="green" if g.closes else "red",
                ms=7,
                clip_on=False,
                zorder=4,
            )
    ax.plot([], [], ls="none", marker="^", color="green", label="CTB feature: pair closes on it")
    ax.plot([], [], ls="none", marker="x", color="red", label="CTB feature: no witness")
    ax.set_xlabel("fingertip separation l [mm] (vertical lines: span range)")
    ax.set_ylabel("samples")
    ax.set_title(
        "pair spans; markers: CTB thicknesses + pad diameter (green: closes, red: no witness)",
        fontsize=9,
    )
    ax.legend(fontsize=8)
    handles = [
        Rectangle((0, 0), 1, 1, facecolor=c, label=f"finger {f}: fingertip samples, home shaded")
        for f, c in FINGER_COLOURS.items()
    ]
    handles += [
        Rectangle((0, 0), 1, 1, facecolor=STRUCTURE_COLOUR, alpha=0.5, label="structure (home)"),
        Rectangle((0, 0), 1, 1, facecolor="#f2efe6", edgecolor="#6b6b6b", label="Astrobee body"),
        Rectangle(
            (0, 0),
            1,
            1,
            facecolor="white",
            edgecolor="black",
            ls="--",
            label="bay envelope (ASSUMED size)",
        ),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle(
        f"Reach of the deployed fingers ({a.samples:,} samples; below the bottom face up to "
        f"{a.below_vehicle * 1e3:.0f} mm; self-collision-free {a.collision_free_fraction:.1%})",
        fontsize=11,
    )
    fig.savefig(path, dpi=dpi)
    return path


# ----------------------------------------------------------------- Markdown


def _assumption_block(lines: Sequence[str]) -> list[str]:
    return ["> **Assumptions**", ">", *[f"> - {line}" for line in lines], ""]


def envelope_markdown(a: EnvelopeAnalysis, command: str, figure: str) -> str:
    """The envelope report as Markdown."""
    g = a.given
    q = g.q
    finger = ", ".join(f"{q[f'A_{j}']:.4f}" for j in ("mcp_flex", "mcp_abd", "pip", "dip"))
    tight = g.tightest
    out = [
        "# Envelope report: the stowed payload in Astrobee's two lower bays",
        "",
        f"Generated by `{command}` from `{display_path(a.design_source)}` (timings: "
        "`envelope.timing.json`, not committed).",
        "",
        *_assumption_block(a.assumptions()),
        "## Verdict",
        "",
    ]
    if g.passed:
        out.append(
            f"**The stowed payload fits** the {_size(a.vehicle.bay_size)} envelope with "
            f"**{tight.clearance * 1e3:.1f} mm** of clearance at its tightest ({tight.name}, "
            f"{tight.wall} wall); no self-collision; the deployment path is clear."
        )
    else:
        status = "fits inside" if g.fits else "does **not** fit inside"
        out.append(
            f"**The stowed configuration fails the envelope check.** Every part {status} the "
            f"envelope"
            + (f" (tightest {tight.clearance * 1e3:.1f} mm, {tight.name})" if g.fits else "")
            + ", but:"
        )
        out.append("")
        out += [f"- {f}" for f in g.failures()]
    out += [
        "",
        f"Stowed configuration: stage {q['stage'] * 1e3:.1f} mm, rail {q['rail'] * 1e3:.1f} mm, "
        f"every finger [mcp_flex, mcp_abd, pip, dip] = [{finger}] rad.",
        "",
        f"![cross-sections]({figure})",
        "",
        "## Parts in the envelope",
        "",
        "Clearance is the python-fcl distance from the part's mesh to the nearest wall; a "
        "negative value is the protrusion (the farthest part point beyond the walls). "
        "Outside volume is the manifold3d difference part - envelope.",
        "",
        "| part | inside | clearance [mm] | nearest / crossed wall | outside volume [mm^3] |",
        "| --- | --- | ---: | --- | ---: |",
    ]
    for p in g.parts:
        note = " (mounted on the +z face)" if p.mounted else ""
        out.append(
            f"| {p.name} | {'yes' if p.inside else '**no**'} | {p.clearance * 1e3:.2f} | "
            f"{p.wall}{note} | {p.outside_volume * 1e9:.1f} |"
        )
    out += ["", "## Self-collision (stowed)", ""]
    if g.collisions:
        out += ["| links | depth [mm] | shared volume [mm^3] |", "| --- | ---: | ---: |"]
        for c in g.collisions:
            out.append(
                f"| {c.a} / {c.b} | {-c.distance * 1e3:.1f} | {c.overlap_volume * 1e9:.0f} |"
            )
    else:
        c = g.min_self_clearance
        out.append(f"None. Closest non-adjacent links: {c.a} / {c.b}, {c.distance * 1e3:.2f} mm.")
    excluded = ", ".join(f"{p} / {c}" for p, c in a.excluded_pairs)
    out += [
        "",
        f"Checked: every pair of links except the {len(a.excluded_pairs)} parent/child pairs "
        f"joined by a joint (they meet at the joint by construction): {excluded}.",
        "Overlap is the exact shared volume of the two solids (manifold3d intersection); depth "
        "is the GJK/EPA penetration of their convex pieces.",
    ]
    if a.approximate:
        pieces = ", ".join(f"{n} (+{ex:.1%})" for n, ex in a.approximate)
        out.append(
            f"Convex pieces larger than their part (hull volume excess): {pieces}; they only "
            "affect depths and clearances, never the overlap volumes."
        )
    s = g.sweep
    out += [
        "",
        "## Deployment sweep",
        "",
        f"The stage travels {a.given.q['stage'] * 1e3:.0f} -> "
        f"{_stage_upper(a) * 1e3:.0f} mm with the fingers stowed. Distances to the vehicle body "
        "(five boxes around the open bays) and to the base, at "
        f"{s.samples} stage positions; every interval between them is proved contact-free "
        "(the distance is 1-Lipschitz in the travel)"
        + ("" if s.certified else " **except where the halving stopped**")
        + ".",
        "",
        f"- vehicle and base: {'clear' if s.vehicle_clear else '**contact**'}; closest "
        f"{s.min_distance * 1e3:.2f} mm ({s.between[0]} / {s.between[1]}) at stage "
        f"{s.at_stage * 1e3:.1f} mm",
        "- parts the stage carries (they move as one body): "
        + (
            "clear"
            if not any(c.colliding and "base" not in (c.a, c.b) for c in g.self_contacts)
            else "**collide** (see self-collision)"
        ),
        f"- deployment path clear: **{'yes' if s.clear else 'no'}**",
        "",
    ]
    out += ["## Stowed-posture search", ""]
    if a.search is None:
        out.append("Not run (it runs when the given posture fails, or with `--search`).")
    else:
        sr, sc = a.search, a.suggested
        assert sc is not None
        fing = ", ".join(f"{v:.4f}" for v in sr.finger)
        out += [
            "The posture shared by the four fingers, inside the joint limits, that maximises "
            "the smallest of the fingers' envelope clearances and their signed distances to "
            f"every non-adjacent link ({sr.evaluations} evaluations: a "
            "6^4 grid, then Nelder-Mead from the 3 best):",
            "",
            f"- finger [mcp_flex, mcp_abd, pip, dip] = [{fing}] rad",
            f"- smallest clearance {sr.clearance * 1e3:.2f} mm, limited by {sr.limited_by}",
            f"- checked like the given posture: fits {'yes' if sc.fits else 'no'}, min clearance "
            f"{sc.min_clearance * 1e3:.2f} mm, self-collision "
            f"{'yes' if sc.self_collision else 'no'}, deployment path "
            f"{'clear' if sc.sweep.clear else 'blocked'}: "
            f"**{'passes' if sc.passed else 'fails'}**",
        ]
        if not sc.passed:
            out += [
                "",
                "No finger posture stows this design: change the design. Failures of the "
                "best posture:",
                "",
            ]
            out += [f"  - {f}" for f in sc.failures()[:8]]
    out += [
        "",
        "## Method",
        "",
        "- Containment: a part is inside when every vertex of its convex pieces is inside "
        "the (convex) envelope, which is exact for polyhedral solids, and the manifold3d "
        "difference part - envelope has no volume.",
        "- Clearance: python-fcl distance between the part's triangle mesh and slabs on the "
        "six walls; protrusion: the largest distance of a part vertex outside the envelope.",
        "- The mounted part's contact with the +z (mount) face is its mounting, not a clearance.",
        "",
    ]
    return "\n".join(out)


def _stage_upper(a: EnvelopeAnalysis) -> float:
    return float(a.extra.get("stage_upper", 0.0))


def _size(size: Sequence[float]) -> str:
    return " x ".join(f"{v * 1e3:.0f}" for v in size) + " mm"


def reach_markdown(a: ReachAnalysis, command: str, figure: str) -> str:
    """The reach report as Markdown."""
    j = reach_json(a)
    out = [
        "# Reach report: what the deployed fingers can reach and grasp",
        "",
        f"Generated by `{command}` from `{display_path(a.design_source)}`: {a.samples:,} "
        f"configurations (seed {a.seed}).",
        "",
        *_assumption_block(a.assumptions()),
        "## Summary",
        "",
        f"- Fingertips reach **{a.below_vehicle * 1e3:.1f} mm** below the vehicle's bottom face "
        f"(home posture, fingers straight: {a.home_below_vehicle * 1e3:.1f} mm; the pads reach "
        f"{a.pairs[0].pad_contact / 2 * 1e3:.0f} mm further).",
        f"- Pair spacing over the rail: **{a.rail_spacing[0] * 1e3:.1f} .. "
        f"{a.rail_spacing[1] * 1e3:.1f} mm** (x distance between the pairs' MCP centres).",
        f"- Self-collision-free samples: **{a.collision_free_fraction:.1%}**; touching the "
        f"vehicle: {j['vehicle_contact_fraction']:.1%}; free of both: "
        f"{j['free_fraction_with_vehicle']:.1%}.",
        "",
        f"![reach]({figure})",
        "",
        "## Pairs",
        "",
        "Span is eq. 2's fingertip separation l = |p2 - p1|. The minimum is where the pads "
        "touch when the fingertip points can come closer than the pad diameter (they can: the "
        "geometric minimum is given too).",
        "",
        "| pair | fingers | span min [mm] | span max [mm] | geometric min [mm] | "
        "free samples | collision-free span [mm] | opposing, below vehicle [mm] |",
        "| --- | --- | ---: | ---: | ---: | ---: | --- | --- |",
    ]
    for p in a.pairs:
        out.append(
            f"| {p.name} | {' / '.join(p.fingers)} | {p.span_min * 1e3:.1f} | "
            f"{p.span.maximum * 1e3:.1f} | {p.span.minimum * 1e3:.1f} | {p.free_fraction:.1%} | "
            f"{_rng(p.free_span)} | {_rng(p.opposed_span)} |"
        )
    out += [
        "",
        "## CTB grasp check",
        "",
        f"A pair closes on a thickness t when a witness exists: joints inside the limits, the "
        f"pinch axis within {np.degrees(OPPOSITION_CONE):.0f} deg of the across-array axis, both "
        "pads wholly below the vehicle's bottom face, fingertip separation t + pad diameter "
        "(to 0.1 mm), and no contact of the pair's links with anything (the other pair aside).",
        "",
        "| feature | thickness [mm] | source | pair L | pair R |",
        "| --- | ---: | --- | --- | --- |",
    ]
    by_feature: dict[str, dict[str, Any]] = {}
    for p in a.pairs:
        for g in p.grasps:
            by_feature.setdefault(g.feature.name, {"f": g.feature})[p.name] = g
    for name, row in by_feature.items():
        f = row["f"]
        cells = []
        for pair in ("L", "R"):
            g = row.get(pair)
            if g is None:
                cells.append("-")
            elif g.closes:
                cells.append(
                    f"closes ({np.degrees(g.angle):.0f} deg, {g.depth * 1e3:.0f} mm below)"
                )
            elif np.isfinite(g.span):
                cells.append(f"no witness (nearest opposing candidate l = {g.span * 1e3:.1f} mm)")
            else:
                cells.append("no witness")
        out.append(f"| {name} | {f.thickness * 1e3:.1f} | {f.source} | {cells[0]} | {cells[1]} |")
    out += [
        "",
        "## Fingertip workspaces",
        "",
        "Reachable: samples in which the finger's links touch nothing (the other fingers "
        "aside, which can move away).",
        "",
        "| finger | reachable samples | hull volume [cm^3] | x [mm] | y [mm] | z [mm] | "
        "below bottom face [mm] |",
        "| --- | ---: | ---: | --- | --- | --- | ---: |",
    ]
    for w in a.workspaces:
        rng = [f"{lo * 1e3:.0f} .. {hi * 1e3:.0f}" for lo, hi in zip(w.lower, w.upper)]
        out.append(
            f"| {w.finger} | {w.reachable:.1%} | {w.hull_volume * 1e6:.0f} | {rng[0]} | {rng[1]} | "
            f"{rng[2]} | "
            f"{w.below_vehicle * 1e3:.1f} |"
        )
    out += ["", "## Most frequent contacts", "", "| links | samples |", "| --- | ---: |"]
    for c in j["collision_pairs"]:
        out.append(f"| {' / '.join(c['links'])} | {c['fraction']:.1%} |")
    out += [
        "",
        "## Timings",
        "",
        "Wall-clock timings change from run to run, so they are not in the committed report: "
        "see `reach.timing.json` (not committed) or the `--json` output.",
        "",
        "## Method",
        "",
        "- Uniform samples of the 17 manipulation joints inside their limits, stage deployed; "
        "batched (vectorised numpy) forward kinematics of the kinematic tree.",
        "- Span range: every combination of one finger's samples with the other's (both hang "
        "from the same link): nearest by a k-d tree, farthest over the hull vertices, both "
        "refined by L-BFGS-B.",
        "- Collisions: MuJoCo on the convex pieces of the link solids; parent/child links "
        "never collide.",
        "",
    ]
    return "\n".join(out)


def _rng(r: tuple[float, float]) -> str:
    if not np.all(np.isfinite(r)):
        return "none"
    return f"{r[0] * 1e3:.1f} .. {r[1] * 1e3:.1f}"


# ----------------------------------------------------------------- writers


TIMING_KEYS = ("seconds", "timings_s")
"""JSON keys holding wall-clock timings: kept out of the committed report files."""


def _split_timings(obj: Any, path: str = "") -> tuple[Any, dict[str, Any]]:
    """(``obj`` without timing keys, the timings by dotted path)."""
    if not isinstance(obj, dict):
        return obj, {}
    kept, timings = {}, {}
    for key, value in obj.items():
        where = f"{path}.{key}" if path else key
        if key in TIMING_KEYS:
            timings[where] = value
        else:
            kept[key], inner = _split_timings(value, where)
            timings.update(inner)
    return kept, timings


PROVENANCE_KEY = "provenance"
"""What a report was computed from (commit, version): recorded, but not a figure."""


def _same_figures(path: Path, text: str) -> bool:
    """Whether the file at ``path`` holds the same report as ``text``: byte for byte, or for
    JSON the same apart from its provenance (a new commit alone changes no figure)."""
    old = path.read_bytes()
    if old == text.encode():
        return True
    if path.suffix != ".json":
        return False
    try:
        before = json.loads(old)
    except ValueError:
        return False
    after = json.loads(text)
    if not isinstance(before, dict):
        return False
    before.pop(PROVENANCE_KEY, None)
    after.pop(PROVENANCE_KEY, None)
    return before == after


def _write_report(
    out_dir: Path,
    stem: str,
    markdown: str,
    data: dict[str, Any],
    draw: Callable[[Path], Any],
    force: bool,
) -> dict[str, Path]:
    """Write ``<stem>.md/.json/.png`` only when the report's figures changed.

    Timings go to ``<stem>.timing.json`` (not committed) every run. Identical ``md`` and
    ``json`` leave all three files untouched; different ones replace existing files only
    with ``force``, each through a temporary file and a rename.

    Raises:
        OverwriteError: The report changed, files exist, and ``force`` is false.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    committed, timings = _split_timings(data)
    texts = {
        out_dir / f"{stem}.md": markdown,
        out_dir / f"{stem}.json": json.dumps(committed, indent=2) + "\n",
    }
    paths = {"png": out_dir / f"{stem}.png", "md": out_dir / f"{stem}.md"}
    paths["json"] = out_dir / f"{stem}.json"
    paths["timing"] = out_dir / f"{stem}.timing.json"
    replace_file(paths["timing"], json.dumps(timings, indent=2) + "\n")
    same = [p for p, t in texts.items() if p.exists() and _same_figures(p, t)]
    if len(same) == len(texts) and paths["png"].exists():
        return {"timing": paths["timing"]}  # nothing but the timings changed
    differ = [p for p in (*texts, paths["png"]) if p.exists() and p not in same]
    if differ and not force:
        raise OverwriteError(
            f"{differ[0]}: the report's figures changed ({', '.join(p.name for p in differ)} "
            "would be replaced); pass --force to replace them, or --out DIR"
        )
    with replacing(paths["png"]) as tmp:
        draw(tmp)
    for path, text in texts.items():
        replace_file(path, text)
    return paths


def write_envelope(
    geom: PayloadGeometry,
    a: EnvelopeAnalysis,
    out_dir: Path,
    command: str,
    record: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
    *,
    force: bool = False,
) -> dict[str, Path]:
    """Write ``envelope.md``, ``envelope.png`` and ``envelope.json`` into ``out_dir`` when
    the report changed (see :func:`_write_report`); returns the paths written. ``record``
    adds fields to the JSON (e.g. its provenance)."""
    a.extra["stage_upper"] = geom.tree.joint_map["stage"].upper
    return _write_report(
        out_dir,
        "envelope",
        envelope_markdown(a, command, "envelope.png"),
        envelope_json(a) if record is None else record(envelope_json(a)),
        lambda path: envelope_figure(geom, a, path),
        force,
    )


def write_reach(
    geom: PayloadGeometry,
    a: ReachAnalysis,
    out_dir: Path,
    command: str,
    t_start: float | None = None,
    record: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
    *,
    force: bool = False,
) -> dict[str, Path]:
    """Write ``reach.md``, ``reach.png`` and ``reach.json`` into ``out_dir`` when the
    report changed (see :func:`_write_report`); returns the paths written.

    Args:
        geom: Collision geometry.
        a: The analysis.
        out_dir: Output directory (created).
        command: The command that reproduces the report.
        t_start: ``time.perf_counter()`` at the command's start: when given, ``a.seconds``
            becomes the wall time up to the writing.
        record: Adds fields to the JSON (e.g. its provenance).
        force: Replace a committed report whose figures changed.
    """
    if t_start is not None:
        a.seconds = time.perf_counter() - t_start
    return _write_report(
        out_dir,
        "reach",
        reach_markdown(a, command, "reach.png"),
        reach_json(a) if record is None else record(reach_json(a)),
        lambda path: reach_figure(geom, a, path),
        force,
    )


__all__ = [
    "envelope_figure",
    "envelope_json",
    "envelope_markdown",
    "reach_figure",
    "reach_markdown",
    "write_envelope",
    "write_reach",
]
