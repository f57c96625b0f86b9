"""The force allocation of Astrobee's 12-nozzle model (:class:`ForceAllocation`, a base
of :class:`~payload.sim.propulsion.Propulsion`) and its result (:class:`Allocation`).

Allocation (:meth:`ForceAllocation.allocate`): the reachable body wrenches form the zonotope
``{B t : 0 <= t <= t_max}``, not a box. The allocation delivers the largest ``lambda w``,
``lambda`` in [0, 1], that is reachable, with the smallest total thrust: inside the
polytope the wrench is met exactly, outside it is scaled down along its own direction
(saturation keeps the wrench's direction). For speed at 50 Hz the scale comes from the
polytope's facets (precomputed half-spaces); the thrusts from the binding facet when
saturated, else from the basic solutions of the 6-nozzle bases (precomputed inverses),
with a linear programme (HiGHS) as the last resort. The facet's least squares call
numpy's LAPACK kernel directly (the same bits as ``np.linalg.lstsq``, without its
per-call overhead) and its bounded least squares is SciPy's BVLS made the same way
(:mod:`payload.sim.lsq`: the same bits as SciPy's, at a fraction of its per-call cost).

The thrust bounds, the wrench matrix and the linear programme are the model's
(:mod:`payload.sim.propulsion`); the two per-step searches and the facet solve are also
compiled (:mod:`payload.sim.allocation_c`, :mod:`payload.sim.facet_c`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from payload.sim.errors import PropulsionError
from payload.sim.lsq import bvls
from payload.sim.lsq import lstsq as _lstsq
from payload.sim.nozzles import N_NOZZLES

BVLS_TOL = 1e-10
"""Stopping tolerance of the facet's bounded least squares (``lsq_linear``'s ``tol``)."""


def _bvls(
    a: np.ndarray, b: np.ndarray, ub: np.ndarray, start: np.ndarray | None = None
) -> np.ndarray:
    """``scipy.optimize.lsq_linear(a, b, bounds=(0, ub), method="bvls", tol=BVLS_TOL).x``
    without its argument checks: the unbounded least squares (``lstsq`` with
    ``rcond=-1``, as ``lsq_linear`` computes it) if it is inside the bounds, else SciPy's
    BVLS started from it (:func:`payload.sim.lsq.bvls`: the same operations, so the same
    result).

    Args:
        a: Matrix, shape (m, n).
        b: Right-hand side, shape (m,).
        ub: Upper bounds, shape (n,) (the lower bounds are 0).
        start: The unbounded least-squares solution ``lstsq(a, b, rcond=-1)`` when the
            caller already has it (None: computed here).

    Returns:
        The bounded least-squares solution, shape (n,).
    """
    lb = np.zeros(a.shape[1])
    x = _lstsq(a, b, -1.0)[0] if start is None else start
    if ((x >= lb) & (x <= ub)).all():
        return x
    return bvls(a, b, x, lb, ub, BVLS_TOL)


def _facet_solve(
    a: np.ndarray, rest: np.ndarray, ub: np.ndarray, tol: float, same_rank: bool
) -> np.ndarray:
    """The thrusts of a facet's in-plane nozzles (:meth:`Propulsion._on_facet`): the least
    squares ``lstsq(a, rest)``; if it leaves the bounds ``[0, ub]`` by more than ``tol``
    (more nozzles than the facet's dimension lie in its plane), bounded least squares
    (scipy's BVLS as ``lsq_linear(method="bvls")`` runs it), started from the solution just
    found when it is the one ``rcond=-1`` gives (``same_rank``)."""
    sol = _lstsq(a, rest)[0]
    if (sol < -tol).any() or (sol > ub + tol).any():
        sol = _bvls(a, rest, ub, sol if same_rank else None)
    return sol


def _allclose(a: np.ndarray, b: np.ndarray, rtol: float, atol: float) -> bool:
    """``np.allclose(a, b, rtol, atol)``: numpy's own test first (``|a - b| <= atol +
    rtol |b|`` with ``b`` finite, which implies it), numpy itself only when that fails."""
    if ((np.abs(a - b) <= atol + rtol * np.abs(b)) & np.isfinite(b)).all():
        return True
    return bool(np.allclose(a, b, rtol=rtol, atol=atol))


@dataclass(frozen=True)
class Allocation:
    """One allocation.

    Attributes:
        thrust: Nozzle thrusts, shape (12,) [N], each in [0, its bound].
        force: Body force the thrusts make, shape (3,) [N].
        torque: Body torque about Astrobee's centre of mass, shape (3,) [N m].
        scale: The fraction of the requested wrench delivered (1 inside the polytope).
    """

    thrust: np.ndarray
    force: np.ndarray
    torque: np.ndarray
    scale: float

    @classmethod
    def zero(cls) -> Allocation:
        """The allocation of a zero wrench: every nozzle closed."""
        z = np.zeros(3)
        return cls(np.zeros(N_NOZZLES), z, z.copy(), 1.0)


class _FacetParts(dict):
    """A dict filled on first access of each key by ``make(key)``."""

    def __init__(self, make: Callable[[int], Any]) -> None:
        super().__init__()
        self._make = make

    def __missing__(self, key: int) -> Any:
        value = self[key] = self._make(key)
        return value


class ForceAllocation:
    """The force allocation of :class:`~payload.sim.propulsion.Propulsion` (its base): the
    polytope's facets and extents, the thrusts of a wrench on a facet or inside the
    polytope, and :meth:`allocate`. It reads the model's wrench matrix ``matrix`` (6, 12)
    and thrust bounds ``thrust_max`` (12,), and calls its linear programme ``_lp`` as the
    last resort (:meth:`_solve`).
    """

    matrix: np.ndarray
    thrust_max: np.ndarray

    @cached_property
    def _bases(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every basic solution of the bounded LP, precomputed: each invertible 6-nozzle
        basis with each choice of its 6 other nozzles at zero or at their bound.

        Returns:
            (basis indices (K, 6), inverses (K, 6, 6), basis thrust offsets (K, 64, 6),
            thrust of the nozzles at their bound per pattern (K, 64)), with
            ``t_basis = inv @ w - offset``.
        """
        idx, inv, off, fixed = [], [], [], []
        patterns = np.array(list(itertools.product((0.0, 1.0), repeat=6)))  # (64, 6)
        for combo in itertools.combinations(range(N_NOZZLES), 6):
            sub = self.matrix[:, combo]
            if abs(np.linalg.det(sub)) <= 1e-12:
                continue
            rest = [k for k in range(N_NOZZLES) if k not in combo]
            at_bound = patterns * self.thrust_max[rest]  # (64, 6) thrust of the others
            sub_inv = np.linalg.inv(sub)
            idx.append(combo)
            inv.append(sub_inv)
            off.append((at_bound @ self.matrix[:, rest].T) @ sub_inv.T)
            fixed.append(at_bound)
        return np.array(idx), np.array(inv), np.array(off), np.array(fixed)

    @cached_property
    def facets(self) -> tuple[np.ndarray, np.ndarray]:
        """The polytope as half-spaces ``normals @ w <= offsets``: (normals (K, 6), offsets
        (K,)). Every facet of a zonotope is spanned by generators, so the normals of all
        5-nozzle subsets (both signs) with offsets ``sum_i t_max_i max(0, n . b_i)`` (the
        support function) describe it exactly."""
        normals = []
        for combo in itertools.combinations(range(N_NOZZLES), 5):
            u, sv, _ = np.linalg.svd(self.matrix[:, combo])
            if sv[-1] < 1e-9 * sv[0]:
                continue
            n = u[:, 5]
            normals += [n, -n]
        nrm = np.array(normals)
        offsets = np.maximum(nrm @ self.matrix, 0.0) @ self.thrust_max
        return nrm, offsets

    def extent(self, wrench: np.ndarray) -> float:
        """Largest ``lambda`` with ``lambda * wrench`` (6,) reachable (inf for zero)."""
        return self._extent(np.asarray(wrench, dtype=float))[0]

    @cached_property
    def _kernels(self) -> Any:
        """The two per-step searches compiled (:mod:`payload.sim.allocation_c`: numpy's
        bits, checked on probe wrenches when built), or None to run them in numpy."""
        from payload.sim.allocation_c import compiled_searches

        return compiled_searches(self)

    def _extent(self, wrench: np.ndarray) -> tuple[float, int]:
        """(largest scale, binding facet) for ``wrench`` (6,): ``(inf, -1)`` if none binds."""
        kernels = self._kernels
        if kernels is not None and wrench.shape == (6,):
            return kernels.extent(wrench)
        return self._extent_numpy(wrench)

    def _extent_numpy(self, wrench: np.ndarray) -> tuple[float, int]:
        normals, offsets = self.facets
        along = normals @ wrench
        pos = along > 1e-15
        if not pos.any():
            return math.inf, -1
        ratio = np.divide(offsets, along, out=np.full(len(offsets), np.inf), where=pos)
        k = int(ratio.argmin())
        return float(ratio[k]), k

    @cached_property
    def _facet_parts(self) -> _FacetParts:
        """Per facet ``k`` (``self._facet_parts[k]``, worked out on first use: a trial
        saturates on a few dozen of the facets): the thrusts of the nozzles pushing
        outward (at their bound, the others 0), the in-plane nozzles, their wrench
        columns, their bounds, and whether ``lstsq`` finds the same rank of those columns
        with numpy's default cutoff and with ``rcond=-1`` (then both give the same
        solution: the cutoff only decides which singular values count, and the rank
        depends on the matrix alone)."""
        return _FacetParts(self._facet_part)

    def _facet_part(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
        proj = self.facets[0][k] @ self.matrix
        eps = 1e-9 * float(np.abs(proj).max())
        out = np.where(proj > eps, self.thrust_max, 0.0)
        free = np.flatnonzero(np.abs(proj) <= eps)
        a_free = self.matrix[:, free]
        probe = np.ones(6)
        same = _lstsq(a_free, probe)[1] == _lstsq(a_free, probe, -1.0)[1]
        return out, free, a_free, self.thrust_max[free], same

    @cached_property
    def _facet_tol(self) -> float:
        return 1e-7 * float(self.thrust_max.max())

    def _on_facet(self, wrench: np.ndarray, k: int) -> np.ndarray | None:
        """Thrusts for a wrench on facet ``k``: nozzles pushing outward at their bound,
        inward ones closed, the ones in the facet's plane solved for the rest."""
        out, free, a_free, ub, same_rank = self._facet_parts[k]
        out = out.copy()
        rest = wrench - self.matrix @ out
        kernel = self._facet_kernel
        sol = None if kernel is None else kernel(a_free, rest, ub, self._facet_tol, same_rank)
        if sol is None:
            sol = _facet_solve(a_free, rest, ub, self._facet_tol, same_rank)
        out[free] = np.clip(sol, 0.0, ub)
        if not _allclose(self.matrix @ out, wrench, rtol=1e-7, atol=1e-10):
            return None
        return out

    @cached_property
    def _facet_kernel(self) -> Any:
        """:func:`_facet_solve` compiled (:mod:`payload.sim.facet_c`, checked when built
        on this propulsion's facets), or None."""
        from payload.sim.facet_c import compiled_facet_solve

        def problems() -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, float, bool]]:
            rng = np.random.default_rng(4)
            normals, offsets = self.facets
            for k in range(0, len(offsets), max(1, len(offsets) // 40)):
                out, _, a_free, ub, same_rank = self._facet_parts[k]
                for scale in (1.0, 1.2, 2.0):  # on the facet and beyond it, pulled sideways
                    pull = rng.normal(scale=0.3, size=normals.shape[1])
                    w = normals[k] * offsets[k] * scale + pull
                    yield a_free, w - self.matrix @ out, ub, self._facet_tol, same_rank

        return compiled_facet_solve(_facet_solve, problems(), BVLS_TOL, N_NOZZLES, len(self.matrix))

    @cached_property
    def _least_tol(self) -> float:
        return 1e-9 * float(self.thrust_max.max())

    def _least_thrust(self, wrench: np.ndarray) -> np.ndarray | None:
        """:meth:`_least_thrust_numpy`, compiled when it can be (:attr:`_kernels`)."""
        kernels = self._kernels
        if kernels is not None and wrench.shape == (6,):
            return kernels.least_thrust(wrench)
        return self._least_thrust_numpy(wrench)

    def _least_thrust_numpy(self, wrench: np.ndarray) -> np.ndarray | None:
        """The least-total-thrust solution of ``B t = w, 0 <= t <= t_max`` by enumerating
        the basic solutions (the LP optimum is one of them); None if none is feasible.

        First without the upper bounds (the other nozzles all closed): if that optimum
        respects the bounds it is the bounded optimum too; else the dual-feasible basic
        solutions."""
        idx, _, _, fixed = self._bases
        ub = self._basis_bounds
        tol = self._least_tol
        # (K, 6): the other nozzles closed; the inverses stacked as one (6K, 6) matrix
        # make one matrix-vector product instead of K (the same row dot products)
        t0 = (self._stacked_inverses @ wrench).reshape(-1, 6)
        # the feasible rows only: the first least sum among them, as argmin over all rows
        # with the others at inf finds it
        rows = np.flatnonzero((t0 >= -tol).all(axis=1))
        if rows.size:
            k = int(rows[t0[rows].sum(axis=1).argmin()])
            if (t0[k] <= ub[k] + tol).all():
                out = np.zeros(N_NOZZLES)
                out[idx[k]] = t0[k]
                return np.clip(out, 0.0, self.thrust_max)
        # the optimum is a basic solution whose basis is also dual feasible: with the dual
        # y = 1 B_k^-1, a nozzle outside the basis sits at its bound where its reduced
        # cost 1 - y a_j is negative and at zero where it is positive (either where it is
        # zero). Only those (basis, pattern) pairs can be optimal: :attr:`_candidates`.
        ck, cj, c_off, c_fixed = self._candidates
        tb = t0[ck] - c_off  # (M, 6)
        rows = np.flatnonzero(((tb >= -tol) & (tb <= self._candidate_ceiling)).all(axis=1))
        if not rows.size:
            return None
        m = int(rows[(tb[rows].sum(axis=1) + c_fixed[rows]).argmin()])
        k, j = int(ck[m]), int(cj[m])
        out = np.zeros(N_NOZZLES)
        out[self._basis_rest[k]] = fixed[k, j]
        out[idx[k]] = tb[m]
        return np.clip(out, 0.0, self.thrust_max)

    @cached_property
    def _stacked_inverses(self) -> np.ndarray:
        """The basis inverses of :attr:`_bases` one above the other: (6K, 6)."""
        return np.ascontiguousarray(self._bases[1].reshape(-1, 6))

    @cached_property
    def _basis_rest(self) -> np.ndarray:
        """Per basis, the 6 nozzles outside it, ascending: (K, 6)."""
        rest = []
        for basis in self._bases[0].tolist():
            inside = set(basis)
            rest.append([n for n in range(N_NOZZLES) if n not in inside])
        return np.array(rest)

    @cached_property
    def _candidate_bounds(self) -> np.ndarray:
        """The basis nozzles' thrust bounds per candidate of :attr:`_candidates`: (M, 6)."""
        return self._basis_bounds[self._candidates[0]]

    @cached_property
    def _candidate_ceiling(self) -> np.ndarray:
        """:attr:`_candidate_bounds` plus the least-thrust tolerance: (M, 6)."""
        return self._candidate_bounds + self._least_tol

    @cached_property
    def _candidates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The dual-feasible (basis, bound pattern) pairs of the least-thrust LP: (basis
        index (M,), pattern index (M,), basis thrust offsets (M, 6), thrust of the
        nozzles at their bound (M,)). A reduced cost within rounding of zero admits
        both choices, so degenerate bases keep every optimal pattern."""
        idx, inv, off, fixed = self._bases
        patterns = np.array(list(itertools.product((0.0, 1.0), repeat=6)))  # (64, 6)
        ck, cj = [], []
        for k in range(len(idx)):
            y = inv[k].sum(axis=0)  # 1^T B_k^-1
            rest = self._basis_rest[k]
            reduced = 1.0 - y @ self.matrix[:, rest]  # (6,)
            tie = np.abs(reduced) <= 1e-9
            want = (reduced < 0).astype(float)
            fits = np.all((patterns == want) | tie, axis=1)
            for j in np.flatnonzero(fits):
                ck.append(k)
                cj.append(int(j))
        ck_a, cj_a = np.array(ck), np.array(cj)
        return ck_a, cj_a, off[ck_a, cj_a], fixed[ck_a, cj_a].sum(axis=1)

    @cached_property
    def _basis_bounds(self) -> np.ndarray:
        return self.thrust_max[self._bases[0]]

    def _solve(self, wrench: np.ndarray) -> np.ndarray:
        """Least total thrust for a reachable ``wrench`` (basis enumeration, else LP)."""
        t = self._least_thrust(wrench)
        if t is not None:
            return t
        res = self._lp(np.concatenate([np.ones(N_NOZZLES), [0.0]]), wrench, (1.0, 1.0))
        if res.status != 0:
            raise PropulsionError(f"force allocation failed: {res.message}")
        return np.clip(res.x[:N_NOZZLES], 0.0, self.thrust_max)

    def allocate(self, force: np.ndarray, torque: np.ndarray) -> Allocation:
        """Nozzle thrusts for a body wrench about Astrobee's centre of mass.

        Inside the reachable polytope the wrench is met exactly (with the least total
        thrust); outside it the largest reachable multiple ``s w``, ``0 <= s < 1``, is
        delivered, so the wrench keeps its direction.

        Args:
            force: Body force, shape (3,) [N].
            torque: Body torque, shape (3,) [N m].
        """
        w = np.concatenate([np.asarray(force, float), np.asarray(torque, float)])
        if w.shape != (6,) or not np.isfinite(w).all():
            raise PropulsionError("allocate: force and torque must be 3 finite numbers each")
        if not w.any():
            return Allocation.zero()
        lam, k = self._extent(w)
        return self._finish(w, lam, k)

    def _finish(self, w: np.ndarray, lam: float, k: int) -> Allocation:
        """The allocation of a finite nonzero wrench ``w`` (6,) whose extent is ``lam``
        with binding facet ``k`` (:meth:`_extent`)."""
        thrust = None
        if lam < 1.0:  # outside: the binding facet gives the thrusts directly
            thrust = self._on_facet(lam * w, k)
        scale = min(1.0, lam) if thrust is not None else min(1.0, lam * (1.0 - 1e-9))
        if thrust is None:
            thrust = self._solve(scale * w)
        out = self.matrix @ thrust
        return Allocation(thrust, out[:3], out[3:], scale)

    def wrench(self, thrust: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Body force and torque of nozzle thrusts (12,) [N] (the PMC simulator's map)."""
        out = self.matrix @ np.asarray(thrust, dtype=float)
        return out[:3], out[3:]


__all__ = ["BVLS_TOL", "Allocation", "ForceAllocation", "PropulsionError"]
