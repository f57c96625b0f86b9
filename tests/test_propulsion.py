"""Astrobee's 12-nozzle propulsion: geometry, polytope, allocation, and MuJoCo's side."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from scipy.optimize import linprog, lsq_linear

from payload.sim import SimDriver, WorldConfig, build_world
from payload.sim.allocation import _bvls, _lstsq
from payload.sim.propulsion import (
    BVLS_TOL,
    INCH,
    Propulsion,
    PropulsionError,
    shared_propulsion,
)
from payload.sim.vehicle import FLIGHT_MODES, MassProperties, VehicleController, VehicleError

NOMINAL = FLIGHT_MODES["nominal"]


@pytest.fixture(scope="module")
def nozzles() -> Propulsion:
    return Propulsion(NOMINAL.force)


@pytest.fixture(scope="module")
def bare_world():
    return build_world(WorldConfig(ctb=None))


def _lp_extent(p: Propulsion, w: np.ndarray) -> float:
    """Largest lambda with lambda * w reachable, from a plain LP written here."""
    n = 12
    a_eq = np.hstack([p.matrix, -w.reshape(6, 1)])
    cost = np.zeros(n + 1)
    cost[-1] = -1.0
    bounds = [(0.0, u) for u in p.thrust_max] + [(0.0, None)]
    res = linprog(cost, A_eq=a_eq, b_eq=np.zeros(6), bounds=bounds, method="highs")
    assert res.status == 0
    return float(res.x[-1])


def test_thrust_on_the_robot_points_against_the_nozzle_axis(nozzles):
    # PM1 nozzle 1 sits at (6.00, 4.01, -1.56) in with axis +x: it pushes the robot to -x
    t = np.zeros(12)
    t[0] = 0.1
    force, torque = nozzles.wrench(t)
    np.testing.assert_allclose(force, [-0.1, 0.0, 0.0], atol=1e-15)
    r = np.array([6.00, 4.01, -1.56]) * INCH
    np.testing.assert_allclose(torque, np.cross(r, [-0.1, 0.0, 0.0]), atol=1e-15)


def test_per_axis_force_maxima_are_the_published_ones(nozzles):
    for i in range(3):
        e = np.zeros(6)
        e[i] = 1.0
        got = min(_lp_extent(nozzles, e), _lp_extent(nozzles, -e))
        assert got == pytest.approx(NOMINAL.force[i], rel=1e-8)
        # the facet description of the polytope agrees with the LP
        assert min(nozzles.extent(e), nozzles.extent(-e)) == pytest.approx(got, rel=1e-8)
    # the other mode scales with its own figures
    hard = Propulsion(FLIGHT_MODES["difficult"].force)
    np.testing.assert_allclose(hard.pure_force_max(), FLIGHT_MODES["difficult"].force, rtol=1e-8)


def test_the_programmes_answers_are_kept_in_the_cache_bit_for_bit(monkeypatch, tmp_path):
    """The first Propulsion for a mode fits its bounds (and finds its pure torques) by
    linear programmes and keeps their answers; the next process reads the same bits back
    without a programme; a damaged file is worked out again."""
    from payload.sim import propulsion

    monkeypatch.setenv("PAYLOAD_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(propulsion._Extents, "_OPEN", {})
    first = Propulsion(NOMINAL.force)
    torque = first.pure_torque_max()
    (kept,) = tmp_path.glob("propulsion_extents_*.json")

    def no_programme(*args, **kwargs):
        raise AssertionError("a linear programme was solved")

    monkeypatch.setattr(propulsion._Extents, "_OPEN", {})  # the next process
    with monkeypatch.context() as m:
        m.setattr(Propulsion, "_lp", no_programme)
        again = Propulsion(NOMINAL.force)
        assert again.pure_torque_max().tobytes() == torque.tobytes()
    assert again.thrust_max.tobytes() == first.thrust_max.tobytes()
    np.testing.assert_allclose(again.pure_force_max(), NOMINAL.force, rtol=1e-8)
    for i in range(3):  # the kept answers are the programme's (written here)
        e = np.zeros(6)
        e[i] = 1.0
        assert again.max_along(e) == pytest.approx(_lp_extent(again, e), rel=1e-9)
    kept.write_text("{")
    monkeypatch.setattr(propulsion._Extents, "_OPEN", {})
    assert Propulsion(NOMINAL.force).thrust_max.tobytes() == first.thrust_max.tobytes()


def test_force_and_torque_share_the_nozzles(nozzles):
    """Peak force and peak torque cannot be had together: not a box."""
    fx = NOMINAL.force[0]
    tz = float(nozzles.pure_torque_max()[2])
    w = np.array([fx, 0, 0, 0, 0, tz])
    assert nozzles.extent(w) < 0.99


def test_allocation_inside_the_polytope_is_exact_and_least_thrust(nozzles):
    rng = np.random.default_rng(1)
    scale = np.array([0.3, 0.15, 0.15, 0.03, 0.03, 0.03])
    inside = 0
    for w in rng.normal(size=(60, 6)) * scale:
        lam = _lp_extent(nozzles, w)
        w = w * min(1.0, 0.98 * lam)  # inside
        a = nozzles.allocate(w[:3], w[3:])
        assert a.scale == 1.0
        assert np.all(a.thrust >= 0) and np.all(a.thrust <= nozzles.thrust_max)
        np.testing.assert_allclose(np.concatenate([a.force, a.torque]), w, atol=1e-12)
        np.testing.assert_allclose(nozzles.matrix @ a.thrust, w, atol=1e-12)
        res = linprog(
            np.ones(12),
            A_eq=nozzles.matrix,
            b_eq=w,
            bounds=[(0.0, u) for u in nozzles.thrust_max],
            method="highs",
        )
        assert a.thrust.sum() == pytest.approx(res.fun, rel=1e-7, abs=1e-12)
        inside += 1
    assert inside == 60


def test_saturation_keeps_the_wrench_direction(nozzles):
    rng = np.random.default_rng(2)
    scale = np.array([0.3, 0.15, 0.15, 0.03, 0.03, 0.03])
    for w in rng.normal(size=(40, 6)) * scale:
        lam = _lp_extent(nozzles, w)
        w = w * (1.5 * lam)  # 1.5 times the reachable extent along w
        a = nozzles.allocate(w[:3], w[3:])
        out = np.concatenate([a.force, a.torque])
        assert a.scale == pytest.approx(1.0 / 1.5, rel=1e-6)
        np.testing.assert_allclose(out, a.scale * w, rtol=1e-7, atol=1e-10)
        assert np.all(a.thrust >= 0) and np.all(a.thrust <= nozzles.thrust_max + 1e-12)
        # on the boundary: no larger multiple is reachable
        assert _lp_extent(nozzles, out) == pytest.approx(1.0, rel=1e-6)


def test_fast_facet_solve_matches_numpy_and_scipy(nozzles):
    """The direct LAPACK least squares and the BVLS call give numpy's and scipy's bits:
    the saturated allocation equals the binding facet's solve written here with
    ``np.linalg.lstsq`` and ``lsq_linear(method="bvls")`` (the facet's parts and tolerance
    are the allocation's own, not typed again)."""
    rng = np.random.default_rng(3)
    scale = np.array([0.3, 0.15, 0.15, 0.03, 0.03, 0.03])
    tol = nozzles._facet_tol
    bounded = 0
    for w in rng.normal(size=(300, 6)) * scale:
        if rng.random() < 0.3:
            w[rng.random(6) < 0.4] = 0.0  # axis-aligned requests hit degenerate facets
        if not np.any(w):
            continue
        w = w * (nozzles.extent(w) * rng.uniform(1.05, 3.0))  # outside: onto a facet
        lam, k = nozzles._extent(w)  # the binding facet
        ref, free, a, ub, _ = nozzles._facet_parts[k]
        ref = ref.copy()
        rest = lam * w - nozzles.matrix @ ref
        sol = np.linalg.lstsq(a, rest, rcond=None)[0]
        np.testing.assert_array_equal(_lstsq(a, rest)[0], sol)
        start = np.linalg.lstsq(a, rest, rcond=-1)[0]
        np.testing.assert_array_equal(_lstsq(a, rest, -1.0)[0], start)
        if np.any(sol < -tol) or np.any(sol > ub + tol):
            lb = np.zeros(len(free))
            sol = lsq_linear(a, rest, bounds=(lb, ub), method="bvls", tol=BVLS_TOL).x
            np.testing.assert_array_equal(_bvls(a, rest, ub), sol)
            np.testing.assert_array_equal(_bvls(a, rest, ub, start), sol)
            bounded += 1
        ref[free] = np.clip(sol, 0.0, ub)
        got = nozzles.allocate(w[:3], w[3:])
        assert got.scale == lam
        np.testing.assert_array_equal(got.thrust, ref)
    assert bounded > 50  # the bounded least squares ran
    # general bounded problems (inconsistent, rank-deficient): scipy's BVLS, bit for bit
    for _ in range(200):
        m, n = rng.integers(3, 9, size=2)
        a = rng.normal(size=(m, n))
        if rng.random() < 0.3:
            a[:, -1] = a[:, 0]
        b = rng.normal(size=m) * 3.0
        ub = rng.uniform(0.1, 1.0, size=n)
        want = lsq_linear(a, b, bounds=(np.zeros(n), ub), method="bvls", tol=BVLS_TOL).x
        np.testing.assert_array_equal(_bvls(a, b, ub), want)


def test_bvls_gives_scipys_bits_on_general_bounded_problems():
    """payload.sim.lsq.bvls against SciPy's own BVLS (``lsq_linear(method="bvls")``):
    any lower and upper bounds, starts inside and outside them, rank-deficient and
    inconsistent systems, a short iteration budget; the same bits every time."""
    from payload.sim.lsq import bvls

    rng = np.random.default_rng(31)
    moved = 0
    for _ in range(400):
        m, n = rng.integers(2, 10, size=2)
        a = rng.normal(size=(m, n))
        if rng.random() < 0.3:
            a[:, -1] = a[:, 0] * rng.uniform(0.5, 2.0)
        b = rng.normal(size=m) * rng.uniform(0.5, 5.0)
        lb = -rng.uniform(0.0, 1.0, size=n)
        ub = lb + rng.uniform(0.05, 2.0, size=n)
        max_iter = None if rng.random() < 0.8 else int(rng.integers(1, 4))
        want = lsq_linear(a, b, bounds=(lb, ub), method="bvls", tol=BVLS_TOL, max_iter=max_iter)
        x0 = np.linalg.lstsq(a, b, rcond=-1)[0]  # lsq_linear's start
        got = bvls(a, b, x0, lb, ub, BVLS_TOL, max_iter)
        if ((x0 < lb) | (x0 > ub)).any():
            moved += 1
            np.testing.assert_array_equal(got, want.x)
    assert moved > 300  # most problems needed the bounded solve


def test_bad_inputs(nozzles):
    with pytest.raises(PropulsionError):
        Propulsion((0.68, -1.0, 0.3))
    with pytest.raises(PropulsionError):
        nozzles.allocate(np.array([np.nan, 0, 0]), np.zeros(3))
    plant = MassProperties(10.0, np.zeros(3), np.eye(3) * 0.15)
    with pytest.raises(VehicleError, match="propulsion"):
        VehicleController(plant, propulsion="jets")


def test_controller_plans_inside_the_polytope():
    plant = MassProperties(26.0, np.array([0.0, 0.0, -0.31]), np.diag([1.2, 1.2, 0.4]))
    ctl = VehicleController(plant, propulsion="nozzles")
    box = VehicleController(plant, propulsion="box")
    assert ctl.nozzles is not None
    for i in range(3):
        e = np.zeros(3)
        e[i] = ctl.force_max[i]
        for sign in (1.0, -1.0):
            w = sign * np.concatenate([e, np.cross(plant.com, e)])
            assert _lp_extent(ctl.nozzles, w) >= 1.0  # the planned force and its moment fit
    assert not np.allclose(ctl.force_max, box.force_max)
    np.testing.assert_allclose(ctl.accel_max, np.minimum(NOMINAL.accel, 0.8 * ctl.force_max / 26))


def test_nozzle_forces_reproduce_the_wrench_in_mujoco(bare_world):
    """Applied at the nozzle positions, read back from qfrc_applied."""
    sim = SimDriver(bare_world, propulsion="nozzles")
    w, d = bare_world, sim.data
    mujoco.mj_forward(sim.model, d)
    force, torque = np.array([0.12, -0.05, 0.03]), np.array([0.004, -0.006, 0.01])
    alloc = sim.controller.nozzles.allocate(force, torque)
    assert alloc.scale == 1.0
    sim.apply_thrusts(alloc)
    rot = d.xmat[w.astrobee].reshape(3, 3)
    v = w.astrobee_dof
    np.testing.assert_allclose(d.qfrc_applied[v : v + 3], rot @ force, atol=1e-12)
    # a free joint's rotational dofs are in the body frame: the body torque about its CoM
    np.testing.assert_allclose(d.qfrc_applied[v + 3 : v + 6], torque, atol=1e-12)
    others = np.delete(d.qfrc_applied, np.arange(v, v + 6))
    assert not np.any(others) and not np.any(d.xfrc_applied)


def test_box_model_stays_available(bare_world):
    from payload.schema import VehicleTwist

    sim = SimDriver(bare_world, propulsion="box")
    sim.command_twist(VehicleTwist(np.array([0.1, 0, 0]), np.zeros(3), 0.0))
    sim.step(5)
    a = bare_world.astrobee
    assert np.any(sim.data.xfrc_applied[a]) and not np.any(sim.data.qfrc_applied)
    assert sim.controller.allocation is None
    nz = SimDriver(bare_world)
    nz.command_twist(VehicleTwist(np.array([0.1, 0, 0]), np.zeros(3), 0.0))
    state = nz.step(5)
    assert not np.any(nz.data.xfrc_applied) and np.any(nz.data.qfrc_applied)
    alloc = nz.controller.allocation
    np.testing.assert_allclose(state.wrench.force, alloc.force)


@pytest.mark.parametrize("kernel", ["missing", "rejects"])
def test_least_squares_falls_back_to_numpys_wrapper(monkeypatch, kernel):
    """Without numpy's kernel, or with one that refuses the call (another numpy), the
    facet least squares is numpy's own ``lstsq``: same solution and rank."""
    from payload.sim import lsq

    def refuse(*args, **kwargs):
        raise ValueError("signature")

    monkeypatch.setattr(lsq, "_GELSD", None if kernel == "missing" else refuse)
    rng = np.random.default_rng(11)
    for cols in (3, 6, 8):
        a = rng.normal(size=(6, cols))
        a[:, -1] = a[:, 0]  # rank-deficient: the cut-off matters
        b = rng.normal(size=6)
        for rcond in (None, -1.0):
            x, rank = _lstsq(a, b, rcond)
            want = np.linalg.lstsq(a, b, rcond=rcond)
            np.testing.assert_array_equal(x, want[0])
            assert rank == want[2] == min(6, cols - 1)


def test_one_propulsion_per_flight_mode_gives_a_fresh_ones_bits():
    """Controllers share their flight mode's Propulsion (bounds fitted once a process);
    its lazily filled tables do not depend on what was asked first: a fresh Propulsion
    asked the same wrenches in reverse order gives the same thrusts, bit for bit."""
    plant = MassProperties(12.0, np.array([0.0, 0.0, -0.05]), np.diag([0.2, 0.2, 0.15]))
    shared = shared_propulsion(NOMINAL.force)
    assert shared is shared_propulsion(tuple(NOMINAL.force))
    assert VehicleController(plant).nozzles is VehicleController(plant).nozzles is shared
    assert shared_propulsion(FLIGHT_MODES["difficult"].force) is not shared
    rng = np.random.default_rng(5)
    scale = np.array([0.3, 0.15, 0.15, 0.03, 0.03, 0.03])
    wrenches = [
        w * (shared.extent(w) * rng.uniform(0.3, 3.0)) for w in rng.normal(size=(80, 6)) * scale
    ]
    fresh = Propulsion(NOMINAL.force)
    theirs = {i: fresh.allocate(w[:3], w[3:]) for i, w in reversed(list(enumerate(wrenches)))}
    saturated = 0
    for i, w in enumerate(wrenches):
        mine = shared.allocate(w[:3], w[3:])
        assert mine.thrust.tobytes() == theirs[i].thrust.tobytes()
        assert mine.scale == theirs[i].scale
        saturated += mine.scale < 1.0
    assert 0 < saturated < len(wrenches)  # both the facet and the basis solutions ran


def test_the_kept_extents_are_bounded(monkeypatch, tmp_path):
    """Past its bound the cache file of a layout starts afresh: the answers stay the
    programme's."""
    import json

    from payload.sim import propulsion

    monkeypatch.setenv("PAYLOAD_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(propulsion._Extents, "_OPEN", {})
    monkeypatch.setattr(propulsion, "MAX_KEPT_EXTENTS", 3)
    solved: list[str] = []
    put = propulsion._Extents.put

    def counted(self, key, extent):
        solved.append(key)
        put(self, key, extent)

    monkeypatch.setattr(propulsion._Extents, "put", counted)
    p = Propulsion(NOMINAL.force)
    for axis in range(3, 6):  # programmes beyond the construction's own
        e = np.zeros(6)
        e[axis] = 1.0
        assert p.max_along(e) == pytest.approx(_lp_extent(p, e), rel=1e-9)
    (kept,) = tmp_path.glob("propulsion_extents_*.json")
    held = json.loads(kept.read_text())
    # three kept at most, then afresh: after n answers, the last (n - 1) % 3 + 1 of them
    n = len(solved)
    assert n > 3 and sorted(held) == sorted(solved[n - ((n - 1) % 3 + 1) :])


def test_later_searches_and_facet_solves_run_the_short_check_and_still_refuse(
    fresh_checks, monkeypatch
):
    """The allocation's compiled searches and facet solve are checked on all their probes
    the first time (400 wrenches; 300 random problems), then, once a stamp says a build of
    the same size passed, on the first tenth; a numpy answer that differs there still
    refuses the kernel."""
    from payload import native
    from payload.sim import allocation_c, facet_c
    from payload.sim.allocation import _facet_solve
    from payload.sim.nozzles import N_NOZZLES

    real = Propulsion._extent_numpy
    asked: list[int] = []
    lie_at: list[int | None] = [None]

    def extent(self, w):
        asked.append(1)
        lam, k = real(self, w)
        return (2.0 * lam + 1.0, k) if len(asked) == lie_at[0] else (lam, k)

    monkeypatch.setattr(Propulsion, "_extent_numpy", extent)

    def searches(lie=None):
        asked.clear()
        lie_at[0] = lie
        return Propulsion(FLIGHT_MODES["nominal"].force)._kernels, len(asked)

    first, n = searches()
    assert first is not None and n == allocation_c._PROBES == 400
    again, n = searches()
    assert again is not None and n == 400 // native.SHORT_SHARE
    assert searches(lie=n - 3) == (None, n - 3)

    def facet(lie=None):
        calls: list[int] = []

        def reference(*problem):
            calls.append(1)
            x = _facet_solve(*problem)
            return x + 1.0 if len(calls) == lie else x

        made = facet_c.compiled_facet_solve(reference, [], BVLS_TOL, N_NOZZLES, 6)
        return made, len(calls)

    kernel, n = facet()
    full = facet_c.RANDOM_PROBES
    assert kernel is not None and full / 3 < n <= full  # what it leaves to numpy is not asked
    short, m = facet()
    assert short is not None and full / 3 / native.SHORT_SHARE < m <= full / native.SHORT_SHARE
    assert facet(lie=m) == (None, m)
