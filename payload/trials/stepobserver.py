"""What a trial's teleoperation session makes of each control step: the recorder's step
record (:func:`step_record`, from what the loop hands its observer; for any driver: the
simulator, the hardware-in-the-loop rig, the live session) and the world as the synthetic
operator sees it (:func:`world_view`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from payload.retarget.casadi_solver import PairRetargeter
from payload.rotations import quat_to_matrix
from payload.teleop.loop import StepContext
from payload.teleop.operator import WorldView
from payload.teleop.pipeline import pair_index
from payload.trials.acquisition import handle_in_body, handle_site
from payload.trials.records import MODULE_NAMES, StepRecord


def world_view(driver: Any) -> Callable[[Any, float], WorldView]:
    """What the synthetic operator sees of the simulated world at each step (``state``:
    the driver's world state now, read from its data)."""
    site = handle_site(driver)

    def view(state: Any, t: float) -> WorldView:
        rot = quat_to_matrix(state.astrobee_quat)
        return WorldView(
            t,
            state.astrobee_pos,
            rot,
            rot @ state.astrobee_linear,
            state.ctb_pos,
            bool(state.opposing_contact),
            handle_in_body(driver, site, rot),
        )

    return view


def step_record(ctx: StepContext, driver: Any, retargeters: dict[str, PairRetargeter]) -> Any:
    """The recorder's step from what the loop hands its observer (for any driver with
    ``module_at``: the simulator, the hardware-in-the-loop rig, the live session).

    It reads the context's snapshots (frozen or fresh arrays) and the driver's layout
    alone, never the driver's live state: a trial's recorder makes it up to a second
    after its step (:meth:`~payload.trials.recorder.TrialRecorder.write_later`), with the
    other steps of its batch (:func:`step_records`)."""
    return StepRecord(**_step_fields(ctx, driver, retargeters))


def step_records(calls: list[tuple[Any, ...]]) -> list[Any]:
    """``[step_record(*args) for args in calls]``, made as one batch
    (:meth:`StepRecord.many <payload.trials.records.StepRecord.many>`): what the recorder
    calls at a flush (``step_record.many``)."""
    return StepRecord.many([_step_fields(*args) for args in calls])


step_record.many = step_records  # type: ignore[attr-defined]


def _step_fields(
    ctx: StepContext, driver: Any, retargeters: dict[str, PairRetargeter]
) -> dict[str, Any]:
    """The fields of :func:`step_record`'s step."""
    st, fr = ctx.state, ctx.frame
    step = ctx.step
    q = ctx.command.q
    twist = np.concatenate([ctx.twist.linear, ctx.twist.angular])
    rot = quat_to_matrix(st.astrobee_quat)
    ctb_module = driver.module_at(st.ctb_pos)
    return {
        "t": ctx.t,
        "phase": ctx.phase,
        "left_joints": fr.left.joints,
        "right_joints": fr.right.joints,
        "left_tracked": bool(fr.left.tracked),
        "right_tracked": bool(fr.right.tracked),
        "q_left": step.q_left if step else q[pair_index(retargeters["L"])],
        "q_right": step.q_right if step else q[pair_index(retargeters["R"])],
        "rail_cmd": float(q[-1]),
        "twist_cmd": twist,
        "q_cmd": q,
        "deploy_cmd": float(ctx.command.deploy),
        "q_meas": ctx.payload.q,
        "deploy_meas": float(ctx.payload.deploy),
        "astrobee_pos": st.astrobee_pos,
        "astrobee_quat": st.astrobee_quat,
        "astrobee_twist": np.concatenate([rot @ st.astrobee_linear, st.astrobee_angular]),
        "ctb_pos": st.ctb_pos,
        "ctb_quat": st.ctb_quat,
        "contact": bool(st.opposing_contact),
        "ctb_module": MODULE_NAMES.get(ctb_module.value, "outside")
        if ctb_module is not None
        else "outside",
    }


__all__ = ["MODULE_NAMES", "step_record", "step_records", "world_view"]
