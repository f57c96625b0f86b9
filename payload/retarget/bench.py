"""``payload bench retarget``: production against reference on the same targets, same run.

The target stream is deterministic (seeded) and has two parts per pair:

* a smooth pinch-open-rotate trajectory at 50 Hz: a synthetic thumb and index
  (fingertip and distal-joint points in the wrist frame) open and close, roll about
  the forearm and drift, with 0.5 mm of Gaussian noise on every point; the
  pinch-to-open calibration (:mod:`payload.retarget.calibration`) maps it to robot
  targets and posture references;
* random reachable targets: joint configurations drawn uniformly in the pair's box,
  pushed through forward kinematics (Pinocchio), each a jump from the last command,
  with the posture reference of their span.

Three loops run over the same stream, each solver warm-started from its own previous
answer (its temporal term refers to that answer too): the scipy reference and the
production solver under both budgets (``paper``: at most 20 residual evaluations per
pair solve; ``converged``). Every answer's cost is then evaluated by one independent
implementation (Pinocchio + numpy) and compared with the best-known optimum of that
solve (:mod:`payload.retarget.optimum`: scipy trf/soft_l1 with 400 evaluations from
several starts, lowest kept); ``optimum_fraction`` is the fraction within 1e-3
relative; with self-collision modelled (``config.collisions``, off by default: ``--config`` with
``[retarget] collisions = true``) the objective
carries the collision penalty and only answers that keep the margin in the solver's own
geometry count, so the optimum is the constrained one. ``collision_free_fraction`` is
the fraction of answers python-fcl finds free of self-collision on the URDF's collision
meshes (:mod:`payload.retarget.meshcheck`), an independent check.

Times are wall-clock per pair solve, including each solver's Python call
(``median_us``, ``p99_us``), with the same calls' thread CPU time beside them
(``cpu_median_us``, ``cpu_p99_us``). Every call is timed once: a call another process
preempted (its wall time exceeds its CPU time by more than :data:`PREEMPTED_US` and by
half) is counted in ``preempted_calls`` and keeps its time. The loops run one after
the other, and nothing but the solves runs inside one (answers are costed afterwards).
The production solves are then replayed twice (not counted in ``preempted_calls``):
interleaved, per pair solve the reference's solve of the same step, then each budget's
(``interleaved_median_us``, ``interleaved_p99_us``: cold caches, as in a control loop
that simulates or renders between solves; on a shared 2-core VM this costs about twice
the own-loop time), and back to back (``isolated_median_us``).
``production`` is the production solver under the configuration's budget (default
``paper``); ``cost_not_worse_fraction`` compares its costs with the reference's, step by
step.
"""

from __future__ import annotations

import platform
import time
import warnings
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from payload.retarget.calibration import PairCalibration, calibrate, pair_range
from payload.retarget.casadi_solver import PairRetargeter
from payload.retarget.errors import RetargetError
from payload.retarget.features import PairFeatures, PairKinematics, features_from_points
from payload.retarget.hand import HandDescription, load_hand
from payload.retarget.meshcheck import PairMeshCheck
from payload.retarget.objective import BUDGETS, RetargetConfig
from payload.retarget.optimum import (
    OPTIMUM_NFEV,
    OPTIMUM_TOLERANCE,
    RANDOM_STARTS,
    CompiledObjective,
    best_known_cost,
)
from payload.retarget.reference import ReferenceRetargeter
from payload.schema import CONTROL_DT

DT = CONTROL_DT
"""Control period of the target stream [s] (the 50 Hz loop's)."""

COST_TOLERANCE = 1e-3
"""A production cost counts as not worse when ``<= reference * (1 + COST_TOLERANCE)``."""

NOISE = 0.5e-3
"""Standard deviation of the noise on every synthetic hand point [m]."""

PREEMPTED_US = 200.0
"""A timed call whose wall time exceeds its thread CPU time by this much [us] (and by half
its CPU time) was preempted by another process; it is counted (``preempted_calls``), and
its time stays in the statistics."""


def _rx(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def synthetic_hand(opening: float, roll: float, drift: np.ndarray) -> np.ndarray:
    """Thumb and index points ``[p_thumb, p_index, a_thumb, a_index]`` in the wrist frame.

    Wrist frame: x along the hand, y to the left, z up. The thumb tip is below the
    index tip; their span is 15 mm at ``opening = 0`` and 110 mm at 1.

    Args:
        opening: 0 = pinch, 1 = open (may overshoot slightly).
        roll: Rotation of the pinch about the wrist x axis [rad].
        drift: Offset of the pinch centre [m], shape (3,).

    Returns:
        Points, shape (4, 3) [m].
    """
    rot = _rx(roll)
    half = 0.5 * (0.015 + opening * 0.095)
    centre = np.array([0.09, 0.0, -0.02]) + drift
    d = rot @ np.array([0.0, 0.0, 1.0])
    beta = 0.9 * (1.0 - opening)
    u1 = rot @ np.array([np.cos(beta), 0.0, np.sin(beta)])
    u2 = rot @ np.array([np.cos(beta), 0.0, -np.sin(beta)])
    p1, p2 = centre - half * d, centre + half * d
    return np.array([p1, p2, p1 - 0.025 * u1, p2 - 0.025 * u2])


def human_pinch_and_open() -> tuple[PairFeatures, PairFeatures]:
    """The synthetic operator's calibration poses (no noise): pinch, then open."""
    zero = np.zeros(3)
    return (
        features_from_points(*synthetic_hand(0.0, 0.0, zero)),
        features_from_points(*synthetic_hand(1.0, 0.0, zero)),
    )


@dataclass(frozen=True)
class StreamStep:
    """One target of the stream for one pair.

    Attributes:
        kind: ``trajectory`` or ``random``.
        targets: Robot targets, shape (13,).
        q_ref: Posture reference, shape (n,).
    """

    kind: str
    targets: np.ndarray
    q_ref: np.ndarray


def target_stream(
    pk: PairKinematics, calibration: PairCalibration, steps: int, seed: int, phase: float = 0.0
) -> list[StreamStep]:
    """The deterministic target stream of one pair: trajectory first, then random jumps.

    Args:
        pk: The pair's kinematics.
        calibration: The pair's calibration (maps the synthetic hand to targets).
        steps: Number of steps; ``steps - steps // 2`` trajectory, ``steps // 2`` random.
        seed: Seed of the noise and the random configurations.
        phase: Time offset of the trajectory [s] (pairs move out of step).
    """
    rng = np.random.default_rng(seed)
    out = []
    n_traj = steps - steps // 2
    for k in range(n_traj):
        t = k * DT + phase
        opening = -0.05 + 1.1 * (0.5 - 0.5 * np.cos(2 * np.pi * t / 3.0))
        roll = 0.6 * np.sin(2 * np.pi * t / 5.0)
        drift = 0.01 * np.array([np.sin(2 * np.pi * t / 4.0), np.sin(2 * np.pi * t / 6.0), 0.0])
        pts = synthetic_hand(opening, roll, drift) + rng.normal(0.0, NOISE, (4, 3))
        targets, q_ref = calibration.command(features_from_points(*pts))
        out.append(StreamStep("trajectory", targets.as_vector(), q_ref))
    qs = pk.lower + rng.random((steps // 2, pk.n)) * pk.range
    for f in pk.features_batch(qs):
        out.append(StreamStep("random", f, calibration.posture_reference(f[0])))
    return out


@dataclass
class _Loop:
    """One solver's own loop over the stream: warm-started from its own answers."""

    name: str
    solvers: dict[str, Any]
    wall_us: list[float] = field(default_factory=list)
    cpu_us: list[float] = field(default_factory=list)
    preempted: int = 0
    cost: list[float] = field(default_factory=list)
    best: list[float] = field(default_factory=list)
    iterations: list[int] = field(default_factory=list)
    evaluations: list[int] = field(default_factory=list)
    converged: list[bool] = field(default_factory=list)
    collision: list[bool] = field(default_factory=list)
    clearance: list[float] = field(default_factory=list)
    span_err: list[float] = field(default_factory=list)
    answers: list[np.ndarray] = field(default_factory=list)
    inputs: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)
    kinds: list[str] = field(default_factory=list)
    violations: int = 0

    def optimal(self) -> np.ndarray:
        """Solves within the tolerance of the best-known optimum; an answer inside the
        self-collision margin is never optimal (nor does its cost lower the optimum)."""
        c = np.array(self.cost)
        free = np.array(self.clearance) >= 0 if self.clearance else np.ones(c.size, bool)
        b = np.where(free, np.minimum(np.array(self.best), c), np.array(self.best))
        return free & (c <= b * (1.0 + OPTIMUM_TOLERANCE))


def _stats(us: np.ndarray, cpu_us: np.ndarray) -> dict[str, float]:
    return {
        "median_us": round(float(np.median(us)), 2),
        "p99_us": round(float(np.percentile(us, 99)), 2),
        "mean_us": round(float(np.mean(us)), 2),
        "max_us": round(float(np.max(us)), 2),
        "cpu_median_us": round(float(np.median(cpu_us)), 2),
        "cpu_p99_us": round(float(np.percentile(cpu_us, 99)), 2),
    }


def _budget_stats(lp: _Loop, checked: bool, cold: np.ndarray) -> dict[str, Any]:
    ev = np.array(lp.evaluations)
    out: dict[str, Any] = {
        "median_us": round(float(np.median(lp.wall_us)), 2),
        "p99_us": round(float(np.percentile(lp.wall_us, 99)), 2),
        "interleaved_median_us": round(float(np.median(cold)), 2),
        "interleaved_p99_us": round(float(np.percentile(cold, 99)), 2),
        "cpu_median_us": round(float(np.median(lp.cpu_us)), 2),
        "cpu_p99_us": round(float(np.percentile(lp.cpu_us, 99)), 2),
        "evaluations_median": float(np.median(ev)),
        "evaluations_max": int(ev.max()),
        "optimum_fraction": round(float(lp.optimal().mean()), 4),
        "collision_free_fraction": (
            round(1.0 - float(np.mean(lp.collision)), 4) if checked else None
        ),
        "preempted_calls": lp.preempted,
    }
    return out


def _timed(lp: _Loop, solve: Any, *args: Any) -> Any:
    """One solve, timed once: wall and thread CPU time [us]. A call another process
    preempted (wall exceeds CPU time by PREEMPTED_US and by half) is counted, not re-run."""
    clock, cpu = time.perf_counter_ns, time.thread_time_ns
    u0, t0 = cpu(), clock()
    out = solve(*args)
    t1, u1 = clock(), cpu()
    wall, used = (t1 - t0) / 1e3, (u1 - u0) / 1e3
    lp.wall_us.append(wall)
    lp.cpu_us.append(used)
    lp.preempted += int(wall - used >= max(PREEMPTED_US, 0.5 * used))
    return out


def _run_loops(
    loops: list[_Loop], pairs: list[str], streams: dict[str, list[StreamStep]], progress: bool
) -> None:
    """Each solver's own loop over the stream, one loop after the other: a step solves
    every pair once, warm-started from the solver's own previous answer; nothing but the
    solves runs inside a loop (the answers are costed afterwards)."""
    steps = len(next(iter(streams.values())))

    def one_step(lp: _Loop, k: int) -> None:
        for name in pairs:
            st = streams[name][k]
            solver = lp.solvers[name]
            q_prev = solver.command
            q, info = _timed(lp, solver.solve, st.targets, q_prev, st.q_ref)
            lp.answers.append(q)
            lp.inputs.append((name, st.targets, q_prev, st.q_ref))
            lp.kinds.append(st.kind)
            lp.iterations.append(info.iterations)
            lp.evaluations.append(info.evaluations)
            lp.converged.append(info.converged)

    if progress:
        from rich.console import Console
        from rich.progress import Progress

        with Progress(console=Console(stderr=True), transient=True) as bar:
            task = bar.add_task("retarget bench", total=steps * len(loops))
            for lp in loops:
                for k in range(steps):
                    one_step(lp, k)
                    bar.advance(task)
    else:
        for lp in loops:
            for k in range(steps):
                one_step(lp, k)
    for lp in loops:  # the bookkeeping, outside the timed loops
        for i, (name, targets, q_prev, q_ref) in enumerate(lp.inputs):
            solver, q = lp.solvers[name], lp.answers[i]
            lp.cost.append(solver.cost(q, targets, q_ref, q_prev))
            lp.violations += int(np.sum((q < solver.lower) | (q > solver.upper)))
            if lp.kinds[i] == "random":
                lp.span_err.append(abs(solver.features(q).span - targets[0]) * 1e3)


def _replay(loops: list[_Loop], between: _Loop | None = None) -> dict[str, np.ndarray]:
    """The loops' solves again, per pair solve one of each loop in turn, after ``between``'s
    solve of the same step when given (interleaved as a control loop that does other work
    between solves would run them: cold caches), else back to back. Wall time [us] per
    solve and loop; the answers are not used."""
    clock = time.perf_counter_ns
    out: dict[str, list[float]] = {lp.name: [] for lp in loops}
    for i in range(len(loops[0].inputs)):
        if between is not None:
            name, *args = between.inputs[i]
            between.solvers[name].solve(*args)
        for lp in loops:
            name, targets, q_prev, q_ref = lp.inputs[i]
            t0 = clock()
            lp.solvers[name].solve(targets, q_prev, q_ref)
            out[lp.name].append((clock() - t0) / 1e3)
    return {k: np.array(v) for k, v in out.items()}


def _judge(
    loops: list[_Loop],
    pks: dict[str, PairKinematics],
    checks: dict[str, PairMeshCheck | None],
    seed: int,
) -> None:
    """Best-known optimum of every solve of every loop, and the FCL collision check."""
    rng = np.random.default_rng(seed + 7)
    judge = {n: loops[-1].solvers[n] for n in pks}  # a production solver: its objective
    objectives = {n: judge[n].objective for n in pks}
    compiled = {n: CompiledObjective(pks[n], judge[n].config) for n in pks}
    clear = {n: (judge[n].clearance if judge[n].collisions else None) for n in pks}
    for i in range(len(loops[0].inputs)):
        others = [lp.answers[i] for lp in loops]
        for lp in loops:
            name, targets, q_prev, q_ref = lp.inputs[i]
            lp.best.append(
                best_known_cost(
                    pks[name],
                    objectives[name],
                    compiled[name],
                    targets,
                    q_prev,
                    q_ref,
                    others,
                    rng,
                    clear[name],
                )
            )
            if clear[name] is not None:
                lp.clearance.append(clear[name](lp.answers[i]))
            check = checks[name]
            if check is not None and check.available:
                lp.collision.append(checks[name].in_collision(lp.answers[i]))


def run_bench(
    hand: HandDescription | None = None,
    steps: int = 1000,
    seed: int = 0,
    config: RetargetConfig | None = None,
    backend: str = "auto",
    progress: bool = False,
) -> dict[str, Any]:
    """Run the reference and both production budgets on the same target stream.

    Args:
        hand: Hand description (``None``: ours); every pair of the hand is benchmarked.
        steps: Control steps; each step solves every pair once in each solver's loop.
        seed: Seed of the stream.
        config: Eq. 3 settings (``None``: the paper's); its ``budget`` is the one
            reported as ``production``.
        backend: Production backend (``auto``, ``compiled`` or ``vm``).
        progress: Show a progress bar on stderr.

    Returns:
        The JSON-ready result (fields listed in docs/retargeting.md).

    Raises:
        RetargetError: ``steps`` below 2, or an invalid hand or setting.
    """
    if steps < 2:
        raise RetargetError(f"--steps must be >= 2, got {steps}")
    hand = hand if hand is not None else load_hand()
    config = config or RetargetConfig()
    kin = hand.kinematics()
    setup_t0 = time.perf_counter()
    pairs = list(hand.pairs)
    pks, streams, checks = {}, {}, {}
    solvers: dict[str, dict[str, Any]] = {"reference": {}, **{b: {} for b in BUDGETS}}
    pinch, open_ = human_pinch_and_open()
    for i, name in enumerate(pairs):
        pk = pks[name] = PairKinematics(hand, name, kin)
        with warnings.catch_warnings():
            # A fallback to the virtual machine is reported as "backend_reason" instead.
            warnings.simplefilter("ignore", RuntimeWarning)
            for b in BUDGETS:
                cfg = config.replace(budget=b)
                solvers[b][name] = PairRetargeter(hand, name, cfg, pk, backend=backend)
        solvers["reference"][name] = ReferenceRetargeter(hand, name, config, pk)
        cal = calibrate(pinch, open_, pair_range(pk, collisions=config.collisions))
        streams[name] = target_stream(pk, cal, steps, seed + 1000 * i, phase=1.3 * i)
        try:
            checks[name] = PairMeshCheck(pk)
        except RetargetError:
            if config.collisions:  # the model needs the meshes too: said in one line
                raise
            checks[name] = None  # a hand without its meshes: no FCL check
    setup_s = time.perf_counter() - setup_t0

    loops = [_Loop(w, solvers[w]) for w in ("reference", *BUDGETS)]
    _run_loops(loops, pairs, streams, progress)
    judge_t0 = time.perf_counter()
    _judge(loops, pks, checks, seed)
    judge_s = time.perf_counter() - judge_t0
    by_name = {lp.name: lp for lp in loops}
    ref, prod = by_name["reference"], by_name[config.budget]
    checked = all(c is not None and c.available for c in checks.values())

    cold = _replay([by_name[b] for b in BUDGETS], between=ref)
    # back to back (warm caches): what the solver costs when the loop does little else
    isolated = _replay([prod])[prod.name]

    prod_us, ref_us = np.array(prod.wall_us), np.array(ref.wall_us)
    pc, rc = np.array(prod.cost), np.array(ref.cost)
    kind = np.array(prod.kinds)
    not_worse = pc <= rc * (1.0 + COST_TOLERANCE)
    p_stats: dict[str, Any] = _stats(prod_us, np.array(prod.cpu_us))
    r_stats: dict[str, Any] = _stats(ref_us, np.array(ref.cpu_us))
    its = np.array(prod.iterations)
    backends = [r.backend for r in prod.solvers.values()]
    p_stats.update(
        {
            "backend": "compiled" if all(b == "compiled" for b in backends) else "vm",
            "backend_reason": next(
                (r.backend_reason for r in prod.solvers.values() if r.backend_reason), None
            ),
            "budget": config.budget,
            "iterations_median": float(np.median(its)),
            "iterations_max": int(its.max()),
            "iteration_cap": config.max_iterations,
            "converged_fraction": round(float(np.mean(prod.converged)), 4),
            "isolated_median_us": round(float(np.median(isolated)), 2),
            "interleaved_median_us": round(float(np.median(cold[config.budget])), 2),
            "interleaved_p99_us": round(float(np.percentile(cold[config.budget], 99)), 2),
            "isolated_p99_us": round(float(np.percentile(isolated, 99)), 2),
            "preempted_remeasured": 0,
            "preempted_calls": prod.preempted,
        }
    )
    r_stats.update(
        {
            "nfev_median": float(np.median(ref.evaluations)),
            "max_nfev": config.max_nfev,
            "preempted_remeasured": 0,
            "preempted_calls": ref.preempted,
            "optimum_fraction": round(float(ref.optimal().mean()), 4),
            "collision_free_fraction": (
                round(1.0 - float(np.mean(ref.collision)), 4) if checked else None
            ),
        }
    )
    by_kind = {}
    for kd in ("trajectory", "random"):
        m = kind == kd
        by_kind[kd] = {
            "pair_solves": int(m.sum()),
            "cost_not_worse_fraction": round(float(not_worse[m].mean()), 4),
            "production_median_us": round(float(np.median(prod_us[m])), 2),
            "reference_median_us": round(float(np.median(ref_us[m])), 2),
            "production_cost_median": round(float(np.median(pc[m])), 6),
            "reference_cost_median": round(float(np.median(rc[m])), 6),
            "optimum_fraction": {lp.name: round(float(lp.optimal()[m].mean()), 4) for lp in loops},
        }
    return {
        "steps": steps,
        "pairs": pairs,
        "pair_solves": len(prod.wall_us),
        "reference": r_stats,
        "production": p_stats,
        "budgets": {b: _budget_stats(by_name[b], checked, cold[b]) for b in BUDGETS},
        "speedup_median": round(float(np.median(ref_us) / np.median(prod_us)), 2),
        "cost_not_worse_fraction": round(float(not_worse.mean()), 4),
        "cost_better_fraction": round(float(np.mean(pc < rc * (1.0 - COST_TOLERANCE))), 4),
        "span_error_mm_median": round(float(np.median(prod.span_err)), 4),
        "span_error_mm_p95": round(float(np.percentile(prod.span_err, 95)), 4),
        "span_error_mm_median_reference": round(float(np.median(ref.span_err)), 4),
        "bound_violations": int(sum(lp.violations for lp in loops)),
        "by_kind": by_kind,
        "timing": {
            "loops": "each solver's own loop, one after the other, nothing but the solves "
            "inside (median_us, p99_us, speedup_median, by_kind)",
            "interleaved": "production solves replayed per pair solve after the reference's "
            "and the other budget's solve of the same step (cold caches)",
            "isolated": "production solves replayed back to back",
        },
        "optimum": {
            "method": "scipy least_squares trf/soft_l1, analytic Jacobian (compiled CasADi "
            "kinematics), every start's answer costed with Pinocchio",
            "max_nfev_per_start": OPTIMUM_NFEV,
            "starts": "previous command, posture reference, rest, every loop's answer, "
            f"{RANDOM_STARTS} seeded random",
            "relative_tolerance": OPTIMUM_TOLERANCE,
            "judge_s": round(judge_s, 1),
        },
        "collision_check": {
            "library": "python-fcl",
            "geometry": "URDF collision meshes",
            "link_pairs": {n: len(c.pairs) for n, c in checks.items()},
            "solver_terms": {
                n: (len(pks[n].collision.terms) if config.collisions else 0) for n in pks
            },
            "margin_m": {n: pks[n].collision.margin for n in pks},
        },
        "hand": hand.name,
        "seed": seed,
        "config": asdict(config),
        "setup_s": round(setup_s, 3),
        "machine": {"python": platform.python_version(), "cpu": platform.machine()},
    }
