"""The reach report's figure: fingertip clouds in three views, the span histograms."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import manifold3d as m3d
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.legend import Legend
from matplotlib.legend_handler import HandlerTuple
from matplotlib.lines import Line2D
from matplotlib.transforms import ScaledTranslation, Transform

from payload.design.params import FINGERS
from payload.envelope.drawing import (
    AXES,
    AXIS_LABEL,
    FAIL_COLOUR,
    FINGER_COLOURS,
    PASS_COLOUR,
    STRUCTURE_COLOUR,
    draw_vehicle,
    legend_box,
    part_colour,
    polygon_patch,
    polygons,
    posed_solids,
    to_view,
    vehicle_legend,
)
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.grasp import CTB_FEATURES, GraspFeature, GraspResult
from payload.envelope.reach import ReachAnalysis
from payload.envelope.vehicle import Vehicle
from payload.envelope.verdict import reach_passed
from payload.envelope.workspace import Workspace

PAD_IN = 0.1
"""The figure's margin around its panels [in] (matplotlib's 3/72 left the side view's
axis label touching the left edge)."""

LEGEND_GAP_IN = 0.15
"""Between the span panel's two side legends [in]."""


def reach_figure(
    geom: PayloadGeometry, a: ReachAnalysis, path: Path, dpi: int = 100, points: int = 2500
) -> Path:
    """Fingertip clouds with the vehicle outline in three views, and the span histograms."""
    rng = np.random.default_rng(0)
    fig = Figure(figsize=(13, 10))
    fig.set_layout_engine("constrained", w_pad=PAD_IN, h_pad=PAD_IN)  # labels off the edge
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 2)
    home = posed_solids(geom, geom.tree.posture("home"))
    views = (
        (axes[0, 0], 1, "side view (x-z)"),
        (axes[0, 1], 0, "front view (y-z)"),
        (axes[1, 0], 2, "top view (x-y)"),
    )
    for ax, axis, title in views:
        _cloud_panel(ax, axis, title, home, a.vehicle, a.workspaces, rng, points)
    _span_panel(axes[1, 1], a, geom.tree.design.finger.pad.radius)
    handles = [
        legend_box(f"finger {f}: fingertip samples, home shaded", facecolor=c)
        for f, c in FINGER_COLOURS.items()
    ]
    handles += [
        legend_box("structure (home)", facecolor=STRUCTURE_COLOUR, alpha=0.5),
        *vehicle_legend(),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=4, fontsize=8, frameon=False)
    passed = reach_passed(a)  # the verdict first, in its colour, as the review's
    fig.suptitle(
        f"Reach of the deployed fingers: {'passes' if passed else 'FAILS'} "
        f"({a.samples:,} samples; {_depth(a.below_vehicle)}; "
        f"{a.collision_free_fraction:.1%} of them free of self-collision)",
        fontsize=11,
        color=PASS_COLOUR if passed else FAIL_COLOUR,
    )
    fig.savefig(path, dpi=dpi)
    return path


VIEW_MARGIN_MM = 15
"""Margin of the side, front and top views around what they show [mm]."""

PAIR_ROWS = {"L": 0.035, "R": 0.085}
"""Height of each pair's row in the span panel (its span range, its grasp markers), as a
fraction of the axes: in a band of :data:`ROWS_BAND` under the histograms."""
ROWS_BAND = 0.12
"""Fraction of the span panel's height under the histograms' zero: the pairs' rows."""
PAIR_COLOURS = {"L": "#1f77b4", "R": "#ff7f0e"}
"""One colour per pair in the span panel."""
GRASP_MARKERS: dict[bool, dict[str, str]] = {
    True: {"marker": "^", "color": PASS_COLOUR},
    False: {"marker": "x", "color": FAIL_COLOUR},
}
"""A CTB feature's marker in the span panel, by whether the pair closes on it (a green
triangle) or not (no witness: a red cross)."""


def _depth(x: float) -> str:
    """The fingertips' depth below the bottom face (NaN: no finger moved free)."""
    if not np.isfinite(x):
        return "no finger moved free in any sample"
    return f"below the bottom face up to {x * 1e3:.0f} mm"


def _cloud_panel(
    ax: Any,
    axis: int,
    title: str,
    home: Mapping[str, m3d.Manifold],
    vehicle: Vehicle,
    workspaces: Sequence[Workspace],
    rng: np.random.Generator,
    points: int,
) -> None:
    """Reachable fingertip samples (``points`` per finger) seen along ``axis``, home shaded."""
    h, v = AXES[axis]
    draw_vehicle(ax, vehicle, axis, full_body=True)
    if axis != 2:
        ax.axhline(vehicle.bottom_z * 1e3, color="#6b6b6b", lw=0.8)
    for name, solid in home.items():
        patch = polygon_patch(
            polygons(to_view(solid, axis).project(), axis),
            facecolor=part_colour(name),
            alpha=0.5,
            edgecolor="none",
            zorder=2,
        )
        if patch is not None:
            ax.add_patch(patch)
    for w in workspaces:
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
    blo, bhi = vehicle.body_lower * 1e3, vehicle.body_upper * 1e3
    shaded = [np.reshape(solid.bounding_box(), (2, 3)) * 1e3 for solid in home.values()]
    allp = np.vstack([blo, bhi, *shaded, *(w.points * 1e3 for w in workspaces)])
    lo = allp.min(axis=0) - VIEW_MARGIN_MM
    hi = allp.max(axis=0) + VIEW_MARGIN_MM
    if axis != 2:  # the body's lower part only, and the whole bay envelope (its top too)
        top = max(vehicle.bottom_z * 1e3 + 80, vehicle.bay_upper[2] * 1e3 + VIEW_MARGIN_MM)
        hi[2] = min(hi[2], top)
    ax.set_xlim(lo[h], hi[h])
    ax.set_ylim(lo[v], hi[v])
    ax.set_aspect("equal")
    ax.set_xlabel(f"{AXIS_LABEL[h]} [mm]")
    ax.set_ylabel(f"{AXIS_LABEL[v]} [mm]")
    ax.set_title(f"{title}: reachable fingertip samples, home posture shaded", fontsize=9)


def _span_panel(ax: Any, a: ReachAnalysis, pad_radius: float) -> None:
    """Histograms of the pairs' fingertip separations and, under them, a row per pair: its
    span range and the CTB features (their thickness plus the pad diameter) it closes on."""
    r = pad_radius
    bins = np.linspace(0, max(p.span.maximum for p in a.pairs) * 1e3, 80)
    for p in a.pairs:
        colour = PAIR_COLOURS[p.name]
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
    # the pairs' rows in a band of their own under the histograms: equal span ranges and
    # markers at the same thickness stay apart, and none of them hides a bin
    top = ax.get_ylim()[1]
    ax.set_ylim(-top * ROWS_BAND / (1 - ROWS_BAND), top)
    ax.set_yticks([t for t in ax.get_yticks() if 0 <= t <= top])
    ax.axhline(0, color="black", lw=0.5)
    for p in a.pairs:
        colour, row = PAIR_COLOURS[p.name], PAIR_ROWS[p.name]
        lo, hi = p.span_min * 1e3, p.span.maximum * 1e3
        ax.plot(
            [lo, hi],
            [row, row],
            color=colour,
            lw=2.0,
            marker="|",
            ms=9,
            mew=2.0,
            transform=ax.get_xaxis_transform(),
            label=f"pair {p.name}: span range {lo:.1f} .. {hi:.1f} mm",
        )
        for g in p.grasps:
            ax.plot(
                [_separation_mm(g.feature, r)],
                [row],
                **GRASP_MARKERS[g.closes],
                ms=7,
                clip_on=False,
                zorder=4,
                transform=ax.get_xaxis_transform(),
            )
        ax.annotate(
            p.name,
            (0, row),
            xycoords="axes fraction",
            xytext=(-4, 0),
            textcoords="offset points",
            ha="right",
            va="center",
            fontsize=8,
            color=colour,
        )
    ax.plot([], [], ls="none", **GRASP_MARKERS[True], label="CTB feature: pair closes on it")
    ax.plot([], [], ls="none", **GRASP_MARKERS[False], label="CTB feature: no witness")
    ax.set_xlabel("fingertip separation l [mm]")
    ax.set_ylabel("samples")
    ax.set_title(
        "pair spans; under them a row per pair (L lower, R upper): its span range and the\n"
        "CTB thicknesses + pad diameter (green: the pair closes on it, red: no witness)",
        fontsize=9,
    )
    # beside the panel, where it covers no bin, line or marker; the features' under it, its
    # top its measured height below the panel's top, whatever the layout makes of the panel
    # (not clipped to the panel, as an added artist is by default, so the layout makes room)
    spans = ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    fig = ax.get_figure()
    drop = spans.get_window_extent().height / fig.dpi + LEGEND_GAP_IN
    under = ax.transAxes + ScaledTranslation(0, -drop, fig.dpi_scale_trans)
    ax.add_artist(_feature_legend(ax, a, r, under)).set_clip_on(False)


def _separation_mm(feature: GraspFeature, pad_radius: float) -> float:
    """Where a feature's marker stands: the fingertip separation that closes the pads on
    it, its thickness plus the pad diameter [mm]."""
    return (feature.thickness + 2 * pad_radius) * 1e3


def _feature_legend(ax: Any, a: ReachAnalysis, pad_radius: float, under: Transform) -> Legend:
    """Beside the span panel, under its legend (its top left at axes (1.01, 1) in
    ``under``, a transform that drops it below that legend): which grasp feature each
    marker column is, one entry per feature in the markers' order (left to right), its
    markers (one per pair, as the rows draw them) and its separation; the markers stand
    too close together (a few mm apart) for a name beside each. Titled "CTB features",
    or "grasp features" when ``--thickness`` values are among them."""
    by_feature: dict[str, list[GraspResult]] = {}
    for p in a.pairs:
        for g in p.grasps:
            by_feature.setdefault(g.feature.name, []).append(g)
    handles, labels = [], []
    for name, grasps in sorted(by_feature.items(), key=lambda kv: kv[1][0].feature.thickness):
        handles.append(
            tuple(Line2D([], [], ls="none", ms=6, **GRASP_MARKERS[g.closes]) for g in grasps)
        )
        labels.append(f"{_separation_mm(grasps[0].feature, pad_radius):.1f} mm: {name}")
    pairs = ", ".join(p.name for p in a.pairs)
    given = any(g.feature not in CTB_FEATURES for p in a.pairs for g in p.grasps)
    what = "grasp features" if given else "CTB features"
    return Legend(
        ax,
        handles,
        labels,
        handler_map={tuple: HandlerTuple(ndivide=None, pad=0.6)},
        title=f"{what}, left to right\n(markers: pair {pairs}; l = thickness + pad diameter)",
        title_fontsize=8,
        fontsize=8,
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
        bbox_transform=under,
        borderaxespad=0,
        alignment="left",
    )


__all__ = [
    "reach_figure",
]
