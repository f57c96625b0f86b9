"""The base safety filter against random constant requests from safe starts.

Each run places the loaded stack (the CTB held in the scripted pinch) at a random point of
a random keep-in box of the station, moving along a random direction at up to 0.06 m/s,
and then asks for 0.2 m/s along that direction, with no turn or a full-rate turn
(+-0.1 rad/s), for 15 s. A start counts only if it lies in the filter's safe set: no
barrier row binds at the present velocity, and every vehicle, payload and CTB geom is at
least 60 mm from the station. The station is measured as a trial measures it
(:class:`payload.sim.station.StationMonitor`: MuJoCo's contacts and ``mj_geomDistance``),
independently of the filter's own sampled boxes. Writes a Markdown report.

Usage::

    python analyses/filter_sweep.py --runs 200 --seed 11 12 13 14 \
        --out analyses/safety-filter/sweep.md
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from payload.schema import CONTROL_DT, VehicleTwist
from payload.sim.stack import hold_ctb, place_stack
from payload.sim.station import StationMonitor
from payload.sim.world import build_world
from payload.sim.zones import station_zones
from payload.teleop.base_filter import MARGIN_TOLERANCE, BaseSafetyFilter, SafetyConfig
from payload.teleop.channels import BaseConfig

SECONDS = 15.0
"""Length of each run [s]."""
BASE = BaseConfig()
"""The base channel's bounds: the request is its full speed, the turn its full rate."""
START_CLEARANCE = 0.06
"""Least clearance of a start [m]."""


def fly(world, held, pos, v0, want, yaw) -> tuple[float, int] | None:
    """One run: (least clearance [m], control steps in contact), or None when the start
    is not in the filter's safe set."""
    sim = place_stack(world, held, pos, v0)
    c = sim.controller
    filt = BaseSafetyFilter(world, BASE, c.accel_max, float(c.jerk[0]))
    monitor = StationMonitor(world)
    d = sim.data
    rot = d.xmat[world.astrobee].reshape(3, 3)
    rows = filt._constraints(d, rot, d.xpos[world.astrobee], np.r_[v0, 0.0])
    if rows[2] < 0.0 or monitor.read(d).clearance < START_CLEARANCE:
        return None
    sim.twist_filter = filt
    least, touching = np.inf, 0
    for _ in range(round(SECONDS / CONTROL_DT)):
        rot = d.xmat[world.astrobee].reshape(3, 3)
        sim.command_twist(VehicleTwist(rot.T @ want, rot.T @ np.array([0.0, 0.0, yaw]), 0.0))
        sim.step()
        reading = monitor.read(d)
        least = min(least, reading.clearance)
        touching += bool(reading.contact)
    return least, touching


Row = tuple[int, str, np.ndarray, np.ndarray, float, float, float, int]
"""One run: seed, keep-in box, start, direction, start speed, yaw rate, least clearance,
steps in contact."""


def sweep(seed: int, runs: int) -> list[Row]:
    """``runs`` runs from safe starts drawn with ``seed``."""
    world = build_world()
    held = hold_ctb(world)
    zones = station_zones(world.layout)
    rng = np.random.default_rng(seed)
    rows: list[Row] = []
    while len(rows) < runs:
        box = int(rng.integers(len(zones.keepin)))
        lo, hi = (np.asarray(v, float) for v in zones.keepin[box])
        pos = lo + rng.uniform(0.25, 0.75, 3) * (hi - lo)
        pos += rng.uniform(-0.4, 0.4, 3) * np.minimum(hi - lo, 1.0)
        way = rng.normal(size=3)
        way /= np.linalg.norm(way)
        speed = rng.uniform(0.0, 0.06)
        yaw = float(rng.choice([0.0, BASE.max_yaw_rate, -BASE.max_yaw_rate]))
        run = fly(world, held, pos, speed * way, BASE.max_speed * way, yaw)
        if run is None:
            continue
        rows.append((seed, zones.names[box], pos, way, speed, yaw, *run))
        print(f"seed {seed} {len(rows)}/{runs}: least {run[0] * 1e3:.1f} mm", file=sys.stderr)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=200, help="runs per seed")
    parser.add_argument("--seed", type=int, nargs="+", default=[11, 12, 13, 14])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--workers", type=int, default=2, help="processes (one seed each)")
    args = parser.parse_args(argv)
    margin = SafetyConfig().margin
    spawn = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=args.workers, mp_context=spawn) as pool:
        parts = list(pool.map(sweep, args.seed, [args.runs] * len(args.seed)))
    rows = [row for part in parts for row in part]

    def line(label: str, part: list) -> str:
        low = np.array([r[6] for r in part])
        return (
            f"| {label} | {len(part)} | {sum(r[7] > 0 for r in part)} "
            f"| {int((low < margin - MARGIN_TOLERANCE).sum())} | {int((low < margin).sum())} "
            f"| {low.min() * 1e3:.1f} mm |"
        )

    least = np.array([r[6] for r in rows])
    lines = [
        "# The base safety filter from safe starts (analyses/filter_sweep.py)",
        "",
        f"{args.runs} runs per seed, each {SECONDS:.0f} s of a constant {BASE.max_speed:g} m/s "
        "request "
        "with the CTB held, the filter's default settings; the clearance is MuJoCo's, not "
        f"the filter's. Margin {margin * 1e3:.0f} mm, tolerance {MARGIN_TOLERANCE * 1e3:.0f} mm.",
        "",
        "| seed | runs | in contact | below margin - tolerance | below margin | least clearance |",
        "| --- | --- | --- | --- | --- | --- |",
        *(line(str(seed), [r for r in rows if r[0] == seed]) for seed in args.seed),
        line("all", rows),
        "",
        "The five closest runs:",
        "",
        "| seed | box | start [m] | direction | start speed [m/s] | yaw [rad/s] | least [mm] |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for i in np.argsort(least)[:5]:
        seed, name, pos, way, speed, yaw, low, _ = rows[i]
        lines.append(
            f"| {seed} | {name} | {np.round(pos, 3).tolist()} | {np.round(way, 2).tolist()} "
            f"| {speed:.3f} | {yaw:+.1f} | {low * 1e3:.1f} |"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
