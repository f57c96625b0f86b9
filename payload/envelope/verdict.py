"""The verdict a report prints first, and the change of its headline figures.

Every report leads with one ``verdict:`` line: whether the design passes (the stowed fit;
the grasp: every pair closes on a CTB feature) and the tightest or failing parts. When a
report follows a changed design, the headline figures of the previous report
(``<stem>.prev.json``) and of the new one are printed side by side.
"""

from __future__ import annotations

from typing import Any

from payload.envelope import REACH_SAMPLES
from payload.envelope.fit_results import (
    TIGHT_CLEARANCE,
    EnvelopeAnalysis,
    StowedCheck,
    clearance_text,
)
from payload.envelope.reach import ReachAnalysis
from payload.envelope.workspace import MIN_HULL_POINTS
from payload.errors import first_of

HEADLINES: dict[str, tuple[tuple[str, str, str], ...]] = {
    "envelope": (
        ("passed", "passes", ""),
        ("fits", "fits the bays", ""),
        ("min_clearance_mm", "min clearance", "mm"),
        ("tightest.part", "tightest part", ""),
        ("min_self_clearance_mm", "min self-clearance", "mm"),
        ("deploy_path_clear", "deployment path clear", ""),
    ),
    "reach": (
        ("passed", "passes", ""),
        ("below_vehicle_mm", "fingertips below the vehicle", "mm"),
        ("collision_free_fraction", "self-collision-free fraction", ""),
        ("pairs.L.span_max_mm", "pair L widest span", "mm"),
        ("pairs.R.span_max_mm", "pair R widest span", "mm"),
        ("rail_spacing_mm.max", "rail spacing max", "mm"),
    ),
}
"""Per report: (dotted JSON key, label, unit) of the figures whose change is printed."""

SETTINGS: dict[str, tuple[str, ...]] = {"envelope": (), "reach": ("samples", "seed")}
"""Per report: the run's settings (JSON keys) that move its figures without any change to
the design (a reach sampled 1,000 times against 100,000): named first when they changed."""


def envelope_verdict(a: EnvelopeAnalysis) -> str:
    """``verdict: fits ...`` (``verdict: fits, tight ...`` when a clearance is under
    :data:`~payload.envelope.fit_results.TIGHT_CLEARANCE`: a pass all the same) or
    ``verdict: FAILS ...`` for the stowed payload."""
    g = a.given
    if a.passed:
        t = g.tightest
        return (
            f"verdict: {g.fits_words}: every part inside the bays, min clearance "
            f"{clearance_text(t.clearance)} ({t.name}, {t.wall} wall); no self-collision; "
            f"deployment path clear{_unfolding_tight(g)}{g.tight_tail}"
        )
    return "verdict: FAILS: " + first_of(g.failures(), 3)


def unfolding_tight(g: StowedCheck) -> str:
    """``a / b 0.22 mm apart as the fingers unfold`` when the unfolding's closest approach
    is under :data:`~payload.envelope.fit_results.TIGHT_CLEARANCE`, else empty: a motion
    that passes this close is worth a second look, as a stowed fit is (the servos trail
    their goals on the way)."""
    u = g.unfolding
    if not (u.clear and u.min_distance < TIGHT_CLEARANCE):
        return ""
    d = clearance_text(u.min_distance)
    return f"{u.between[0]} / {u.between[1]} {d} apart as the fingers unfold"


def _unfolding_tight(g: StowedCheck) -> str:
    """`` (tight: ...)`` of :func:`unfolding_tight`, or empty: the verdict's words."""
    said = unfolding_tight(g)
    return f" (tight: {said})" if said else ""


def reach_passed(a: ReachAnalysis) -> bool:
    """Whether every finger reached in enough samples to measure its workspace, the
    deployed fingertips reach below the vehicle and every pair closes on at least one of
    the CTB features checked (a sampled search: with few ``--samples`` a grasp can be
    missed; the default 100,000 is what the committed report uses)."""
    return (
        too_few_reachable(a) is None and a.below_vehicle > 0 and all(_closes_on(p) for p in a.pairs)
    )


def too_few_reachable(a: ReachAnalysis) -> str | None:
    """What is wrong when a finger's links touched nothing in too few samples to measure
    its workspace (a finger that almost never moves free, or too sparse a sampling), with
    what to do; None when every finger reached often enough."""
    few = [w for w in a.workspaces if w.too_few]
    if not few:
        return None
    which = ", ".join(f"{w.finger} ({len(w.points)})" for w in few)
    return (
        f"finger{'s' if len(few) > 1 else ''} {which} moved free in fewer than "
        f"{MIN_HULL_POINTS} of the {a.samples:,} samples, too few to measure a workspace: "
        "sample more (--samples), or the design leaves the finger almost no free posture"
    )


def _closes_on(pair: Any) -> list[str]:
    return [g.feature.name for g in pair.grasps if g.closes]


def sampling_caveat(a: ReachAnalysis) -> str:
    """What a reach verdict adds when it was sampled more sparsely than the default
    (:data:`~payload.envelope.REACH_SAMPLES`): ``; sampled 2,000 times (default 100,000): a
    grasp can be missed`` (the two pairs, mirror images, then close down to
    different thicknesses); empty at the default or more."""
    if a.samples >= REACH_SAMPLES:
        return ""
    return f"; sampled {a.samples:,} times (default {REACH_SAMPLES:,}): a grasp can be missed"


def reach_verdict(a: ReachAnalysis) -> str:
    """``verdict: grasps ...`` or ``verdict: FAILS ...`` for the reach report, with the
    :func:`sampling_caveat` of a sparse sampling."""
    return _reach_verdict(a) + sampling_caveat(a)


def _reach_verdict(a: ReachAnalysis) -> str:
    if reach_passed(a):
        thinnest = {
            p.name: min((g for g in p.grasps if g.closes), key=lambda g: g.feature.thickness)
            for p in a.pairs
        }
        closes = ", ".join(
            f"pair {name} closes down to {g.feature.thickness * 1e3:.1f} mm ({g.feature.name})"
            for name, g in thinnest.items()
        )
        return (
            f"verdict: grasps: {closes}; "
            f"fingertips reach {a.below_vehicle * 1e3:.1f} mm below the vehicle"
        )
    bad = [
        f"pair {p.name} closes on none of the {len(p.grasps)} CTB features checked (spans "
        f"{p.span_min * 1e3:.1f} .. {p.span.maximum * 1e3:.1f} mm)"
        for p in a.pairs
        if not _closes_on(p)
    ]
    if a.below_vehicle <= 0:  # (NaN: no finger reached at all, said below)
        bad.insert(0, "the deployed fingertips do not reach below the vehicle")
    few = too_few_reachable(a)
    if few is not None:
        bad.insert(0, few)
    return "verdict: FAILS: " + first_of(bad, 3)


def _get(data: dict[str, Any], dotted: str) -> Any:
    node: Any = data
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def _show(value: Any, unit: str) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if value is None:
        return "-"
    if isinstance(value, float):
        text = f"{value:.2f}" if unit == "mm" else f"{value:.4g}"
        return f"{text} {unit}".strip()
    return f"{value}{' ' + unit if unit else ''}"


def headline_changes(stem: str, before: dict[str, Any], after: dict[str, Any]) -> str:
    """One line: each headline figure of report ``stem`` that changed, ``old -> new``,
    after the run's settings that changed (:data:`SETTINGS`: the figures moved with them
    too, not only with the design)."""
    settings = [
        f"{key} {_show(before.get(key), '')} -> {_show(after.get(key), '')}"
        for key in SETTINGS.get(stem, ())
        if before.get(key) != after.get(key)
    ]
    line = _figure_changes(stem, before, after)
    if settings:
        head = f"changed since {stem}.prev.json: "
        return f"{head}run with other settings ({', '.join(settings)}); {line[len(head) :]}"
    return line


def _figure_changes(stem: str, before: dict[str, Any], after: dict[str, Any]) -> str:
    changed = []
    for key, label, unit in HEADLINES[stem]:
        old, new = _get(before, key), _get(after, key)
        if old != new:
            changed.append(f"{label} {_show(old, unit)} -> {_show(new, unit)}")
    if not changed:
        figures = [{k: v for k, v in d.items() if k != "provenance"} for d in (before, after)]
        if figures[0] == figures[1]:  # the design file changed (its hash), no figure did
            return f"changed since {stem}.prev.json: the design file only (every figure as before)"
        return f"changed since {stem}.prev.json: other figures only (headline figures as before)"
    return f"changed since {stem}.prev.json: " + "; ".join(changed)


__all__ = [
    "HEADLINES",
    "envelope_verdict",
    "headline_changes",
    "reach_passed",
    "reach_verdict",
    "sampling_caveat",
    "too_few_reachable",
    "unfolding_tight",
]
