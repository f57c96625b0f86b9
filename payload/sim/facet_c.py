"""The saturated allocation's facet solve as compiled C, with numpy's bits.

When a requested wrench lies outside what the nozzles can give, :meth:`Propulsion._on_facet
<payload.sim.propulsion.Propulsion._on_facet>` solves for the thrusts of the nozzles in
the binding facet's plane: a least squares, and when its answer leaves the bounds,
SciPy's bounded-variable least squares (BVLS, as :func:`payload.sim.lsq.bvls` runs it).
In numpy that is a few dozen calls on arrays of six to twelve numbers and two to ten
LAPACK solves, about 160 to 200 us for one control step in six of a trial. Here it is one
C call that does the same operations in the same order:

* every least squares is LAPACK's ``dgelsd`` of the OpenBLAS numpy loaded, called as
  numpy's ``lstsq`` calls it: the matrix copied column by column, the right-hand side in
  a column of ``max(m, n)`` rows, the workspace sizes from a query of ``dgelsd`` itself
  on every call, the cutoff numpy's default ``eps * max(m, n)`` or ``-1``;
* ``A.dot(x)`` and ``A.T.dot(r)`` are numpy's CBLAS ``dgemv`` with the layouts numpy
  hands it (a facet's columns, picked out of the nozzle matrix, lie in Fortran order:
  ``A`` column-major and its transpose row-major; C order the other way round),
  ``np.dot(r, r)`` its ``ddot``;
* ``argmax``/``argmin`` keep the first extreme value, or the first NaN, as numpy's do;
  the largest KKT violation is NaN when any is (numpy's ``max``); elementwise arithmetic
  and comparisons are single IEEE operations (no fused multiply-adds:
  :data:`payload.native.CFLAGS`).

:func:`compiled_facet_solve` checks the kernel against the numpy code on probe problems
(the allocation's own facets and random ones) when it is built, and returns None (the
numpy code runs) without a C compiler, without numpy's OpenBLAS and its ``dgelsd``, with
``PAYLOAD_NATIVE=0``, or on a single differing bit. A call the kernel cannot take (a
LAPACK failure, an empty or one-column problem, more columns than it holds) returns None
and the numpy code answers it, raising numpy's errors.
"""

from __future__ import annotations

import ctypes
import logging
from collections.abc import Callable, Iterable

import numpy as np

from payload import native
from payload.sim.lsq import EPS

log = logging.getLogger(__name__)

NUMPY_DGELSD = "scipy_dgelsd_64_"
"""LAPACK's ``dgelsd`` in the OpenBLAS numpy's wheels bundle (64-bit integers, Fortran
calling convention): what numpy's ``lstsq`` runs."""

SOURCE = r"""
#include <stdlib.h>

/* MAXM (the rows: a wrench's), MAXN (the most columns) and EPS (float64's machine
   epsilon, numpy's lstsq cutoff factor) are defined by the loader */

typedef void (*dgelsd_fn)(const int64_t *m, const int64_t *n, const int64_t *nrhs,
                          double *a, const int64_t *lda, double *b, const int64_t *ldb,
                          double *s, const double *rcond, int64_t *rank, double *work,
                          const int64_t *lwork, int64_t *iwork, int64_t *info);

typedef struct {
    dgelsd_fn gelsd; dgemv_fn gemv; ddot_fn dot;
    int fortran;  /* A column-major (numpy's F order), else row-major */
} blas;

/* A[i, j] of the (m, n) matrix as it lies */
#define AT(f, a, m, n, i, j) ((f)->fortran ? (a)[(j) * (m) + (i)] : (a)[(i) * (n) + (j)])

/* numpy's A.dot(x) into out: dgemv with the layout numpy hands it (lda n row-major, m
   column-major) */
static void matvec(const blas *f, const double *a, int64_t m, int64_t n, const double *x,
                   double *out)
{
    if (f->fortran) f->gemv(COL_MAJOR, NO_TRANS, m, n, 1.0, a, m, x, 1, 0.0, out, 1);
    else f->gemv(ROW_MAJOR, NO_TRANS, m, n, 1.0, a, n, x, 1, 0.0, out, 1);
}

/* numpy's lstsq(A[:, cols], rhs, rcond)[0] into z (ncols): 0, or -1 when LAPACK fails */
static int lstsq(const blas *f, const double *a, int64_t m, int64_t n,
                 const int64_t *cols, int64_t nc, const double *rhs, double rcond,
                 double *z)
{
    int64_t ldb = m > nc ? m : nc, lda = m > 1 ? m : 1, one = 1, rank = 0, info = 0;
    int64_t lwork = -1, iwq = 0;
    double A[MAXM * MAXN], B[MAXN > MAXM ? MAXN : MAXM], S[MAXM], wq = 0.0;
    if (ldb < 1) ldb = 1;
    f->gelsd(&m, &nc, &one, A, &lda, B, &ldb, S, &rcond, &rank, &wq, &lwork, &iwq, &info);
    if (info != 0) return -1;
    lwork = (int64_t)wq;
    double *work = malloc(sizeof(double) * (size_t)(lwork > 0 ? lwork : 1));
    int64_t *iwork = malloc(sizeof(int64_t) * (size_t)(iwq > 0 ? iwq : 1));
    if (!work || !iwork) { free(work); free(iwork); return -1; }
    for (int64_t j = 0; j < nc; j++)          /* column-major copy of A[:, cols] */
        for (int64_t i = 0; i < m; i++)
            A[j * m + i] = AT(f, a, m, n, i, cols[j]);
    for (int64_t i = 0; i < m; i++) B[i] = rhs[i];
    f->gelsd(&m, &nc, &one, A, &lda, B, &ldb, S, &rcond, &rank, work, &lwork, iwork, &info);
    free(work); free(iwork);
    if (info != 0) return -1;
    for (int64_t j = 0; j < nc; j++) z[j] = B[j];
    return 0;
}

/* numpy's A.dot(x) - b into r */
static void residual(const blas *f, const double *a, int64_t m, int64_t n,
                     const double *x, const double *b, double *r)
{
    double ax[MAXM];
    matvec(f, a, m, n, x, ax);
    for (int64_t i = 0; i < m; i++) r[i] = ax[i] - b[i];
}

/* numpy's A.T.dot(r): the transpose (n, m) lies the other way round (row-major with lda
   m for a column-major A, column-major with lda n for a row-major one) */
static void gradient(const blas *f, const double *a, int64_t m, int64_t n,
                     const double *r, double *g)
{
    if (f->fortran) f->gemv(ROW_MAJOR, NO_TRANS, n, m, 1.0, a, m, r, 1, 0.0, g, 1);
    else f->gemv(COL_MAJOR, NO_TRANS, n, m, 1.0, a, n, r, 1, 0.0, g, 1);
}

/* numpy's argmax/argmin: the first extreme, or the first NaN */
static int64_t arg_extreme(const double *v, int64_t n, int largest)
{
    int64_t best = 0;
    if (isnan(v[0])) return 0;
    for (int64_t i = 1; i < n; i++) {
        if (isnan(v[i])) return i;
        if (largest ? v[i] > v[best] : v[i] < v[best]) best = i;
    }
    return best;
}

/* SciPy's compute_kkt_optimality: max of g * on_bound, |g| where free (NaN if any) */
static double kkt(const double *g, const double *on_bound, int64_t n)
{
    double best = 0.0;
    for (int64_t i = 0; i < n; i++) {
        double v = on_bound[i] == 0.0 ? fabs(g[i]) : g[i] * on_bound[i];
        if (isnan(v)) return v;
        if (i == 0 || v > best) best = v;
    }
    return best;
}

/* payload.sim.lsq.bvls(A, b, x_lsq, 0, ub, tol) into x */
static int bvls(const blas *f, const double *a, int64_t m, int64_t n, const double *b,
                const double *x_lsq, const double *ub, double tol, double *x)
{
    const double eps = EPS;
    double on_bound[MAXN], r[MAXM], g[MAXN], xa[MAXN], bf[MAXM], z[MAXN], ax[MAXM];
    double xf[MAXN], alphas[2 * MAXN];
    int64_t fs[MAXN], nfs = 0, v[2 * MAXN];
    char active[MAXN], viol[MAXN];
    for (int64_t i = 0; i < n; i++) {
        x[i] = x_lsq[i]; on_bound[i] = 0.0;
        if (x[i] <= 0.0) { x[i] = 0.0; on_bound[i] = -1.0; }
        if (x[i] >= ub[i]) { x[i] = ub[i]; on_bound[i] = 1.0; }
    }
    for (int64_t i = 0; i < n; i++) {
        active[i] = on_bound[i] != 0.0;
        if (!active[i]) fs[nfs++] = i;
    }
    residual(f, a, m, n, x, b, r);
    double cost = 0.5 * f->dot(m, r, 1, r, 1);
    gradient(f, a, m, n, r, g);
    int64_t iteration = 0;
    while (nfs > 0) {  /* initialisation: the free variables' least squares until feasible */
        iteration++;
        for (int64_t i = 0; i < n; i++) xa[i] = x[i] * (active[i] ? 1.0 : 0.0);
        matvec(f, a, m, n, xa, ax);
        for (int64_t i = 0; i < m; i++) bf[i] = b[i] - ax[i];
        if (lstsq(f, a, m, n, fs, nfs, bf, eps * (double)(m > nfs ? m : nfs), z)) return -1;
        int any = 0;
        for (int64_t j = 0; j < nfs; j++) {
            int64_t i = fs[j];
            int lo = z[j] < 0.0, hi = z[j] > ub[i];
            viol[j] = lo || hi;
            any |= viol[j];
            if (lo) { x[i] = 0.0; active[i] = 1; on_bound[i] = -1.0; }
        }
        for (int64_t j = 0; j < nfs; j++) {
            int64_t i = fs[j];
            if (z[j] > ub[i]) { x[i] = ub[i]; active[i] = 1; on_bound[i] = 1.0; }
        }
        for (int64_t j = 0; j < nfs; j++) if (!viol[j]) x[fs[j]] = z[j];
        residual(f, a, m, n, x, b, r);
        cost = 0.5 * f->dot(m, r, 1, r, 1);
        gradient(f, a, m, n, r, g);
        if (!any) break;
        int64_t k = 0;
        for (int64_t j = 0; j < nfs; j++) if (!viol[j]) fs[k++] = fs[j];
        nfs = k;
    }
    int64_t max_iter = n + iteration;
    double optimality = kkt(g, on_bound, n);
    for (int64_t it = iteration; it < max_iter; it++) {  /* BVLS loop A */
        if (optimality < tol) break;
        for (int64_t i = 0; i < n; i++) xa[i] = g[i] * on_bound[i];
        on_bound[arg_extreme(xa, n, 1)] = 0.0;
        for (;;) {  /* BVLS loop B */
            nfs = 0;
            for (int64_t i = 0; i < n; i++) {
                active[i] = on_bound[i] != 0.0;
                if (!active[i]) fs[nfs++] = i;
            }
            if (nfs == 0) break;  /* numpy's lstsq of no columns: no z, nothing violated */
            for (int64_t j = 0; j < nfs; j++) xf[j] = x[fs[j]];
            for (int64_t i = 0; i < n; i++) xa[i] = x[i] * (active[i] ? 1.0 : 0.0);
            matvec(f, a, m, n, xa, ax);
            for (int64_t i = 0; i < m; i++) bf[i] = b[i] - ax[i];
            if (lstsq(f, a, m, n, fs, nfs, bf, eps * (double)(m > nfs ? m : nfs), z))
                return -1;
            int64_t nv = 0, nl = 0;
            for (int64_t j = 0; j < nfs; j++) if (z[j] < 0.0) v[nv++] = j;
            nl = nv;
            for (int64_t j = 0; j < nfs; j++) if (z[j] > ub[fs[j]]) v[nv++] = j;
            if (nv > 0) {
                for (int64_t k = 0; k < nv; k++) {
                    int64_t j = v[k];
                    double bound = k < nl ? 0.0 : ub[fs[j]];
                    alphas[k] = (bound - xf[j]) / (z[j] - xf[j]);
                }
                int64_t i = arg_extreme(alphas, nv, 0);
                double alpha = alphas[i], keep = 1.0 - alpha;
                for (int64_t j = 0; j < nfs; j++) {
                    xf[j] *= keep;
                    xf[j] += alpha * z[j];
                    x[fs[j]] = xf[j];
                }
                on_bound[fs[v[i]]] = i < nl ? -1.0 : 1.0;
            } else {
                for (int64_t j = 0; j < nfs; j++) x[fs[j]] = z[j];
                break;
            }
        }
        residual(f, a, m, n, x, b, r);
        double cost_new = 0.5 * f->dot(m, r, 1, r, 1);
        int stalled = cost - cost_new < tol * cost;
        cost = cost_new;
        gradient(f, a, m, n, r, g);
        optimality = kkt(g, on_bound, n);
        if (stalled) break;
    }
    return 0;
}

/* Propulsion._on_facet's solve: lstsq(a, rest); if out of bounds (by tol), _bvls from it
   (same_rank) or from lstsq(a, rest, rcond=-1). 0, or -1: numpy answers. */
int payload_facet_solve(void *gelsd, void *gemv, void *dot, const double *a, int fortran,
                        int64_t m, int64_t n, const double *rest, const double *ub,
                        double facet_tol, double bvls_tol, int same_rank, double *sol)
{
    const double eps = EPS;
    blas f = {(dgelsd_fn)gelsd, (dgemv_fn)gemv, (ddot_fn)dot, fortran};
    int64_t cols[MAXN];
    double x[MAXN];
    if (m < 2 || m > MAXM || n < 2 || n > MAXN) return -1;
    for (int64_t j = 0; j < n; j++) cols[j] = j;
    if (lstsq(&f, a, m, n, cols, n, rest, eps * (double)(m > n ? m : n), sol)) return -1;
    int out = 0;
    for (int64_t j = 0; j < n; j++) out |= sol[j] < -facet_tol;
    for (int64_t j = 0; j < n; j++) out |= sol[j] > ub[j] + facet_tol;
    if (!out) return 0;
    if (!same_rank && lstsq(&f, a, m, n, cols, n, rest, -1.0, sol)) return -1;
    int inside = 1;
    for (int64_t j = 0; j < n; j++) inside &= (sol[j] >= 0.0) & (sol[j] <= ub[j]);
    if (inside) return 0;
    if (bvls(&f, a, m, n, rest, sol, ub, bvls_tol, x)) return -1;
    for (int64_t j = 0; j < n; j++) sol[j] = x[j];
    return 0;
}
"""


class CompiledFacetSolve:
    """The facet solve of :meth:`Propulsion._on_facet
    <payload.sim.propulsion.Propulsion._on_facet>` in C (one call; see the module).

    Args:
        lib: The kernel's library.
        functions: The addresses of numpy's ``dgelsd``, ``dgemv`` and ``ddot``.
        bvls_tol: BVLS's stopping tolerance.
    """

    def __init__(self, lib: ctypes.CDLL, functions: Iterable[int], bvls_tol: float) -> None:
        fn = lib.payload_facet_solve
        ptr, i64 = ctypes.c_void_p, ctypes.c_int64
        fn.restype = ctypes.c_int
        fn.argtypes = [ptr, ptr, ptr, ptr, ctypes.c_int, i64, i64, ptr, ptr, ctypes.c_double,
                       ctypes.c_double, ctypes.c_int, ptr]  # fmt: skip
        self._fn = fn
        self._functions = tuple(functions)
        self._bvls_tol = float(bvls_tol)

    def __call__(
        self, a: np.ndarray, rest: np.ndarray, ub: np.ndarray, tol: float, same_rank: bool
    ) -> np.ndarray | None:
        """The in-plane thrusts (a fresh array), or None: the numpy code is to answer."""
        m, n = a.shape
        layout = native.gemv_layout(a)
        if not (
            layout is not None
            and rest.dtype == ub.dtype == np.float64
            and rest.flags.c_contiguous
            and ub.flags.c_contiguous
            and rest.shape == (m,)
            and ub.shape == (n,)
        ):
            return None
        sol = np.empty(n)  # each call's own: no state is shared between calls
        failed = self._fn(
            *self._functions, a.ctypes.data, layout[0] == native.CBLAS_COL_MAJOR, m, n,
            rest.ctypes.data, ub.ctypes.data,
            tol, self._bvls_tol, bool(same_rank), sol.ctypes.data,
        )  # fmt: skip
        return None if failed else sol


Problem = tuple[np.ndarray, np.ndarray, np.ndarray, float, bool]
"""A facet solve's inputs: ``(a, rest, ub, tol, same_rank)``."""


RANDOM_PROBES = 300
"""Random problems of the facet solve's full self-check (:func:`compiled_facet_solve`)."""


def random_problems(n: int, rows: int, columns: int, seed: int = 0) -> list[Problem]:
    """Bounded least-squares problems like the facets' (``rows`` rows, 2 to ``columns`` columns,
    some of them parallel, right-hand sides in and beyond reach), the self-check's probes."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        cols = int(rng.integers(2, columns + 1))
        a = rng.normal(size=(rows, cols))
        if i % 4 == 1:  # repeated columns: rank-deficient, as coplanar nozzles are
            a[:, cols - 1] = a[:, 0]
        ub = rng.uniform(0.2, 1.0, size=cols)
        rest = a @ rng.uniform(-0.5, 1.5, size=cols) * rng.uniform(0.5, 1.5)
        if i % 2:  # Fortran order, as a facet's columns picked out of the nozzle matrix lie
            a = np.asfortranarray(a)
        out.append((a, rest, ub, 1e-7, bool(i % 3)))
    return out


@native.reported("facet solve")
def compiled_facet_solve(
    reference: Callable[..., np.ndarray],
    problems: Iterable[Problem],
    bvls_tol: float,
    columns: int,
    rows: int,
) -> CompiledFacetSolve | None:
    """The compiled facet solve of ``rows`` wrench components for up to ``columns``
    in-plane nozzles (more go to numpy),
    or None to run ``reference(a, rest, ub, tol, same_rank)`` (the numpy solve): no
    compiler, no numpy OpenBLAS or ``dgelsd``, ``PAYLOAD_NATIVE=0``, a failed build, or a
    self-check on ``problems`` (the allocation's own facets) and :data:`RANDOM_PROBES` of
    :func:`random_problems` that differs in a single bit (a problem the kernel leaves to
    numpy is not a difference, but at least some must be its own); the first tenth of
    each once a build of the same size passed, here or in an earlier process
    (:func:`payload.native.probes`)."""
    prelude = f"#define MAXM {rows}\n#define MAXN {columns}\n#define EPS {EPS!r}\n"
    loaded = native.load_blas_kernel(
        "facet", SOURCE, "the facet solve kernel", log, NUMPY_DGELSD, native.NUMPY_DGEMV,
        native.NUMPY_DDOT, prelude=prelude,
    )  # fmt: skip
    if loaded is None:
        return None
    kernel = CompiledFacetSolve(loaded[0], loaded[1:], bvls_tol)
    key = (rows, columns)

    def check(n: int) -> bool:
        own = list(problems)
        if n < RANDOM_PROBES:
            own = own[: max(1, len(own) // native.SHORT_SHARE)]
        answered = 0
        with np.errstate(all="ignore"):
            for problem in [*own, *random_problems(n, rows, columns)]:
                mine = kernel(*problem)
                if mine is None:
                    continue
                theirs = reference(*problem)
                if mine.tobytes() != np.asarray(theirs, dtype=np.float64).tobytes():
                    log.warning("facet solve: numpy (the compiled solve differs)")
                    return False
                answered += 1
        if not answered:
            log.warning("facet solve: numpy (the kernel answered none of its probes)")
            return False
        return True

    if not native.self_checked(loaded[0], key, RANDOM_PROBES, check):
        return None
    return kernel


__all__ = [
    "NUMPY_DGELSD",
    "RANDOM_PROBES",
    "SOURCE",
    "CompiledFacetSolve",
    "compiled_facet_solve",
    "random_problems",
]
