"""Homing of the rail and the stage, power-up and REBOOT as the XC330 does them, hard
stops, the grasp's load, and faults seen within one cycle (the status alert bit).

The emulator keeps the physical output position (``pos``, in the servo map's tick frame)
apart from the count the servo reports; the checks compare the driver's reading with
that physical position, read through the emulator's control channel.
"""

from __future__ import annotations

import random
import threading
import time

import numpy as np
import pytest
from conftest import reg

from firmware_interface.control_table import ADDR, TICKS_PER_REV
from firmware_interface.driver import DynamixelDriver
from firmware_interface.emulator import EmulatorProcess
from firmware_interface.errors import HardwareFault, HomingError, NotHomedError
from firmware_interface.options import EMULATOR_LATENCY_MS as LAT  # [ms] reply allowance
from firmware_interface.servo_map import load_servo_map, travel_ticks
from firmware_interface.servo_model import OVERLOAD_S, ServoModel
from payload.schema import PayloadCommand


@pytest.fixture(scope="module")
def smap():
    return load_servo_map()


def _stage_reading(drv, smap) -> float:
    """The driver's stage position as ticks of the map's frame."""
    spec = smap.servos[17]
    return spec.zero + spec.direction * drv.read().deploy / spec.units_per_tick


def _band_ticks(design) -> float:
    """The stage's static friction dead band [ticks], from the design's constants by hand:
    at rest, friction holds the shaft while the proportional current's torque
    kt (P / 128) e mA is below the Coulomb friction (the design has no I gain)."""
    s = design.servo
    return s.coulomb / (s.kt * s.gains.stage[0] / 128 * 1e-3)


def _go(drv, cmd, timeout=4.0):
    """Command until the stage is at rest inside its friction dead band around the goal
    (plus a tick: half of the goal's rounding, half of Present Position's)."""
    tol = (_band_ticks(drv.design) + 1.0) * drv.map.servos[17].units_per_tick
    t0 = time.monotonic()
    last = None
    while time.monotonic() - t0 < timeout:
        drv.send(cmd)
        st = drv.read()
        near = abs(st.deploy - cmd.deploy) <= tol and drv.fault is None
        if near and st.deploy == last:
            return st
        last = st.deploy
        time.sleep(0.005)
    raise AssertionError(f"did not reach {cmd.deploy} m")


# -- the servo model alone (no process) -------------------------------------------------------
def test_power_up_and_reboot_keep_the_angle_within_one_turn_and_lose_the_count():
    s = ServoModel(18, position=-7125.0)
    assert s.get("present_position") == -7125 % TICKS_PER_REV  # 1067: within one turn
    assert s.physical == -7125.0
    s._set("homing_offset", 5000)  # EEPROM: kept across a REBOOT
    s.reboot()
    assert s.get("homing_offset") == 5000
    assert s.get("present_position") == 1067 + 5000
    s.pos += 3 * TICKS_PER_REV  # three turns on the multi-turn count ...
    s.power_cycle()  # ... lost at power-up; the physical position is not
    assert s.get("present_position") == 1067 + 5000 and s.physical == -7125.0 + 3 * 4096


def test_hard_stop_holds_the_output_and_overloads_after_the_protection_time():
    s = ServoModel(17, position=1500.0, stops=(1024.0, 6456.0))
    s._set("operating_mode", 5)
    s._set("torque_enable", 1)
    s._set("goal_position", -20000)
    t = 0.0
    while t < 1.0:  # 476 ticks at no more than 81 rpm: there within 0.1 s
        t += 0.001
        s.advance(t)
    assert s.physical == 1024.0 and s.vel == 0.0 and s.hw_error == 0
    while t < 1.0 + OVERLOAD_S:
        t += 0.001
        s.advance(t)
    assert s.hw_error & (1 << 5)  # pushed into the stop at the current cap: overload


def test_a_load_the_current_cap_cannot_hold_stalls_the_finger():
    free, loaded = ServoModel(3, 2048.0), ServoModel(3, 2048.0)
    for s in (free, loaded):
        s._set("operating_mode", 5)
        s._set("goal_current", 350)
        s._set("torque_enable", 1)
        s._set("goal_position", 2548)
    loaded.load_ma = -400.0  # the contact pushes back harder than 350 mA can
    for k in range(1, 301):
        free.advance(k * 1e-3)
        loaded.advance(k * 1e-3)
    assert free.physical > 2500 and loaded.physical == 2048.0
    assert abs(loaded.current) == 350 and loaded.vel == 0.0


# -- the driver against the emulator ----------------------------------------------------------
def test_power_cycle_mid_travel_homes_within_one_tick_before_any_deploy(smap):
    """The stage powered up mid-travel, the fingers stowed (with them out and the stage
    not down the bring-up refuses: tests/test_firmware_stowing.py)."""
    from firmware_interface.servo_map import posture_command

    stage, rail = smap.servos[17], smap.servos[16]
    curled = posture_command(None, "stowed").q
    mid = stage.to_ticks(0.04)  # -3322: not within one turn of the map's zero
    with EmulatorProcess(positions={18: mid, 17: rail.to_ticks(0.03)}) as emu:
        assert reg(emu.table(18), "present_position") == mid % TICKS_PER_REV
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            with pytest.raises(NotHomedError, match="rail and stage not homed"):
                drv.send(PayloadCommand(np.zeros(17), 0.075, 0.0))
            assert reg(emu.table(18), "goal_position") == 0  # nothing reached the stage
            drv.bring_up()
            true = emu.servos()[18]["pos"]
            assert true == stage.zero  # homed at the stowed stop
            assert abs(_stage_reading(drv, smap) - true) <= 1.0
            _go(drv, PayloadCommand(curled, 0.04, 0.0))
            before = emu.servos()[18]["pos"]
            assert abs(before - mid) <= _band_ticks(drv.design)  # at rest in its dead band
            assert abs(_stage_reading(drv, smap) - before) <= 1.0
        # power cycle with the stage mid-travel (torque off since the driver closed):
        # EEPROM (Homing Offset) kept, count lost, the shaft where it was
        before = emu.servos()[18]["pos"]
        emu.power_cycle()
        s18 = emu.servos()[18]
        assert s18["pos"] == before and 0 <= s18["count"] < TICKS_PER_REV
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            with pytest.raises(NotHomedError):
                drv.send(PayloadCommand(np.zeros(17), 0.075, 0.0))
            drv.bring_up()
            assert abs(_stage_reading(drv, smap) - emu.servos()[18]["pos"]) <= 1.0
            _go(drv, PayloadCommand(curled, 0.06, 0.0))
            true = emu.servos()[18]["pos"]
            assert abs(true - stage.to_ticks(0.06)) <= _band_ticks(drv.design)
            assert abs(_stage_reading(drv, smap) - true) <= 1.0


@pytest.mark.parametrize("where", ["at the stop", "mid-travel"])
def test_a_blocked_rail_is_refused_not_homed(smap, where):
    """A rail whose shaft is blocked stalls at once under the homing current, which alone
    reads as the hard stop: the rail was homed wherever it stood, and mid-travel that
    made the driver read 0 m where the rail was 30 mm out. The free-travel check (driven
    off the stall, it must move) refuses it, naming the rail and how far it went, and
    leaves its torque off; the stage, free, is not named."""
    rail = smap.servos[16]
    at = {} if where == "at the stop" else {17: rail.to_ticks(0.03)}
    with (
        EmulatorProcess(faults=["block:17"], positions=at) as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv,
    ):
        start = emu.servos()[17]["pos"]
        with pytest.raises(HomingError) as refused:
            drv.bring_up()
        said = str(refused.value)
        assert said.startswith("homing: rail (0.0 of ") and "stage" not in said, said
        assert "the drive is jammed" in said
        s17 = emu.servos()[17]
        assert s17["pos"] == start and not s17["torque"]
        assert 17 not in drv.homed


def test_homing_drives_each_linear_servo_off_its_stop_and_back(smap):
    """The free-travel check moves a free rail and stage off the stop, by half to all of a
    tenth of their travel (seen on the emulator's physical position while the bring-up
    runs, after each first reached its stop), and still leaves both exactly at their
    stops, homed."""
    rail, stage = smap.servos[16], smap.servos[17]
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv,
    ):
        seen = {17: 0.0, 18: 0.0}
        stopped: set[int] = set()
        done = threading.Event()

        def watch() -> None:
            while not done.is_set():
                servos = emu.servos()
                for i, spec in ((17, rail), (18, stage)):
                    off = spec.direction * (servos[i]["pos"] - spec.zero)
                    if i in stopped:  # how far off the stop, once it has been there
                        seen[i] = max(seen[i], off)
                    elif off == 0:
                        stopped.add(i)
                time.sleep(0.005)

        watcher = threading.Thread(target=watch)
        watcher.start()
        try:
            drv.bring_up()
        finally:
            done.set()
            watcher.join()
        spans = travel_ticks(smap, drv.design)
        for i in (17, 18):
            span = spans[i][1] - spans[i][0]
            assert 0.05 * span <= seen[i] <= 0.11 * span, (i, seen[i], span)
        servos = emu.servos()
        assert servos[17]["pos"] == rail.zero and servos[18]["pos"] == stage.zero
        assert {17, 18} <= drv.homed


def test_recover_of_the_stage_rehomes_it(smap):
    """The stage rebooted mid-travel, the fingers stowed (with them out, ``recover()``
    refuses: tests/test_firmware_stowing.py): homed again at its stop."""
    from firmware_interface.servo_map import posture_command

    stage = smap.servos[17]
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv,
    ):
        drv.bring_up()
        cmd = PayloadCommand(posture_command(drv.design, "stowed").q, 0.05, 0.0)
        _go(drv, cmd)
        emu.fault("error:18:overload")
        drv.read()
        assert isinstance(drv.fault, HardwareFault) and drv.fault.id == 18
        rec = drv.recover()  # REBOOT: the stage's count is lost, it is homed again
        assert rec.ids == (18,) and 18 in drv.homed
        s = emu.servos()[18]
        assert s["reboots"] == 1 and s["pos"] == stage.zero
        assert abs(_stage_reading(drv, smap) - s["pos"]) <= 1.0
        _go(drv, cmd)
        true = emu.servos()[18]["pos"]
        assert abs(true - stage.to_ticks(0.05)) <= _band_ticks(drv.design)
        assert abs(_stage_reading(drv, smap) - true) <= 1.0


def test_injected_overload_at_a_random_cycle_stops_within_one_control_period(smap):
    rng = random.Random(34)
    k_fault = rng.randrange(5, 40)
    victim = rng.choice(smap.ids)
    period = 0.02  # 50 Hz
    with (
        EmulatorProcess() as emu,
        # the periodic health read never comes: only the status alert bit can see it
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, health_every=10_000) as drv,
    ):
        drv.bring_up()
        cmd = PayloadCommand(np.zeros(17), 0.02, 0.0)
        for k in range(60):
            t0 = time.monotonic()
            if k == k_fault:
                emu.fault(f"error:{victim}:overload")
                t_fault = time.monotonic()
            drv.send(cmd)
            st = drv.read()
            if k == k_fault:
                assert drv.fault is not None and drv.fault.id == victim
                assert drv.fault.bits == ["overload"]
                assert time.monotonic() - t_fault < period
                break
            assert drv.fault is None
            time.sleep(max(0.0, period - (time.monotonic() - t0)))
        tables = emu.tables()
        # the safe stop (hold) reached every servo: its goal is the position read in the
        # fault's cycle (a moving servo then brakes to it, lightly damped, in its own time)
        read = np.append(st.q, st.deploy)
        for spec, v in zip(smap.servos, read):
            if spec.id != victim:
                held = round(spec.zero + spec.direction * v / spec.units_per_tick)
                assert reg(tables[spec.id], "goal_position") == held, spec.id
        assert reg(tables[victim], "torque_enable") == 0
        assert tables[victim][ADDR["hardware_error_status"]] == 1 << 5


def test_a_power_loss_mid_session_stops_the_payload_and_recover_rehomes(smap):
    """The bus's power drops and comes back mid-session (a brown-out, a loose supply
    lead): every servo restarts torque off, its multi-turn count lost. The stowed stage,
    homed from a count two turns away, then reads -7168 ticks, two turns from its true
    1024 (the emulator's physical position); the driver used to read on, every servo
    limp and the stage's position wrong, with no word. Now the next health read (every
    ``health_every`` reads) sees torque off where the driver had it on: the payload is
    stopped naming the servos, and ``recover()`` brings them back, the stage homed again."""
    stage = smap.servos[17]
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, health_every=5) as drv,
    ):
        drv.bring_up()  # homing leaves the stage stowed, at its stop
        assert emu.servos()[18]["pos"] == stage.zero
        hold = PayloadCommand(drv.read().q, drv.read().deploy, 0.0)
        emu.power_cycle()
        for _ in range(drv.health_every):
            drv.send(hold)
            drv.read()
        assert isinstance(drv.fault, HardwareFault), "the reset went unseen"
        assert {drv.fault.id, *(f.id for f in drv.fault.also)} == set(smap.ids)
        assert "reset" in str(drv.fault)
        rec = drv.recover()
        assert set(rec.ids) == set(smap.ids) and 18 in drv.homed and drv.fault is None
        servos = emu.servos()
        assert all(s["torque"] for s in servos.values())
        assert abs(_stage_reading(drv, smap) - servos[18]["pos"]) <= 1.0


def test_a_reboot_keeps_the_supply_voltage_the_servo_reads():
    """Present Input Voltage is the supply's (0.1 V a unit, e-Manual), not a RAM default:
    an emulated servo on an 11.1 V supply reads 111 before and after a REBOOT and a power
    cycle (it read the register's default, 5.0 V, after either)."""
    import dataclasses

    from firmware_interface.servo_dynamics import default_plant

    plant = dataclasses.replace(default_plant(), voltage=11.1)
    reads = 111  # 11.1 V in the e-Manual's 0.1 V units
    s = ServoModel(1, plant=plant)
    assert s.get("present_input_voltage") == reads
    s.reboot()
    assert s.get("present_input_voltage") == reads
    s.power_cycle()
    assert s.get("present_input_voltage") == reads
