"""The compiled pair solve's control flow as a C loop.

:func:`payload.retarget.lm_graph.build_solve_function` expresses the starts and the
guarded Levenberg-Marquardt iterations as nested ``casadi.Function.conditional`` calls;
CasADi's generated code then copies the whole state (about 230 doubles with collision
groups) in and out of every level and start, and each level is its own piece of code. Here
the same sequence is a plain C loop (:func:`driver_source`): the residual evaluations, a
start's parameters and start points, an iteration's acceptance choices (``decide``) and
the outputs are the CasADi functions of :class:`payload.retarget.lm_graph.SolveParts`,
generated into the same file; a start's first state (``init``), its result (``finish``)
and an iteration's proposal (``propose``) are written here in C, with the graph's
operations in the graph's order (CasADi's ``if_else`` as ``(c ? a : 0) + (!c ? b : 0)``),
which keeps the code a cold solve has to fetch small. An iteration evaluates its candidate
into a buffer laid out as the state's head and copies only what it keeps; a converged or
capped start stops at a comparison. The answers are the graph's to the bit (a test
compares the two, with and without collision groups): a change to
``lm_graph._proposal``, ``_collapse``, ``_better`` or ``init`` must be made here too.

The loop has the calling convention of a CasADi-generated function (``arg``, ``res``,
``iw``, ``w``, ``mem``; ``<name>_work`` reports the work sizes), so
:class:`payload.retarget.compiled._CompiledSolve` loads it like the graph's code;
``<name>_step`` wraps it for the teleoperation loop (inputs checked finite, the command
and bounds carried into the next solve's anchor).
"""

from __future__ import annotations

from payload.retarget.budget import RESUME
from payload.retarget.compiled import c_ints, c_reals, code_generator, work_sizes
from payload.retarget.lm_graph import (
    _BOUND_EPS,
    _CURVATURE_FLOOR,
    _DAMPING_EPS,
    _MAX_STEP,
    _MU0,
    SolveParts,
)

_DRIVER = r"""
/* ---- the solve's control flow (payload.retarget.lm_c) ---- */
#define NQ {n}
#define NG {ng}
#define NP {npar}
#define NX {nx}
#define NS {nstarts}
#define I_COST {i_cost}
#define I_G {i_g}
#define I_H {i_h}
#define I_CLEAR {i_clear}
#define I_BOUNDS {i_bounds}
#define I_FREE {i_free}
#define I_MU {i_mu}
#define I_IT {i_it}
#define I_DONE {i_done}
#define I_EV {i_ev}
#define SUB_W {sub_w}
static const casadi_real CAP[NS] = {{{caps}}};
static const int LEVELS[NS] = {{{levels}}};
static const int RESUME[NS] = {{{resume}}}; /* continue from the best point met */
static const casadi_real INITIAL[NX] = {{{initial}}};

/* an evaluation's outputs (cost, g, H, clearance, bounds) where the state holds them */
static const int AT[5] = {{I_COST, I_G, I_H, I_CLEAR, I_BOUNDS}};

static const casadi_real LB[NQ] = {{{lower}}};
static const casadi_real UB[NQ] = {{{upper}}};
#define GTOL {gtol}
#define MU0 {mu0}
#define I_REC_COST {i_rec_cost}
#define I_REC_CLEAR {i_rec_clear}
#define I_REC_BOUNDS {i_rec_bounds}

static const casadi_real LB_EPS[NQ] = {{{lower_eps}}};
static const casadi_real UB_EPS[NQ] = {{{upper_eps}}};
static const casadi_real RANGE[NQ] = {{{span}}};
#define MAX_STEP {max_step}
#define CURVATURE_FLOOR {curvature_floor}
#define DAMPING_EPS {damping_eps}

/* a x = b for a symmetric positive definite a (column-major, lower triangle read) by
   Cholesky, the operations of payload.retarget.lm_graph._cholesky_solve in its order */
static void cholesky_solve(const casadi_real* a, const casadi_real* b, casadi_real* x) {{
  casadi_real low[NQ * NQ], y[NQ], s;
  int i, j, k;
  _Pragma("GCC unroll 8") for (j = 0; j < NQ; ++j) {{
    s = a[j + j * NQ];
    _Pragma("GCC unroll 8") for (k = 0; k < j; ++k) s = s - low[j * NQ + k] * low[j * NQ + k];
    low[j * NQ + j] = sqrt(s);
    _Pragma("GCC unroll 8") for (i = j + 1; i < NQ; ++i) {{
      s = a[i + j * NQ];
      _Pragma("GCC unroll 8") for (k = 0; k < j; ++k) s = s - low[i * NQ + k] * low[j * NQ + k];
      low[i * NQ + j] = s / low[j * NQ + j];
    }}
  }}
  _Pragma("GCC unroll 8") for (i = 0; i < NQ; ++i) {{
    s = b[i];
    _Pragma("GCC unroll 8") for (k = 0; k < i; ++k) s = s - low[i * NQ + k] * y[k];
    y[i] = s / low[i * NQ + i];
  }}
  _Pragma("GCC unroll 8") for (i = NQ - 1; i >= 0; --i) {{
    s = y[i];
    _Pragma("GCC unroll 8") for (k = i + 1; k < NQ; ++k) s = s - low[k * NQ + i] * x[k];
    x[i] = s / low[i * NQ + i];
  }}
}}

/* the damped system over the joints f marks free, the others (fixed) held: its lower
   triangle, h * f f^T + diag(fixed + f * damping) */
static void damped(const casadi_real* h, const casadi_real* f, const casadi_real* fixed,
                   const casadi_real* damping, casadi_real* a) {{
  int i, j;
  _Pragma("GCC unroll 8") for (j = 0; j < NQ; ++j) {{
    a[j + j * NQ] = h[j + j * NQ] * (f[j] * f[j]) + (fixed[j] + f[j] * damping[j]);
    _Pragma("GCC unroll 8") for (i = j + 1; i < NQ; ++i)
      a[i + j * NQ] = h[i + j * NQ] * (f[i] * f[j]);
  }}
}}

/* (h v)[i], the sum in CasADi's order */
static casadi_real row_times(const casadi_real* h, int i, const casadi_real* v) {{
  casadi_real s = h[i] * v[0];
  int j;
  _Pragma("GCC unroll 8") for (j = 1; j < NQ; ++j) s = s + h[i + j * NQ] * v[j];
  return s;
}}

/* propose: one iteration's candidate qc from state x and its predicted decrease, the
   operations of payload.retarget.lm_graph._proposal */
static void propose(const casadi_real* x, casadi_real* qc, casadi_real* pr) {{
  const casadi_real *q = x, *g = x + I_G, *h = x + I_H;
  casadi_real active[NQ], f[NQ], damping[NQ], a[NQ * NQ], b[NQ], d[NQ], e[NQ];
  casadi_real lo[NQ], hi[NQ], fixed[NQ], f2[NQ], dfix[NQ], step[NQ], hs[NQ], m = 0.0, s, t;
  int i;
  for (i = 0; i < NQ; ++i) {{
    active[i] = (q[i] <= LB_EPS[i] && 0.0 < g[i]) || (UB_EPS[i] <= q[i] && g[i] < 0.0);
    f[i] = 1.0 - active[i];
    damping[i] = x[I_MU] * fmax(h[i + i * NQ], CURVATURE_FLOOR) + DAMPING_EPS;
    b[i] = f[i] * g[i];
  }}
  damped(h, f, active, damping, a);
  cholesky_solve(a, b, d);
  for (i = 0; i < NQ; ++i) {{
    d[i] = -d[i];
    lo[i] = f[i] * (q[i] + d[i] < LB[i]);
    hi[i] = f[i] * (q[i] + d[i] > UB[i]);
    fixed[i] = fmax(active[i], lo[i] + hi[i]);
    f2[i] = 1.0 - fixed[i];
    dfix[i] = lo[i] * (LB[i] - q[i]) + hi[i] * (UB[i] - q[i]);
  }}
  for (i = 0; i < NQ; ++i) b[i] = -f2[i] * (g[i] + row_times(h, i, dfix));
  damped(h, f2, fixed, damping, a);
  cholesky_solve(a, b, e);
  for (i = 0; i < NQ; ++i) {{
    d[i] = dfix[i] + f2[i] * e[i];
    s = fabs(d[i]) / RANGE[i];
    m = i ? fmax(m, s) : s;
  }}
  t = fmax(1.0, m / MAX_STEP);
  for (i = 0; i < NQ; ++i) {{
    qc[i] = fmin(fmax(q[i] + d[i] / t, LB[i]), UB[i]);
    step[i] = qc[i] - q[i];
  }}
  for (i = 0; i < NQ; ++i) hs[i] = row_times(h, i, step);
  s = g[0] * step[0];
  for (i = 1; i < NQ; ++i) s = s + g[i] * step[i];
  t = step[0] * hs[0];
  for (i = 1; i < NQ; ++i) t = t + step[i] * hs[i];
  *pr = -(s + 0.5 * t);
}}

/* CasADi's SX if_else to the bit: (c ? a : 0) + (!c ? b : 0) (so -0 becomes +0) */
#define SEL(c, a, b) ((((c) != 0) ? (a) : 0.0) + (((c) != 0) ? 0.0 : (b)))

/* init: a start's first state x from its evaluation in head (the state's head laid out:
   q, cost, g, H, clearance, bounds) and the best state so far (its counts) */
static void start_state(casadi_real* x, const casadi_real* head, const casadi_real* best) {{
  int i;
  casadi_real c = 0.0 <= head[I_CLEAR], m = 0.0, pg;
  for (i = 0; i < I_FREE; ++i) x[i] = head[i];
  for (i = 0; i < NQ; ++i) x[I_FREE + i] = SEL(c, head[i], head[i]);
  x[I_REC_COST] = SEL(c, head[I_COST], INFINITY);
  x[I_REC_CLEAR] = SEL(c, head[I_CLEAR], -INFINITY);
  for (i = 0; i < NG; ++i) x[I_REC_BOUNDS + i] = SEL(c, head[I_BOUNDS + i], head[I_BOUNDS + i]);
  x[I_MU] = MU0;
  for (i = 0; i < NQ; ++i) {{ /* the projected gradient's largest magnitude */
    pg = fabs(head[i] - fmin(fmax(head[i] - head[I_G + i], LB[i]), UB[i]));
    m = i ? fmax(m, pg) : pg;
  }}
  x[I_DONE] = m <= GTOL;
  x[I_IT] = best[I_IT];
  x[I_EV] = best[I_EV] + 1.0;
}}

/* finish: a start's result st (its best collision-free point when it met one) into best
   when better (payload.retarget.lm_graph._collapse and _better), the counts always */
static void finish_start(casadi_real* best, const casadi_real* x, casadi_real* st) {{
  int i;
  casadi_real c = x[I_REC_COST] < INFINITY, f_new, f_old, better;
  for (i = 0; i < NQ; ++i) st[i] = SEL(c, x[I_FREE + i], x[i]);
  st[I_COST] = SEL(c, x[I_REC_COST], x[I_COST]);
  for (i = I_G; i < I_CLEAR; ++i) st[i] = SEL(c, x[i], x[i]);
  st[I_CLEAR] = SEL(c, x[I_REC_CLEAR], x[I_CLEAR]);
  for (i = 0; i < NG; ++i) st[I_BOUNDS + i] = SEL(c, x[I_REC_BOUNDS + i], x[I_BOUNDS + i]);
  for (i = I_FREE; i <= I_MU; ++i) st[i] = SEL(c, x[i], x[i]);
  st[I_DONE] = SEL(c, (x[I_DONE] != 0 && x[I_REC_COST] == x[I_COST]), x[I_DONE]);
  st[I_IT] = SEL(c, x[I_IT], x[I_IT]);
  st[I_EV] = SEL(c, x[I_EV], x[I_EV]);
  f_new = 0.0 <= st[I_CLEAR];
  f_old = 0.0 <= best[I_CLEAR];
  better = (f_new != 0 && (st[I_COST] < best[I_COST] || f_old == 0))
           || (f_old == 0 && f_new == 0 && best[I_CLEAR] < st[I_CLEAR]);
  for (i = 0; i < I_IT; ++i) best[i] = SEL(better, st[i], best[i]);
  best[I_IT] = st[I_IT];
  best[I_EV] = st[I_EV];
}}

/* w: best, two states, par, start points, the candidate (its q and evaluation, laid out
   as the state's head) and its predicted decrease, then the called functions' work */
#define W_SIZE (3 * NX + NP + NS * NQ + I_FREE + 1)

/* the evaluation at head[0..NQ) written into the rest of head */
static int evaluate_at(casadi_real* head, const casadi_real* p, const casadi_real* qa,
                       const casadi_real* ba, casadi_int* iw, casadi_real* ws) {{
  const casadi_real* a[{sz_arg}];
  casadi_real* r[{sz_res}];
  int i;
  a[0] = head; a[1] = p; a[2] = qa; a[3] = ba;
  for (i = 0; i < 5; ++i) r[i] = head + AT[i];
  return {name}_evaluate(a, r, iw, ws, 0);
}}

/* (q_prev, targets, q_ref, q_anchor, bounds) -> (q, info, bounds_out) */
CASADI_SYMBOL_EXPORT int {name}(const casadi_real** arg, casadi_real** res, casadi_int* iw,
                               casadi_real* w, int mem) {{
  casadi_real *best = w, *x = best + NX, *y = x + NX, *p = y + NX, *starts = p + NP;
  casadi_real *cand = starts + NS * NQ, *pr = cand + I_FREE, *ws = pr + 1, flag[4];
  const casadi_real* a[{sz_arg}];
  casadi_real* r[{sz_res}];
  int k, level, i, stop;
  (void)mem;
  a[0] = arg[0]; a[1] = arg[1]; a[2] = arg[2];
  r[0] = p; r[1] = starts;
  if ({name}_prep(a, r, iw, ws, 0)) return 1;
  for (i = 0; i < NX; ++i) best[i] = INITIAL[i];
  for (k = 0; k < NS; ++k) {{
    if (best[I_EV] >= CAP[k]) continue; /* no evaluation left under this start's cap */
    /* a RESUME start begins at the best point met so far */
    for (i = 0; i < NQ; ++i) cand[i] = RESUME[k] ? best[i] : starts[k * NQ + i];
    /* the first start carries the input anchor's bounds, the others the best state's */
    if (evaluate_at(cand, p, k ? best : arg[3], k ? best + I_BOUNDS : arg[4], iw, ws))
      return 1;
    start_state(x, cand, best);
    stop = x[I_DONE] != 0 || x[I_EV] >= CAP[k];
    for (level = 0; level < LEVELS[k] && !stop; ++level) {{
      propose(x, cand, pr);
      if (evaluate_at(cand, p, x, x + I_BOUNDS, iw, ws)) return 1;
      a[0] = x; a[1] = cand; a[2] = pr; a[3] = cand + I_COST; a[4] = cand + I_G;
      a[5] = cand + I_CLEAR;
      r[0] = flag; r[1] = flag + 1; r[2] = flag + 2; r[3] = flag + 3;
      if ({name}_decide(a, r, iw, ws, 0)) return 1;
      if (flag[1] != 0) {{ /* the best collision-free point met: [q, cost, clearance, bounds] */
        for (i = 0; i < NQ; ++i) x[I_FREE + i] = cand[i];
        x[I_REC_COST] = cand[I_COST];
        x[I_REC_CLEAR] = cand[I_CLEAR];
        for (i = 0; i < NG; ++i) x[I_REC_BOUNDS + i] = cand[I_BOUNDS + i];
      }}
      if (flag[0] != 0) for (i = 0; i < I_FREE; ++i) x[i] = cand[i]; /* a lower cost: kept */
      x[I_MU] = flag[2];
      x[I_DONE] = flag[3];
      x[I_IT] = x[I_IT] + 1.0;
      x[I_EV] = x[I_EV] + 1.0;
      stop = x[I_DONE] != 0 || x[I_EV] >= CAP[k];
    }}
    finish_start(best, x, y);
  }}
  a[0] = best;
  r[0] = res[0]; r[1] = res[1]; r[2] = res[2];
  return {name}_outputs(a, r, iw, ws, 0);
}}

/* One teleoperation step around {name}: 2 (nothing solved) unless q_prev, targets and
   q_ref are all finite; after the solve, its command and bounds become the next solve's
   anchor (arg[3], arg[4]: the caller's own buffers). */
CASADI_SYMBOL_EXPORT int {name}_step(const casadi_real** arg, casadi_real** res, casadi_int* iw,
                                    casadi_real* w, int mem) {{
  int i;
  for (i = 0; i < NQ; ++i)
    if (!isfinite(arg[0][i]) || !isfinite(arg[2][i])) return 2;
  for (i = 0; i < NP - 2 * NQ; ++i)
    if (!isfinite(arg[1][i])) return 2;
  if ({name}(arg, res, iw, w, mem)) return 1;
  for (i = 0; i < NQ; ++i) ((casadi_real*)arg[3])[i] = res[0][i];
  for (i = 0; i < NG; ++i) ((casadi_real*)arg[4])[i] = res[2][i];
  return 0;
}}

CASADI_SYMBOL_EXPORT int {name}_work(casadi_int* sz_arg, casadi_int* sz_res, casadi_int* sz_iw,
                                    casadi_int* sz_w) {{
  if (sz_arg) *sz_arg = 5;
  if (sz_res) *sz_res = 3;
  if (sz_iw) *sz_iw = {sz_iw};
  if (sz_w) *sz_w = W_SIZE + SUB_W;
  return 0;
}}
"""


def driver_source(parts: SolveParts, name: str) -> str:
    """The C file of one pair solve: the parts (built with ``prefix=name + "_"``,
    :func:`payload.retarget.lm_graph.solve_parts`) generated by CasADi, and the loop that
    drives them, exported as ``name`` (same inputs and outputs as
    :func:`payload.retarget.lm_graph.build_solve_function`'s function)."""
    cg = code_generator(f"{name}.c")
    fns = {part: getattr(parts, part) for part in ("prep", "evaluate", "decide", "outputs")}
    for part, named in fns.items():
        if named.name() != f"{name}_{part}":
            raise ValueError(f"solve part {named.name()!r}: built without the prefix {name}_")
        cg.add(named)
    sizes = work_sizes(list(fns.values()))  # a function's sz_arg covers its n_in
    lay = parts.layout
    code = _DRIVER.format(
        name=name,
        n=parts.n,
        ng=parts.groups,
        npar=parts.npar,
        nx=lay["size"],
        nstarts=len(parts.starts),
        i_cost=lay["cost"],
        i_g=lay["g"],
        i_h=lay["h"],
        i_clear=lay["clear"],
        i_bounds=lay["bounds"],
        i_free=lay["free"],
        i_mu=lay["mu"],
        i_it=lay["it"],
        i_done=lay["done"],
        i_ev=lay["ev"],
        i_rec_cost=lay["rec_cost"],
        i_rec_clear=lay["rec_clear"],
        i_rec_bounds=lay["rec_bounds"],
        sub_w=sizes["w"],
        sz_iw=sizes["iw"],
        sz_arg=sizes["arg"],
        sz_res=sizes["res"],
        caps=c_reals([cap for cap, _ in parts.starts]),
        levels=c_ints([levels for _, levels in parts.starts]),
        resume=c_ints([int(tag == RESUME) for tag in parts.tags]),
        initial=c_reals(list(parts.initial)),
        lower=c_reals(list(parts.lower)),
        upper=c_reals(list(parts.upper)),
        gtol=c_reals([parts.gtol]),
        mu0=c_reals([_MU0]),
        lower_eps=c_reals(list(parts.lower + _BOUND_EPS)),
        upper_eps=c_reals(list(parts.upper - _BOUND_EPS)),
        span=c_reals(list(parts.upper - parts.lower)),  # PairKinematics.range
        max_step=c_reals([_MAX_STEP]),
        curvature_floor=c_reals([_CURVATURE_FLOOR]),
        damping_eps=c_reals([_DAMPING_EPS]),
    )
    return cg.dump() + code


__all__ = ["driver_source"]
