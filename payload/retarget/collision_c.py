"""The collision part of a residual evaluation as one C loop over the groups.

:meth:`CollisionGroups.penalty_function
<payload.retarget.collision_eval.CollisionGroups.penalty_function>` expresses the group
skipping with nested ``casadi.Function.conditional`` calls; CasADi's generated code then
copies every argument and result through each level, which costs more than the few groups
it evaluates. Here the same computation is a plain C loop: a group whose carried bound is
beyond the band costs one comparison, else its midpoint bound (the ``gate`` function)
decides whether its ``exact`` function runs. Both are the CasADi SX functions of
:meth:`~payload.retarget.collision_eval.CollisionGroups.kind_functions`
(algorithmic differentiation included), generated into the same file; the loop
accumulates the penalty, its gradient and its curvature from their outputs.

The loop is a CasADi ``external`` function, so the solver's graph calls it like any other
function and the generated solver links it in (:class:`NativeCollision`); it needs a C
compiler, so without one the solver keeps the conditional form (same values; a test
compares the two).
"""

from __future__ import annotations

import casadi as ca

from payload.retarget.collision_eval import CollisionGroups
from payload.retarget.compiled import (
    build_library,
    c_ints,
    c_reals,
    code_generator,
    work_sizes,
)
from payload.retarget.objective import RetargetConfig

_DISPATCH = r"""
/* ---- the group loop (payload.retarget.collision_c) ---- */
#define NG {ng}
#define NC {nc}
#define NQ {n}
#define BAND {band!r}
static const int KIND[NG] = {{{kinds}}}; /* 0: capsule-box, 1: capsule pair */
static const int CAP[NG] = {{{caps}}};
static const int OTHER[NG] = {{{others}}};
#define NK {width}
static const casadi_real K[NG][NK] = {{{consts}}};
/* per kind, its constant inputs' count and their offsets in a row of K */
static const int NCONST[2] = {{{nconst}}};
static const int OFFSET[2][NK] = {{{offsets}}};
typedef int (*kind_fn)(const casadi_real**, casadi_real**, casadi_int*, casadi_real*, int);
static const kind_fn GATE[2] = {{{name}_box_gate, {name}_pair_gate}};
static const kind_fn EXACT[2] = {{{name}_box_exact, {name}_pair_exact}};
/* capsule c's ends' Jacobian in q (6 x NQ), computed only for a capsule with a term in
   the band */
static const kind_fn JAC[NC] = {{{jacs}}};

static void constants(const int kind, const casadi_real* k, const casadi_real** ar) {{
  int i;
  for (i = 0; i < NCONST[kind]; ++i) ar[i] = k + OFFSET[kind][i];
}}

/* the Jacobian of capsule c's ends at q, computed once per call */
static const casadi_real* jacobian(int c, const casadi_real* q, casadi_real (*store)[6 * NQ],
                                   int* have, casadi_int* iwk, casadi_real* wk) {{
  const casadi_real* ar[{szarg}];
  casadi_real* rs[{szres}];
  if (!have[c]) {{
    ar[0] = q;
    rs[0] = store[c];
    if (JAC[c](ar, rs, iwk, wk, 0)) return 0;
    have[c] = 1;
  }}
  return store[c];
}}

/* (ends_0..ends_{{NC-1}} (6), q (NQ), bounds (NG))
   -> (S, dS/dq (NQ), group minima (NG), A (NQ x NQ)) */
CASADI_SYMBOL_EXPORT int {name}(const casadi_real** arg, casadi_real** res, casadi_int* iw,
                               casadi_real* w, int mem) {{
  const casadi_real* pre = arg[NC + 1];
  const casadi_real* q = arg[NC];
  casadi_real s = 0, dq[NQ], a[NQ * NQ], mins[NG], gate, over, c, grad[12], u[NQ];
  casadi_real store[NC][6 * NQ];
  int have[NC];
  const casadi_real *j1, *j2;
  casadi_real wk[{szw}];
  casadi_int iwk[{sziw}];
  const casadi_real* ar[{szarg}];
  casadi_real* rs[{szres}];
  int g, i, j, m, kind;
  for (i = 0; i < NQ; ++i) dq[i] = 0;
  for (i = 0; i < NQ * NQ; ++i) a[i] = 0;
  for (i = 0; i < NC; ++i) have[i] = 0;
  for (g = 0; g < NG; ++g) {{
    const casadi_real b = pre ? pre[g] : 0;
    if (b >= BAND) {{ mins[g] = b; continue; }} /* the carried bound proves it far */
    kind = KIND[g];
    m = 0;
    ar[m++] = arg[CAP[g]];
    if (kind) ar[m++] = arg[OTHER[g]];
    constants(kind, K[g], ar + m);
    rs[0] = &gate;
    if (GATE[kind](ar, rs, iwk, wk, 0)) return 1;
    if (gate >= BAND) {{ mins[g] = fmax(b, gate); continue; }} /* the midpoint bound does */
    rs[0] = &over; rs[1] = &c; rs[2] = grad;
    if (EXACT[kind](ar, rs, iwk, wk, 0)) return 1;
    mins[g] = c;
    if (over > 0) {{ /* u = J^T grad: the clearance's gradient in q */
      j1 = jacobian(CAP[g], q, store, have, iwk, wk);
      j2 = jacobian(OTHER[g], q, store, have, iwk, wk);
      if (!j1 || !j2) return 1;
      for (i = 0; i < NQ; ++i) {{
        u[i] = 0;
        for (m = 0; m < 6; ++m) u[i] += j1[m + 6 * i] * grad[m];
        if (kind) for (m = 0; m < 6; ++m) u[i] += j2[m + 6 * i] * grad[6 + m];
      }}
      s += over * over;
      for (i = 0; i < NQ; ++i) dq[i] -= 2.0 * over * u[i];
      for (j = 0; j < NQ; ++j)
        for (i = 0; i < NQ; ++i) a[i + NQ * j] += u[i] * u[j];
    }}
  }}
  if (res[0]) res[0][0] = s;
  if (res[1]) for (i = 0; i < NQ; ++i) res[1][i] = dq[i];
  if (res[2]) for (g = 0; g < NG; ++g) res[2][g] = mins[g];
  if (res[3]) for (i = 0; i < NQ * NQ; ++i) res[3][i] = a[i];
  return 0;
}}

static const casadi_int SP_ENDS[] = {{{sp_ends}}};
static const casadi_int SP_PRE[] = {{{sp_pre}}};
static const casadi_int SP_ONE[] = {{{sp_one}}};
static const casadi_int SP_Q[] = {{{sp_q}}};
static const casadi_int SP_A[] = {{{sp_a}}};
CASADI_SYMBOL_EXPORT casadi_int {name}_n_in(void) {{ return NC + 2; }}
CASADI_SYMBOL_EXPORT casadi_int {name}_n_out(void) {{ return 4; }}
CASADI_SYMBOL_EXPORT const casadi_int* {name}_sparsity_in(casadi_int i) {{
  return i < NC ? SP_ENDS : i == NC ? SP_Q : i == NC + 1 ? SP_PRE : 0;
}}
CASADI_SYMBOL_EXPORT const casadi_int* {name}_sparsity_out(casadi_int i) {{
  static const casadi_int* out[4] = {{SP_ONE, SP_Q, SP_PRE, SP_A}};
  return i >= 0 && i < 4 ? out[i] : 0;
}}
CASADI_SYMBOL_EXPORT int {name}_work(casadi_int* sz_arg, casadi_int* sz_res, casadi_int* sz_iw,
                                    casadi_int* sz_w) {{
  if (sz_arg) *sz_arg = NC + 2;
  if (sz_res) *sz_res = 4;
  if (sz_iw) *sz_iw = 0;
  if (sz_w) *sz_w = 0;
  return 0;
}}
"""


class NativeCollision:
    """The collision part of one pair's residual evaluation in C (see the module).

    Args:
        groups: The pair's collision groups.
        config: Retargeting settings (the band).
        name: The C symbol of the loop (the solver's name plus ``_collision``).
        compiler: The C compiler.

    Attributes:
        name: The loop's C symbol.
        groups: The pair's collision groups.
        source: The C file (the kind functions and the loop), to compile into the solver.
        function: The loop as a CasADi ``external`` function: ``(ends (6) per capsule,
            q (n), bounds (groups)) -> (S, dS/dq, group minima, A)`` (a capsule's ends'
            Jacobian computed in the loop, only for a capsule with a term in the band), as
            :meth:`CollisionGroups.penalty_function
            <payload.retarget.collision_eval.CollisionGroups.penalty_function>` returns
            after the capsule ends.
    """

    def __init__(
        self, groups: CollisionGroups, config: RetargetConfig, name: str, compiler: str
    ) -> None:
        self.name = name
        self.groups = groups
        pk = groups.pk
        n, ncap, ng = pk.n, len(pk.collision.capsules), len(groups)
        cg = code_generator(f"{name}.c")
        generated = []
        for kind in ("box", "pair"):
            for fn, part in zip(groups.kind_functions(kind, config), ("gate", "exact")):
                ins = fn.sx_in()
                generated.append(
                    ca.Function(f"{name}_{kind}_{part}", ins, fn.call(ins), {"cse": True})
                )
        # Each capsule's ends' Jacobian on its own, sliced from the one Jacobian of all
        # the ends (the same expressions, so the same bits as computing them together).
        qs = ca.SX.sym("q", n)
        jac = ca.densify(ca.jacobian(groups.ends_function()(qs), qs))
        for c in range(ncap):
            rows = jac[6 * c : 6 * c + 6, :]
            generated.append(ca.Function(f"{name}_jac_{c}", [qs], [rows], {"cse": True}))
        for fn in generated:
            cg.add(fn)
        sizes = work_sizes(generated)
        # Each kind's constant inputs (after its capsule ends), as CasADi lays them out.
        layout = []
        for kind, ne in (("box", 1), ("pair", 2)):
            gate = groups.kind_functions(kind, config)[0]
            counts = [int(gate.nnz_in(i)) for i in range(ne, gate.n_in())]
            layout.append([sum(counts[:i]) for i in range(len(counts))] + [sum(counts)])
        width = max(row[-1] for row in layout)
        kinds, caps, others, consts = [], [], [], []
        for g, (cap, box, other) in enumerate(groups.keys()):
            values = groups.group_constants(g)
            flat = [float(x) for v in values for x in ca.DM(v).full().ravel(order="F")]
            kinds.append(0 if box else 1)
            caps.append(cap)
            others.append(other if not box else cap)
            if len(flat) != layout[kinds[-1]][-1]:  # pragma: no cover - a model change
                raise AssertionError(f"group {g}: constants do not fit its kind's inputs")
            consts.append("{" + c_reals(flat + [0.0] * (width - len(flat))) + "}")
        offsets = [row[:-1] + [0] * (width - len(row) + 1) for row in layout]
        sp = {
            "sp_ends": ca.Sparsity.dense(6, 1),
            "sp_pre": ca.Sparsity.dense(ng, 1),
            "sp_one": ca.Sparsity.dense(1, 1),
            "sp_q": ca.Sparsity.dense(n, 1),
            "sp_a": ca.Sparsity.dense(n * n, 1),
        }
        loop = _DISPATCH.format(
            ng=ng,
            nc=ncap,
            n=n,
            band=float(config.collision_band),
            kinds=c_ints(kinds),
            caps=c_ints(caps),
            others=c_ints(others),
            consts=", ".join(consts),
            width=width,
            nconst=c_ints([len(row) - 1 for row in layout]),
            offsets=", ".join("{" + c_ints(row) + "}" for row in offsets),
            name=name,
            szw=sizes["w"],
            sziw=sizes["iw"],
            szarg=sizes["arg"],
            szres=sizes["res"],
            jacs=", ".join(f"{name}_jac_{c}" for c in range(ncap)),
            **{k: c_ints(list(v.compress())) for k, v in sp.items()},
        )
        self.source = cg.dump() + loop
        # its own library name: the solver's cache pruning (by name prefix) leaves it alone
        path = build_library(
            f"loop_{name}", {f"{name}.c": self.source}, compiler, what="the collision loop"
        )
        self.function = ca.external(name, str(path))

    def penalty_function(self) -> ca.Function:
        """``(q, pre-bounds) -> (S, dS/dq, group minima, A)``: the capsule ends, then the
        C loop (same contract as :meth:`CollisionGroups.penalty_function
        <payload.retarget.collision_eval.CollisionGroups.penalty_function>`)."""
        pk = self.groups.pk
        q, pre = ca.MX.sym("q", pk.n), ca.MX.sym("pre", len(self.groups))
        ncap = len(pk.collision.capsules)
        qs = ca.SX.sym("q", pk.n)
        e = self.groups.ends_function()(qs)
        split = ca.Function("capsule_ends", [qs], [e[6 * i : 6 * i + 6] for i in range(ncap)])
        # the loop computes a capsule's Jacobian itself, when one of its terms is in the band
        return ca.Function("collision_penalty", [q, pre], self.function(*split(q), q, pre))


__all__ = ["NativeCollision"]
