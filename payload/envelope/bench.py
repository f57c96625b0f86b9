"""``payload bench reach``: the reach check against MuJoCo's own collision, same run, and
``payload report reach`` timed as a user runs it.

1. The compiled overlap check (:mod:`payload.envelope.overlap`, MuJoCo's kinematics) and
   the reference it replaced, MuJoCo's ``mj_collision`` at its defaults, on the same
   samples in this process, one after the other, twice (the faster of each is kept):
   microseconds a sample, their ratio, and every (sample, body, body) row compared.
2. ``payload report reach --samples N --json`` in a fresh interpreter (imports, the
   forked workers, the report), ``runs`` times: wall and CPU time (user + sys, workers
   included). The report goes to a temporary folder holding a copy of the project's
   report, so an unchanged report is not redrawn, as in the project itself, and the
   project's ``analyses/`` is never touched.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from payload.envelope.collisions import CollisionModel
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.overlap import compile_check
from payload.envelope.pairs import ReachError
from payload.envelope.report_files import PROVENANCE_KEY
from payload.envelope.sampling import sample_configurations
from payload.envelope.vehicle import Vehicle

REACH_AIM_S = 3.0
"""Issue 35's aim for ``payload report reach`` at its default sample count on the 2-core
machine [s]."""


def _mujoco_rows(model: CollisionModel, samples: np.ndarray) -> tuple[set, float]:
    """MuJoCo's own answer: ``mj_collision`` at the model's options (MuJoCo's defaults),
    one sample at a time; (rows, seconds)."""
    m, d = model.model, model.data
    qpos = model.qpos(samples)
    rows: set[tuple[int, int, int]] = set()
    t = time.perf_counter()
    for k in range(len(samples)):
        d.qpos[:] = qpos[k]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        if d.ncon:
            bodies = np.sort(m.geom_bodyid[d.contact.geom], axis=1)
            rows.update((k, int(a), int(b)) for a, b in bodies)
    return rows, time.perf_counter() - t


def _overlap_rows(model: CollisionModel, samples: np.ndarray) -> tuple[set, float]:
    """The compiled check in this process (:meth:`CollisionModel.check`); (rows, seconds)."""
    t = time.perf_counter()
    c = model.check(samples)
    seconds = time.perf_counter() - t
    return set(zip(c.index.tolist(), c.body_a.tolist(), c.body_b.tolist())), seconds


def compare_checks(
    geom: PayloadGeometry, vehicle: Vehicle, samples: int, seed: int = 0
) -> dict[str, Any]:
    """Part 1: the compiled check against ``mj_collision`` on the same samples."""
    model = CollisionModel(geom, vehicle)
    q = sample_configurations(geom.tree, samples, np.random.default_rng(seed))
    compile_check()  # load (or compile) the check before timing it
    times: dict[str, list[float]] = {"overlap": [], "mujoco": []}
    for _ in range(2):
        ours, t_ours = _overlap_rows(model, q)
        ref, t_ref = _mujoco_rows(model, q)
        times["overlap"].append(t_ours)
        times["mujoco"].append(t_ref)
    overlap_us = min(times["overlap"]) / samples * 1e6
    mujoco_us = min(times["mujoco"]) / samples * 1e6
    return {
        "check_samples": samples,
        "overlap_us": overlap_us,
        "mujoco_us": mujoco_us,
        "speedup": mujoco_us / overlap_us,
        "rows": len(ref),
        "rows_only_overlap": len(ours - ref),
        "rows_only_mujoco": len(ref - ours),
        "identical": ours == ref,
    }


def _name_the_project(report: Path, root: Path) -> None:
    """Give a copy of a project's report the project it came from, as a report written
    outside its project's ``analyses/`` carries it (the copy is then that design's report
    there, which the timed command replaces only when its figures change)."""
    if not report.exists():
        return
    data = json.loads(report.read_text())
    prov = data.get(PROVENANCE_KEY)
    if isinstance(prov, dict) and "project" not in prov:
        data[PROVENANCE_KEY] = {"project": str(root), **prov}
        report.write_text(json.dumps(data, indent=2) + "\n")


def time_report(
    root: Path, analyses: Path, samples: int, runs: int, aim_samples: int
) -> dict[str, Any]:
    """Part 2: ``payload report reach --samples N --json`` in a fresh interpreter;
    ``aim_samples``: the sample count :data:`REACH_AIM_S` is for."""
    walls, cpus, analysis_s = [], [], []
    with tempfile.TemporaryDirectory(prefix="bench-reach-") as tmp:
        for f in analyses.glob("reach.*"):
            if f.suffix in (".json", ".md", ".png") and not f.name.endswith(".timing.json"):
                shutil.copy2(f, Path(tmp) / f.name)
        _name_the_project(Path(tmp) / "reach.json", root)
        cmd = [sys.executable, "-m", "payload", "report", "reach", "--samples", str(samples)]
        cmd += ["--json", "--out", tmp, "--project", str(root)]
        for _ in range(runs):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t = time.perf_counter()
            done = subprocess.run(cmd, cwd=root, capture_output=True, text=True, check=False)
            wall = time.perf_counter() - t
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            try:  # exit 1 with a report: a failing verdict, still timed
                seconds = json.loads(done.stdout)["seconds"]
            except (ValueError, KeyError, TypeError):
                last = (done.stderr.strip().splitlines() or ["no output"])[-1]
                raise ReachError(
                    f"bench reach: the timed report exited {done.returncode}: {last}"
                ) from None
            walls.append(wall)
            cpus.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
            analysis_s.append(seconds)
    return {
        "samples": samples,
        "report_wall_s": walls,
        "report_wall_median_s": statistics.median(walls),
        "report_cpu_s": cpus,
        "report_analysis_s": analysis_s,
        "aim_s": REACH_AIM_S,
        # every run under the aim (None: the aim is for another sample count)
        "within_aim": max(walls) < REACH_AIM_S if samples == aim_samples else None,
        "aim_samples": aim_samples,
    }


def run_reach_bench(
    geom: PayloadGeometry,
    vehicle: Vehicle,
    root: Path,
    analyses: Path,
    samples: int,
    check_samples: int,
    runs: int,
    seed: int,
    aim_samples: int,
) -> dict[str, Any]:
    """Both parts; the load average before and after (figures on a busy machine are
    indicative only)."""
    load_before = os.getloadavg()[0]
    out = compare_checks(geom, vehicle, check_samples, seed)
    out.update(time_report(root, analyses, samples, runs, aim_samples))
    out["load"] = [round(load_before, 2), round(os.getloadavg()[0], 2)]
    return out


__all__ = ["REACH_AIM_S", "compare_checks", "run_reach_bench", "time_report"]
