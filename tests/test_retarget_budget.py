"""Retargeting budgets (issue 14): every residual evaluation counted, the paper's budget
never exceeded, and the best-known optimum reached on our hand and on two other hands.

The evaluation counts are checked against independent counters: a counting
``casadi.Callback`` standing in for the production solver's one residual function (in
CasADi's virtual machine), and a counting residual function handed to scipy, whose own
``nfev`` must agree. Optimality is judged by :func:`payload.retarget.optimum.best_known_cost`
(scipy trf/soft_l1 from several starts), costs by Pinocchio and numpy.
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from conftest import hand_file, replace_once
from scipy.optimize import least_squares

from payload.project import current_project
from payload.retarget import (
    N_FEATURES,
    PairKinematics,
    PairRetargeter,
    ReferenceRetargeter,
    RetargetConfig,
    RetargetError,
    calibrate,
    load_hand,
    pair_range,
)
from payload.retarget.bench import human_pinch_and_open, target_stream
from payload.retarget.budget import evaluation_cap
from payload.retarget.casadi_solver import build_solve_function
from payload.retarget.optimum import CompiledObjective, best_known_cost

HANDS_DIR = Path(__file__).resolve().parents[1] / "payload" / "retarget" / "hands"
EXTRA_HANDS = ("thumb_abduction_first.toml", "offset_distal.toml")


class Counted(ca.Callback):
    """A CasADi function that counts its calls."""

    def __init__(self, f: ca.Function) -> None:
        ca.Callback.__init__(self)
        self.f, self.count = f, 0
        self.construct("counted_evaluate", {})

    def get_n_in(self) -> int:
        return self.f.n_in()

    def get_n_out(self) -> int:
        return self.f.n_out()

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return self.f.sparsity_in(i)

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return self.f.sparsity_out(i)

    def eval(self, arg: list) -> list:
        self.count += 1
        return self.f.call(arg)


@pytest.fixture(scope="module")
def pk() -> PairKinematics:
    return PairKinematics(None, "L")


def _hard_problems(pk: PairKinematics, seed: int, k: int):
    """Reachable targets far from the warm start (random jumps), posture reference = rest."""
    rng = np.random.default_rng(seed)
    for _ in range(k):
        q_true = pk.lower + rng.random(pk.n) * pk.range
        q_prev = pk.lower + rng.random(pk.n) * pk.range
        yield pk.features(q_true).as_vector(), q_prev, pk.rest


@pytest.mark.parametrize(
    ("budget", "collisions"), [("paper", False), ("converged", False), ("paper", True)]
)
def test_production_counts_every_residual_evaluation(pk, budget, collisions):
    counters: list[Counted] = []

    def wrap(f: ca.Function) -> Counted:
        counters.append(Counted(f))
        return counters[-1]

    config = RetargetConfig(budget=budget, collisions=collisions)
    counted = build_solve_function(pk, config, "counted", wrap_evaluate=wrap)
    plain = build_solve_function(pk, config, "plain")
    (counter,) = counters
    unknown = np.full(counted.nnz_in(4), -np.inf)  # no collision bounds known yet
    assert (unknown.size > 0) == collisions
    for targets, q_prev, q_ref in _hard_problems(pk, 3, 4 if budget == "paper" else 2):
        counter.count = 0
        q, info, _ = counted(q_prev, targets, q_ref, q_prev, unknown)
        q2, info2, _ = plain(q_prev, targets, q_ref, q_prev, unknown)
        info, info2 = np.array(info).ravel(), np.array(info2).ravel()
        assert counter.count == int(info[3])  # the solver's own count is every call
        np.testing.assert_allclose(np.array(q), np.array(q2), atol=1e-12)
        assert info2[3] == info[3]
        assert counter.count <= evaluation_cap(config)
        if budget == "paper":
            assert counter.count <= 20


def test_reference_evaluations_are_scipys_nfev(pk):
    ref = ReferenceRetargeter(kinematics=pk)
    obj = ref.objective
    for targets, q_prev, q_ref in _hard_problems(pk, 4, 3):
        _, info = ref.solve(targets, q_prev, q_ref)
        calls = [0]

        def fun(q, targets=targets, q_prev=q_prev, q_ref=q_ref, calls=calls):
            calls[0] += 1
            f, _ = pk.features_jacobian(q)
            return obj.residuals(f, q, targets, q_ref, q_prev)

        def jac(q):
            _, jf = pk.features_jacobian(q)
            return obj.jacobian(jf)

        res = least_squares(
            fun,
            q_prev,
            jac=jac,
            bounds=(pk.lower, pk.upper),
            method="trf",
            loss="soft_l1",
            max_nfev=20,
        )
        assert calls[0] == res.nfev  # what scipy counts is every call of the residuals
        assert info.evaluations == res.nfev <= 20


def test_paper_budget_is_never_exceeded(pk):
    r = PairRetargeter(kinematics=pk)
    assert r.config.budget == "paper"
    used = []
    for targets, q_prev, q_ref in _hard_problems(pk, 5, 200):
        q, info = r.solve(targets, q_prev, q_ref)
        used.append(info.evaluations)
        assert np.all(q >= r.lower) and np.all(q <= r.upper)
    assert max(used) <= 20 and min(used) >= 1


@pytest.mark.parametrize("collisions", [False, True])
def test_table_seeds_alternate_full_and_geometric_picks(pk, collisions):
    """The converged budget's table starts, recomputed with numpy from the table: picks
    alternate between the lowest eq. 3 cost and the lowest geometric cost, never twice the
    same posture; with collisions modelled, the table keeps only margin-keeping postures."""
    from payload.retarget.budget import TABLE_STARTS, seed_table, table_seeds
    from payload.retarget.objective import soft_l1

    cfg = RetargetConfig(budget="converged", collisions=collisions)
    qs, fs = seed_table(pk, collisions)
    if collisions:
        assert pk.collision.distances_many(qs).min() >= pk.collision.margin
    t, qr, q0 = ca.MX.sym("t", N_FEATURES), ca.MX.sym("qr", pk.n), ca.MX.sym("q0", pk.n)
    picks = ca.Function("picks", [t, qr, q0], table_seeds(pk, cfg, t, qr, q0, TABLE_STARTS))
    scales = cfg.feature_scales()
    for targets, q_prev, q_ref in _hard_problems(pk, 31, 3):
        geo = (scales * (fs - targets)) ** 2
        post = (cfg.w_p * (qs - q_ref) / pk.range) ** 2
        temp = (cfg.w_t * (qs - q_prev) / pk.range) ** 2
        costs = [
            soft_l1(np.hstack([geo, post, temp])).sum(axis=1),
            soft_l1(geo).sum(axis=1),
        ]
        taken: list[int] = []
        for j, got in enumerate(picks(targets, q_ref, q_prev)):
            order = [i for i in np.argsort(costs[j % 2], kind="stable") if i not in taken]
            taken.append(order[0])
            np.testing.assert_allclose(np.array(got).ravel(), qs[order[0]], rtol=0, atol=1e-12)


def test_paper_seed_table_is_the_first_margin_keeping_candidates(pk):
    """The paper budget's table (its first :data:`PAPER_SEEDS`, found a chunk of candidates
    at a time) is the same postures, in order, as filtering every candidate by its
    clearance: here each candidate's clearance from the numpy and Pinocchio distances
    (``PairCollision.clearance``), not the compiled ones the table uses."""
    from payload.retarget.budget import PAPER_SEEDS, seed_candidates, seed_table

    qs, fs = seed_table(pk, True, PAPER_SEEDS)
    cands = seed_candidates(pk)
    want = []
    for q in cands:
        if pk.collision.clearance(q) >= 0.0:
            want.append(q)
            if len(want) == PAPER_SEEDS:
                break
    assert len(want) == PAPER_SEEDS
    np.testing.assert_array_equal(qs, np.array(want))
    np.testing.assert_array_equal(fs, pk.features_batch(qs))


@pytest.mark.parametrize("chunk", [1, 7, 300])
def test_the_seed_table_stops_when_full_whatever_the_chunk(pk, monkeypatch, tmp_path, chunk):
    """Any chunk size gives the table all candidates filtered at once would (the compiled
    distances of every candidate, the first PAPER_SEEDS kept), and evaluates no more
    candidates than the chunk holding the last posture taken (a cache of its own: the
    table is computed)."""
    from payload.retarget import budget, collision_cache
    from payload.retarget.collision import register

    register()
    monkeypatch.setattr(collision_cache, "cache_dir", lambda: tmp_path)
    col = pk.collision
    cands = budget.seed_candidates(pk)
    clear = np.flatnonzero(col.distances_many(cands).min(axis=0) >= col.margin)
    want = cands[clear[: budget.PAPER_SEEDS]]
    evaluated = []
    real = type(col).distances_many
    monkeypatch.setattr(budget, "SEED_CHUNK", chunk)
    monkeypatch.setattr(
        type(col),
        "distances_many",
        lambda self, qs, *a: evaluated.append(len(qs)) or real(self, qs, *a),
    )
    qs, _ = budget.seed_table(pk, True, budget.PAPER_SEEDS)
    np.testing.assert_array_equal(qs, want)
    last = int(clear[budget.PAPER_SEEDS - 1])
    assert sum(evaluated) == min((last // chunk + 1) * chunk, len(cands))


def test_the_seed_table_kept_on_disk_is_the_computed_one(monkeypatch, tmp_path):
    """A pair whose collision geometry is cached keeps its seed table beside it: the next
    pair built from the same model loads the same postures, to the bit, without
    evaluating a distance; another table size is another entry."""
    from payload.retarget import budget, collision_cache
    from payload.retarget.collision import register

    register()
    monkeypatch.setattr(collision_cache, "cache_dir", lambda: tmp_path)
    first = PairKinematics(load_hand(), "R")
    qs, fs = budget.seed_table(first, True, budget.PAPER_SEEDS)
    assert first.collision.key is not None
    assert len(list(tmp_path.glob("pair_postures_*.npz"))) == 1
    second = PairKinematics(load_hand(), "R")
    monkeypatch.setattr(budget, "_clear_first", lambda *a: pytest.fail("computed, not loaded"))
    again, fs_again = budget.seed_table(second, True, budget.PAPER_SEEDS)
    assert again.tobytes() == qs.tobytes() and fs_again.tobytes() == fs.tobytes()
    monkeypatch.undo()
    monkeypatch.setattr(collision_cache, "cache_dir", lambda: tmp_path)
    budget.seed_table(second, True, 100)
    assert len(list(tmp_path.glob("pair_postures_*.npz"))) == 2


def test_budget_setting_is_validated():
    assert RetargetConfig().budget == "paper"
    assert RetargetConfig(budget="converged").budget == "converged"
    with pytest.raises(RetargetError, match="budget: expected one of paper, converged"):
        RetargetConfig(budget="fast")


def _optimum_fraction(
    hand_path: Path | None, budget: str, steps: int, collisions: bool = False
) -> float:
    """Fraction of the bench stream's solves within 1e-3 of the best-known optimum."""
    hand = load_hand(hand_path)
    kin = hand.kinematics()
    pinch, open_ = human_pinch_and_open()
    rng = np.random.default_rng(0)
    ok = []
    for i, name in enumerate(hand.pairs):
        pk = PairKinematics(hand, name, kin)
        r = PairRetargeter(hand, name, RetargetConfig(budget=budget, collisions=collisions), pk)
        compiled = CompiledObjective(pk, r.config)
        cal = calibrate(pinch, open_, pair_range(pk, collisions=r.collisions))
        for st in target_stream(pk, cal, steps, 1000 * i, phase=1.3 * i):
            q_prev = r.command
            q, _ = r.solve(st.targets, q_prev, st.q_ref)
            cost = r.cost(q, st.targets, st.q_ref, q_prev)
            # with self-collision modelled: the constrained optimum (answers that keep the
            # margin), and an answer inside the margin is never optimal
            clear = r.clearance if r.collisions else None
            best = best_known_cost(
                pk, r.objective, compiled, st.targets, q_prev, st.q_ref, [q], rng, clear
            )
            free = clear is None or clear(q) >= 0
            ok.append(free and cost <= min(best, cost) * (1.0 + 1e-3))
    return float(np.mean(ok))


@pytest.mark.parametrize(
    "hand",
    [
        None,
        "thumb_abduction_first.toml",
        "offset_distal.toml",
    ],
)
def test_converged_budget_reaches_the_optimum_on_every_hand(hand):
    path = None if hand is None else HANDS_DIR / hand
    assert _optimum_fraction(path, "converged", 60) >= 0.999


@pytest.mark.parametrize("hand", [None, "offset_distal.toml"])
def test_converged_budget_reaches_the_constrained_optimum_with_collisions(hand):
    # the hands with collision geometry; the optimum is the constrained one (answers that
    # keep the margin), found by scipy from the informed and random starts. With the
    # earlier 60-iteration cap ours gave 0.975 here (starts stopped along the penalty band).
    path = None if hand is None else HANDS_DIR / hand
    assert _optimum_fraction(path, "converged", 60, collisions=True) >= 0.999


def test_converged_starts_reach_a_many_start_optimum_on_a_hand_not_ours(tmp_path):
    """A hand file of its own, never used to choose the starts: our URDF under another
    design's margin (3.5 mm, not 2 mm; the shipped test hands have no link pair that can
    come inside a margin) and another rest posture, the model on. Jumps to the targets of
    random postures inside the margin (where the penalty makes several basins) from a
    random warm start. The brute-force optimum: scipy trf/soft_l1 from the informed starts
    and 24 more random postures, costed with Pinocchio, only margin-keeping answers; the
    converged budget's answer keeps the margin and is within 1e-3 of it on every case."""
    text = current_project().design_path.read_text()
    assert "collision_margin = 0.002" in text
    (tmp_path / "design.toml").write_text(
        replace_once(text, "collision_margin = 0.002", "collision_margin = 0.0035")
    )
    hand = load_hand(hand_file(tmp_path, load_hand().urdf, "design.toml"))
    assert hand.collision_margin == 0.0035
    pk = PairKinematics(hand, "R")
    r = PairRetargeter(hand, "R", RetargetConfig(budget="converged", collisions=True), pk)
    compiled = CompiledObjective(pk, r.config)
    rng = np.random.default_rng(8)
    q_true = pk.lower + rng.random((40, pk.n)) * pk.range
    q_true = [q for q in q_true if r.clearance(q) < 0][:4]  # targets inside the margin
    assert len(q_true) == 4
    inside = 0
    for qt in q_true:
        targets = pk.features(qt).as_vector()
        q_prev = pk.lower + rng.random(pk.n) * pk.range
        q_ref = pk.lower + rng.random(pk.n) * pk.range  # not the rest posture either
        q, info = r.solve(targets, q_prev, q_ref)
        many = list(pk.lower + rng.random((24, pk.n)) * pk.range)
        best = best_known_cost(
            pk, r.objective, compiled, targets, q_prev, q_ref, many, rng, r.clearance
        )
        assert r.clearance(q) >= 0
        assert r.cost(q, targets, q_ref, q_prev) <= best * (1.0 + 1e-3)
        inside += info.clearance < r.config.collision_band  # the penalty acts there
    assert inside > 0
