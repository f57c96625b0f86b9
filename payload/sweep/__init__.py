"""Design sweeps: every combination of some design values, each point a design project
built, envelope-checked, reach-analysed (and optionally flown in trials) on Dask.

``payload sweep --set KEY=V1,V2 --set KEY=A:B:N --out DIR`` is the command line
(:mod:`payload.sweep.cli`); :func:`plan` and :func:`run_points` are the library.
"""

from payload.sweep.grid import Axis, SweepError, edit_design, grid, parse_set
from payload.sweep.point import POINT_FIELDS, point_commands, run_point
from payload.sweep.report import sweep_json, write_sweep
from payload.sweep.run import DEFAULT_SAMPLES, plan, run_points

__all__ = [
    "DEFAULT_SAMPLES",
    "POINT_FIELDS",
    "Axis",
    "SweepError",
    "edit_design",
    "grid",
    "parse_set",
    "plan",
    "point_commands",
    "run_point",
    "run_points",
    "sweep_json",
    "write_sweep",
]
