"""payload.vecmath gives numpy's results to the last bit (the loops rely on it to keep
trials bit-identical), and the per-axis jerk-limited profile matches the array form."""

from __future__ import annotations

import numpy as np

from payload.vecmath import add_reduce, all_finite, clip, cross, norm


def test_norm_and_cross_are_numpys_to_the_bit() -> None:
    rng = np.random.default_rng(0)
    for _ in range(2000):
        scale = 10.0 ** rng.uniform(-12, 6)
        a, b = rng.normal(size=3) * scale, rng.normal(size=3)
        assert norm(a) == np.linalg.norm(a)
        assert np.array_equal(cross(a, b), np.cross(a, b))
    m = rng.normal(size=(25, 3))
    assert norm(m[:, 1]) == np.linalg.norm(m[:, 1])  # strided
    assert norm(m) == np.linalg.norm(m)  # flattened, as numpy does
    assert norm(np.array([3, 4])) == 5.0 == np.linalg.norm(np.array([3, 4]))
    f32 = rng.normal(size=3).astype(np.float32)
    assert norm(f32) == float(np.linalg.norm(f32))


def test_clip_and_the_reductions_are_numpys_to_the_bit() -> None:
    """``clip`` against ``np.clip`` and ``add_reduce`` against ``ndarray.sum`` on values
    with signed zeros, NaN, infinities and bounds equal to the values; as arrays and
    floats, array and scalar bounds."""
    rng = np.random.default_rng(1)
    special = np.array([0.0, -0.0, np.nan, np.inf, -np.inf, 1.0, -1.0, 0.5])
    for _ in range(300):
        x = np.concatenate([rng.normal(size=9), rng.choice(special, size=7)])
        lo = np.concatenate([rng.normal(size=9) - 1.0, rng.choice(special, size=7)])
        hi = lo + np.abs(rng.normal(size=16))
        for args in ((x, lo, hi), (x, -0.5, 0.5), (x, 0.0, -0.0), (x, -0.0, 0.0)):
            assert clip(*args).tobytes() == np.clip(*args).tobytes()
        for v in x.tolist():
            assert np.float64(clip(v, -0.0, 0.5)).tobytes() == np.clip(v, -0.0, 0.5).tobytes()
        with np.errstate(invalid="ignore", over="ignore"):  # inf - inf; an overflowing sum
            for part in (x[:9], x, x[::2], rng.normal(size=200) * 1e300):
                assert np.float64(add_reduce(part)).tobytes() == np.float64(part.sum()).tobytes()


def test_all_finite_is_numpys_isfinite_all() -> None:
    """The finite-sum shortcut against ``np.isfinite(a).all()``: NaN, infinities of both
    signs, both together (their sum is NaN), and finite values whose sum overflows."""
    rng = np.random.default_rng(3)
    cases = [rng.normal(size=17), rng.normal(size=(25, 3)), np.full(4, 1e308), np.zeros(0)]
    for bad in (np.nan, np.inf, -np.inf):
        for a in (rng.normal(size=17), rng.normal(size=(25, 3))):
            a.flat[int(rng.integers(a.size))] = bad
            cases.append(a)
    both = rng.normal(size=9)
    both[2], both[5] = np.inf, -np.inf
    cases.append(both)
    with np.errstate(invalid="ignore", over="ignore"):
        for a in cases:
            assert all_finite(a) == bool(np.isfinite(a).all())


def _profile_step_arrays(profile, target: np.ndarray, dt: float):
    """The array form of JerkLimitedProfile.step (before it ran on floats)."""
    j, a_max = profile.jerk, profile.accel
    e = target - profile.velocity
    s = np.where(e >= 0.0, 1.0, -1.0)
    a = s * profile.acceleration
    dist = np.abs(e)
    quad = 1.0 / (2.0 * j)
    lin = 0.5 * dt
    const = a * lin - dist
    with np.errstate(invalid="ignore"):
        up = (-lin + np.sqrt(lin * lin - 4.0 * quad * np.minimum(const, 0.0))) / (2.0 * quad)
        down = (lin - np.sqrt(lin * lin + 4.0 * quad * np.maximum(const, 0.0))) / (2.0 * quad)
    x = np.where(const <= 0.0, up, down)
    x = np.clip(x, a - j * dt, a + j * dt)
    x = np.clip(x, -a_max, a_max)
    v_new = profile.velocity + s * 0.5 * (a + x) * dt
    a_new = s * x
    arrived = (np.abs(target - v_new) <= 1e-12 + 1e-9 * np.abs(target)) & (np.abs(a_new) <= j * dt)
    return np.where(arrived, target, v_new), np.where(arrived, 0.0, a_new)


def test_jerk_limited_profile_matches_the_array_form() -> None:
    from payload.sim.vehicle import JerkLimitedProfile

    rng = np.random.default_rng(1)
    accel, jerk = np.array([0.02, 0.02, 0.03, 0.1, 0.1, 0.2]), np.full(6, 0.05)
    p = JerkLimitedProfile(accel, jerk)
    target = rng.normal(scale=0.1, size=6)
    for k in range(3000):
        if k % 400 == 0:
            target = rng.normal(scale=0.1, size=6) * (k % 800 != 0)  # moves and rests
        want = _profile_step_arrays(p, target, 0.02)
        got = p.step(target, 0.02)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]), k
