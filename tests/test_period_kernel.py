"""The control period's compiled calls (payload.sim.period_c) do what the driver's Python
does, to the bit, over a driven run; a build with other bits is refused."""

from __future__ import annotations

import numpy as np
import pytest

from payload.schema import PayloadCommand, VehicleTwist
from payload.sim import SimDriver, WorldConfig


def _drive(driver: SimDriver, steps: int) -> list[bytes]:
    """A run of piecewise-constant twists (at rest, within and beyond the mode's speed,
    the controller switched off and on) and payload goals, reset half-way; every array a
    period writes, after every step."""
    rng = np.random.default_rng(9)
    d = driver.data
    q0 = driver.read().q.copy()
    out = []
    mode = driver.controller.mode
    for k in range(steps):
        if k == steps // 2:  # a reset: new data, goals and targets, the period made again
            driver.reset()
            d = driver.data
        if k % 10 == 0:
            scale = (0.0, 0.5, 1.0, 3.0)[(k // 10) % 4]
            twist = VehicleTwist(
                rng.normal(size=3) * mode.speed * scale,
                rng.normal(size=3) * mode.omega * scale,
                0.0,
            )
            driver.command_twist(None if k % 70 == 40 else twist)
            driver.send(PayloadCommand(q0 + rng.normal(scale=0.3, size=q0.shape), 0.01, 0.0))
        state = driver.step(1)
        alloc = driver.controller.allocation
        out += [d.qpos.tobytes(), d.qvel.tobytes(), d.ctrl.tobytes(), d.qfrc_applied.tobytes()]
        out += [d.xfrc_applied.tobytes(), state.wrench.force.tobytes()]
        out += [np.float64(driver.ctb_external_max).tobytes()]
        out.append(b"" if alloc is None else alloc.thrust.tobytes())
    return out


def test_the_compiled_period_is_the_drivers_python_to_the_bit(monkeypatch):
    """Two drivers from the same start, one with the compiled period and one with the
    Python it replaces, driven alike for 120 control steps: the same state, controls,
    applied forces, wrench, thrusts and CTB watch after every step."""
    with SimDriver(WorldConfig()) as compiled:
        assert compiled._period_kernel is not None  # a compiler and numpy's OpenBLAS here
        first = compiled._period_kernel
        mine = _drive(compiled, 120)
        assert compiled._period_kernel is not None and compiled._period_kernel is not first
    monkeypatch.setattr(SimDriver, "_period_kernel", property(lambda self: None))
    with SimDriver(WorldConfig()) as plain:
        theirs = _drive(plain, 120)
    assert len(mine) == len(theirs)
    differing = [i for i, (a, b) in enumerate(zip(mine, theirs)) if a != b]
    assert differing == []


def test_a_period_with_other_bits_is_refused(refused_kernel):
    """A body twist read as the rotation itself instead of its transpose (the layout of
    the matrix handed to dgemv) is refused by the self-check: the driver runs the Python."""
    from payload.sim import period_c

    with refused_kernel(
        period_c,
        "p->gemv(COL_MAJOR, NO_TRANS, 3, 3",
        "p->gemv(ROW_MAJOR, NO_TRANS, 3, 3",
    ):
        with SimDriver(WorldConfig(ctb=None)) as driver:
            assert driver._period_kernel is None
            driver.command_twist(VehicleTwist(np.array([0.05, 0.0, 0.0]), np.zeros(3), 0.0))
            driver.step(3)  # the Python period
            assert driver.controller.allocation is not None


@pytest.mark.parametrize("ctb", [None, "single"])
def test_the_period_is_made_for_its_data_goals_and_controller(ctb):
    """A reset (new data, goals and targets) makes the period again; without a CTB the
    watch is off and the watch's largest force stays 0."""
    config = WorldConfig() if ctb else WorldConfig(ctb=None)
    with SimDriver(config) as driver:
        first = driver._period_kernel
        assert first is not None and driver._period_kernel is first
        driver.command_twist(VehicleTwist(np.array([0.02, 0.0, 0.0]), np.zeros(3), 0.0))
        driver.step(2)
        driver.reset()
        second = driver._period_kernel
        assert second is not None and second is not first and second.data is driver.data
        driver.step(2)
        assert driver.ctb_external_max == 0.0
