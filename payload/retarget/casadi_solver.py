"""The production solver: eq. 3 as one compiled CasADi function per pair.

The whole pair solve is one CasADi expression graph: the forward kinematics rebuilt
from the Pinocchio model (:mod:`payload.retarget.symbolic`), the residuals of eq. 3,
their Jacobian by algorithmic differentiation, and a capped sequence of guarded
iterations of a projected Levenberg-Marquardt method on the soft-L1 cost
``sum(sqrt(1 + r^2) - 1)`` (the same value scipy's ``loss="soft_l1"`` minimises):

* gradient ``g = J^T (r / sqrt(1 + r^2))`` and the IRLS curvature
  ``H = J^T diag(1 / sqrt(1 + r^2)) J``, whose quadratic model majorises the soft-L1
  cost (iteratively reweighted least squares), so the steps stay safe far from the
  solution where the soft-L1 terms are nearly linear;
* a joint on a bound with the gradient pushing outward is held; the damped system
  ``(H + mu diag(H)) delta = -g`` is solved by Cholesky for the others; joints the step
  would push through a bound stop on it and the rest are solved again with that
  displacement fixed; no joint moves more than 10 % of its range per iteration; the
  step is projected onto the box, so no iterate ever leaves the bounds;
* a step is kept only if it lowers the cost; ``mu`` follows the gain ratio (Nielsen's
  rule) and grows fourfold on a rejection; with self-collision modelled the iterates may
  cross the margin (the penalty residual pushes them out) and each start returns the best
  collision-free point it met, so no answer is inside the margin; the collision terms are
  evaluated in groups, each only while a carried bound cannot prove it beyond the
  penalty band (:mod:`payload.retarget.collision_eval`);
* iterations are nested ``casadi.Function.conditional`` calls: each returns at once
  when the projected gradient (``config.gtol``) or the relative decrease
  (``config.ftol``) says converged, and there are at most ``config.max_iterations`` of
  them: a hard cap.

The graph is generated as C, compiled with the system C compiler into a shared
library cached under :func:`cache_dir` by the hash of its code, and called directly
through ``ctypes`` on preallocated buffers: one call per pair solve, a few
microseconds of Python around it (a ``casadi.Function`` call from Python alone costs
about 20 us). Without a compiler the same graph runs in CasADi's virtual machine, except
that with self-collision modelled the compiled solver's collision part is a C loop
(:mod:`payload.retarget.collision_c`) and the virtual machine's the equivalent
conditional CasADi form.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from payload.cache import cache_dir  # noqa: F401  (old import path)
from payload.retarget import compiled as _compiled_mod
from payload.retarget.collision_c import NativeCollision
from payload.retarget.collision_cache import load_solver, solver_key, store_solver
from payload.retarget.collision_eval import CollisionGroups
from payload.retarget.compiled import (  # noqa: F401  (old import paths)
    _CFLAGS,
    _compiled_or_none,
    _CompiledSolve,
    _prune,
    _slug,
)
from payload.retarget.errors import RetargetError
from payload.retarget.features import N_FEATURES, PairFeatures, PairKinematics
from payload.retarget.hand import HandDescription
from payload.retarget.lm_c import driver_source
from payload.retarget.lm_graph import (  # noqa: F401  (old import paths)
    _better,
    _cholesky_solve,
    _layout,
    _step_functions,
    build_solve_function,
    safe_posture,
    solve_parts,
)
from payload.retarget.objective import RetargetConfig
from payload.retarget.solver import Retargeter, SolveInfo

BACKENDS = ("auto", "compiled", "vm")
"""``compiled``: generated C through ctypes; ``vm``: CasADi's virtual machine; ``auto``:
compiled when a C compiler works, else the virtual machine."""


class PairRetargeter(Retargeter):
    """The production pair retargeter: eq. 3 in one compiled CasADi call.

    Args:
        hand: Hand description (``None``: ours).
        pair: Pair name (``L`` or ``R`` for ours); ``None``: the pair of ``kinematics``,
            else the hand's first pair.
        config: Eq. 3 settings (``None``: the paper's constants).
        kinematics: An existing :class:`PairKinematics` to share.
        backend: ``auto``, ``compiled`` or ``vm`` (see :data:`BACKENDS`).

    Attributes:
        backend: The backend in use (``compiled`` or ``vm``).
        function: The CasADi function of one pair solve.
        library: Path of the compiled shared library, or ``None`` in the virtual machine.
        backend_reason: Why ``auto`` fell back to the virtual machine (one line, naming
            the compiler log file when compiling failed), else ``None``.

    ``solve(targets, q_prev=None, q_ref=None) -> (q, info)``: see
    :meth:`~payload.retarget.solver.Retargeter.solve`. An instance owns its solver's
    buffers: use one per thread.
    """

    def __init__(
        self,
        hand: HandDescription | None = None,
        pair: str | None = None,
        config: RetargetConfig | None = None,
        kinematics: PairKinematics | None = None,
        backend: str = "auto",
    ) -> None:
        if backend not in BACKENDS:
            raise RetargetError(f"backend: expected one of {BACKENDS}, got {backend!r}")
        super().__init__(hand, pair, config, kinematics)
        name = f"payload_retarget_{_slug(self.kinematics.hand.name)}_{_slug(self.pair)}"
        self.library: Path | None = None
        self.backend_reason: str | None = None
        self._compiled: _CompiledSolve | None = None
        compiler = _compiled_mod._compiler() if backend != "vm" else None
        if backend == "compiled" and compiler is None:
            raise RetargetError("backend 'compiled' needs a C compiler (set CC or install gcc)")
        # With a compiler, the collision part is a C loop over the groups linked into the
        # solver (payload.retarget.collision_c); the virtual machine runs the conditional
        # CasADi form of the same computation. The loop is built when first needed (the
        # property): a solver found in the cache has it already.
        self._native: NativeCollision | None = None
        self._native_compiler = compiler if self.collisions else None
        self._name = name
        self._function: ca.Function | None = None  # built on first use (the property)
        if compiler is not None:
            key = self._solver_key(compiler)
            self._compiled = self._cached_solver(key)
        if compiler is not None and self._compiled is None:
            # the graph (and the collision loop) outside the try, as a missing compiler
            # leaves them: an error building them is raised as it is
            parts = self._parts()
            self._function = build_solve_function(self.kinematics, self.config, name, parts=parts)
            try:
                native = self.native
                extra = {f"{native.name}.c": native.source} if native is not None else None
                self._compiled = _CompiledSolve(
                    self._function, compiler, extra, driver_source(parts, name)
                )
            except (RetargetError, OSError) as exc:
                if self.native is not None:  # the virtual machine: the conditional form
                    self.native = None
                    self._function = None
                reason = _one_line(exc)
                if backend == "compiled":
                    if isinstance(exc, RetargetError):
                        raise
                    raise RetargetError(f"loading the retargeting solver failed: {reason}") from exc
                self.backend_reason = reason
                warnings.warn(
                    f"retargeting solver not compiled ({reason}); using CasADi's virtual machine",
                    RuntimeWarning,
                    stacklevel=2,
                )
                self._compiled = None
            else:
                self._store_solver(key, compiler)
        if self._compiled is not None:
            self.library = self._compiled.path
        elif compiler is None and backend == "auto":
            self.backend_reason = "no C compiler found (set CC or install gcc)"
        self.backend: str = "compiled" if self._compiled is not None else "vm"
        c = self._compiled  # carried bounds, one per group
        self._groups = c.inputs[4].size if c is not None else int(self.function.nnz_in(4))
        self._forget_bounds()

    @property
    def native(self) -> NativeCollision | None:
        """The collision part of an evaluation as a C loop
        (:class:`~payload.retarget.collision_c.NativeCollision`), compiled into the solver;
        None without self-collision, without a C compiler, or when it could not be made
        (said in a warning: the conditional CasADi form is used). Built on first use: a
        solver the cache names was built with it."""
        compiler = self._native_compiler
        if compiler is not None:
            self._native_compiler = None
            try:
                self._native = NativeCollision(
                    CollisionGroups(self.kinematics),
                    self.config,
                    f"{self._name}_collision",
                    compiler,
                )
            except (RetargetError, OSError, RuntimeError) as exc:
                warnings.warn(
                    f"collision loop not compiled ({_one_line(exc)}); using the conditional "
                    "CasADi form",
                    RuntimeWarning,
                    stacklevel=2,
                )
        return self._native

    @native.setter
    def native(self, value: NativeCollision | None) -> None:
        self._native_compiler = None
        self._native = value

    @property
    def function(self) -> ca.Function:
        """The CasADi function of one pair solve (:func:`~payload.retarget.lm_graph.
        build_solve_function`; with the collision loop in C when :attr:`native`), built
        on first use: a compiled solver found in the cache needs none."""
        if self._function is None:
            self._function = build_solve_function(
                self.kinematics, self.config, self._name, parts=self._parts()
            )
        return self._function

    def _parts(self) -> Any:
        """The solve's pieces (:func:`~payload.retarget.lm_graph.solve_parts`), named for
        this solver's library."""
        penalty = self.native.penalty_function() if self.native is not None else None
        return solve_parts(self.kinematics, self.config, penalty, prefix=f"{self._name}_")

    def _solver_key(self, compiler: str) -> str | None:
        """The disk cache's key of this pair's compiled solver
        (:func:`~payload.retarget.collision_cache.solver_key`): the pair's model, the
        compiler, its flags, the settings and the symbol (the collision loop's C follows
        from the model, its geometry's files and the workbench's sources, all in the key)."""
        flags = " ".join(_compiled_mod._flags(compiler))
        return solver_key(self.kinematics, compiler, flags, repr(self.config), self._name)

    def _cached_solver(self, key: str | None) -> _CompiledSolve | None:
        """The compiled solver the cache names under ``key``, loaded without building the
        CasADi graph, or None (none named; its library gone, foreign or of other sizes)."""
        stored = load_solver(key) if key is not None else None
        if stored is None:
            return None
        _, sizes_in, sizes_out = stored
        n, groups = self.n, sizes_in[-1] if sizes_in else -1
        info = len(SolveInfo._fields)  # the report output, a value per field
        if sizes_in != [n, N_FEATURES, n, n, groups] or sizes_out != [n, info, groups]:
            return None
        try:
            return _CompiledSolve.loaded(self._name, *stored)
        except (RetargetError, OSError, AttributeError):  # torn or foreign: built again
            return None

    def _store_solver(self, key: str | None, compiler: str) -> None:
        """Name the solver just compiled in the cache under ``key``: not when its collision
        geometry was not one the cache keeps (derived without the compiled distances, or
        from files that changed meanwhile), nor one compiled without its collision loop,
        nor when the key changed while it was built."""
        c = self._compiled
        if key is None or c is None or key != self._solver_key(compiler):
            return
        if self.collisions:
            col = self.kinematics.collision
            if self.native is None or col.key is None or not col.compiled_distances(col.terms):
                return
        store_solver(key, c.path, *c.sizes)

    def _forget_bounds(self) -> None:
        """No carried collision bounds: the groups' clearance bounds and the posture they
        hold at (the last answer), carried into the next solve
        (payload.retarget.collision_eval), are unknown (``-inf``) at the rest posture."""
        self._anchor_q = self.kinematics.rest.copy()
        self._anchor_b = np.full(self._groups, -np.inf)
        if self._compiled is not None:
            self._compiled.inputs[3][:] = self._anchor_q
            self._compiled.inputs[4][:] = self._anchor_b

    def reset(self, q: np.ndarray | None = None) -> None:
        """Set the held command (``None``: the rest posture), clipped to the limits, and
        forget the carried collision bounds: a reset solver answers as a new one does."""
        super().reset(q)
        self._forget_bounds()

    def solve(
        self,
        targets: PairFeatures | np.ndarray,
        q_prev: np.ndarray | None = None,
        q_ref: np.ndarray | None = None,
    ) -> tuple[np.ndarray, SolveInfo]:
        """Solve eq. 3 for the pair: one call into the compiled solver.

        Same contract as :meth:`Retargeter.solve
        <payload.retarget.solver.Retargeter.solve>`: a NaN or infinite input raises
        :class:`RetargetError` and leaves :attr:`command` unchanged. Well-formed numpy
        inputs take a fast path that writes them straight into the solver's buffers.
        """
        c = self._compiled
        n = self.n
        if (
            c is None
            or not (q_prev is None or (type(q_prev) is np.ndarray and q_prev.shape == (n,)))
            or not (q_ref is None or (type(q_ref) is np.ndarray and q_ref.shape == (n,)))
        ):
            return super().solve(targets, q_prev, q_ref)
        q_in, t_in, r_in = c.inputs[:3]
        if type(targets) is np.ndarray and targets.shape == (N_FEATURES,):
            t_in[:] = targets
        elif isinstance(targets, PairFeatures):
            try:
                t_in[:] = targets.as_vector()
            except (ValueError, TypeError):
                return super().solve(targets, q_prev, q_ref)
        else:
            return super().solve(targets, q_prev, q_ref)
        q_in[:] = self._command if q_prev is None else q_prev
        r_in[:] = self.kinematics.rest if q_ref is None else q_ref
        if not c.step():  # the finiteness check and the anchor update in C
            return super().solve(targets, q_prev, q_ref)  # raises, naming the value
        return self.finish_step()

    def step_entry(self) -> tuple[tuple[int, ...], list[np.ndarray]] | None:
        """For a caller that fills the solve's inputs in C and runs its step entry there
        (:mod:`payload.teleop.pair_c`): the entry and its arguments
        (:meth:`_CompiledSolve.step_entry`) and the solver's inputs (command, targets,
        posture reference, then the anchor the step updates), or None (no compiled step).
        Such a caller writes :attr:`held_command` into the command input, and after a
        step that returned 0 calls :meth:`finish_step`."""
        c = self._compiled
        entry = c.step_entry() if c is not None else None
        return None if entry is None else (entry, c.inputs)

    def checkpoint(self) -> Callable[[], None]:
        """A function that puts the held command and the compiled solver's inputs (the
        anchor among them) back as they are now: for a check that solves and must leave
        the retargeter as it found it (:mod:`payload.teleop.pair_c`'s self-check)."""
        held = self._command.copy()
        c = self._compiled
        inputs = [] if c is None else c.inputs
        saved = [a.copy() for a in inputs]

        def restore() -> None:
            self.hold(held)
            for a, b in zip(inputs, saved):
                a[:] = b

        return restore

    @property
    def held_command(self) -> np.ndarray:
        """The held command itself, the next solve's warm start (not a copy: read it,
        don't change it; :attr:`command` is a copy)."""
        return self._command

    @property
    def step_output(self) -> np.ndarray:
        """The array the compiled step writes its command into (what :meth:`finish_step`
        takes), for a caller that reads it in C after the step.

        Raises:
            ValueError: No compiled solver.
        """
        c = self._compiled
        if c is None:
            raise ValueError("no compiled solver")
        return c.outputs[0]

    def finish_step(self) -> tuple[np.ndarray, SolveInfo]:
        """The answer of the compiled step that just ran (:meth:`solve`'s): its command,
        now held, and its report."""
        c = self._compiled
        q = c.outputs[0].copy()
        self._command = q
        return q.copy(), _info(c.outputs[1], self.collisions)

    def _solve(
        self, targets: np.ndarray, q_prev: np.ndarray, q_ref: np.ndarray
    ) -> tuple[np.ndarray, SolveInfo]:
        c = self._compiled
        if c is not None:
            c.inputs[0][:] = q_prev
            c.inputs[1][:] = targets
            c.inputs[2][:] = q_ref
            c()
            q = c.outputs[0].copy()
            c.inputs[3][:] = q
            c.inputs[4][:] = c.outputs[2]
            info = c.outputs[1]
        else:
            out = self.function(q_prev, targets, q_ref, self._anchor_q, self._anchor_b)
            q = np.array(out[0], dtype=float).reshape(-1)
            info = np.array(out[1], dtype=float).reshape(-1)
            self._anchor_q = q.copy()
            self._anchor_b = np.array(out[2], dtype=float).reshape(-1)
        return q, _info(info, self.collisions)


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line, whatever the OS or the compiler says."""
    return " ".join(str(exc).split())


def _info(info: np.ndarray, collisions: bool) -> SolveInfo:
    cost, iterations, converged, evaluations, clearance = info.tolist()
    if not collisions:
        clearance = float("inf")  # no margin: none measured
    return SolveInfo(cost, int(iterations), converged > 0.5, int(evaluations), clearance)
