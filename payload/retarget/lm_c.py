"""The compiled pair solve's control flow as a C loop.

:func:`payload.retarget.lm_graph.build_solve_function` expresses the starts and the
guarded Levenberg-Marquardt iterations as nested ``casadi.Function.conditional`` calls;
CasADi's generated code then copies the whole state (about 230 doubles with collision
groups) in and out of every level and start, and each level is its own piece of code. Here
the same sequence is a plain C loop (:func:`driver_source`) over the same CasADi functions
(:class:`payload.retarget.lm_graph.SolveParts`, generated into the same file): an
iteration evaluates its candidate into a buffer laid out as the state's head and copies
only what it keeps; a converged or capped start stops at a comparison. The arithmetic is
the generated functions' (``decide`` makes ``accept``'s choices), called in the same order
on the same values, so the answers are the graph's to the bit (a test compares the two).

The loop has the calling convention of a CasADi-generated function (``arg``, ``res``,
``iw``, ``w``, ``mem``; ``<name>_work`` reports the work sizes), so
:class:`payload.retarget.compiled._CompiledSolve` loads it like the graph's code.
"""

from __future__ import annotations

from payload.retarget.compiled import c_ints, c_reals, code_generator
from payload.retarget.lm_graph import SolveParts

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
static const casadi_real INITIAL[NX] = {{{initial}}};

/* an evaluation's outputs (cost, g, H, clearance, bounds) where the state holds them */
static const int AT[5] = {{I_COST, I_G, I_H, I_CLEAR, I_BOUNDS}};

static const casadi_real LB[NQ] = {{{lower}}};
static const casadi_real UB[NQ] = {{{upper}}};
#define GTOL {gtol}
#define MU0 {mu0}
#define I_REC_COST (I_FREE + NQ)
#define I_REC_CLEAR (I_FREE + NQ + 1)
#define I_REC_BOUNDS (I_FREE + NQ + 2)

/* CasADi's SX if_else to the bit: (c ? a : 0) + (!c ? b : 0) (so -0 becomes +0) */
#define SEL(c, a, b) ((((c) != 0) ? (a) : 0.0) + (((c) != 0) ? 0.0 : (b)))

/* init: a start's first state x from its evaluation in head (the state's head laid out:
   q, cost, g, H, clearance, bounds) and the best state so far (its counts) */
static void start_state(casadi_real* x, const casadi_real* head, const casadi_real* best) {{
  int i;
  casadi_real c = 0.0 <= head[I_CLEAR], m = 0.0, pg;
  for (i = 0; i < I_FREE; ++i) x[i] = head[i];
  for (i = 0; i < NQ; ++i) x[I_FREE + i] = SEL(c, head[i], head[i]);
  x[I_REC_COST] = SEL(c, head[I_COST], casadi_inf);
  x[I_REC_CLEAR] = SEL(c, head[I_CLEAR], -casadi_inf);
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
  casadi_real c = x[I_REC_COST] < casadi_inf, f_new, f_old, better;
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
    for (i = 0; i < NQ; ++i) cand[i] = starts[k * NQ + i];
    /* the first start carries the input anchor's bounds, the others the best state's */
    if (evaluate_at(cand, p, k ? best : arg[3], k ? best + I_BOUNDS : arg[4], iw, ws))
      return 1;
    start_state(x, cand, best);
    stop = x[I_DONE] != 0 || x[I_EV] >= CAP[k];
    for (level = 0; level < LEVELS[k] && !stop; ++level) {{
      a[0] = x;
      r[0] = cand; r[1] = pr;
      if ({name}_propose(a, r, iw, ws, 0)) return 1;
      if (evaluate_at(cand, p, x, x + I_BOUNDS, iw, ws)) return 1;
      a[0] = x; a[1] = cand; a[2] = pr; a[3] = cand + I_COST; a[4] = cand + I_G;
      a[5] = cand + I_CLEAR;
      r[0] = flag; r[1] = flag + 1; r[2] = flag + 2; r[3] = flag + 3;
      if ({name}_decide(a, r, iw, ws, 0)) return 1;
      if (flag[1] != 0) {{ /* the best collision-free point met: [q, cost, clearance, bounds] */
        for (i = 0; i < NQ; ++i) x[I_FREE + i] = cand[i];
        x[I_FREE + NQ] = cand[I_COST];
        x[I_FREE + NQ + 1] = cand[I_CLEAR];
        for (i = 0; i < NG; ++i) x[I_FREE + NQ + 2 + i] = cand[I_BOUNDS + i];
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
    fns = {
        part: getattr(parts, part) for part in ("prep", "evaluate", "propose", "decide", "outputs")
    }
    sizes = {"w": 1, "iw": 1, "arg": 1, "res": 1}  # a function's sz_arg covers its n_in
    for part, named in fns.items():
        if named.name() != f"{name}_{part}":
            raise ValueError(f"solve part {named.name()!r}: built without the prefix {name}_")
        cg.add(named)
        sizes["w"] = max(sizes["w"], int(named.sz_w()))
        sizes["iw"] = max(sizes["iw"], int(named.sz_iw()))
        sizes["arg"] = max(sizes["arg"], int(named.sz_arg()))
        sizes["res"] = max(sizes["res"], int(named.sz_res()))
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
        sub_w=sizes["w"],
        sz_iw=sizes["iw"],
        sz_arg=sizes["arg"],
        sz_res=sizes["res"],
        caps=c_reals([cap for cap, _ in parts.starts]),
        levels=c_ints([levels for _, levels in parts.starts]),
        initial=c_reals(list(parts.initial)),
        lower=c_reals(list(parts.lower)),
        upper=c_reals(list(parts.upper)),
        gtol=c_reals([parts.gtol]),
        mu0=c_reals([parts.mu0]),
    )
    return cg.dump() + code


__all__ = ["driver_source"]
