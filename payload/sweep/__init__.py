"""Design sweeps: every combination of some design values, each point a design project
built, envelope-checked, reach-analysed (and optionally flown in trials) on Dask.

``payload sweep --set KEY=V1,V2 --set KEY=A:B:N --out DIR`` is the command line
(:mod:`payload.sweep.cli`); :func:`plan` and :func:`run_points` are the library.


Names load on first use (module ``__getattr__``), so importing the package (or
a command module inside it) costs no numerical library.
"""

from __future__ import annotations

from payload.lazy import lazy_exports

_LAZY: dict[str, str] = {
    "Axis": "payload.sweep.grid",
    "SweepError": "payload.sweep.grid",
    "edit_design": "payload.sweep.grid",
    "parse_set": "payload.sweep.grid",
    "POINT_FIELDS": "payload.sweep.point",
    "point_commands": "payload.sweep.point",
    "run_point": "payload.sweep.point",
    "sweep_json": "payload.sweep.report",
    "write_sweep": "payload.sweep.report",
    "DEFAULT_SAMPLES": "payload.sweep.run",
    "plan": "payload.sweep.run",
    "run_points": "payload.sweep.run",
}
"""Each public name and the module defining it."""

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
