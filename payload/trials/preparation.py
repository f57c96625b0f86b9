"""A trial's set-up before its session starts (:func:`set_up_trial`: the retargeters, the
CTB under the teleoperated pinch, the teleoperation config and the operator's plan), the
base safety filter of its driver, and the recording's opening and closing metadata.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from payload.design.params import load_design
from payload.project import Project, current_project, provenance
from payload.retarget.calibration import PairRange
from payload.retarget.casadi_solver import PairRetargeter
from payload.sim.zones import zones_record
from payload.teleop.calibration import CalibrationProcedure
from payload.teleop.operator import OperatorPlan
from payload.teleop.pipeline import TeleopConfig
from payload.trials.acquisition import place_ctb_for_teleop, place_offset
from payload.trials.records import MODULE_NAMES
from payload.trials.retargeters import retargeting
from payload.trials.sources import _Source


def design_hash(project: Project | None = None) -> str:
    """SHA-256 of ``project``'s design file (first 16 hex digits; default: the current
    project). :func:`payload.project.provenance` gives the full record."""
    return provenance(project or current_project())["design_sha256"][:16]


def module_rects(layout: Any) -> list[dict[str, float | str]]:
    """The ISS layout's module zones as the recording's metadata lists them (name and
    x, y extents [m]), for the route figure and replays."""
    out = []
    for zone in layout.zones():
        out.append(
            {
                "name": MODULE_NAMES.get(zone.module.value, zone.module.value),
                "x_min": float(zone.lo[0]),
                "y_min": float(zone.lo[1]),
                "x_max": float(zone.hi[0]),
                "y_max": float(zone.hi[1]),
            }
        )
    return out


class TrialSetup(NamedTuple):
    """What a trial is set up with before the session starts."""

    retargeters: dict[str, PairRetargeter]
    ranges: dict[str, PairRange]
    config: TeleopConfig
    plan: OperatorPlan
    calibration: CalibrationProcedure
    recorded: dict[str, Any]  # the figures of the set-up, recorded in the metadata


def set_up_trial(driver: Any, seed: int, source_spec: _Source, project: Project) -> TrialSetup:
    """Retargeters, the CTB under the teleoperated pinch (with the seeded acquisition
    offset), the teleoperation config and the operator's plan."""
    layout = driver.world.layout
    retargeters, ranges = retargeting(
        project, source_spec.retarget_budget, source_spec.retarget_collisions
    )
    grasp_body = place_ctb_for_teleop(driver, retargeters, ranges)
    recorded = source_spec.recorded
    offset, yaw = place_offset(
        driver, seed, recorded.get("ctb_offset_m"), recorded.get("ctb_yaw_deg")
    )
    setup = {
        "retarget_budget": source_spec.retarget_budget,
        "retarget_collisions": source_spec.retarget_collisions,
        "controller": source_spec.controller,
        "controller_overrides": source_spec.controller_overrides,
        "ctb": source_spec.ctb,
        "propulsion": source_spec.propulsion,
        "physics_dt": source_spec.physics_dt,
        "base_filter": source_spec.base_filter,
        "link_delay": source_spec.link_delay,
        **zones_record(source_spec.zones),
        "ctb_offset_m": [float(v) for v in offset],
        "ctb_yaw_deg": float(yaw),
        "grasp_body_m": [float(v) for v in grasp_body],
    }
    calibration = CalibrationProcedure()
    config = TeleopConfig.from_design(load_design(driver.world.config.design))
    plan = OperatorPlan(
        route=layout.route(),
        heading0=layout.start_yaw(),
        base=config.base,
        grasp_body=grasp_body,
    )
    return TrialSetup(retargeters, ranges, config, plan, calibration, setup)


def trial_meta(
    seed: int, source_spec: _Source, traits: dict, prov: dict, layout: Any, setup: TrialSetup
) -> dict[str, Any]:
    """The recording's opening metadata."""
    from payload.trials.metrics import confirmed_definition

    return {
        "seed": int(seed),
        "operator": source_spec.operator,
        "design_hash": prov["design_sha256"][:16],
        "provenance": prov,
        "traits": traits,
        **source_spec.meta(),
        "route": layout.route().tolist(),
        "modules": module_rects(layout),
        "contact_definition": confirmed_definition(),
        **setup.recorded,
    }


def closing_meta(
    driver: Any, source: Any, stats: Any, scene: Any, replayed: dict[str, Any]
) -> dict[str, Any]:
    """The recording's closing metadata: how the session went (with the station
    contacts, the least station clearance and the filter's active time). The synthetic
    operator's acquisition state is its own; a replay's is its recording's (``replayed``:
    the replayed recording's metadata), whose hands it repeats."""
    operator = getattr(source, "operator", None)
    return {
        **scene.summary(),
        "steps": stats.steps,
        # "max_time": the session-length cap ended it before the operator finished
        "ended_by": stats.ended_by or None,
        "pipeline_median_us": float(np.median(stats.pipeline_us)) if stats.pipeline_us else None,
        "warnings": driver.warnings(),
        "ctb_external_max": driver.ctb_external_max,
        "equality_constraints": int(driver.model.neq),
        "acquisition_state": (
            operator.acquisition if operator is not None else replayed.get("acquisition_state")
        ),
    }


def base_filter_for(driver: Any, base: Any, zones: Any = None) -> Any:
    """The base safety filter for a simulator driver: the base channel's bounds and the
    deceleration its vehicle controller gives the loaded stack."""
    from payload.teleop.base_filter import BaseSafetyFilter

    c = driver.controller
    return BaseSafetyFilter(driver.world, base, c.accel_max, float(c.jerk[0]), zones)


__all__ = [
    "TrialSetup",
    "base_filter_for",
    "closing_meta",
    "design_hash",
    "module_rects",
    "set_up_trial",
    "trial_meta",
]
