"""One ISS cargo-transport trial: simulator + teleoperation pipeline + recorder + metrics.

``run_trial(seed, operator, replay, out_dir)`` builds the default world (Astrobee with
the deployed payload at the start of the route in Kibo, a single CTB under the fingers),
lets the operator (synthetic, or a replayed hand recording) calibrate, acquire the CTB
and fly it to Node 2, records every 50 Hz step into ``log.mcap`` and the raw hand frames
into ``hands.jsonl`` (so any trial can be replayed bit for bit), then scores it.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from payload.design.build import PROJECT_ROOT
from payload.design.params import load_design
from payload.errors import PayloadError
from payload.retarget.calibration import PairRange, pair_range
from payload.retarget.casadi_solver import PairRetargeter
from payload.retarget.objective import RetargetConfig
from payload.rotations import quat_to_matrix
from payload.teleop.calibration import CalibrationProcedure, Captures
from payload.teleop.loop import (
    ReplaySource,
    StepContext,
    SyntheticSource,
    run_session,
)
from payload.teleop.operator import OperatorPlan, SyntheticOperator, WorldView
from payload.teleop.pipeline import (
    TeleopConfig,
    TeleopPipeline,
    calibrate_operator,
    pair_index,
)
from payload.teleop.replay import HandRecordingWriter, read_hand_recording

log = logging.getLogger(__name__)

MODULE_NAMES = {"kibo": "kibo", "vestibule": "hatch", "node2": "node2"}
MAX_TRIAL_S = 240.0


class TrialError(PayloadError):
    """A trial could not be run (bad operator choice, unreadable replay)."""


_RETARGETERS: dict[str, dict[str, PairRetargeter]] = {}
_RANGES: dict[str, PairRange] = {}


def retargeting(
    budget: str = "paper",
) -> tuple[dict[str, PairRetargeter], dict[str, PairRange]]:
    """Production retargeters (with this evaluation budget, see
    :attr:`RetargetConfig.budget <payload.retarget.RetargetConfig.budget>`) and pair
    ranges for our hand (built once per process and budget)."""
    if budget not in _RETARGETERS:
        from threadpoolctl import threadpool_limits

        config = RetargetConfig(budget=budget)
        built: dict[str, PairRetargeter] = {}
        # single-threaded like the trials themselves, so every process finds the same ranges
        with threadpool_limits(limits=1):
            for pair in ("L", "R"):
                built[pair] = PairRetargeter(pair=pair, config=config)
                if pair not in _RANGES:
                    _RANGES[pair] = pair_range(built[pair].kinematics)
        _RETARGETERS[budget] = built
    return _RETARGETERS[budget], _RANGES


def design_hash() -> str:
    """SHA-256 of the design file the models were generated from (first 16 hex digits)."""
    data = (PROJECT_ROOT / "cad" / "design.toml").read_bytes()
    return hashlib.sha256(data).hexdigest()[:16]


def _module_rects(layout: Any) -> list[dict[str, float | str]]:
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


def place_ctb_for_teleop(
    driver: Any, retargeters: dict[str, PairRetargeter], ranges: dict[str, PairRange]
) -> None:
    """Move the CTB so its handle sits where the teleoperated pinch closes on it.

    The pinch the operator commands follows the posture reference of the calibrated pair
    ranges. For each pair, the span at which the reference posture's pads first reach the
    handle's side faces is found by bisection; the handle bar is centred on the mean of
    the four fingertips there. Only the CTB's initial pose changes.
    """
    import mujoco

    from payload.design.tree import MANIPULATION_JOINTS
    from payload.sim.world import PAYLOAD_PREFIX

    w, m = driver.world, driver.model
    data = mujoco.MjData(m)
    data.qpos[:] = driver.data.qpos
    handle = w.config.handle
    a = w.astrobee_qpos
    rot = quat_to_matrix(driver.data.qpos[a + 3 : a + 7])
    pad = float(m.geom_size[next(iter(w.pad_geoms.values()))][0])

    def tips_at(pair: str, span: float) -> np.ndarray:
        r = retargeters[pair]
        for name, v in zip(r.joints, ranges[pair].posture(span)):
            data.qpos[w.qpos[MANIPULATION_JOINTS.index(name)]] = v
        mujoco.mj_kinematics(m, data)
        sites = r.kinematics.hand.pair(pair).tips
        return np.array([data.site(f"{PAYLOAD_PREFIX}{s}").xpos for s in sites])

    tips = []
    for pair in retargeters:
        lo, hi = ranges[pair].span_min, ranges[pair].span_max
        for _ in range(40):  # across-array gap between the pads = handle width
            mid = 0.5 * (lo + hi)
            t = tips_at(pair, mid)
            gap = abs(float(rot[:, 1] @ (t[0] - t[1]))) - 2 * pad
            lo, hi = (mid, hi) if gap < handle.width else (lo, mid)
        tips.append(tips_at(pair, 0.5 * (lo + hi)))
    centre = np.vstack(tips).mean(axis=0)
    # the bag hangs below its handle bar: bar centre -> bag centre along the body -z axis
    size = w.config.ctb_size
    drop = handle.height / 2.0 + handle.standoff + size.height / 2.0
    c = w.ctb_qpos
    driver.data.qpos[c : c + 3] = centre - rot[:, 2] * drop
    mujoco.mj_forward(m, driver.data)


def run_trial(
    seed: int,
    operator: str = "synthetic",
    replay: Path | None = None,
    out_dir: Path | None = None,
    *,
    max_time: float = MAX_TRIAL_S,
    progress: bool = False,
    retarget_budget: str = "paper",
) -> dict[str, Any]:
    """Run one trial and write its folder (reproducible: see :func:`_run_trial`).

    The numerical libraries run single-threaded during the trial: multi-threaded BLAS
    sums in a different order, and the contact dynamics amplify the last-bit
    differences, so the same seed would otherwise give slightly different trials in a
    campaign worker and in a terminal.
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        return _run_trial(
            seed,
            operator,
            replay,
            out_dir,
            max_time=max_time,
            progress=progress,
            retarget_budget=retarget_budget,
        )


def _run_trial(
    seed: int,
    operator: str = "synthetic",
    replay: Path | None = None,
    out_dir: Path | None = None,
    *,
    max_time: float = MAX_TRIAL_S,
    progress: bool = False,
    retarget_budget: str = "paper",
) -> dict[str, Any]:
    """Run one trial and write its folder.

    Args:
        seed: Seed of the synthetic operator (ignored for replays except as a label).
        operator: ``synthetic`` or ``replay``.
        replay: The hand recording (``hands.jsonl``) to replay.
        out_dir: Trial folder (default ``runs/trial-<seed>``).
        max_time: Cap on the session length [s].
        progress: Show a progress bar.
        retarget_budget: Evaluation budget of the pair solves (``paper``: at most 20
            residual evaluations each; ``converged``), recorded with the trial.

    Returns:
        The metrics (as written to ``metrics.json``).
    """
    from payload.sim.driver import SimDriver
    from payload.trials.campaign import finish_trial
    from payload.trials.metrics import CONFIRM_MAX_GAP_S, CONFIRM_MIN_S
    from payload.trials.recorder import StepRecord, TrialRecorder

    if operator not in ("synthetic", "replay"):
        raise TrialError(f"operator must be 'synthetic' or 'replay', got {operator!r}")
    out = Path(out_dir) if out_dir is not None else Path("runs") / f"trial-{seed:04d}"
    out.mkdir(parents=True, exist_ok=True)
    driver = SimDriver()
    layout = driver.world.layout
    retargeters, ranges = retargeting(retarget_budget)
    place_ctb_for_teleop(driver, retargeters, ranges)
    calibration = CalibrationProcedure()
    config = TeleopConfig.from_design(load_design(driver.world.config.design))

    if operator == "synthetic":
        plan = OperatorPlan(route=layout.route(), heading0=layout.start_yaw(), base=config.base)
        synthetic = SyntheticOperator(plan, seed, calibration)
        source: Any = SyntheticSource(synthetic)
        traits = dict(vars(synthetic.traits))
    else:
        if replay is None:
            raise TrialError("operator 'replay' needs a hand recording file")
        _, frames = read_hand_recording(replay)
        source = ReplaySource(frames)
        traits = {"replay": str(replay)}

    q0 = driver.read().q

    def make_pipeline(captures: Captures, heading: float) -> TeleopPipeline:
        cal = calibrate_operator(captures, ranges, config.rail_travel, heading)
        return TeleopPipeline(cal, retargeters, config, initial=q0)

    def view(state: Any, t: float) -> WorldView:
        rot = quat_to_matrix(state.astrobee_quat)
        return WorldView(
            t,
            state.astrobee_pos,
            rot,
            rot @ state.astrobee_linear,
            state.ctb_pos,
            bool(state.opposing_contact),
        )

    rec_path = out / "log.mcap"
    hands_path = out / "hands.jsonl"
    meta = {
        "seed": int(seed),
        "operator": operator,
        "design_hash": design_hash(),
        "retarget_budget": retarget_budget,
        "traits": traits,
        "route": layout.route().tolist(),
        "modules": _module_rects(layout),
        "contact_definition": {"min_interval_s": CONFIRM_MIN_S, "max_gap_s": CONFIRM_MAX_GAP_S},
    }
    bar = None
    if progress:
        from rich.progress import Progress

        bar = Progress(transient=True)
        task = bar.add_task(f"trial {seed}", total=max_time)
        bar.start()
    try:
        with (
            TrialRecorder(rec_path, overwrite=True) as recorder,
            HandRecordingWriter(hands_path, meta={"seed": int(seed)}) as hands_out,
        ):
            recorder.write_meta(meta)

            def on_step(ctx: StepContext) -> None:
                st, fr = ctx.state, ctx.frame
                hands_out.write(fr)
                step = ctx.step
                q = ctx.command.q
                twist = np.concatenate([ctx.twist.linear, ctx.twist.angular])
                rot = quat_to_matrix(st.astrobee_quat)
                ctb_module = driver.module_at(st.ctb_pos)
                recorder.write(
                    StepRecord(
                        t=ctx.t,
                        phase=ctx.phase,
                        left_joints=fr.left.joints,
                        right_joints=fr.right.joints,
                        left_tracked=bool(fr.left.tracked),
                        right_tracked=bool(fr.right.tracked),
                        q_left=step.q_left if step else q[pair_index(retargeters["L"])],
                        q_right=step.q_right if step else q[pair_index(retargeters["R"])],
                        rail_cmd=float(q[-1]),
                        twist_cmd=twist,
                        q_cmd=q,
                        deploy_cmd=float(ctx.command.deploy),
                        q_meas=ctx.payload.q,
                        deploy_meas=float(ctx.payload.deploy),
                        astrobee_pos=st.astrobee_pos,
                        astrobee_quat=st.astrobee_quat,
                        astrobee_twist=np.concatenate(
                            [rot @ st.astrobee_linear, st.astrobee_angular]
                        ),
                        ctb_pos=st.ctb_pos,
                        ctb_quat=st.ctb_quat,
                        contact=bool(st.opposing_contact),
                        ctb_module=MODULE_NAMES.get(ctb_module.value, "outside")
                        if ctb_module is not None
                        else "outside",
                    )
                )
                if bar is not None:
                    bar.update(task, completed=ctx.t)

            stats = run_session(
                driver,
                source,
                calibration,
                make_pipeline,
                max_time=max_time,
                on_step=on_step,
                world_view=view,
            )
            recorder.write_meta(
                {
                    "steps": stats.steps,
                    "pipeline_median_us": float(np.median(stats.pipeline_us))
                    if stats.pipeline_us
                    else None,
                    "warnings": driver.warnings(),
                }
            )
    finally:
        if bar is not None:
            bar.stop()
        driver.close()
    result = finish_trial(out, rec_path)  # scored with the contact definition it recorded
    result["steps"] = stats.steps
    result["retarget_budget"] = retarget_budget
    (out / "metrics.json").write_text(json.dumps(result, indent=2) + "\n")
    return result
