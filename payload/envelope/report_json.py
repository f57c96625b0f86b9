"""The envelope and reach reports as plain data (lengths in mm)."""

from __future__ import annotations

from typing import Any

import numpy as np

from payload.envelope.fit_results import TIGHT_CLEARANCE, EnvelopeAnalysis, StowedCheck
from payload.envelope.reach import ReachAnalysis
from payload.envelope.vehicle import display_path
from payload.envelope.verdict import reach_passed


def _mm(x: float) -> float | None:
    return round(float(x) * 1e3, 2) if np.isfinite(x) else None


def reach_json(a: ReachAnalysis) -> dict[str, Any]:
    """The reach analysis as plain data (lengths in mm)."""
    mm = _mm
    pairs = {}
    for p in a.pairs:
        pairs[p.name] = {
            "fingers": list(p.fingers),
            "span_min_mm": mm(p.span_min),
            "span_max_mm": mm(p.span.maximum),
            "span_min_geometric_mm": mm(p.span.minimum),
            "pad_contact_mm": mm(p.pad_contact),
            "collision_free_fraction": round(p.free_fraction, 4),
            "collision_free_span_mm": {"min": mm(p.free_span[0]), "max": mm(p.free_span[1])},
            "opposed_span_mm": {"min": mm(p.opposed_span[0]), "max": mm(p.opposed_span[1])},
            "grasp": [
                {
                    "feature": g.feature.name,
                    "thickness_mm": mm(g.feature.thickness),
                    "source": g.feature.source,
                    "closes": bool(g.closes),
                    "span_mm": mm(g.span),
                    "opposition_deg": round(float(np.degrees(g.angle)), 1)
                    if np.isfinite(g.angle)
                    else None,
                    "below_vehicle_mm": mm(g.depth),
                    "q": [round(float(v), 4) for v in g.q],
                }
                for g in p.grasps
            ],
        }
    selfc, vehc = a.contacts.self_collision(), a.contacts.vehicle_contact()
    return {
        "design": display_path(a.design_source),
        "samples": int(a.samples),
        "seed": int(a.seed),
        "seconds": round(a.seconds, 2),
        "pairs": pairs,
        "rail_spacing_mm": {"min": mm(a.rail_spacing[0]), "max": mm(a.rail_spacing[1])},
        "below_vehicle_mm": mm(a.below_vehicle),
        "collision_free_fraction": round(a.collision_free_fraction, 4),
        "vehicle_contact_fraction": round(float(vehc.mean()), 4),
        "free_fraction_with_vehicle": round(float((~selfc & ~vehc).mean()), 4),
        "home_below_vehicle_mm": mm(a.home_below_vehicle),
        "fingers": {
            w.finger: {
                "hull_volume_cm3": round(w.hull_volume * 1e6, 1)
                if np.isfinite(w.hull_volume)
                else None,
                "bbox_min_mm": [mm(v) for v in w.lower],
                "bbox_max_mm": [mm(v) for v in w.upper],
                "below_vehicle_mm": mm(w.below_vehicle),
                "reachable_fraction": round(w.reachable, 4),
            }
            for w in a.workspaces
        },
        "collision_pairs": [
            {"links": list(k), "fraction": round(v / a.samples, 4)}
            for k, v in sorted(a.contacts.pair_counts().items(), key=lambda kv: -kv[1])[:12]
        ],
        "timings_s": {k: round(v, 2) for k, v in a.timings.items()},
        "assumptions": a.assumptions(),
        "passed": reach_passed(a),
    }


def _check_json(check: StowedCheck) -> dict[str, Any]:
    sweep = check.sweep
    closest = check.min_self_clearance
    return {
        "fits": check.fits,
        "min_clearance_mm": _mm(check.min_clearance),
        "tightest": {"part": check.tightest.name, "wall": check.tightest.wall},
        "parts": [
            {
                "name": p.name,
                "inside": p.inside,
                "clearance_mm": _mm(p.clearance),
                "protrusion_mm": _mm(p.protrusion),
                "wall": p.wall,
                "outside_volume_mm3": round(p.outside_volume * 1e9, 3),
                "mounted": p.mounted,
                "wall_clearance_mm": [_mm(w) for w in p.wall_clearance],
            }
            for p in check.parts
        ],
        "self_collision": check.self_collision,
        "self_collisions": [
            {
                "links": [c.a, c.b],
                "depth_mm": _mm(-c.distance),
                "overlap_mm3": round(c.overlap_volume * 1e9, 1),
            }
            for c in check.collisions
        ],
        "min_self_clearance_mm": _mm(closest.distance),
        "min_self_clearance_links": [closest.a, closest.b],
        "deploy_path_clear": check.deploy_clear,
        "deploy_path": {
            "vehicle_clear": sweep.vehicle_clear,
            "carried_parts_clear": not any(
                c.colliding and "base" not in (c.a, c.b) for c in check.self_contacts
            ),
            "min_distance_mm": _mm(sweep.min_distance),
            "at_stage_mm": _mm(sweep.at_stage),
            "between": list(sweep.between),
            "samples": sweep.samples,
            "certified": sweep.certified,
            "first_contact_mm": _mm(sweep.first_contact),
            "unfolding": {  # the fingers and the rail to home, the stage down
                "clear": check.unfolding.clear,
                "samples": check.unfolding.samples,
                "certified": check.unfolding.certified,
                "evaluated": check.unfolding.evaluated,
                "min_distance_mm": _mm(check.unfolding.min_distance),
                "between": list(check.unfolding.between),
                "collisions": [
                    {"links": [c.a, c.b], "depth_mm": _mm(-c.distance)}
                    for c in check.unfolding.collisions
                ],
                "vehicle_hits": [
                    {"link": h.link, "body": h.body, "depth_mm": _mm(-h.distance)}
                    for h in check.unfolding.hits
                ],
            },
        },
        "passed": check.passed,
        "failures": check.failures(),
        "tight_clearance_mm": _mm(TIGHT_CLEARANCE),
        "tight": [
            *(
                {"part": p.name, "wall": p.wall, "clearance_mm": _mm(p.clearance)}
                for p in check.tight_parts
            ),
            *({"links": [c.a, c.b], "clearance_mm": _mm(c.distance)} for c in check.tight_pairs),
        ],
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
            "min_clearance_mm": _mm(a.search.clearance),
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


__all__ = [
    "envelope_json",
    "reach_json",
]
