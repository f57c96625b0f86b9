"""Small dense least squares for the 50 Hz nozzle allocation, without per-call overhead.

:func:`lstsq` is ``np.linalg.lstsq`` for a 2-D matrix and a 1-D right-hand side, calling
numpy's own LAPACK kernel (``dgelsd``) directly with the arguments numpy gives it: the
same LAPACK call, so the same bits, without the wrapper's checks and copies (which cost
as much as the solve for a 6 x 12 matrix).

:func:`bvls` is SciPy's bounded-variable least squares (Stark and Parker's BVLS as
``scipy.optimize.lsq_linear(method="bvls")`` runs it, ``scipy/optimize/_lsq/bvls.py``)
made the same way: the same sequence of array operations on the same arrays, each free
set's least squares through :func:`lstsq`, but without the result object, the step norms
and the printing the solver does not use to decide anything. It therefore returns the
same bits as SciPy's (tests/test_propulsion.py compares them on random problems and on
the allocation's own facet problems).
"""

from __future__ import annotations

import numpy as np

try:  # numpy's LAPACK least-squares kernel (dgelsd), the one np.linalg.lstsq calls
    from numpy.linalg import _umath_linalg

    _GELSD = getattr(_umath_linalg, "lstsq", None)
except ImportError:  # pragma: no cover - another numpy: np.linalg.lstsq itself
    _GELSD = None

EPS = float(np.finfo(float).eps)
"""float64's machine epsilon: numpy's default ``lstsq`` cutoff is ``EPS * max(m, n)``."""


def lstsq(a: np.ndarray, b: np.ndarray, rcond: float | None = None) -> tuple[np.ndarray, int]:
    """``np.linalg.lstsq(a, b, rcond)`` for a real 2-D ``a`` and 1-D ``b``: the solution
    and the rank.

    Where numpy's kernel is unavailable or LAPACK fails, numpy's wrapper (which raises
    its usual error).

    Args:
        a: Matrix, shape (m, n), float64.
        b: Right-hand side, shape (m,), float64.
        rcond: Relative singular-value cutoff (None: numpy's default ``eps * max(m, n)``).

    Returns:
        (least-squares solution (n,), numerical rank of ``a``).
    """
    m, n = a.shape
    cutoff = EPS * max(m, n) if rcond is None else rcond
    if _GELSD is not None:
        try:
            with np.errstate(over="ignore", divide="ignore", under="ignore", invalid="raise"):
                x, _, rank, _ = _GELSD(a, b[:, None], cutoff, signature="ddd->ddid")
            return x[:, 0], int(rank)
        except (FloatingPointError, TypeError, ValueError):
            pass  # LAPACK did not converge, or another numpy's kernel: numpy's wrapper
    x, _, rank, _ = np.linalg.lstsq(a, b, rcond=cutoff)
    return x, int(rank)


def _kkt_violation(g: np.ndarray, on_bound: np.ndarray) -> float:
    """Largest violation of the KKT conditions (SciPy's ``compute_kkt_optimality``)."""
    g_kkt = g * on_bound
    free_set = on_bound == 0
    g_kkt[free_set] = np.abs(g[free_set])
    return np.max(g_kkt)


def bvls(
    A: np.ndarray,
    b: np.ndarray,
    x_lsq: np.ndarray,
    lb: np.ndarray,
    ub: np.ndarray,
    tol: float,
    max_iter: int | None = None,
) -> np.ndarray:
    """``scipy.optimize._lsq.bvls.bvls(A, b, x_lsq, lb, ub, tol, max_iter, 0).x``.

    Args:
        A: Matrix, shape (m, n).
        b: Right-hand side, shape (m,).
        x_lsq: The unbounded least-squares solution to start from, shape (n,).
        lb: Lower bounds, shape (n,).
        ub: Upper bounds, shape (n,).
        tol: Stopping tolerance (relative cost change and KKT violation).
        max_iter: Iterations of the main loop (None: ``n``).

    Returns:
        The bounded least-squares solution, shape (n,).
    """
    n = A.shape[1]
    x = x_lsq.copy()
    on_bound = np.zeros(n)
    mask = x <= lb
    x[mask] = lb[mask]
    on_bound[mask] = -1
    mask = x >= ub
    x[mask] = ub[mask]
    on_bound[mask] = 1
    free_set = on_bound == 0
    active_set = ~free_set
    (free_set,) = np.nonzero(free_set)
    r = A.dot(x) - b
    cost = 0.5 * np.dot(r, r)
    g = A.T.dot(r)
    iteration = 0
    # initialisation: free variables' least squares until it is feasible
    while free_set.size > 0:
        iteration += 1
        b_free = b - A.dot(x * active_set)
        z = lstsq(A[:, free_set], b_free)[0]
        lbv = z < lb[free_set]
        ubv = z > ub[free_set]
        v = lbv | ubv
        if np.any(lbv):
            ind = free_set[lbv]
            x[ind] = lb[ind]
            active_set[ind] = True
            on_bound[ind] = -1
        if np.any(ubv):
            ind = free_set[ubv]
            x[ind] = ub[ind]
            active_set[ind] = True
            on_bound[ind] = 1
        ind = free_set[~v]
        x[ind] = z[~v]
        r = A.dot(x) - b
        cost = 0.5 * np.dot(r, r)
        g = A.T.dot(r)
        if np.any(v):
            free_set = free_set[~v]
        else:
            break
    max_iter = (n if max_iter is None else max_iter) + iteration
    optimality = _kkt_violation(g, on_bound)
    for _ in range(iteration, max_iter):  # BVLS loop A
        if optimality < tol:
            break
        on_bound[np.argmax(g * on_bound)] = 0
        while True:  # BVLS loop B
            free_set = on_bound == 0
            active_set = ~free_set
            (free_set,) = np.nonzero(free_set)
            x_free = x[free_set]
            lb_free = lb[free_set]
            ub_free = ub[free_set]
            b_free = b - A.dot(x * active_set)
            z = lstsq(A[:, free_set], b_free)[0]
            (lbv,) = np.nonzero(z < lb_free)
            (ubv,) = np.nonzero(z > ub_free)
            v = np.hstack((lbv, ubv))
            if v.size > 0:
                alphas = np.hstack((lb_free[lbv] - x_free[lbv], ub_free[ubv] - x_free[ubv])) / (
                    z[v] - x_free[v]
                )
                i = np.argmin(alphas)
                i_free = v[i]
                alpha = alphas[i]
                x_free *= 1 - alpha
                x_free += alpha * z
                x[free_set] = x_free
                on_bound[free_set[i_free]] = -1 if i < lbv.size else 1
            else:
                x[free_set] = z
                break
        r = A.dot(x) - b
        cost_new = 0.5 * np.dot(r, r)
        stalled = cost - cost_new < tol * cost
        cost = cost_new
        g = A.T.dot(r)
        optimality = _kkt_violation(g, on_bound)
        if stalled:
            break
    return x


__all__ = ["EPS", "bvls", "lstsq"]
