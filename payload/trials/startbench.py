"""How quickly the workbench's commands start (``payload bench start``): each measured in
fresh interpreters, as a user or a campaign worker meets it (docs/speed.md, "How a start
is kept quick"; the measurements: docs/speed-log.md, "A start with the safety layers").

What is measured, each the wall time of a fresh process (or of the part named), after
one untimed run that fills the caches (compiled kernels, the models' fingerprint, the
span ranges, the collision geometry):

* ``version_s``, ``help_s``: the whole ``payload --version`` and ``payload --help``
  (issue 31 asks for under :data:`START_AIM_S`);
* ``worker_import_s``: a Dask worker's imports before its first trial
  (:func:`payload.trials.bench.worker_import_seconds`; the issue asks for under
  :data:`WORKER_AIM_S`);
* ``retargeters_s``, ``retargeters_collisions_s``: importing and building the two
  pairs' retargeters without and with the self-collision model (the ``paper`` and the
  ``safe`` profile's);
* ``safety_filter_s``: importing and building the base safety filter on a built world;
* ``teleop_serve_s``: ``payload teleop serve`` (the simulator, the ``safe`` profile)
  from its start to its "serving" line.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from payload.trials.bench import child_env, worker_import_seconds

START_AIM_S = 0.3
"""Issue 31's aim for ``payload --help`` and ``payload --version`` [s]."""

WORKER_AIM_S = 0.5
"""Issue 31's aim for a Dask worker's imports [s]."""

LABELS: dict[str, str] = {
    "version_s": "payload --version (whole process)",
    "help_s": "payload --help (whole process)",
    "worker_import_s": "a campaign worker's imports",
    "retargeters_s": "the retargeters (paper profile)",
    "retargeters_collisions_s": "the retargeters with the self-collision model",
    "safety_filter_s": "the base safety filter",
    "teleop_serve_s": "teleop serve, start to serving",
}
"""Each measure's name (its JSON field) and what the text output calls it, in the order
they are taken (:func:`measures`)."""

NAMES: tuple[str, ...] = tuple(LABELS)
"""The measures' names, in order."""

AIMS: dict[str, float] = {
    "version_s": START_AIM_S,
    "help_s": START_AIM_S,
    "worker_import_s": WORKER_AIM_S,
}
"""The measures issue 31 gives an aim, and the aim [s]."""

SERVE_TIMEOUT_S = 120.0
"""How long ``teleop serve`` may take to say it is serving before the bench gives up."""

_RETARGETERS = (
    "import sys, time\n"
    "t = time.perf_counter()\n"
    "from payload.trials.retargeters import retargeting\n"
    "retargeting(None, 'paper', sys.argv[1] == '1')\n"
    "print(time.perf_counter() - t)\n"
)

_FILTER = (
    "import time\n"
    "from payload.sim.driver import SimDriver\n"
    "from payload.sim.world import build_world\n"
    "from payload.teleop.channels import BaseConfig\n"
    "from payload.trials.preparation import base_filter_for\n"
    "sim = SimDriver(build_world())\n"
    "t = time.perf_counter()\n"
    "base_filter_for(sim, BaseConfig())  # imports the filter's module\n"
    "print(time.perf_counter() - t)\n"
)


class StartBenchError(RuntimeError):
    """A measured command failed (its own last line of output is in the message)."""


def _env(project: Path) -> dict[str, str]:
    """A fresh process's environment: this process's ``payload`` first on the path, the
    project named, and Python's output unbuffered (the serve line is read as it comes)."""
    env = child_env()
    env["PAYLOAD_PROJECT"] = str(project)
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _run(args: list[str], env: dict[str, str], what: str) -> str:
    done = subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, env=env, check=False
    )
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise StartBenchError(f"{what} failed (exit {done.returncode}): {tail}")
    return done.stdout


def _whole(args: list[str], env: dict[str, str], what: str) -> float:
    """Wall time of a whole fresh process running ``python args``."""
    t = time.perf_counter()
    _run(args, env, what)
    return time.perf_counter() - t


def _printed(code: str, env: dict[str, str], what: str, *argv: str) -> float:
    """The seconds a fresh process running ``code`` prints last."""
    return float(_run(["-c", code, *argv], env, what).split()[-1])


def serve_ready_seconds(env: dict[str, str]) -> float:
    """Wall time from starting ``payload teleop serve`` (the simulator) to its "serving"
    line (on any free port); the server is then stopped as Ctrl-C stops it."""
    t = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "payload", "teleop", "serve", "--port", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
        start_new_session=True,
    )  # fmt: skip
    seen: list[str] = []
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith("serving"):
                return time.perf_counter() - t
            seen.append(line.strip())
            if time.perf_counter() - t > SERVE_TIMEOUT_S:
                break
        last = seen[-1] if seen else "(no output)"
        raise StartBenchError(f"teleop serve did not start serving: {last}")
    finally:
        try:
            os.killpg(proc.pid, signal.SIGINT)
            proc.communicate(timeout=30)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            proc.kill()
            proc.communicate()


def measures(project: Path) -> dict[str, Callable[[], float]]:
    """Each measure's name and a call that takes it once, for ``project``."""
    env = _env(project)
    return {
        "version_s": lambda: _whole(["-m", "payload", "--version"], env, "payload --version"),
        "help_s": lambda: _whole(["-m", "payload", "--help"], env, "payload --help"),
        "worker_import_s": worker_import_seconds,
        "retargeters_s": lambda: _printed(_RETARGETERS, env, "the retargeters", "0"),
        "retargeters_collisions_s": lambda: _printed(
            _RETARGETERS, env, "the retargeters with the self-collision model", "1"
        ),
        "safety_filter_s": lambda: _printed(_FILTER, env, "the base safety filter"),
        "teleop_serve_s": lambda: serve_ready_seconds(env),
    }


def check_names(only: tuple[str, ...] | None) -> None:
    """Raise ValueError naming what in ``only`` is not a measure (and the measures)."""
    unknown = sorted(set(only or ()) - set(NAMES))
    if unknown:
        raise ValueError(f"no measure {', '.join(unknown)} (there are: {', '.join(NAMES)})")


def run_start_bench(
    project: Path,
    repeat: int = 3,
    say: Callable[[str], None] | None = None,
    only: tuple[str, ...] | None = None,
) -> dict[str, Any]:
    """Every measure of the module text (or those named in ``only``, in the module's
    order), ``repeat`` times after one untimed run each: ``{name: median}`` with ``runs``
    (each measure's values), ``repeat``, the aims and the load average before and after.

    Raises:
        ValueError: ``only`` names a measure there is not.
    """
    from statistics import median

    check_names(only)
    every = measures(project)
    load_before = list(os.getloadavg())
    runs: dict[str, list[float]] = {}
    for name, take in every.items():
        if only is not None and name not in only:
            continue
        take()  # fills the caches this measure reads; not counted
        runs[name] = [take() for _ in range(repeat)]
        if say is not None:
            say(f"{name}: " + ", ".join(f"{v:.3f}" for v in runs[name]))
    return {
        **{name: median(values) for name, values in runs.items()},
        "runs": runs,
        "repeat": repeat,
        "aims": {name: aim for name, aim in AIMS.items() if name in runs},
        "load": [load_before, list(os.getloadavg())],
    }


__all__ = [
    "AIMS",
    "LABELS",
    "NAMES",
    "SERVE_TIMEOUT_S",
    "START_AIM_S",
    "WORKER_AIM_S",
    "StartBenchError",
    "check_names",
    "measures",
    "run_start_bench",
    "serve_ready_seconds",
]
