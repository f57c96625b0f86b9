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


SETTINGS = {
    "gain_linear": 5.0,
    "gain_angular": 5.0,
    "reference_share": 0.5,
    "mode": "quiet",
    "propulsion": "box",
    "nozzles": None,
    "plant": None,
    "torque_max": np.ones(3),
    "force_max": np.ones(3),
    "accel_max": np.ones(3),
    "alpha_max": np.ones(3),
    "jerk": np.ones(6),
    "profile": None,
}


def test_the_controllers_settings_are_fixed_when_it_is_made():
    """The compiled period copies the controller's settings when it is made, and numpy's
    code derives its bounds from them then: a setting changed afterwards would reach one
    and not the other, or not the bounds. So each refuses a new value, its arrays refuse
    writes, and the driver goes on as before; the plant's arrays the caller gave stay the
    caller's to write. The propulsion model (shared by every controller of its flight
    mode) refuses writes too."""
    from payload.sim.vehicle import MassProperties, VehicleController, VehicleError

    with SimDriver() as driver:
        c = driver.controller
        driver.command_twist(VehicleTwist(np.array([0.03, 0.0, 0.0]), np.zeros(3), 0.0))
        driver.step(3)
        for name, value in SETTINGS.items():
            with pytest.raises(VehicleError, match=rf"VehicleController\.{name} is fixed"):
                setattr(c, name, value)
        arrays = [c.torque_max, c.force_max, c.accel_max, c.alpha_max, c.jerk, c.plant.com]
        arrays += [c.plant.inertia, c.profile.accel, c.profile.jerk]
        arrays += [c.nozzles.matrix, c.nozzles.thrust_max, c.nozzles.positions]  # shared
        for a in arrays:
            with pytest.raises(ValueError, match="read-only"):
                a[0] = 1.0
        with pytest.raises(VehicleError, match=r"JerkLimitedProfile\.jerk is fixed"):
            c.profile.jerk = np.ones(6)
        assert c.gain_linear == 1.0 and driver.step(1).wrench.force.shape == (3,)
    com, inertia = np.zeros(3), np.eye(3)
    VehicleController(MassProperties(10.0, com, inertia))
    com[0], inertia[0, 0] = 0.01, 2.0  # still the caller's arrays, still writeable
