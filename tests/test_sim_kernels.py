"""The simulator's compiled kernels (the allocation's searches, the controller's step, the
thrusts, the station bound) give numpy's bits, and fall back when they cannot."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from payload import native
from payload.sim import allocation_c, vehicle_c
from payload.sim.propulsion import BVLS_TOL, Propulsion
from payload.sim.vehicle import FLIGHT_MODES, MassProperties, VehicleController


@pytest.fixture(scope="module")
def bare_driver():
    from payload.sim import SimDriver, WorldConfig

    with SimDriver(WorldConfig(ctb=None)) as d:
        yield d


@pytest.fixture(scope="module", params=sorted(FLIGHT_MODES))
def prop(request) -> Propulsion:
    return Propulsion(FLIGHT_MODES[request.param].force)


def _branch(p: Propulsion, w: np.ndarray) -> str:
    """Which way numpy's least-thrust search ends for ``w``, worked out here from the
    tables: the unbounded optimum, a dual-feasible candidate, or none."""
    t0 = (p._stacked_inverses @ w).reshape(-1, 6)
    ok = (t0 >= -p._least_tol).all(axis=1)
    if ok.any():
        k = np.flatnonzero(ok)[np.argmin(t0[ok].sum(axis=1))]
        if (t0[k] <= p._basis_bounds[k] + p._least_tol).all():
            return "unbounded optimum"
    return "candidate" if p._least_thrust_numpy(w) is not None else "none"


def test_numpys_dgemv_is_what_matmul_runs():
    """numpy's bundled CBLAS dgemv, called as matmul calls it, gives matmul's bits; a
    left-to-right sum of the products does not (so the kernels must call it)."""
    address = native.numpy_dgemv()
    assert address is not None  # numpy's PyPI wheels bundle OpenBLAS
    i64, ptr = ctypes.c_int64, ctypes.c_void_p
    dgemv = ctypes.CFUNCTYPE(
        None, ctypes.c_int, ctypes.c_int, i64, i64, ctypes.c_double, ptr, i64, ptr, i64,
        ctypes.c_double, ptr, i64,
    )(address)  # fmt: skip
    rng = np.random.default_rng(11)
    naive_differs = 0
    for shape in ((3, 3), (6, 6), (6, 12), (1344, 6), (3024, 6)):
        for order in "CF":  # row-major, and column-major (the nozzle matrix's layout)
            for _ in range(20):
                a = np.asarray(rng.normal(size=shape), order=order)
                x = rng.normal(size=shape[1])
                cblas, ld = native.gemv_layout(a)
                y = np.empty(shape[0])
                dgemv(cblas, native.CBLAS_NO_TRANS, shape[0], shape[1], 1.0, a.ctypes.data, ld,
                      x.ctypes.data, 1, 0.0, y.ctypes.data, 1)  # fmt: skip
                assert y.tobytes() == (a @ x).tobytes()
                naive = np.array([sum(float(u) * float(v) for u, v in zip(r, x)) for r in a])
                naive_differs += int((naive != a @ x).sum())
    assert naive_differs > 0


def test_the_compiled_searches_give_numpys_bits(prop):
    kernels = prop._kernels
    assert kernels is not None  # a compiler and numpy's OpenBLAS are here
    seen: dict[str, int] = {}
    wrenches = allocation_c.probe_wrenches(prop, 3000, seed=123)
    for w in wrenches:
        lam, k = kernels.extent(w)
        want_lam, want_k = prop._extent_numpy(w)
        assert k == want_k and np.float64(lam).tobytes() == np.float64(want_lam).tobytes()
        got, want = kernels.least_thrust(w), prop._least_thrust_numpy(w)
        if want is None:
            assert got is None
        else:
            assert got.tobytes() == want.tobytes()  # the sign of zero included
        branch = _branch(prop, w)
        seen[branch] = seen.get(branch, 0) + 1
    # every way the search can end was taken, and zero has no facet
    assert set(seen) == {"unbounded optimum", "candidate", "none"}, seen
    assert kernels.extent(np.zeros(6)) == prop._extent_numpy(np.zeros(6)) == (np.inf, -1)


def test_allocations_with_and_without_the_kernels_are_the_same(prop, monkeypatch):
    """The whole allocation (facet, basis and LP paths) with the compiled searches and
    facet solve and with numpy's: the same thrusts, wrench and scale, bit for bit."""
    assert prop._kernels is not None and prop._facet_kernel is not None  # built before:
    monkeypatch.setenv("PAYLOAD_NATIVE", "0")
    plain = Propulsion(tuple(prop.axis_force))
    assert plain._kernels is None and plain._facet_kernel is None
    rng = np.random.default_rng(4)
    scale = np.array([0.3, 0.15, 0.15, 0.03, 0.03, 0.03])
    saturated = 0
    for d in rng.normal(size=(300, 6)) * scale:
        w = d * (prop.extent(d) * rng.uniform(0.3, 2.0))
        mine, theirs = prop.allocate(w[:3], w[3:]), plain.allocate(w[:3], w[3:])
        assert mine.thrust.tobytes() == theirs.thrust.tobytes()
        assert mine.force.tobytes() == theirs.force.tobytes()
        assert mine.torque.tobytes() == theirs.torque.tobytes()
        assert mine.scale == theirs.scale
        saturated += mine.scale < 1.0
    assert 0 < saturated < 300


def test_a_kernel_with_other_bits_is_refused(refused_kernel):
    """The self-check compares the built kernels with numpy on probe wrenches: a kernel
    summing its rows right to left (the same sums in exact arithmetic) is refused and
    numpy's code runs."""
    p = Propulsion(FLIGHT_MODES["nominal"].force)
    with refused_kernel(
        allocation_c,
        "double a = r[0];\n    for (int i = 1; i < NB; i++) a += r[i];",
        "double a = r[NB - 1];\n    for (int i = NB - 2; i >= 0; i--) a += r[i];",
    ):
        assert p._kernels is None
    w = np.array([0.1, 0.05, -0.02, 0.001, 0.0, -0.002])
    assert p.allocate(w[:3], w[3:]).scale == 1.0  # numpy's searches answer


def test_the_compiled_facet_solve_is_numpys_lstsq_and_scipys_bvls(prop):
    """The facet solve in C against numpy's ``lstsq`` and SciPy's own BVLS
    (``lsq_linear(method="bvls")``, started as ``lsq_linear`` starts it), bit for bit, on
    problems shaped like the facets' in both memory orders, many of them bounded."""
    from scipy.optimize import lsq_linear

    kernel = prop._facet_kernel
    assert kernel is not None
    rng = np.random.default_rng(21)
    bounded = fortran = 0
    for i in range(400):
        n = int(rng.integers(2, 13))
        a = rng.normal(size=(6, n))
        if i % 5 == 2:
            a[:, -1] = a[:, 0]  # coplanar nozzles: rank-deficient
        if i % 2:
            a = np.asfortranarray(a)
            fortran += 1
        ub = rng.uniform(0.1, 1.0, size=n)
        rest = a @ rng.uniform(-0.6, 1.6, size=n)
        want, _, rank, _ = np.linalg.lstsq(a, rest, rcond=None)
        # BVLS starts from this solution when rcond=-1 (lsq_linear's) finds the same rank
        got = kernel(a, rest, ub, 1e-7, rank == np.linalg.lstsq(a, rest, rcond=-1)[2])
        if (want < -1e-7).any() or (want > ub + 1e-7).any():
            want = lsq_linear(a, rest, bounds=(np.zeros(n), ub), method="bvls", tol=BVLS_TOL).x
            bounded += 1
        assert got is not None and got.tobytes() == want.tobytes(), i
    assert bounded > 150 and fortran == 200


def test_a_facet_solve_with_other_bits_is_refused(refused_kernel):
    """A step length computed as a product with the reciprocal (the same in exact
    arithmetic) is refused by the self-check, and numpy's facet solve answers."""
    from payload.sim import facet_c

    p = Propulsion(FLIGHT_MODES["nominal"].force)
    compiled = Propulsion(FLIGHT_MODES["nominal"].force)
    assert compiled._facet_kernel is not None  # the real C, built before the change
    with refused_kernel(
        facet_c,
        "alphas[k] = (bound - xf[j]) / (z[j] - xf[j]);",
        "alphas[k] = (bound - xf[j]) * (1.0 / (z[j] - xf[j]));",
    ):
        assert p._facet_kernel is None
    w = np.array([0.5, 0.4, -0.3, 0.02, 0.01, -0.02])
    a, b = p.allocate(w[:3], w[3:]), compiled.allocate(w[:3], w[3:])
    assert a.scale < 1.0 and a.thrust.tobytes() == b.thrust.tobytes()  # numpy's solve, saturated


def test_a_problem_the_facet_kernel_cannot_take_goes_to_numpy(prop):
    """One column (numpy multiplies it by a scalar, not with dgemv) or a wrong dtype: the
    kernel answers None (so that ``_on_facet`` runs the numpy solve)."""
    kernel = prop._facet_kernel
    a, rest, ub = np.ones((6, 1)), np.ones(6), np.ones(1)
    assert kernel(a, rest, ub, 1e-7, True) is None
    assert kernel(np.ones((6, 3), dtype=np.float32), rest, np.ones(3), 1e-7, True) is None


def test_without_a_compiler_numpy_searches(monkeypatch, tmp_path):
    with_kernels = Propulsion(FLIGHT_MODES["nominal"].force)
    assert with_kernels._kernels is not None
    monkeypatch.setenv("PAYLOAD_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(native, "find_compiler", lambda: None)
    p = Propulsion(FLIGHT_MODES["nominal"].force)
    assert p._kernels is None
    assert not list(tmp_path.glob("allocation_*.so"))
    w = np.array([0.2, 0.05, 0.0, 0.0, 0.0, 0.01])
    assert p.extent(w) == with_kernels.extent(w)
    assert (
        p.allocate(w[:3], w[3:]).thrust.tobytes()
        == with_kernels.allocate(w[:3], w[3:]).thrust.tobytes()
    )
    with pytest.raises(ValueError):  # a wrench of another shape: numpy's error, as before
        with_kernels.extent(np.ones(3))


def test_a_failing_compiler_falls_back_to_numpy(monkeypatch, tmp_path, caplog):
    monkeypatch.setenv("PAYLOAD_CACHE_DIR", str(tmp_path))
    cc = tmp_path / "bad-cc"
    cc.write_text("#!/bin/sh\necho 'allocation.c:1: error: no' >&2\nexit 1\n")
    cc.chmod(0o755)
    monkeypatch.setattr(native, "find_compiler", lambda: str(cc))
    p = Propulsion(FLIGHT_MODES["nominal"].force)
    with caplog.at_level("WARNING", logger="payload.sim.allocation_c"):
        assert p._kernels is None
    assert "compiling the allocation kernels failed" in caplog.text
    assert list(tmp_path.glob("allocation_*.log"))  # the compiler's words are kept


# -- the controller's step and the thrusts -------------------------------------------------------
def _plants() -> list[MassProperties]:
    """Astrobee alone (centred) and with a bag off-centre (inertia not diagonal)."""
    rng = np.random.default_rng(8)
    a = rng.normal(size=(3, 3))
    return [
        MassProperties(10.0, np.zeros(3), np.diag([0.16, 0.15, 0.16])),
        MassProperties(
            15.3, np.array([0.03, -0.05, 0.21]), np.diag([0.5, 0.6, 0.4]) + 0.01 * a @ a.T
        ),
    ]


@pytest.mark.parametrize("mode", sorted(FLIGHT_MODES))
@pytest.mark.parametrize("plant", range(2))
def test_the_compiled_control_step_gives_numpys_bits(mode, plant):
    """2,000 control steps from the same states through numpy's code (its allocation's
    searches in numpy too) and the kernel: the same wrench, thrusts, scale and profile
    state in every bit, with every outcome of the step taken (allocated, zero wrench,
    saturated on a facet)."""
    from payload.schema import VehicleTwist

    ctl = VehicleController(_plants()[plant], mode)
    kernel = ctl._kernel
    assert kernel is not None
    codes: list[int] = []
    step = kernel._step
    kernel._step = lambda dt: codes.append(step(dt)) or codes[-1]
    rng = np.random.default_rng(21)
    prof = ctl.profile
    command = VehicleTwist.zero()
    lin, ang = np.zeros(3), np.zeros(3)
    for i in range(2000):
        if i % 100 == 0:  # rest, moving, turning, beyond the mode's limits
            scale = (0.0, 0.3, 1.0, 3.0)[(i // 100) % 4]
            command = VehicleTwist(
                rng.normal(size=3) * ctl.mode.speed * scale,
                rng.normal(size=3) * ctl.mode.omega * scale * (i % 300 != 0),
                0.0,
            )
        start = (prof.velocity.copy(), prof.acceleration.copy())
        cache = ctl.nozzles.__dict__
        searches, cache["_kernels"] = cache["_kernels"], None  # the reference: numpy throughout
        try:
            want = ctl._update_numpy(command, lin, ang, 0.02)
        finally:
            ctl.nozzles.__dict__["_kernels"] = searches
        want_alloc, want_state = ctl.allocation, (prof.velocity, prof.acceleration)
        prof.velocity, prof.acceleration = start[0].copy(), start[1].copy()
        got = ctl.update(command, lin, ang, 0.02)
        assert got.force.tobytes() == want.force.tobytes(), i
        assert got.torque.tobytes() == want.torque.tobytes(), i
        assert ctl.allocation.thrust.tobytes() == want_alloc.thrust.tobytes(), i
        assert ctl.allocation.scale == want_alloc.scale, i
        assert prof.velocity.tobytes() == want_state[0].tobytes(), i
        assert prof.acceleration.tobytes() == want_state[1].tobytes(), i
        # the measured twist lags the reference (a vehicle that follows it, with noise),
        # and now and then is knocked far off it (the feedback saturates the nozzles)
        knock = 0.1 if 150 <= i % 300 < 170 else 2e-4
        lin = prof.velocity[:3] * 0.97 + rng.normal(scale=knock, size=3) * (i % 300 > 20)
        ang = prof.velocity[3:] * 0.97 + rng.normal(scale=knock, size=3) * (i % 300 > 20)
    assert {0, 1, 2} <= set(codes), sorted(set(codes))


def test_the_control_kernel_follows_a_reset_and_refuses_a_bad_wrench():
    from payload.schema import VehicleTwist
    from payload.sim.propulsion import PropulsionError

    ctl = VehicleController(_plants()[1])
    twin = VehicleController(_plants()[1])
    assert ctl._kernel is not None and twin._kernel is not None
    command = VehicleTwist(np.array([0.1, 0.0, 0.02]), np.array([0.0, 0.0, 0.05]), 0.0)
    for c in (ctl, twin):
        c.reset(np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, 0.01]))
    for i in range(50):
        v = np.array([0.01 + 1e-4 * i, 0.0, 0.0])
        w = np.array([0.0, 0.0, 0.01])
        a = ctl.update(command, v, w, 0.02)
        b = twin._update_numpy(command, v, w, 0.02)
        assert a.force.tobytes() == b.force.tobytes() and a.torque.tobytes() == b.torque.tobytes()
    with pytest.raises(PropulsionError, match="finite"):
        ctl.update(command, np.array([np.nan, 0.0, 0.0]), np.zeros(3), 0.02)


def test_a_control_kernel_with_other_bits_is_refused(refused_kernel):
    """The control step's self-check: a kernel that adds the force's terms in another
    order (the same sum in exact arithmetic) is refused, and numpy's code runs."""
    ctl = VehicleController(_plants()[1])
    with refused_kernel(
        vehicle_c,
        "c->mass * ((acc[i] + c->gain_lin * (ref[i] - v[i])) + cwv[i])",
        "c->mass * (acc[i] + (c->gain_lin * (ref[i] - v[i]) + cwv[i]))",
        attr="CONTROL_SOURCE",
        says="compiled step differs",
    ):
        assert ctl._kernel is None


def test_the_compiled_thrusts_are_mujocos(bare_driver):
    """The thrusts' generalised forces through the kernel and through the numpy loop of
    ``mj_applyFT`` calls, in a moving, rotated state: the same bits; a reset (new data)
    gets a kernel of its own."""
    d = bare_driver
    from payload.schema import VehicleTwist

    d.command_twist(VehicleTwist(np.array([0.05, 0.02, 0.0]), np.array([0.0, 0.0, 0.1]), 0.0))
    d.step(30)
    kernel = d._thrust_kernel
    assert kernel is not None and kernel.data is d.data
    rng = np.random.default_rng(6)
    bounds = d.controller.nozzles.thrust_max
    for _ in range(200):
        thrust = rng.uniform(0.0, 1.0, size=12) * bounds * (rng.random(12) < 0.5)
        mine, theirs = np.zeros(d.model.nv), np.zeros(d.model.nv)
        kernel(thrust, mine)
        d._apply_thrusts_numpy(thrust, theirs)
        assert mine.tobytes() == theirs.tobytes()
        assert np.any(mine != 0.0) == bool(np.any(thrust > 0.0))
    old = d.data
    d.reset()
    assert d.data is not old and d._thrust_kernel is not kernel
    assert d._thrust_kernel.data is d.data


# -- the world and payload read-out ---------------------------------------------------------------
def test_the_compiled_read_out_is_numpys_and_mujocos():
    """Along a flight with the CTB held: the read-out kernel's world state and payload
    state have numpy's bits, and the body-frame velocity is MuJoCo's own
    (``mj_objectVelocity`` in the body frame, a different computation: to rounding)."""
    import mujoco

    from payload.schema import VehicleTwist
    from payload.sim import SimDriver, WorldConfig

    with SimDriver() as d:
        kernel = d._readout
        assert kernel is not None and kernel.data is d.data
        d.command_twist(VehicleTwist(np.array([0.04, -0.02, 0.01]), np.array([0.0, 0.0, 0.2]), 0.0))
        vel = np.zeros(6)
        for _ in range(60):
            d.step(1)
            mujoco.mj_forward(d.model, d.data)  # the rotation and MuJoCo's cvel of this qpos
            mine, theirs = d._world_state_kernel(kernel), d._world_state_numpy()
            for a, b in zip(mine[:7], theirs[:7]):
                assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
            assert mine[7:10] == theirs[7:10] and mine.time == theirs.time
            for a, b in zip(mine.wrench, theirs.wrench):  # the wrench held, each its own copy
                assert a.tobytes() == b.tobytes() and a is not b
            a, b = d._read_kernel(kernel), d._read_numpy()
            for x, y in ((a.q, b.q), (a.dq, b.dq), (a.effort, b.effort)):
                assert x.tobytes() == y.tobytes()
            assert (a.deploy, a.stamp, a.health) == (b.deploy, b.stamp, b.health)
            body = d.world.astrobee
            mujoco.mj_objectVelocity(d.model, d.data, mujoco.mjtObj.mjOBJ_BODY, body, vel, 1)
            np.testing.assert_allclose(mine.astrobee_linear, vel[3:], rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(mine.astrobee_angular, vel[:3], rtol=1e-9, atol=1e-12)
        assert np.linalg.norm(mine.astrobee_angular) > 1e-3  # it turned
    # the read-out's layout is WorldState's fields after the time, in order (the driver
    # builds the state from it by position)
    from payload.sim.driver import WorldState
    from payload.sim.readout_c import WORLD_LAYOUT

    assert WorldState._fields[1 : 1 + len(WORLD_LAYOUT)] == tuple(n for n, _ in WORLD_LAYOUT)
    with SimDriver(WorldConfig(ctb=None)) as bare:  # no CTB: its fields are None either way
        bare.step(3)
        assert bare._readout is not None  # the kernel's world state, against numpy's
        mine, theirs = bare.world_state(), bare._world_state_numpy()
        assert mine.ctb_pos is None and mine.ctb_quat is None and theirs.ctb_pos is None
        for a, b in zip(mine[:5], theirs[:5]):
            assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
        assert mine[7:10] == theirs[7:10]


def test_the_read_out_flags_a_limit_and_an_overload(bare_driver):
    """A coordinate placed at the end of its control range reads LIMIT, an actuator force
    at the world's force limit OVERLOAD (the thresholds from the model, not the driver)."""
    from payload.schema import Health

    d = bare_driver
    assert d._readout is not None
    w, data = d.world, d.data
    saved = data.qpos.copy(), data.actuator_force.copy()
    try:
        assert not d.read().health & Health.LIMIT
        data.qpos[w.qpos[3]] = d.model.actuator_ctrlrange[w.ctrl[3], 1]
        assert d.read().health == Health.LIMIT
        data.actuator_force[w.ctrl[5]] = -w.force_limit[5]  # the 18 actuators' bounds
        assert d.read().health == Health.LIMIT | Health.OVERLOAD
    finally:
        data.qpos[:], data.actuator_force[:] = saved


def test_a_read_out_with_other_bits_is_refused(bare_driver, refused_kernel):
    """A read-out that turns the velocity into the body frame with the rotation itself
    instead of its transpose is refused by the self-check; numpy reads the world."""
    import mujoco

    from payload.sim import readout_c

    built = bare_driver.__dict__.pop("_readouts", None)  # the shared driver's, put back
    try:
        with refused_kernel(
            readout_c,
            "r->gemv(COL_MAJOR, NO_TRANS, 3, 3, 1.0, r->xmat, 3, v, 1, 0.0, out + OFF_LINEAR, 1);",
            "r->gemv(ROW_MAJOR, NO_TRANS, 3, 3, 1.0, r->xmat, 3, v, 1, 0.0, out + OFF_LINEAR, 1);",
        ):
            assert bare_driver._readout is None
        # numpy reads the world: the body-frame velocity is MuJoCo's own, to rounding
        d, w = bare_driver, bare_driver.world
        saved = d.data.qvel.copy()
        d.data.qvel[w.astrobee_dof : w.astrobee_dof + 6] = [0.01, -0.02, 0.03, 0.1, 0.0, -0.05]
        mujoco.mj_forward(d.model, d.data)
        vel = np.zeros(6)
        mujoco.mj_objectVelocity(d.model, d.data, mujoco.mjtObj.mjOBJ_BODY, w.astrobee, vel, 1)
        state = d.world_state()
        np.testing.assert_allclose(state.astrobee_linear, vel[3:], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(state.astrobee_angular, vel[:3], rtol=1e-9, atol=1e-12)
        d.data.qvel[:] = saved
        mujoco.mj_forward(d.model, d.data)
    finally:
        bare_driver.__dict__.pop("_readouts", None)
        if built is not None:
            bare_driver.__dict__["_readouts"] = built


# -- the contact list's readers -----------------------------------------------------------------
def _touching_ctb():
    """A driver whose CTB is moved onto finger A's pad: contacts in the list."""
    import mujoco

    from payload.sim import SimDriver

    d = SimDriver()
    w = d.world
    pad = d.data.geom_xpos[w.pad_geoms["A"]].copy()
    d.data.qpos[w.ctb_qpos : w.ctb_qpos + 3] = pad
    mujoco.mj_forward(d.model, d.data)
    assert d.data.ncon > 0
    return d


def test_the_compiled_contact_readers_are_numpys_and_a_plain_loops():
    """On a contact list rewritten with random pairs and distances (zeros of both signs,
    NaN, flex ids): the compiled readers, the numpy ones and a plain loop over MuJoCo's
    contact structs through the bindings give the same fingers and station contact."""
    from payload.design import FINGERS
    from payload.sim import contacts_c
    from payload.sim.station import StationMonitor

    with _touching_ctb() as d:
        monitor, station = d.monitor, StationMonitor(d.world)
        fingers = monitor._touching_kernel(d.data)
        walls = station._contact_kernel(d.data)
        assert fingers is not None and walls is not None
        n = d.model.ngeom
        geoms = np.concatenate([np.arange(n), [-1]])
        seen = set()
        for _ in contacts_c._rewritten_contacts(d.data, np.random.default_rng(5), geoms, 300):
            bits, hit = 0, False
            for i in range(d.data.ncon):  # the plain loop: one struct at a time
                c = d.data.contact[i]
                a, b = (int(g) % n for g in c.geom)
                if c.dist <= 0.0 and monitor._pair_finger[a, b] >= 0:
                    bits |= 1 << int(monitor._pair_finger[a, b])
                a, b = int(c.geom1) % n, int(c.geom2) % n
                st, mv = station._is_station, station._is_moving
                hit |= bool((st[a] and mv[b]) or (st[b] and mv[a])) and c.dist <= 0.0
            assert fingers(d.data) == monitor._touching_bits(d.data) == bits
            assert walls(d.data) == station._contact_numpy(d.data) == hit
            assert monitor.touching(d.data) == {f for k, f in enumerate(FINGERS) if bits >> k & 1}
            seen.add((bits > 0, hit))
        assert {b for b, _ in seen} == {h for _, h in seen} == {False, True}  # both answers


def test_a_contact_reader_with_other_answers_is_refused(refused_kernel):
    """A fingertip reader that counts only penetrating contacts (dist < 0, not <= 0)
    answers otherwise on the self-check's zero distances: refused, numpy reads them."""
    from payload.sim import contacts_c

    with (
        _touching_ctb() as d,
        refused_kernel(
            contacts_c, "if (!(c->dist <= 0.0)) continue;", "if (!(c->dist < 0.0)) continue;"
        ),
    ):
        assert d.monitor._touching_kernel(d.data) is None
        w, pads = d.world, set()  # the pads in the contact list, one struct at a time
        for i in range(d.data.ncon):
            c = d.data.contact[i]
            for a, b in (c.geom, c.geom[::-1]):
                pads |= {f for f in w.pad_geoms if a == w.pad_geoms[f] and b in w.ctb_geoms
                         and c.dist <= 0.0}  # fmt: skip
        assert pads and d.world_state().touching == pads  # numpy's reader


# -- the station clearance's quick bound ----------------------------------------------------------
def _moved(driver, rng, scale: float) -> None:
    """The vehicle somewhere in the station, now and then near a wall."""
    import mujoco

    d, a = driver.data, driver.world.astrobee_qpos
    d.qpos[a : a + 3] = d.qpos[a : a + 3] + rng.normal(scale=scale, size=3)
    mujoco.mj_forward(driver.model, d)


def test_the_compiled_station_bound_answers_as_numpy(bare_driver):
    from payload.sim.station import StationMonitor

    d = bare_driver
    monitor = StationMonitor(d.world)
    monitor.read(d.data)
    kernel = monitor._bound_kernel(d.data)
    assert kernel is not None and kernel.data is d.data
    rng = np.random.default_rng(12)
    saved = d.data.qpos.copy()
    answers = set()
    try:
        for k in range(300):
            _moved(d, rng, 0.8 if k % 2 else 3.0)
            if k % 50 == 3:
                d.data.geom_xpos[monitor.moving[0], 1] = np.nan
            near = kernel.near()
            assert near == monitor._near_numpy(d.data)
            answers.add(near)
    finally:
        d.data.qpos[:] = saved
    assert answers == {True, False}


def test_a_station_bound_with_other_answers_is_refused(bare_driver, refused_kernel):
    """A bound 5 cm short of the cap on one side answers otherwise on some of the
    self-check's poses: refused, and the numpy test runs."""
    from payload.sim import station_c

    _refused_station(bare_driver, refused_kernel, station_c, "< cap) & (lo[i]",
                     "< cap - 0.05) & (lo[i]", "differs")  # fmt: skip


def _refused_station(driver, refused_kernel, module, old: str, new: str, says: str) -> None:
    """A station monitor on ``driver`` reads with the station kernel's C changed: refused."""
    from payload.sim.station import StationMonitor

    monitor = StationMonitor(driver.world)
    with refused_kernel(module, old, new, says=says):
        monitor.read(driver.data)
        assert monitor._bound_kernel(driver.data) is None


def test_the_compiled_clearance_is_numpys(bare_driver):
    """Near the walls, the clearance through the kernel (the moving boxes as numpy's einsum
    sums them, MuJoCo's own mj_geomDistance) and through numpy: the same bits, boxes
    included, at poses where it measures something."""
    import mujoco

    from payload.sim.station import CLEARANCE_CAP, StationMonitor, _world_aabb

    d = bare_driver
    monitor = StationMonitor(d.world)
    monitor.read(d.data)
    kernel = monitor._bound_kernel(d.data)
    assert kernel is not None and kernel.clearance() is not None
    rng = np.random.default_rng(13)
    saved = d.data.qpos.copy()
    zones = [z for z in d.world.layout.zones() if z.module.name != "VESTIBULE"]
    a = d.world.astrobee_qpos
    measured = 0
    try:
        for k in range(300):
            # anywhere in a module, turned any way: near a wall now and then
            zone = zones[k % len(zones)]
            d.data.qpos[a : a + 3] = rng.uniform(zone.lo, zone.hi)
            q = rng.normal(size=4)
            d.data.qpos[a + 3 : a + 7] = q / np.linalg.norm(q)
            mujoco.mj_forward(d.model, d.data)
            if not kernel.near():
                continue
            mine, theirs = kernel.clearance(), monitor._clearance_numpy(d.data)
            assert np.float64(mine).tobytes() == np.float64(theirs).tobytes()
            lo, hi = _world_aabb(d.model, d.data, monitor.moving)
            assert lo.tobytes() == kernel.boxes[0].tobytes()
            assert hi.tobytes() == kernel.boxes[1].tobytes()
            assert monitor.read(d.data).clearance == theirs
            measured += mine < CLEARANCE_CAP
    finally:
        d.data.qpos[:] = saved
    assert measured > 10


def test_a_clearance_with_other_boxes_is_refused(bare_driver, refused_kernel):
    """The boxes' half-sizes summed left to right (the same in exact arithmetic, not
    numpy's einsum order here) are refused, and numpy reads the clearance."""
    from payload.sim import station_c

    _refused_station(
        bare_driver,
        refused_kernel,
        station_c,
        "(fabs(ri[0]) * h[0] + fabs(ri[2]) * h[2]) + fabs(ri[1]) * h[1]",
        "(fabs(ri[0]) * h[0] + fabs(ri[1]) * h[1]) + fabs(ri[2]) * h[2]",
        "clearance differs",
    )


def test_a_second_station_bound_runs_the_short_check_and_it_still_refuses(
    bare_driver, fresh_checks
):
    """The first build in a process asks the numpy test on all 400 probe poses; a build of
    the same shape after it (a campaign's next trial) on the first 40, and is refused when
    the numpy test answers otherwise on one of them; another shape is checked in full."""
    from payload.sim import station_c
    from payload.sim.station import CLEARANCE_CAP, StationMonitor, _world_aabb

    d = bare_driver
    monitor = StationMonitor(d.world)
    monitor.read(d.data)
    s_lo, s_hi = monitor._station_box
    native._CHECKED.clear()  # the read's own check forgotten: no kernel checked yet
    for stamp in fresh_checks.iterdir():
        stamp.unlink()

    def build(moving, lie_at=None):  # the monitor's own arguments for its kernel
        asked = []

        def reference():
            asked.append(1)
            answer = monitor._near_numpy(d.data)
            return (not answer) if len(asked) == lie_at else answer

        kernel = station_c.compiled_station_bound(
            d.data, moving, monitor._reach, s_lo, s_hi, CLEARANCE_CAP, reference,
            model=d.model, station=monitor.station,
            clearance=lambda: monitor._clearance_numpy(d.data),
            boxes=lambda: _world_aabb(d.model, d.data, moving),
        )  # fmt: skip
        return kernel, len(asked)

    first, asked = build(monitor.moving)
    assert first is not None and asked == 400
    again, asked = build(monitor.moving)
    assert again is not None and asked == 40
    assert build(monitor.moving, lie_at=37) == (None, 37)
    # another shape (a geom less), checked in full
    monitor.moving, monitor._reach = monitor.moving[:-1], monitor._reach[:-1]
    kernel, asked = build(monitor.moving)
    assert kernel is not None and asked == 400


def test_without_mujocos_distance_the_bound_alone_is_compiled(bare_driver, monkeypatch, tmp_path):
    """Without MuJoCo's mj_geomDistance symbol (no /proc/self/maps, say), the quick bound
    is still compiled and numpy reads the clearance near a wall."""
    from payload.sim.station import StationMonitor

    real = native.mujoco_function
    monkeypatch.setattr(
        native, "mujoco_function", lambda name: None if name == "mj_geomDistance" else real(name)
    )
    monitor = StationMonitor(bare_driver.world)
    monitor.read(bare_driver.data)
    kernel = monitor._bound_kernel(bare_driver.data)
    assert kernel is not None and kernel.clearance() is None
