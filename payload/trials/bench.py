"""``payload bench trial``: a whole trial's real-time factor, where its time goes, log size.

The bench runs one synthetic trial in this process exactly as ``payload trial`` does and
times it with wrappers around the stages (each figure is exclusive: time inside a nested
timed stage counts only there):

* ``startup``: building the MuJoCo world (model compile), loading the retargeters (and
  compiling them when not cached), placing the CTB;
* ``physics``: the simulator's control steps (vehicle controller + 20 ``mj_step``);
  of it, ``mj_step_seconds`` is the time inside ``mujoco.mj_step`` alone, and
  ``physics_only_realtime_factor`` the real-time factor a trial could reach if nothing
  but MuJoCo's stepping took time (the ceiling any work outside MuJoCo can approach);
  ``physics_floor_s`` is that same summed ``mj_step`` time (the least a trial can take)
  and ``overhead_ratio`` the wall time over it (1 would be a trial at its physics' cost;
  ``overhead_ratio_cpu`` the same in CPU time, less disturbed by other processes);
* ``contacts``: the world-state read-out after each step (poses, fingertip contacts,
  indicator);
* ``operator``: the synthetic operator producing hand frames;
* ``pipeline``: the teleoperation pipeline (filters, retargeting, rail and base channels);
* ``recording``: building the step records and writing the MCAP file;
* ``scoring``: the metrics (from the recording the recorder kept, or read back from its
  file) and the two figures;
* ``other``: the rest of the loop (phase labels, world views, bookkeeping).

Before the trial, ``worker_import_s``: how long a fresh interpreter takes to import a
trial's modules, what each Dask worker of a campaign pays before its first trial.

:func:`run_trial_bench_repeated` (``--repeat N``) runs the bench N times, each in a fresh
process, and reports the median run with every run's figures: one run's ratio moves with
the machine from run to run and from hour to hour (docs/speed.md).

``warm`` (``--warm``) first runs the same trial once, untimed, in the same process, and
then measures it again: what a campaign's Dask worker pays for its later trials (the
imports done, the kernels loaded and checked, the retargeters' solvers and the world's
compile in the process's caches). The cold run, the default, is what ``payload trial``
costs and what issue 31's aim is measured on.
"""

from __future__ import annotations

import functools
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from payload.cliutil import load_average
from payload.folders import RECORDING

STAGES: tuple[str, ...] = (
    "startup",
    "physics",
    "contacts",
    "operator",
    "pipeline",
    "recording",
    "scoring",
    "other",
)


class _Timers:
    """Exclusive wall and CPU time per stage (a stack of open stages)."""

    def __init__(self) -> None:
        self.wall = dict.fromkeys(STAGES, 0.0)
        self.cpu = dict.fromkeys(STAGES, 0.0)
        self._stack: list[str] = []
        self._mark = (time.perf_counter(), time.process_time())

    def _switch(self) -> None:
        now = (time.perf_counter(), time.process_time())
        if self._stack:
            top = self._stack[-1]
            self.wall[top] += now[0] - self._mark[0]
            self.cpu[top] += now[1] - self._mark[1]
        self._mark = now

    def wrap(self, stage: str, fn: Callable) -> Callable:
        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            self._switch()
            self._stack.append(stage)
            try:
                return fn(*args, **kwargs)
            finally:
                self._switch()
                self._stack.pop()

        return timed


class _StepClock:
    """Wall and CPU time inside ``mujoco.mj_step`` alone (part of ``physics``)."""

    def __init__(self) -> None:
        self.wall = 0.0
        self.cpu = 0.0
        self.steps = 0

    def wrap(self, fn: Callable) -> Callable:
        @functools.wraps(fn)
        def timed(model: Any, data: Any, nstep: int = 1) -> Any:
            w0, c0 = time.perf_counter(), time.process_time()
            try:
                return fn(model, data, nstep)
            finally:
                self.wall += time.perf_counter() - w0
                self.cpu += time.process_time() - c0
                self.steps += nstep

        return timed


@contextmanager
def _stepping_timed(clock: _StepClock) -> Iterator[None]:
    """Time every ``mj_step`` call the simulator makes (it looks the function up on the
    ``mujoco`` module at each control step)."""
    import mujoco

    saved = mujoco.mj_step
    mujoco.mj_step = clock.wrap(saved)
    try:
        yield
    finally:
        mujoco.mj_step = saved


@contextmanager
def _patched(timers: _Timers) -> Iterator[None]:
    """Wrap the stage functions (class attributes) for the duration."""
    from payload.sim.driver import SimDriver
    from payload.teleop.pipeline import TeleopPipeline
    from payload.trials import preparation, runner, scoring
    from payload.trials.recorder import TrialRecorder

    targets = [
        (SimDriver, "__init__", "startup"),
        (preparation, "retargeting", "startup"),
        (preparation, "place_ctb_for_teleop", "startup"),
        (SimDriver, "step", "physics"),
        (SimDriver, "world_state", "contacts"),
        (runner.HeadsetSource, "frame", "operator"),
        (TeleopPipeline, "step", "pipeline"),
        (TrialRecorder, "write_later", "recording"),  # the step records made at its flush
        (TrialRecorder, "write_hands", "recording"),
        (TrialRecorder, "flush", "recording"),
        (scoring, "finish_trial", "scoring"),  # the runner imports it at each trial
    ]
    saved = [(obj, name, getattr(obj, name)) for obj, name, _ in targets]
    try:
        for obj, name, stage in targets:
            setattr(obj, name, timers.wrap(stage, getattr(obj, name)))
        yield
    finally:
        for obj, name, fn in saved:
            setattr(obj, name, fn)


def run_trial_bench(
    seed: int = 0,
    *,
    out_dir: Path | None = None,
    pin: bool = False,
    max_time: float | None = None,
    physics_dt: float | None = None,
    warm: bool = False,
) -> dict:
    """Run one synthetic trial and report its speed, time breakdown and log size.

    Args:
        seed: Trial seed.
        out_dir: Where the trial folder goes (default: a temporary folder, removed).
        pin: Restrict the process to one CPU core (Linux).
        max_time: Cap on the session length [s] (default: the runner's, a whole trial).
        physics_dt: Physics time step [s] (default: the runner's, 1 ms).
        warm: Run the same trial once first, untimed, in this process (into a temporary
            folder, removed), and measure the second: a campaign worker's later trial.

    Returns:
        ``{"sim_seconds", "wall_seconds", "cpu_seconds", "realtime_factor",
        "cpu_realtime_factor", "breakdown" (wall [s] per stage), "breakdown_cpu",
        "mj_step_seconds", "mj_step_cpu_seconds", "mj_step_us" (per 1 ms physics step),
        "physics_only_realtime_factor", "log_bytes", "log_bytes_per_sim_minute", "steps",
        "seed", "success", "warm", "worker_import_s", "kernels" (each compiled kernel of the loop:
        ``compiled`` or ``numpy``), "full_checks" (the kernels that ran a full self-check
        during this run, :func:`payload.native.full_checks`: no check stamp yet, as after
        a change; the figures include them), "environment" (the versions and BLAS kernels
        it ran on: :func:`payload.native.environment`)}``.
    """
    imports = worker_import_seconds()  # first: no trial running beside it
    before = os.sched_getaffinity(0) if pin and hasattr(os, "sched_setaffinity") else None
    if before is not None:
        os.sched_setaffinity(0, {min(before)})
    try:
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(out_dir) if out_dir is not None else Path(tmp) / "trial"
            # on Ctrl-C, not the recorder's "kept": a folder in tmp goes with it
            if warm:
                try:
                    _trial(seed, Path(tmp) / "warm-up", max_time, physics_dt)
                except KeyboardInterrupt as exc:
                    exc.__notes__ = [
                        "nothing kept: interrupted in the bench's untimed first run (--warm), "
                        "in a temporary folder" + ("; --out not written" if out_dir else "")
                    ]
                    raise
            try:
                result = _bench(seed, out, before is not None, max_time, physics_dt)
            except KeyboardInterrupt as exc:
                if out_dir is None:
                    exc.__notes__ = ["nothing kept: the bench's trial ran in a temporary folder"]
                raise
            return {**result, "warm": warm, "worker_import_s": imports}
    finally:
        if before is not None:
            os.sched_setaffinity(0, before)


def _trial(seed: int, out: Path, max_time: float | None, physics_dt: float | None) -> dict:
    """The bench's trial, run by the runner with the bench's options (the runner's
    defaults where None): untimed as ``warm``'s first run, timed inside :func:`_bench`."""
    from payload.trials import runner

    extra: dict[str, Any] = {} if max_time is None else {"max_time": max_time}
    if physics_dt is not None:
        extra["physics_dt"] = physics_dt
    return runner.run_trial(seed, out_dir=out, **extra)


def _bench(
    seed: int, out: Path, pinned: bool, max_time: float | None, physics_dt: float | None
) -> dict:
    from payload.native import environment, full_checks
    from payload.schema import CONTROL_DT

    before = len(full_checks())  # the process's earlier ones are not this run's
    timers = _Timers()
    clock = _StepClock()
    w0, c0 = time.perf_counter(), time.process_time()
    timers._stack.append("startup")  # the imports below count as start-up
    timers._mark = (w0, c0)
    with _patched(timers), _stepping_timed(clock):
        timers._switch()
        timers._stack[-1] = "other"
        result = _trial(seed, out, max_time, physics_dt)
    timers._switch()
    wall, cpu = timers._mark[0] - w0, timers._mark[1] - c0
    sim_seconds = result["steps"] * CONTROL_DT
    size = (out / RECORDING).stat().st_size
    return {
        "seed": seed,
        "success": bool(result.get("success")),
        "steps": result["steps"],
        "sim_seconds": sim_seconds,
        "wall_seconds": wall,
        "cpu_seconds": cpu,
        "realtime_factor": sim_seconds / wall,
        "cpu_realtime_factor": sim_seconds / cpu if cpu > 0 else math.inf,
        "breakdown": dict(timers.wall),
        "breakdown_cpu": dict(timers.cpu),
        "mj_step_seconds": clock.wall,
        "mj_step_cpu_seconds": clock.cpu,
        "mj_step_us": clock.wall / clock.steps * 1e6 if clock.steps else None,
        "physics_dt": result.get("physics_dt"),
        "physics_floor_s": clock.wall,
        "overhead_ratio": wall / clock.wall if clock.wall > 0 else None,
        "overhead_ratio_cpu": cpu / clock.cpu if clock.cpu > 0 else None,
        "physics_only_realtime_factor": sim_seconds / clock.wall if clock.wall > 0 else None,
        "log_bytes": size,
        "log_bytes_per_sim_minute": size / (sim_seconds / 60.0),
        "pinned": pinned,
        "load_average": load_average(),
        "kernels": _kernels(),
        "full_checks": list(full_checks()[before:]),
        "environment": environment(),
    }


def _kernels() -> dict[str, str]:
    """The loop's compiled kernels and whether each ran compiled or in numpy."""
    from payload.native import kernel_status

    return kernel_status()


RUN_FIELDS: tuple[str, ...] = (
    "wall_seconds",
    "cpu_seconds",
    "physics_floor_s",
    "overhead_ratio",
    "overhead_ratio_cpu",
    "mj_step_us",
    "load_average",
    "full_checks",
)
"""What :func:`run_trial_bench_repeated` keeps of each run (``runs``): ``mj_step_us``, the
core's speed of that run, beside its ratio (the ratio moves with it, docs/speed.md)."""


def run_trial_bench_repeated(
    seed: int = 0,
    repeat: int = 3,
    *,
    pin: bool = False,
    max_time: float | None = None,
    physics_dt: float | None = None,
    warm: bool = False,
    progress: Callable[[int, dict], None] | None = None,
) -> dict:
    """``repeat`` runs of :func:`run_trial_bench` one after the other, each in a fresh
    process (the cold process a single ``payload bench trial`` is), each trial in a
    temporary folder.

    Args:
        seed, pin, max_time, physics_dt, warm: As :func:`run_trial_bench`'s (``warm``:
            each fresh process runs the trial once before the measured one).
        repeat: How many runs (at least 1).
        progress: Called with each run's index (from 0) and result as it ends.

    Returns:
        The median run's result (by ``overhead_ratio``; of an even count, the lower of the
        two middle runs), with ``repeat``, ``runs`` (each run's :data:`RUN_FIELDS`, in
        the order run) and ``overhead_ratio_median`` (the runs' median, the middle two
        runs' mean for an even count), ``overhead_ratio_min`` and ``overhead_ratio_max``.

    Raises:
        ValueError: ``repeat`` < 1.
        RuntimeError: A run failed (with the last line it wrote to its error stream).
    """
    if repeat < 1:
        raise ValueError(f"repeat must be >= 1, got {repeat}")
    kwargs = {
        "seed": seed, "pin": pin, "max_time": max_time, "physics_dt": physics_dt, "warm": warm,
    }  # fmt: skip
    code = (
        "import json, sys\n"
        "from payload.trials.bench import run_trial_bench\n"
        "print(json.dumps(run_trial_bench(**json.loads(sys.argv[1]))))\n"
    )
    env = child_env()
    runs: list[dict] = []
    for i in range(repeat):
        done = subprocess.run(
            [sys.executable, "-c", code, json.dumps(kwargs)], capture_output=True, text=True,
            env=env,
        )  # fmt: skip
        if done.returncode != 0:
            said = done.stderr.strip().splitlines() or ["(nothing on its error stream)"]
            raise RuntimeError(
                f"bench run {i + 1} of {repeat} failed (exit {done.returncode}): {said[-1]}"
            )
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
        if progress is not None:
            progress(i, runs[-1])
    ratios = [r["overhead_ratio"] for r in runs]
    middle = sorted(range(repeat), key=lambda i: ratios[i])[(repeat - 1) // 2]
    return {
        **runs[middle],
        "repeat": repeat,
        "runs": [{k: r.get(k) for k in RUN_FIELDS} for r in runs],
        "overhead_ratio_median": statistics.median(ratios),
        "overhead_ratio_min": min(ratios),
        "overhead_ratio_max": max(ratios),
    }


WORKER_MODULES: tuple[str, ...] = ("payload.trials.runner", "payload.trials.campaign")
"""What a Dask worker imports to run its first trial (the campaign's trial function, then
the runner it calls)."""


def worker_import_seconds() -> float:
    """Wall time [s] a fresh interpreter takes to import :data:`WORKER_MODULES` (the
    imports alone, not the interpreter's start), in this process's environment (under
    the ``payload`` command: ``MUJOCO_GL=disable``, as its Dask workers get) and with this
    process's ``payload`` package first on the path.
    """
    code = (
        "import time\n"
        "t = time.perf_counter()\n"
        f"import {', '.join(WORKER_MODULES)}\n"
        "print(time.perf_counter() - t)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=child_env(),
        check=True,
    )  # fmt: skip
    return float(done.stdout.split()[-1])


def child_env() -> dict[str, str]:
    """This process's environment for a fresh interpreter, with this process's ``payload``
    package first on the path (wherever the command runs from)."""
    import payload

    env = dict(os.environ)
    root = str(Path(payload.__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    return env


__all__ = [
    "RUN_FIELDS",
    "STAGES",
    "WORKER_MODULES",
    "child_env",
    "run_trial_bench",
    "run_trial_bench_repeated",
    "worker_import_seconds",
]
