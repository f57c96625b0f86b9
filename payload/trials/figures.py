"""Trial figures: the paper's Fig. 3 (CTB in the Astrobee body frame) and a route plot.

Both are drawn with matplotlib's object API on the Agg canvas (no pyplot state), so they
are safe in Dask workers and threads.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle
from matplotlib.text import Text
from matplotlib.transforms import Bbox

from payload.errors import PayloadError
from payload.rotations import rotate_by_quats
from payload.safeio import replacing
from payload.schema import ENDED_BY_CAP
from payload.trials.metrics import (
    TrialMetrics,
    compute_metrics,
    contact_words,
    ctb_in_body_frame,
    recorded_definition,
)
from payload.trials.recorder import Recording
from payload.trials.records import MODULE_NAMES
from payload.trials.summary_fields import CAP_STOPPED

PHASE_COLORS: dict[str, str] = {
    "calibration": "#d9d9d9",
    "acquisition": "#fdd49e",
    "translation": "#c6dbef",
    "turn": "#d9f0a3",
    "arrival": "#fcc5c0",
    "braking": "#e5d8f0",
}
"""Shading of each phase (Fig. 3 shades acquisition / translation / turn / arrival)."""


class FigureError(PayloadError):
    """A figure cannot be drawn (bad module rectangles, empty recording)."""


class ModuleRect(NamedTuple):
    """An axis-aligned module outline in the world xy plane [m].

    Attributes:
        name: Label, e.g. ``kibo``.
        x_min: Lower x bound [m].
        y_min: Lower y bound [m].
        x_max: Upper x bound [m].
        y_max: Upper y bound [m].
    """

    name: str
    x_min: float
    y_min: float
    x_max: float
    y_max: float


def _as_rect(item: Any) -> ModuleRect:
    if isinstance(item, ModuleRect):
        rect = item
    elif isinstance(item, Mapping):
        try:
            rect = ModuleRect(
                str(item["name"]),
                float(item["x_min"]),
                float(item["y_min"]),
                float(item["x_max"]),
                float(item["y_max"]),
            )
        except KeyError as exc:
            raise FigureError(f"module rectangle {dict(item)} lacks {exc}") from None
    else:
        try:
            name, *bounds = item
            rect = ModuleRect(str(name), *(float(b) for b in bounds))
        except (TypeError, ValueError) as exc:
            raise FigureError(
                f"module rectangle {item!r}: expected (name, x_min, y_min, x_max, y_max)"
            ) from exc
    if not (rect.x_min < rect.x_max and rect.y_min < rect.y_max):
        raise FigureError(f"module rectangle {rect.name!r}: min bounds must be below max bounds")
    return rect


def phases_in_time_order(phase: np.ndarray) -> list[str]:
    """The distinct phases of a recording, in the order they first occur."""
    return list(dict.fromkeys(str(p) for p in phase.tolist()))


def phase_spans(t: np.ndarray, phase: np.ndarray) -> list[tuple[str, float, float]]:
    """Contiguous phases as ``(phase, t_start, t_end)`` [s]; each span ends where the next
    begins (the last one at the last sample)."""
    spans: list[tuple[str, float, float]] = []
    n = len(t)
    i = 0
    while i < n:
        j = i
        while j + 1 < n and phase[j + 1] == phase[i]:
            j += 1
        end = float(t[j + 1]) if j + 1 < n else float(t[j])
        spans.append((str(phase[i]), float(t[i]), end))
        i = j + 1
    return spans


def _shade(ax: Any, spans: Iterable[tuple[str, float, float]]) -> None:
    for name, a, b in spans:
        ax.axvspan(a, b, color=PHASE_COLORS.get(name, "#eeeeee"), alpha=0.6, lw=0, zorder=0)


_EDGE_IN = 0.06
"""Blank border above Fig. 3's two-line title [in]."""
_CTB_SIZE_IN = (9.0, 7.5)
"""Fig. 3's size (width, height) [in]."""
_CTB_MARGINS_IN = {"left": 0.9, "right": 0.08, "top": 0.5, "bottom": 0.85, "hspace": 0.2}
_ROUTE_SIZE_IN = (8.0, 7.0)
"""The route plot's size (width, height) [in]."""
_ROUTE_MARGINS_IN = {"left": 0.75, "right": 0.08, "top": 0.3, "bottom": 0.5}
"""Fixed margins of both figures [in] (left/right/top/bottom from the figure's edges;
hspace between panels): room for the tick labels, axis labels, title and figure legend,
so no layout engine measures the texts (constrained layout drew every text twice more);
tests/test_trials.py draws both with wide tick labels and checks every text is on the
canvas."""


def _margins(size_in: tuple[float, float], margins_in: dict[str, float]) -> dict[str, float]:
    """Gridspec parameters (figure fractions) of margins in inches."""
    w, h = size_in
    out = {
        "left": margins_in["left"] / w,
        "right": 1.0 - margins_in["right"] / w,
        "top": 1.0 - margins_in["top"] / h,
        "bottom": margins_in["bottom"] / h,
    }
    if "hspace" in margins_in:
        out["hspace"] = margins_in["hspace"]
    return out


TRIAL_PNG_COMPRESSION = 1
"""zlib's level for a trial's two PNG figures (Pillow's default is 6): the same pixels,
written in about 0.04 s less each (0.25 -> 0.21 s and 0.14 -> 0.09 s on seed 0's) for
files 8 % and 30 % larger; a trial writes them every time it is scored, a campaign's
committed figure keeps the default."""


def save_figure(fig: Figure, path: Path, dpi: int, png_compression: int | None = None) -> Path:
    """Save ``fig`` to ``path`` (format from the suffix) through a temporary file; a PNG
    at zlib level ``png_compression`` (None: Pillow's default)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)
    fmt = path.suffix.lstrip(".") or "png"
    extra: dict[str, Any] = {}
    if png_compression is not None and fmt == "png":
        extra["pil_kwargs"] = {"compress_level": png_compression}
    with replacing(path) as tmp:  # a crash never leaves half a figure
        fig.savefig(tmp, dpi=dpi, format=fmt, **extra)
    return path


CAP_LABEL = f"session {CAP_STOPPED}"
"""Fig. 3's note on a trial the ``--max-time`` cap stopped (the title has no room for it)."""

_LABEL_SPOTS: tuple[tuple[float, float, str, str], ...] = (
    (0.99, 0.95, "right", "top"),
    (0.01, 0.95, "left", "top"),
    (0.99, 0.05, "right", "bottom"),
    (0.01, 0.05, "left", "bottom"),
    (0.5, 0.95, "center", "top"),
    (0.5, 0.05, "center", "bottom"),
)
"""Where :func:`place_clear_of` tries a label, in order: ``(x, y, ha, va)`` in axes
fractions (the four corners, then the middles of the top and bottom edges)."""


def _crosses(box: Any, lines: Sequence[Line2D]) -> bool:
    """Whether any of ``lines``, as drawn (display coordinates), enters ``box``."""
    for line in lines:
        path = line.get_transform().transform_path(line.get_path())
        if path.intersects_bbox(box, filled=False):
            return True
    return False


def place_clear_of(text: Text, lines: Sequence[Line2D]) -> None:
    """Put ``text`` (placed in its axes' fractions) where its box, white padding included,
    meets none of ``lines``: the first of :data:`_LABEL_SPOTS` that is free. When every
    spot is taken (a curve filling the panel), the axes' y range grows upward until the
    lines leave room under the first spot, so the label never hides data.

    Args:
        text: A text artist whose transform is its axes' ``transAxes``.
        lines: The lines it must not cover (their data as drawn).
    """
    ax = text.axes
    renderer = FigureCanvasAgg(ax.figure).get_renderer()

    def box_at(spot: tuple[float, float, str, str]) -> Any:
        x, y, ha, va = spot
        text.set_position((x, y))
        text.set_horizontalalignment(ha)
        text.set_verticalalignment(va)
        box = text.get_window_extent(renderer)
        if text.get_bbox_patch() is None:
            return box
        text.update_bbox_position_size(renderer)  # the padded box drawn behind the text
        return Bbox.union([box, text.get_bbox_patch().get_window_extent(renderer)])

    lo, _ = ax.get_ylim()  # the autoscaled limits, which the lines are drawn in
    for spot in _LABEL_SPOTS:
        if not _crosses(box_at(spot), lines):
            return
    room = (box_at(_LABEL_SPOTS[0]).y0 - ax.bbox.y0) / ax.bbox.height  # axes fraction
    top = max(float(np.nanmax(line.get_ydata())) for line in lines)
    ax.set_ylim(lo, lo + (top - lo) / (0.97 * room))


def _seed_text(recording: Recording) -> str:
    """ ", seed N" for a recording of a seeded trial (a figure copied out of its folder
    still says which trial it is), else ""."""
    seed = recording.meta.get("seed")
    return f", seed {seed}" if isinstance(seed, int) and not isinstance(seed, bool) else ""


def plot_ctb_body_frame(
    recording: Recording,
    path: str | Path,
    metrics: TrialMetrics | None = None,
    *,
    dpi: int = 120,
) -> Path:
    """Fig. 3 of the paper: CTB centre of mass in the Astrobee body frame over time.

    Four stacked panels: x, y, z of eq. 4 [mm] and the eq. 5 deviation
    ``||b_p_c(t) - b_p_c(t0)||`` [mm], phases shaded, the first confirmed-contact interval
    marked, and the RMS and peak deviations annotated.

    Args:
        recording: The trial recording.
        path: PNG file to write.
        metrics: Precomputed metrics (``None``: computed here with the contact
            definition the recording was made with, as its trial scores it).
        dpi: Resolution [dots per inch].

    Returns:
        The written path.
    """
    if len(recording) == 0:
        raise FigureError("cannot plot an empty recording")
    if metrics is None:  # scored as the trial is: the contact definition it was recorded with
        min_interval, max_gap = recorded_definition(recording)
        metrics = compute_metrics(recording, min_interval_s=min_interval, max_gap_s=max_gap)
    m = metrics
    # the contact definition's name: a rescoring's figures say what they scored
    words = contact_words(m.min_interval_s, m.max_gap_s)
    t = recording.t
    bp = 1e3 * ctb_in_body_frame(recording.astrobee_pos, recording.astrobee_quat, recording.ctb_pos)
    spans = phase_spans(t, recording.phase)

    fig = Figure(figsize=_CTB_SIZE_IN)
    axes = fig.subplots(4, 1, sharex=True, gridspec_kw=_margins(_CTB_SIZE_IN, _CTB_MARGINS_IN))
    labels = ("x", "y", "z")
    has_contact = math.isfinite(m.t0_s)
    data: list[list[Line2D]] = []  # each panel's curve, and the position at t0
    for k, ax in enumerate(axes[:3]):
        _shade(ax, spans)
        data.append(ax.plot(t, bp[:, k], color="#08306b", lw=1.2))
        if has_contact:
            y0 = 1e3 * m.b_p_c_t0_m[k]
            data[k].append(ax.axhline(y0, color="#08306b", lw=0.8, ls="--", alpha=0.7))
        ax.set_ylabel(f"body {labels[k]} [mm]")
        ax.grid(True, alpha=0.3)
    ax = axes[3]
    _shade(ax, spans)
    if has_contact:
        dev = np.linalg.norm(bp - 1e3 * np.asarray(m.b_p_c_t0_m), axis=1)
        ax.plot(t, dev, color="#7f7f7f", lw=0.8, label="outside the interval")
        inside = (t >= m.t0_s) & (t <= m.contact_end_s)
        ax.plot(t[inside], dev[inside], color="#a50f15", lw=1.3, label="first contact interval")
        ax.axhline(m.rms_mm, color="#a50f15", ls="--", lw=0.9, label=f"RMS {m.rms_mm:.1f} mm")
        ax.axhline(m.peak_mm, color="#a50f15", ls=":", lw=0.9, label=f"peak {m.peak_mm:.1f} mm")
        for a in axes:
            a.axvline(m.t0_s, color="k", lw=0.8)
            a.axvline(m.contact_end_s, color="k", lw=0.8, ls="--")
            if math.isfinite(m.arrival_s):
                a.axvline(m.arrival_s, color="#a50f15", lw=0.8, ls="-.")
        ax.legend(loc="best", fontsize=7, ncols=2)
    else:
        ax.text(0.5, 0.5, words.none, transform=ax.transAxes, ha="center")
    ax.set_ylabel("deviation [mm]")
    ax.set_xlabel("time since start of teleoperation [s]")
    ax.grid(True, alpha=0.3)

    present = phases_in_time_order(recording.phase)
    handles = [Patch(color=PHASE_COLORS[p], alpha=0.6, label=p) for p in present]
    fig.legend(
        handles=handles, loc="lower center", ncols=max(1, len(handles)), bbox_to_anchor=(0.5, 0.0)
    )
    verdict = "success" if m.success else "failure"
    if recording.meta.get("ended_by") == ENDED_BY_CAP:  # said where the title has no room
        label = axes[0].text(
            0, 0, CAP_LABEL, transform=axes[0].transAxes, fontsize=8, color="#a50f15",
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
        )  # fmt: skip
        place_clear_of(label, data[0])
    fig.suptitle(
        f"CTB centre of mass in the Astrobee body frame (eq. 4){_seed_text(recording)} -- "
        f"{verdict}, contact {m.contact_s:.1f} s of the {m.duration_s:.1f} s after "
        f"calibration\nvertical: first {words.contact} (t0) solid, its end dashed, "
        "arrival dash-dot; horizontal dashed: the position at t0",
        fontsize=10,
        y=1.0 - _EDGE_IN / _CTB_SIZE_IN[1],
        va="top",
    )
    return save_figure(fig, Path(path), dpi, TRIAL_PNG_COMPRESSION)


def plot_route(
    recording: Recording,
    path: str | Path,
    modules: Sequence[Any] | None = None,
    *,
    dpi: int = 120,
) -> Path:
    """Top-down route plot: Astrobee and CTB world xy paths over the module outlines.

    Args:
        recording: The trial recording.
        path: PNG file to write.
        modules: Optional module outlines: :class:`ModuleRect`, mappings with ``name``,
            ``x_min``, ``y_min``, ``x_max``, ``y_max``, or ``(name, x_min, y_min, x_max,
            y_max)`` tuples [m].
        dpi: Resolution [dots per inch].

    Returns:
        The written path.
    """
    if len(recording) == 0:
        raise FigureError("cannot plot an empty recording")
    rects = [_as_rect(m) for m in (modules or [])]
    from payload.sim.iss import IssModule  # the modules' titles (a trial has loaded it)

    titles = {MODULE_NAMES.get(m.value, m.value): m.title for m in IssModule}  # by recorded name
    fig = Figure(figsize=_ROUTE_SIZE_IN)
    ax = fig.subplots(gridspec_kw=_margins(_ROUTE_SIZE_IN, _ROUTE_MARGINS_IN))
    for i, r in enumerate(rects):
        ax.add_patch(
            Rectangle(
                (r.x_min, r.y_min),
                r.x_max - r.x_min,
                r.y_max - r.y_min,
                facecolor=f"C{i % 10}",
                alpha=0.08,
                edgecolor=f"C{i % 10}",
                lw=1.2,
            )
        )
        # outside the module's left edge: the route runs through narrow modules' insides
        color = f"C{i % 10}"
        label = titles.get(r.name, r.name)
        ax.text(r.x_min, r.y_max, f"{label} ", ha="right", va="top", fontsize=9, color=color)
    pb, pc = recording.astrobee_pos, recording.ctb_pos
    ax.plot(pb[:, 0], pb[:, 1], color="#08306b", lw=1.5, label="Astrobee")
    ax.plot(pc[:, 0], pc[:, 1], color="#a50f15", lw=1.0, ls="--", label="CTB centre of mass")
    ax.plot(*pc[0, :2], "o", color="#a50f15", ms=6, label="CTB start")
    ax.plot(*pc[-1, :2], "s", color="#a50f15", ms=6, label="CTB end")
    # heading arrows (body x axis) every ~10 % of the route
    q = recording.astrobee_quat
    idx = np.unique(np.linspace(0, len(recording) - 1, 11).astype(int))
    heading = rotate_by_quats(q[idx], np.array([1.0, 0.0, 0.0]))
    ax.quiver(
        pb[idx, 0], pb[idx, 1], heading[:, 0], heading[:, 1], color="#08306b", width=0.004,
        scale=25, alpha=0.7,
    )  # fmt: skip
    # the arrows' legend entry (a quiver has none)
    ax.plot([], [], ">", color="#08306b", alpha=0.7, ms=6, label="Astrobee heading (body x)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("world x [m]")
    ax.set_ylabel("world y [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    net = float(np.linalg.norm(pc[-1] - pc[0]))
    capped = f"; {CAP_LABEL}" if recording.meta.get("ended_by") == ENDED_BY_CAP else ""
    ax.set_title(
        f"Route, top view{_seed_text(recording)} (CTB net displacement {net:.2f} m{capped})",
        fontsize=10,
    )
    return save_figure(fig, Path(path), dpi, TRIAL_PNG_COMPRESSION)


__all__ = [
    "CAP_LABEL",
    "PHASE_COLORS",
    "TRIAL_PNG_COMPRESSION",
    "FigureError",
    "ModuleRect",
    "phase_spans",
    "phases_in_time_order",
    "place_clear_of",
    "plot_ctb_body_frame",
    "plot_route",
    "save_figure",
]
