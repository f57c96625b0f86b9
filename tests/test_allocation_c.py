"""The allocation's compiled searches give numpy's bits, and fall back when they cannot."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from payload import native
from payload.sim import allocation_c
from payload.sim.propulsion import Propulsion
from payload.sim.vehicle import FLIGHT_MODES


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
    for shape in ((3, 3), (6, 6), (1344, 6), (3024, 6)):
        for _ in range(20):
            a, x = rng.normal(size=shape), rng.normal(size=shape[1])
            y = np.empty(shape[0])
            dgemv(101, 111, shape[0], shape[1], 1.0, a.ctypes.data, shape[1], x.ctypes.data, 1,
                  0.0, y.ctypes.data, 1)  # fmt: skip
            assert y.tobytes() == (a @ x).tobytes()
            naive = np.array([sum(float(u) * float(v) for u, v in zip(row, x)) for row in a])
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
    with numpy's: the same thrusts, wrench and scale, bit for bit."""
    monkeypatch.setenv("PAYLOAD_NATIVE", "0")
    plain = Propulsion(tuple(prop.axis_force))
    assert plain._kernels is None
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


def test_a_kernel_with_other_bits_is_refused(monkeypatch, tmp_path, caplog):
    """The self-check compares the built kernels with numpy on probe wrenches: a kernel
    summing its rows right to left (the same sums in exact arithmetic) is refused and
    numpy's code runs."""
    monkeypatch.setenv("PAYLOAD_CACHE_DIR", str(tmp_path))
    right_to_left = allocation_c.SOURCE.replace(
        "double a = r[0];\n    for (int i = 1; i < NB; i++) a += r[i];",
        "double a = r[NB - 1];\n    for (int i = NB - 2; i >= 0; i--) a += r[i];",
    )
    assert right_to_left != allocation_c.SOURCE
    monkeypatch.setattr(allocation_c, "SOURCE", right_to_left)
    p = Propulsion(FLIGHT_MODES["nominal"].force)
    with caplog.at_level("WARNING", logger="payload.sim.allocation_c"):
        assert p._kernels is None
    assert "differ" in caplog.text
    w = np.array([0.1, 0.05, -0.02, 0.001, 0.0, -0.002])
    assert p.allocate(w[:3], w[3:]).scale == 1.0  # numpy's searches answer


def test_without_a_compiler_numpy_searches(monkeypatch, tmp_path):
    monkeypatch.setenv("PAYLOAD_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(native, "find_compiler", lambda: None)
    p = Propulsion(FLIGHT_MODES["nominal"].force)
    assert p._kernels is None
    assert not list(tmp_path.glob("allocation_*.so"))
    w = np.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert p.extent(w) == p._extent_numpy(w)[0]


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
