"""Astrobee's propulsion: two propulsion modules, 12 nozzles, and a force allocation.

The nozzles' geometry is :mod:`payload.sim.nozzles` (NASA's propulsion code); the
allocation, :meth:`Propulsion.allocate`, is :mod:`payload.sim.allocation` (both
re-exported here). This module holds the model, its thrust bounds and the polytope's
extents, by linear programme, kept in the cache.

Thrust bound per nozzle. The PMC aerodynamics give a nozzle's thrust proportional to
``Cd^2 * A`` (discharge coefficient squared times open area), and the fully open area is
proportional to the nozzle width, so the bound is ``s_g Cd^2 w`` with one scale per group
of nozzles sharing an axis line (x, y or z). The three scales are solved so that the
largest pure force along each body axis (zero torque, zero force across, the weaker of
the two directions) equals the flight mode's published per-axis maximum at its impeller
speed; that absorbs the impeller pressure, which this model does not simulate
(ASSUMPTION: each nozzle's bound is independent of how far the others are open).
"""

from __future__ import annotations

import functools
import json
from functools import cached_property
from pathlib import Path
from typing import ClassVar

import numpy as np

from payload.cache import cache_dir, dist_version
from payload.safeio import replace_file
from payload.sim.allocation import BVLS_TOL, Allocation, ForceAllocation, PropulsionError
from payload.sim.nozzles import (
    DISCHARGE_COEFFS,
    INCH,
    N_NOZZLES,
    NOZZLE_AXES,
    NOZZLE_POSITIONS_IN,
    NOZZLE_WIDTHS_IN,
)


class Propulsion(ForceAllocation):
    """The 12-nozzle model and its force allocation.

    Args:
        axis_force: Published per-axis force maxima x, y, z of the flight mode [N] (at its
            impeller speed); the thrust bounds are scaled to match them.
        centre: Astrobee's centre of mass in the body frame [m] (the nozzle positions are
            given about the body frame's origin).
    """

    def __init__(
        self, axis_force: tuple[float, float, float], centre: np.ndarray | None = None
    ) -> None:
        target = np.array(axis_force, dtype=float)
        if target.shape != (3,) or not np.all(np.isfinite(target)) or np.any(target <= 0):
            raise PropulsionError(f"Propulsion: axis forces must be 3 positive numbers: {target}")
        self.axis_force = target
        c = np.zeros(3) if centre is None else np.asarray(centre, dtype=float)
        self.positions = NOZZLE_POSITIONS_IN * INCH - c
        self.directions = -NOZZLE_AXES  # thrust on the robot
        self.matrix = np.vstack(
            [self.directions.T, np.cross(self.positions, self.directions).T]
        )  # (6, 12): wrench per newton of each nozzle
        self.group = np.argmax(np.abs(NOZZLE_AXES), axis=1)  # 0 x, 1 y, 2 z
        self.shape = DISCHARGE_COEFFS**2 * NOZZLE_WIDTHS_IN  # relative thrust bounds
        self.thrust_max = self._fit_bounds()
        # read-only: a propulsion model is shared (shared_propulsion), its tables cached
        # and copied by the compiled allocation when built, so nothing may change it
        for a in (target, self.positions, self.directions, self.matrix, self.group):
            a.setflags(write=False)
        self.shape.setflags(write=False)
        self.thrust_max.setflags(write=False)

    # -- bounds ------------------------------------------------------------------------
    def _fit_bounds(self) -> np.ndarray:
        scale = np.ones(3)
        for _ in range(50):
            self.thrust_max = scale[self.group] * self.shape
            got = self.pure_force_max()
            ratio = self.axis_force / got
            scale = scale * ratio
            if np.all(np.abs(ratio - 1.0) < 1e-10):
                break
        else:  # pragma: no cover - the fit converges in a few iterations
            raise PropulsionError(f"Propulsion: thrust bounds do not fit {self.axis_force}")
        return scale[self.group] * self.shape

    def max_along(self, direction: np.ndarray) -> float:
        """Largest ``lambda`` with the wrench ``lambda * direction`` (6,) reachable, by
        linear programming (independent of :attr:`facets`), or its answer for the same
        bounds and direction read back from the cache (:class:`_Extents`, the same bits)."""
        w = np.asarray(direction, dtype=float)
        known = _Extents.of(self.matrix)
        key = known.key(self.thrust_max, w)
        extent = known.get(key)
        if extent is not None:
            return extent
        most = np.zeros(N_NOZZLES + 1)
        most[-1] = -1.0
        res = self._lp(most, w, (0.0, None))
        if res.status != 0:  # pragma: no cover - bounded thrusts bound lambda
            raise PropulsionError(f"polytope extent along {direction}: {res.message}")
        extent = float(res.x[-1])
        known.put(key, extent)
        return extent

    def pure_force_max(self) -> np.ndarray:
        """Per body axis, the largest pure force (zero torque), the weaker direction [N]."""
        out = np.empty(3)
        for i in range(3):
            e = np.zeros(6)
            e[i] = 1.0
            out[i] = min(self.max_along(e), self.max_along(-e))
        return out

    def pure_torque_max(self) -> np.ndarray:
        """Per body axis, the largest pure torque (zero force), the weaker direction [N m]."""
        return self._pure_torque_max.copy()

    @cached_property
    def _pure_torque_max(self) -> np.ndarray:
        out = np.empty(3)
        for i in range(3):
            e = np.zeros(6)
            e[3 + i] = 1.0
            out[i] = min(self.max_along(e), self.max_along(-e))
        return out

    @cached_property
    def thrust_total(self) -> float:
        """Sum of the thrust bounds [N]."""
        return float(self.thrust_max.sum())

    # -- the linear programme (the extents; the allocation's last resort) --------------
    def _lp(self, cost: np.ndarray, wrench: np.ndarray, lam: tuple[float, float | None]):
        from scipy.optimize import linprog

        a_eq = np.hstack([self.matrix, -wrench.reshape(6, 1)])
        bounds = [(0.0, float(u)) for u in self.thrust_max] + [lam]
        return linprog(cost, A_eq=a_eq, b_eq=np.zeros(6), bounds=bounds, method="highs")


MAX_KEPT_EXTENTS = 4096
"""The most polytope extents kept in the cache per nozzle layout (a design asks for a few
dozen; a sweep over carried loads asks for six more per load)."""


class _Extents:
    """The answers of :meth:`Propulsion.max_along`'s linear programmes for one nozzle
    layout, kept in the cache (one file per layout, float hex): a process after the first
    solves none (nor imports ``scipy.optimize``). Named by the layout, this module's code
    and SciPy's version (its HiGHS solves them); each answer by the bounds and direction
    it was asked for."""

    _OPEN: ClassVar[dict[bytes, _Extents]] = {}

    def __init__(self, matrix: np.ndarray) -> None:
        import hashlib

        scipy_version = dist_version("scipy")
        name = hashlib.sha256(
            np.ascontiguousarray(matrix).tobytes()
            + Path(__file__).read_bytes()
            + scipy_version.encode()
        ).hexdigest()[:20]
        self.path = cache_dir() / f"propulsion_extents_{name}.json"
        try:
            self.known = {str(k): str(v) for k, v in json.loads(self.path.read_text()).items()}
        except (OSError, ValueError, TypeError, AttributeError):
            self.known = {}

    @classmethod
    def of(cls, matrix: np.ndarray) -> _Extents:
        """The process's answers for this layout, read from the cache the first time."""
        index = np.ascontiguousarray(matrix).tobytes() + str(cache_dir()).encode()
        if index not in cls._OPEN:
            cls._OPEN[index] = cls(matrix)
        return cls._OPEN[index]

    @staticmethod
    def key(bounds: np.ndarray, direction: np.ndarray) -> str:
        import hashlib

        data = np.ascontiguousarray(bounds, float).tobytes() + direction.tobytes()
        return hashlib.sha256(data).hexdigest()[:32]

    def get(self, key: str) -> float | None:
        try:
            return float.fromhex(self.known[key])
        except (KeyError, ValueError):
            return None

    def put(self, key: str, extent: float) -> None:
        if len(self.known) >= MAX_KEPT_EXTENTS:  # a long sweep of designs: start afresh
            self.known = {}
        self.known[key] = extent.hex()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            replace_file(self.path, json.dumps(self.known, indent=0, sort_keys=True))
        except OSError:  # a read-only cache: solved again by the next process
            pass


@functools.lru_cache(maxsize=8)
def shared_propulsion(axis_force: tuple[float, float, float]) -> Propulsion:
    """The process's one :class:`Propulsion` for these per-axis forces [N]: its thrust
    bounds (linear programmes) and allocation tables are worked out once per process,
    not once per trial (a Dask worker runs several). Nothing changes a Propulsion after
    its construction but its lazily filled tables, which depend on it alone."""
    return Propulsion(axis_force)


__all__ = [
    "BVLS_TOL",
    "DISCHARGE_COEFFS",
    "INCH",
    "MAX_KEPT_EXTENTS",
    "NOZZLE_AXES",
    "NOZZLE_POSITIONS_IN",
    "NOZZLE_WIDTHS_IN",
    "N_NOZZLES",
    "Allocation",
    "Propulsion",
    "PropulsionError",
    "shared_propulsion",
]
