"""DynamixelDriver with the real dynamixel_sdk against the emulated bus on a pty.

Every check reads the emulator's own control tables and state through its control
channel (the emulator's process, not the driver's memory).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator

import numpy as np
import pytest
from conftest import band_ticks, reg, spy_on_the_wire
from dynamixel_sdk import COMM_RX_TIMEOUT, PacketHandler

from firmware_interface import protocol as P
from firmware_interface.control_table import ADDR, BY_NAME
from firmware_interface.driver import DynamixelDriver, failed_start
from firmware_interface.emulator import EmulatorProcess
from firmware_interface.errors import (
    BringUpFailed,
    CommError,
    DynamixelError,
    HardwareFault,
    MissingServoError,
    WrongModelError,
)
from firmware_interface.options import EMULATOR_LATENCY_MS as LAT  # [ms] reply allowance
from firmware_interface.port import SdkPort
from firmware_interface.servo_map import load_servo_map
from firmware_interface.shutdown import TORQUE_OFF_CONFIRM_S
from payload.errors import Terminated
from payload.schema import Health, PayloadCommand


@pytest.fixture(scope="module")
def smap():
    return load_servo_map()


@pytest.fixture(scope="module")
def rig(smap):
    """One emulator and a brought-up driver shared by the non-destructive tests (the
    collision guard off: they command random postures to check the unit conversions; the
    guard has its own tests, test_firmware_guard.py)."""
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, guard=False) as drv,
    ):
        drv.bring_up()
        yield emu, drv


def _tolerance(drv):
    return np.array([s.units_per_tick * band_ticks(s.joint, drv.design) for s in drv.map.servos])


def _settle(drv, cmd, timeout=6.0):
    """Keep commanding until every joint has stopped inside its friction dead band."""
    tol = _tolerance(drv)
    t0 = time.monotonic()
    state = drv.read()
    while time.monotonic() - t0 < timeout:
        drv.send(cmd)
        state = drv.read()
        near = np.abs(np.append(state.q, state.deploy) - _values(cmd)) <= tol
        if np.all(near) and np.all(state.dq == 0.0):
            break
    return state


def _values(cmd):
    return np.append(cmd.q, cmd.deploy)


def _random_command(smap, seed):
    rng = np.random.default_rng(seed)
    v = np.array([rng.uniform(s.lower, s.upper) for s in smap.servos])
    return PayloadCommand(v[:17], float(v[17]), 0.0)


def test_bring_up_writes_the_designs_servo_registers(rig, smap, design):
    """The gains read back from the emulator are the design's [servo.gains] per kind."""
    emu, _ = rig
    tables = emu.tables()
    kinds = {"rail": "rail", "stage": "stage"}
    for spec in smap.servos:
        t = tables[spec.id]
        kind = kinds.get(spec.joint, "abduction" if spec.joint.endswith("abd") else "finger")
        assert reg(t, "model_number") == 1240
        assert reg(t, "operating_mode") == 5, spec.joint
        assert reg(t, "return_delay_time") == smap.return_delay
        p, i, d = (int(g) for g in getattr(design.servo.gains, kind))
        assert (reg(t, "position_p_gain"), reg(t, "position_i_gain"),
                reg(t, "position_d_gain")) == (p, i, d)  # fmt: skip
        assert reg(t, "goal_current") == round(design.servo.current_limit * 1000)
        assert reg(t, "bus_watchdog") == smap.watchdog_ms // 20
        assert reg(t, "torque_enable") == 1
    assert design.servo.gains.finger == (600, 0, 200)
    assert design.servo.gains.abduction == (450, 0, 150)


def test_command_round_trips_to_ticks_and_back_within_one_tick(rig, smap):
    emu, drv = rig
    cmd = _random_command(smap, 1)
    drv.send(cmd)
    state = _settle(drv, cmd)
    tables = emu.tables()
    values = _values(cmd)
    for k, spec in enumerate(smap.servos):
        goal = reg(tables[spec.id], "goal_position")
        # the goal in the emulator's table, converted back by hand: direction and zero
        back = spec.direction * (goal - spec.zero) * spec.units_per_tick
        assert abs(back - values[k]) <= 0.5 * spec.units_per_tick + 1e-12, spec.joint
        measured = np.append(state.q, state.deploy)[k]
        assert abs(measured - values[k]) <= _tolerance(drv)[k], spec.joint


def test_rail_and_stage_ticks_match_the_design_transmission(rig, smap, design):
    emu, drv = rig
    home = _random_command(smap, 2)
    q = home.q.copy()
    q[-1] = 0.0123
    drv.send(PayloadCommand(q, 0.0456, 0.0))
    drv.read()
    tables = emu.tables()
    for spec, x, r in ((smap.servos[16], 0.0123, design.rail.drive_radius),
                       (smap.servos[17], 0.0456, design.stage.drive_radius)):  # fmt: skip
        goal = reg(tables[spec.id], "goal_position")
        shaft_turns = (goal - spec.zero) * spec.direction / 4096
        assert shaft_turns * 2 * np.pi * r == pytest.approx(x, abs=2 * np.pi * r / 4096)


def test_emulator_status_errors_through_the_sdk(rig):
    emu, _ = rig
    port = SdkPort(emu.port, LAT)
    ph = PacketHandler(2.0)
    port.openPort()
    port.setBaudRate(4_000_000)
    try:
        # EEPROM (Operating Mode) with torque on: access error, nothing written
        _, err = ph.write1ByteTxRx(port, 1, ADDR["operating_mode"], 3)
        assert err & 0x7F == P.ERR_ACCESS
        assert reg(emu.table(1), "operating_mode") == 5
        # read-only register
        _, err = ph.write2ByteTxRx(port, 1, ADDR["present_current"], 5)
        assert err & 0x7F == P.ERR_ACCESS
        # out of range, above the Current Limit
        _, err = ph.write1ByteTxRx(port, 1, ADDR["torque_enable"], 7)
        assert err & 0x7F == P.ERR_DATA_RANGE
        _, err = ph.write2ByteTxRx(port, 1, ADDR["goal_current"], 1751)
        assert err & 0x7F in (P.ERR_DATA_RANGE, P.ERR_DATA_LIMIT)
        # a corrupted instruction gets a CRC error status
        raw = bytearray(P.build(2, P.READ, bytes([132, 0, 4, 0])))
        raw[-1] ^= 0xFF
        port.ser.reset_input_buffer()
        port.ser.write(bytes(raw))
        deadline, got = time.monotonic() + 1.0, b""
        while time.monotonic() < deadline and len(got) < 11:
            got += port.ser.read(11 - len(got))
        assert P.parse(got).error & 0x7F == P.ERR_CRC
    finally:
        port.closePort()


def test_missing_servo_at_bring_up_names_its_id_and_joint(smap):
    with (
        EmulatorProcess(faults=["missing:7"]) as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv,
    ):
        with pytest.raises(MissingServoError, match=r"ID 7 \(B_pip\)") as info:
            drv.bring_up()
        assert info.value.ids == [7]


def _untouched(emu) -> bool:
    """No servo of the emulator was configured: each keeps its factory Return Delay Time
    (250, the e-Manual's; the map's is 0) and Operating Mode (3), its torque off."""
    tables = emu.tables()
    factory = {name: BY_NAME[name].default for name in ("return_delay_time", "operating_mode")}
    return all(
        all(reg(t, name) == value for name, value in factory.items())
        and not reg(t, "torque_enable")
        for t in tables.values()
    )  # fmt: skip


def test_a_bring_up_names_every_servo_at_fault_not_only_the_first(smap):
    """A missing servo, one of another model and two with latched hardware errors: the
    bring-up named the missing one only; it now looks at every servo before it configures
    any and names all four, the missing one deciding the error's type."""
    faults = ["error:3:overheating", "error:7:overload", "missing:9", "model:5:1060"]
    with EmulatorProcess(faults=faults) as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            with pytest.raises(BringUpFailed) as info, failed_start(emu.port):
                drv.bring_up()
            cause = info.value.__context__
        assert _untouched(emu)
    assert isinstance(cause, MissingServoError) and cause.ids == [9]
    assert [(type(f), f.id) for f in cause.also] == [
        (WrongModelError, 5), (HardwareFault, 3), (HardwareFault, 7)]  # fmt: skip
    assert [f.bits for f in cause.also[1:]] == [["overheating"], ["overload"]]
    assert str(info.value) == (
        f"bring-up on {emu.port} failed: servo(s) not answering: ID 9 (C_mcp_flex); "
        "servo 5 (B_mcp_flex): model number 1060, not the servo map's 1240: another servo "
        "on this ID?; servo 3 (A_pip): hardware error overheating; servo 7 (B_pip): "
        "hardware error overload (a hardware error stays latched until the servo restarts: "
        "remove its cause (a blocked joint for overload, the supply for input_voltage, "
        "time to cool for overheating), then power-cycle the servos; `payload hw check` "
        "shows every servo's state)"
    )


def test_a_bring_up_reads_every_servos_error_bits_before_configuring_any(smap):
    """Two servos with latched errors and no other fault: the bring-up configured servos
    1 and 2 and stopped at 3, naming it alone; it now configures none and names both, the
    first a HardwareFault with the other in its ``also``."""
    with EmulatorProcess(faults=["error:7:overload", "error:3:input_voltage"]) as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            with pytest.raises(HardwareFault) as info:
                drv.bring_up()
        assert _untouched(emu)
    fault = info.value
    assert (fault.id, fault.joint, fault.bits) == (3, "A_pip", ["input_voltage"])
    assert [(type(f), f.id, f.bits) for f in fault.also] == [(HardwareFault, 7, ["overload"])]
    assert str(fault) == ("servo 3 (A_pip): hardware error input_voltage; "
                          "servo 7 (B_pip): hardware error overload")  # fmt: skip


def test_a_lost_error_read_at_bring_up_is_said_after_the_faults_found(smap, monkeypatch):
    """A servo missing, and servo 7's error-status read lost after its retries (a loose
    cable): the lost read raised at once and the missing servo went unsaid; now the
    missing servo decides the error and the lost read is named after it, and nothing is
    configured."""
    lost = CommError("servo 7 (B_pip): reading hardware_error_status after 3 attempt(s)")
    read = DynamixelDriver._read_reg

    def lose_7(drv: DynamixelDriver, dxl_id: int, address: int, size: int) -> int:
        if dxl_id == 7 and address == ADDR["hardware_error_status"]:
            raise lost
        return read(drv, dxl_id, address, size)

    monkeypatch.setattr(DynamixelDriver, "_read_reg", lose_7)
    with EmulatorProcess(faults=["missing:9", "error:3:overload"]) as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            with pytest.raises(MissingServoError) as info:
                drv.bring_up()
        assert _untouched(emu)
    assert info.value.ids == [9]
    assert [type(f) for f in info.value.also] == [HardwareFault, CommError]
    assert info.value.also[1] is lost
    assert str(info.value).endswith(
        "servo 3 (A_pip): hardware error overload; servo 7 (B_pip): reading "
        "hardware_error_status after 3 attempt(s)"
    )


def test_late_replies_at_bring_up_are_said_with_a_missing_servo(smap, monkeypatch):
    """Servo 9 missing and a reply of servo 3 counted late during the scan: the late
    replies were dropped from the error (only the missing servo named, though the bus's
    latency is the likelier cause); now they are named after it, and no error bits are
    read on that bus."""
    scan = DynamixelDriver.scan

    def late_3(drv: DynamixelDriver) -> dict[int, tuple[int, int]]:
        found = scan(drv)
        drv.port.late[3] = drv.port.late.get(3, 0) + 1
        return found

    monkeypatch.setattr(DynamixelDriver, "scan", late_3)
    with EmulatorProcess(faults=["missing:9", "error:4:overload"]) as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            with pytest.raises(MissingServoError) as info:
                drv.bring_up()
            allowance = drv.port.reply_allowance_ms
        assert _untouched(emu)
    assert [type(f) for f in info.value.also] == [CommError]  # servo 4's bits not read
    assert str(info.value) == (
        "servo(s) not answering: ID 9 (C_mcp_flex); servo 3 (A_pip): replies came after "
        f"the {allowance:.0f} ms reply timeout: the bus answers later than the driver allows "
        "(an adapter's latency timer above the one given: --latency-ms?)"
    )


def test_corrupt_and_dropped_replies_are_retried_within_the_cycle(smap):
    with (
        EmulatorProcess(faults=["corrupt:0.05", "drop:0.03"], seed=3) as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, retries=3) as drv,
    ):
        drv.bring_up()
        start = drv.retry_count
        for _ in range(60):
            drv.send(PayloadCommand(np.zeros(17), 0.07, 0.0))
            drv.read()
        stats = emu.stats()
        assert stats["corrupted"] + stats["dropped"] > 0
        assert drv.retry_count > start
        # every reply lost: reported after the retries, naming the attempts
        emu.fault("drop:1.0")
        with pytest.raises(CommError, match="after 4 attempt"):
            drv.read()


def _cycles(drv, cmd, n: int, pause: float = 0.0) -> None:
    """``n`` control cycles (send, read), ``pause`` seconds apart."""
    for _ in range(n):
        drv.send(cmd)
        drv.read()
        time.sleep(pause)


def test_a_servo_that_stops_answering_mid_session_is_named_alone(smap):
    """The fast sync read fails, the plain sync read it falls back to stops at the servo
    that does not answer: the error names that servo, not every servo on the bus."""
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv,
    ):
        drv.bring_up()
        _cycles(drv, PayloadCommand(np.zeros(17), 0.07, 0.0), 3)
        emu.fault("missing:7")
        with pytest.raises(CommError) as info:
            drv.read()
        assert drv.fallbacks == 1
        message = str(info.value)
        named = {s.id: f"servo {s.id} ({s.joint})" for s in smap.servos}
        assert named.pop(7) in message
        others = list(named.values())
        assert not [o for o in others if o in message], message


def test_latency_delays_every_reply(smap):
    with EmulatorProcess(faults=["latency:8ms"]) as emu:
        port = SdkPort(emu.port, LAT)
        ph = PacketHandler(2.0)
        port.openPort()
        try:
            t0 = time.perf_counter()
            _, result, _ = ph.ping(port, 3)
            assert result == 0 and time.perf_counter() - t0 >= 0.008
        finally:
            port.closePort()


def _until_fault(drv, cmd, timeout=4.0):
    t0 = time.monotonic()
    while drv.fault is None and time.monotonic() - t0 < timeout:
        drv.send(cmd)
        drv.read()
    return drv.fault


@pytest.mark.parametrize("mode", ["hold", "torque_off"])
def test_hardware_error_stops_safely_and_recover_returns_the_servo(smap, mode, caplog):
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, on_fault=mode) as drv,
    ):
        drv.bring_up()
        cmd = PayloadCommand(np.zeros(17), 0.075, 0.0)
        _settle(drv, cmd)
        emu.fault("error:12:overload")
        with caplog.at_level(logging.ERROR, logger="firmware_interface.driver"):
            fault = _until_fault(drv, cmd)
        assert isinstance(fault, HardwareFault)
        assert (fault.id, fault.joint, fault.bits) == (12, "C_dip", ["overload"])
        assert "servo 12 (C_dip): hardware error overload" in caplog.text
        assert drv.read().health & Health.HARDWARE_ERROR
        servos = emu.servos()
        assert not servos[12]["torque"]  # the servo shut itself down
        for i, s in servos.items():
            if i != 12:
                assert s["torque"] == (mode == "hold")
        # stopped: a new command does not reach the servos (the goal stays where the stop
        # left it: the last command's, or where the servo rested, held)
        before = reg(emu.table(1), "goal_position")
        assert abs(before - smap.servos[0].to_ticks(0.0)) <= band_ticks("A_mcp_flex", drv.design)
        moved = cmd.q.copy()
        moved[0] = 0.8
        drv.send(PayloadCommand(moved, 0.075, 0.0))
        assert reg(emu.table(1), "goal_position") == before
        rec = drv.recover()
        assert rec.ids == (12,) and rec.seconds > 0
        servos = emu.servos()
        assert servos[12]["reboots"] == 1 and servos[12]["hw_error"] == 0
        assert all(s["torque"] for s in servos.values())
        t12 = emu.table(12)
        assert reg(t12, "operating_mode") == 5 and reg(t12, "goal_current") == 350
        # back in service: the rebooted servo follows commands again
        q = cmd.q.copy()
        q[11] = -0.2  # C_dip
        state = _settle(drv, PayloadCommand(q, 0.075, 0.0))
        assert state.q[11] == pytest.approx(-0.2, abs=_tolerance(drv)[11])
        assert drv.fault is None


def test_a_blocked_joint_trips_overload_at_the_current_cap(smap):
    with (
        EmulatorProcess(faults=["block:3"]) as emu,
        # the guard off: A_pip at 1 rad brings A's distal capsule (which encloses the pad)
        # inside the margin of C's middle link, and this test is about the current cap
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, guard=False) as drv,
    ):
        drv.bring_up()
        q = np.zeros(17)
        q[2] = 1.0  # A_pip, blocked
        fault = _until_fault(drv, PayloadCommand(q, 0.075, 0.0))
        assert fault is not None and (fault.id, fault.bits) == (3, ["overload"])
        s = emu.servos()[3]
        assert abs(s["current"]) <= 350


def test_close_leaves_every_servo_torque_off_and_is_idempotent(smap):
    with EmulatorProcess() as emu:
        drv = DynamixelDriver(emu.port, smap, latency_timer_ms=LAT)
        drv.bring_up()
        drv.close()
        drv.close()
        # the torque-off is a sync write (no reply): the emulator reads it from the line
        # while its state is asked on another channel, so a loaded machine can answer the
        # question first (seen once in CI); it must show within a second
        end = time.monotonic() + 1.0
        while any(s["torque"] for s in emu.servos().values()) and time.monotonic() < end:
            time.sleep(0.01)
        assert not any(s["torque"] for s in emu.servos().values())


@pytest.mark.parametrize("stop", [KeyboardInterrupt, lambda: Terminated(15)])
def test_ctrl_c_during_a_bus_reply_still_leaves_every_servo_torque_off(smap, stop):
    """Ctrl-C (or SIGTERM, raised as its subclass) lands while the SDK awaits a reply
    (raised out of the serial read, where Python raises it from the signal handler): the
    SDK left the port marked in use, and close()'s torque-off used to fail as "Port is in
    use!" with every servo left torqued. The next command still reaches the servos, and
    close() stops them."""
    with EmulatorProcess() as emu:
        drv = DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, guard=False)
        try:
            drv.bring_up()
            ser = drv.port.ser
            read = ser.read

            def interrupted(n):
                ser.read = read  # once
                raise stop()

            ser.read = interrupted
            with pytest.raises(KeyboardInterrupt):
                drv.read()
            cmd = PayloadCommand(np.full(17, 0.1), 0.0, 0.0)
            drv.send(cmd)  # as the loop's finally does: hold the last command
            # a read's round trip first: the bus's packets are served in order, so the
            # sync write (no reply) has been applied when the emulator's tables are asked
            # (over its control channel, which a loaded machine may serve sooner)
            assert drv.read().q.shape == (17,)
            goals = [reg(emu.table(s.id), "goal_position") for s in smap.servos]
            assert goals == smap.command_ticks(cmd)
            ser.read = interrupted
            with pytest.raises(KeyboardInterrupt):
                drv.read()
        finally:
            drv.close()
        assert not any(s["torque"] for s in emu.servos().values())


def test_a_vanished_device_is_a_comm_error_naming_it(smap, caplog):
    """The emulator killed mid-session (a USB adapter pulled): the read and the command
    after it each raise one CommError naming the device (not the serial library's
    'Input/output error', nor "Port is in use!"); close() still returns."""
    emu = EmulatorProcess()
    try:
        drv = DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, guard=False)
        drv.bring_up()
        drv.read()
        emu.proc.kill()
        emu.proc.wait()
        for action in (drv.read, lambda: drv.send(PayloadCommand(np.zeros(17), 0.0, 0.0))):
            with pytest.raises(CommError) as err:
                action()
            text = str(err.value)
            assert emu.port in text and "serial device failed" in text and "in use" not in text
        with caplog.at_level(logging.WARNING, logger="firmware_interface.driver"):
            drv.close()
        assert "could not turn the torque off" in caplog.text
    finally:
        emu.close()


HOST = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from firmware_interface.driver import DynamixelDriver
    from firmware_interface.options import EMULATOR_LATENCY_MS
    from payload.schema import PayloadCommand
    drv = DynamixelDriver(sys.argv[1], latency_timer_ms=EMULATOR_LATENCY_MS)
    drv.bring_up()
    cmd = PayloadCommand(np.zeros(17), 0.075, 0.0)  # deploy the homed stage: a long move
    drv.send(cmd)
    print("moving", flush=True)
    while True:
        drv.send(cmd)
        drv.read()
        time.sleep(0.01)
    """
)


def test_killing_the_host_stops_the_servos_within_the_watchdog_time(smap):
    wd = smap.watchdog_ms / 1000
    with EmulatorProcess() as emu:
        host = subprocess.Popen([sys.executable, "-c", HOST, emu.port], stdout=subprocess.PIPE)
        try:
            assert host.stdout.readline().strip() == b"moving"
            time.sleep(0.15)
            before = emu.servos()[18]
            assert abs(before["vel"]) > 100  # the stage is moving
            t_kill = time.monotonic()
            os.kill(host.pid, signal.SIGKILL)
            host.wait()
        finally:
            if host.poll() is None:
                host.kill()
        # the tripped servos hold where they were: the moving stage brakes under its PD law
        # (a ~5 Hz second-order servo, docs/servo.md) and is at rest within about a second
        time.sleep(wd + 1.5)
        first = emu.servos()
        time.sleep(0.2)
        later = emu.servos()
        for i, s in later.items():
            assert s["watchdog_trip"] is not None, i
            # the watchdog interval after the last instruction the servo heard, which the
            # host sent before it died (the emulator may read it a few ms late under load)
            assert s["watchdog_trip"] == pytest.approx(s["last_rx"] + wd, abs=1e-9)
            assert s["watchdog_trip"] <= t_kill + wd + 0.05
            assert s["pos"] == first[i]["pos"] and s["vel"] == 0.0
            assert reg(emu.table(i), "bus_watchdog") == 0xFF  # reads -1
        goal = smap.servos[17].to_ticks(0.075)
        assert abs(later[18]["pos"] - goal) > 500  # stopped on the way, not at the goal


def test_every_hardware_error_bit_is_named_and_recovered(smap):
    bits = ["input_voltage", "overheating", "encoder", "electrical_shock", "overload"]
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, health_every=2) as drv,
    ):
        drv.bring_up()
        cmd = PayloadCommand(np.zeros(17), 0.075, 0.0)
        for dxl_id, bit in zip((2, 6, 10, 17, 18), bits):
            emu.fault(f"error:{dxl_id}:{bit}")
            fault = _until_fault(drv, cmd)
            assert fault is not None
            assert (fault.id, fault.joint, fault.bits) == (dxl_id, smap.joint_of(dxl_id), [bit])
            assert drv.recover().ids == (dxl_id,)
        assert [
            s["reboots"] for i, s in sorted(emu.servos().items()) if i in (2, 6, 10, 17, 18)
        ] == [1] * 5


@contextlib.contextmanager
def _running_session(smap, cycles: int) -> Iterator[tuple[EmulatorProcess, DynamixelDriver]]:
    """An emulated bus and a driver brought up on it, ``cycles`` control cycles run (the
    Bus Watchdog armed, nothing tripped)."""
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv,
    ):
        drv.bring_up()
        _cycles(drv, PayloadCommand(np.zeros(17), 0.0, 0.0), cycles, pause=0.02)
        yield emu, drv


def test_a_watchdog_trip_found_by_a_health_check_records_the_silence_that_tripped_it(smap):
    """The host falls silent (no send) for longer than the watchdog, then reads twice: the
    trip is found by the health check after the second read, whose own gap is a few ms;
    the trip records the silence that tripped it, not the last read's gap."""
    from firmware_interface.run import watchdog_report

    stall = 2.5 * smap.watchdog_ms / 1e3  # longer than the map's watchdog
    with _running_session(smap, 3) as (emu, drv):
        drv.check_health()  # the longest silence counts from here
        time.sleep(stall)
        drv.read()
        drv.read()  # a short gap before this one
        assert all(s["watchdog_trip"] is not None for s in emu.servos().values())
        assert drv.watchdog_trips == []
        drv.check_health()
        assert len(drv.watchdog_trips) == 1
        trip = drv.watchdog_trips[0]
        assert trip["silence_s"] >= stall and trip["host_silent_long_enough"] is True
        assert "host silences up to" in watchdog_report(drv.watchdog_trips)["effect"]
        # a trip with the host never silent that long says so (the far end's doing): the
        # servos tripped by a silence, re-armed here as if the host's longest were 4 ms
        time.sleep(stall)
        drv.read()
        drv._rearm_watchdog(0.004)
        assert drv.watchdog_trips[-1]["host_silent_long_enough"] is False
        assert drv._longest_gap == 0.0  # counted afresh from the re-arming
        effect = watchdog_report(drv.watchdog_trips)["effect"]
        # both kinds, each with its own bound (the stall is not the other's "at most")
        assert f"1 after host silences up to {trip['silence_s'] * 1e3:.0f} ms and " in effect
        assert "1 with the host silent for less than the watchdog's time (at most 4 ms" in effect


def test_a_watchdog_trip_mid_session_is_recorded_with_what_it_did(smap):
    from firmware_interface.run import watchdog_report

    with _running_session(smap, 5) as (emu, drv):
        cmd = PayloadCommand(np.zeros(17), 0.0, 0.0)
        assert drv.watchdog_trips == [] and watchdog_report([])["trips"] == 0
        time.sleep(0.25)  # the host falls silent for longer than the 100 ms watchdog
        assert all(s["watchdog_trip"] is not None for s in emu.servos().values())
        drv.send(cmd)  # the next command re-arms them
        assert len(drv.watchdog_trips) == 1
        trip = drv.watchdog_trips[0]
        assert trip["servos"] == smap.ids and trip["silence_s"] >= 0.25
        report = watchdog_report(drv.watchdog_trips)
        assert report["trips"] == 1 and "held" in report["effect"]
        assert "the session continued" in report["effect"]
        assert all(s["watchdog_trip"] is None for s in emu.servos().values())


# -- late, lost and wrong replies ------------------------------------------------------------
@pytest.mark.parametrize("late", ["latency:50ms", "latency:36ms"])
def test_a_reply_after_its_timeout_is_never_taken_as_a_later_requests_answer(smap, late):
    """Replies later than the reply timeout (2 x 16 ms + 2 ms at the SDK's latency timer):
    the SDK's retry, or the next read, took the late reply as its own, and the scan said
    firmware 216 (the low byte of model 1240: a ping's reply read as the firmware's). Now
    the scan fails naming the late replies."""
    # every reply is late (36 and 50 ms > 2 x 16 + 2 ms): the scan fails, naming them,
    # and takes none of them as a later request's answer
    with EmulatorProcess(faults=[late]) as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=16.0) as drv:
            with pytest.raises(CommError, match=r"34 ms reply timeout"):
                drv.scan()


def test_a_servo_of_another_model_is_refused_at_bring_up_by_name(smap):
    """A servo reporting another model number on a mapped ID (here 1060, an XL430) is
    refused before anything is written to it, naming it; the emulator's own table says
    which model it is."""
    with EmulatorProcess(faults=["model:5:1060"]) as emu:
        assert reg(emu.table(5), "model_number") == 1060
        assert reg(emu.table(4), "model_number") == 1240  # the e-Manual's XC330-M288-T
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            with pytest.raises(DynamixelError, match=r"servo 5 \(B_mcp_flex\): model number 1060"):
                drv.bring_up()
        assert not any(s["torque"] for s in emu.servos().values())


def test_recover_refuses_another_model_on_a_rebooted_servos_id(smap, monkeypatch):
    """A servo swapped for another model while it was down (model 1060 answers after the
    REBOOT) is refused by name before its settings are restored: nothing is written to it
    (the driver's registers are the map's model's), and it stays faulted, torque off."""
    with EmulatorProcess() as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, on_fault="hold") as drv:
            drv.bring_up()
            cmd = PayloadCommand(np.zeros(17), drv.design.home.stage, 0.0)
            emu.fault("error:12:overload")
            assert isinstance(_until_fault(drv, cmd), HardwareFault)
            emu.fault("model:12:1060")
            seen = spy_on_the_wire(monkeypatch)
            with pytest.raises(WrongModelError, match=r"servo 12 \(C_dip\): model number 1060"):
                drv.recover()
            monkeypatch.undo()
            assert drv.fault is not None and drv.other_model == {12: 1060}
        assert not emu.servos()[12]["torque"]
    written = [(inst, a) for inst, a in seen[12] if inst in (P.WRITE, P.SYNC_WRITE)]
    assert (P.REBOOT, None) in seen[12] and written == [], sorted(seen[12], key=str)


def test_a_failed_read_names_the_servo_and_the_register_in_the_drivers_words(rig):
    emu, drv = rig
    emu.fault("drop:1.0")
    try:
        with pytest.raises(CommError) as info:
            drv.read_health(3)
    finally:
        emu.clear()
    text = str(info.value)
    assert text.startswith("servo 3 (A_pip): reading hardware_error_status after 3 attempt")
    assert "no reply" in text and "TxRxResult" not in text and "address" not in text


def _lose_the_next_sync_write(drv) -> None:
    """The host's next SYNC_WRITE never reaches the bus (a packet lost on the wire)."""
    ser = drv.port.ser
    write = ser.write

    def lossy(data):
        if len(data) > 7 and data[7] == P.SYNC_WRITE:
            ser.write = write  # once
            return len(data)
        return write(data)

    ser.write = lossy


def _lose_the_first_reply_of(drv, dxl_id: int) -> None:
    """The first read of ``dxl_id``'s Torque Enable gets no reply (a reply lost on the
    wire), whatever the bus's load."""
    read = drv.packet.read1ByteTxRx
    lost = []

    def lossy(port, i, address):
        if i == dxl_id and address == ADDR["torque_enable"] and not lost:
            lost.append(i)
            return 0, COMM_RX_TIMEOUT, 0
        return read(port, i, address)

    drv.packet.read1ByteTxRx = lossy


def test_close_confirms_the_torque_off_and_resends_it_to_a_servo_still_on(smap, caplog):
    """The torque-off sync write lost on the line, and servo 5's first reply lost: close
    reads Torque Enable back, sends the torque-off again to the servos still on (and to 5,
    not read) and confirms each on its second pass; the emulator's servos end torque
    off, and close warns of nothing (every servo confirmed)."""
    with EmulatorProcess() as emu:
        drv = DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, guard=False)
        drv.bring_up()
        assert all(s["torque"] for s in emu.servos().values())
        writes = emu.stats()["packets"]["sync_write"]
        _lose_the_next_sync_write(drv)
        _lose_the_first_reply_of(drv, 5)
        with caplog.at_level(logging.WARNING, logger="firmware_interface.driver"):
            drv.close()
        assert not any(s["torque"] for s in emu.servos().values())
        assert emu.stats()["packets"]["sync_write"] == writes + 1  # the re-send, once
    assert drv.torque_unconfirmed == []
    assert [r.getMessage() for r in caplog.records] == []


def test_close_names_a_servo_it_could_not_confirm_without_raising(smap, caplog):
    with EmulatorProcess() as emu:
        drv = DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, guard=False)
        drv.bring_up()
        emu.fault("missing:7")
        with caplog.at_level(logging.WARNING, logger="firmware_interface.driver"):
            drv.close()
        servos = emu.servos()
        assert servos[7]["torque"] and not any(s["torque"] for i, s in servos.items() if i != 7)
    warned = [r.getMessage() for r in caplog.records if "close:" in r.getMessage()]
    assert len(warned) == 1 and "servo 7 (B_pip)" in warned[0], warned
    others = [f"servo {s.id} ({s.joint})" for s in smap.servos if s.id != 7]
    assert not [o for o in others if o in warned[0]], warned


def test_no_shutdown_writes_to_or_reads_a_servo_of_another_model(smap, monkeypatch, caplog):
    """Servo 5 answers as model 1060 (its byte at the X series' Torque Enable address set
    first) and servo 7 not at all: the bring-up refuses them before configuring any servo,
    but close sync-wrote Torque Enable = 0 (address 64) to servo 5 too and read it back,
    and a safe stop wrote to it as well. Now the host sends servo 5 nothing but the scan's
    ping (not even Firmware Version: the packets on the wire), its byte 64 is still set
    (the emulator's own table), while servo 7 (model unknown) still gets the torque-off
    and servo 4 (the map's model) gets it and is read back; close warns of nothing."""
    torque, goal = ADDR["torque_enable"], ADDR["goal_position"]
    with EmulatorProcess(faults=["model:5:1060", "missing:7"]) as emu:
        drv = DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, guard=False)
        drv.packet.write1ByteTxRx(drv.port, 5, torque, 1)  # not the driver's doing
        seen = spy_on_the_wire(monkeypatch)
        with pytest.raises(MissingServoError) as info:
            drv.bring_up()
        assert [type(f) for f in info.value.also] == [WrongModelError]
        for on_fault in ("hold", "torque_off"):  # the safe stop's two ways
            drv.on_fault = on_fault
            drv.safe_stop()
        with caplog.at_level(logging.WARNING, logger="firmware_interface.driver"):
            drv.close()
        assert emu.table(5)[torque] == 1 and emu.servos()[5]["torque"]
    scan = {(P.PING, None), (P.READ, ADDR["firmware_version"])}  # a servo of the map's model
    assert seen[5] == {(P.PING, None)}, sorted(seen[5], key=str)  # the scan's ping alone
    assert P.BROADCAST_ID not in seen, sorted(seen[P.BROADCAST_ID], key=str)
    # no position was read: the hold is a torque-off too (a goal of zeros would move one)
    stops = {(P.SYNC_WRITE, torque)}
    assert seen[7] == {(P.PING, None)} | stops, sorted(seen[7], key=str)  # never read
    assert scan | stops | {(P.READ, torque)} <= seen[4], sorted(seen[4], key=str)
    assert not any((P.SYNC_WRITE, goal) in s for s in seen.values())
    assert drv.other_model == {5: 1060} and drv.torque_unconfirmed == []
    assert [r.getMessage() for r in caplog.records] == []


def test_a_hold_before_any_position_is_read_moves_no_servo(smap) -> None:
    """A safe stop in "hold" before the driver had read a position sent every servo the
    goal it starts with, tick 0: a servo another program had left holding (torque on, at
    its own position) would have swung to 0. A servo whose position is unknown gets the
    torque-off instead; it stays where it was (the emulator's own goal and position)."""
    torque, goal = ADDR["torque_enable"], ADDR["goal_position"]
    with EmulatorProcess() as emu:
        drv = DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, guard=False)
        drv.packet.write1ByteTxRx(drv.port, 4, torque, 1)  # left holding by another program
        before = int.from_bytes(bytes(emu.table(4)[goal : goal + 4]), "little", signed=True)
        drv.on_fault = "hold"
        drv.safe_stop()
        after = int.from_bytes(bytes(emu.table(4)[goal : goal + 4]), "little", signed=True)
        assert after == before != 0 and not emu.servos()[4]["torque"]
        drv.close()


def test_close_turns_off_a_servo_it_enabled_whatever_model_answers_on_its_id(smap, monkeypatch):
    """The driver enabled servo 5 at bring-up; a later scan finds model 1060 on its ID:
    close still sends it the torque-off and reads it back (the servo it enabled may
    still be there), and the emulator's servo ends torque off."""
    with EmulatorProcess() as emu:
        drv = DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, guard=False)
        drv.bring_up()
        emu.fault("model:5:1060")
        assert drv.scan()[5] == (1060, None) and drv.other_model == {5: 1060}  # fw unread
        seen = spy_on_the_wire(monkeypatch)
        drv.close()
        assert not emu.servos()[5]["torque"]
    torque = ADDR["torque_enable"]
    assert {(P.SYNC_WRITE, torque), (P.READ, torque)} <= seen[5], sorted(seen[5], key=str)
    assert drv.torque_unconfirmed == []


def test_a_fault_of_several_servos_lists_the_others_as_ids():
    also = [HardwareFault(2, "A_mcp_abd", ["overload"]), HardwareFault(5, "B_mcp_flex", [])]
    fault = HardwareFault(3, "A_pip", ["overload"], also=also)
    assert str(fault) == "servo 3 (A_pip): hardware error overload (also IDs 2, 5)"
    assert fault.alone == "servo 3 (A_pip): hardware error overload"


# -- review of the late-reply protection -----------------------------------------------------
def test_a_byte_stuffed_reply_is_read_whole_not_refused_as_corrupt(smap):
    """A value whose bytes hold FF FF FD (Homing Offset -131073: FF FF FD FF) comes back
    byte-stuffed, as a real servo sends it (an FD inserted after FF FF FD); the SDK
    unstuffs it and fixes LEN but leaves the list one byte long. The length check counted
    the list: a corrupt reply, retried, then a CommError. The value read is the one in the
    emulator's own table."""
    value = -131073
    raw = value.to_bytes(4, "little", signed=True)
    assert b"\xff\xff\xfd" in raw
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, guard=False) as drv,
    ):
        drv._write(3, "homing_offset", value)  # torque off: the EEPROM area is writable
        held = emu.table(3)[ADDR["homing_offset"] : ADDR["homing_offset"] + 4]
        assert held == raw
        got = drv._read_reg(3, ADDR["homing_offset"], 4)
        rx = drv.packet._last  # the reply as the SDK read it off the wire
        assert got.to_bytes(4, "little") == held and drv.retry_count == 0
    # stuffed on the wire: the SDK's removeStuffing shortened LEN by the byte it dropped
    assert len(rx) - (rx[5] | rx[6] << 8) - 7 == 1


def test_replies_of_a_sync_read_past_a_silent_servo_are_not_counted_late(smap):
    """Servo 5 goes silent: the plain sync read waits on it while servos 6..18 answer on
    time. Those replies were counted late (each servo once per read), and every later
    error blamed the bus's latency. Now the read names servo 5 alone, nothing is late, and
    the error is the driver's own words, not the SDK's."""
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, guard=False) as drv,
    ):
        drv.bring_up()
        emu.fault("missing:5")
        with pytest.raises(CommError) as info:
            drv.read()
        drv.port.settle()
        assert drv.port.late == {}
    text = str(info.value)
    assert text.startswith("reading feedback after 3 attempt(s): no reply (servo 5"), text
    assert "TxRxResult" not in text and "latency" not in text


def test_close_on_a_silent_bus_returns_soon_and_warns_of_what_it_heard(smap, caplog):
    """Every reply lost: close read Torque Enable of every servo three times (6.4 s at
    16 ms latency); now it stops after a pass with no answer and within its time cap,
    and keeps the servos it could not confirm."""
    with EmulatorProcess() as emu:
        drv = DynamixelDriver(emu.port, smap, latency_timer_ms=16.0, guard=False)
        drv.bring_up()
        emu.fault("drop:1.0")
        t0 = time.monotonic()
        with caplog.at_level(logging.WARNING, logger="firmware_interface.driver"):
            drv.close()
        took = time.monotonic() - t0
        assert not any(s["torque"] for s in emu.servos().values())  # the sync write came
    assert took < TORQUE_OFF_CONFIRM_S + 1.0, took  # its bound, and the sync write's
    assert drv.torque_unconfirmed == sorted(smap.ids)


def test_close_does_not_check_a_servo_that_never_answered(smap, caplog):
    """A servo missing at bring-up is reported there; close read it anyway and warned of
    it again. Now close reads only the servos heard, and confirms them all."""
    with EmulatorProcess(faults=["missing:5"]) as emu:
        drv = DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, guard=False)
        with pytest.raises(MissingServoError):
            drv.bring_up()
        with caplog.at_level(logging.WARNING, logger="firmware_interface.driver"):
            drv.close()
    warned = [r.getMessage() for r in caplog.records if "close:" in r.getMessage()]
    assert warned == [] and drv.torque_unconfirmed == []


def _sdk_status(dxl_id: int, params: bytes) -> bytes:
    """A status packet (error 0, no byte to stuff) built by hand, its CRC the SDK's."""
    body = bytes([0xFF, 0xFF, 0xFD, 0x00, dxl_id, len(params) + 4, 0, 0x55, 0]) + params
    crc = PacketHandler(2.0).updateCRC(0, list(body), len(body))
    return body + bytes([crc & 0xFF, crc >> 8])


def test_the_late_replies_drained_are_counted_past_a_bogus_header_or_a_cut_off_packet():
    """What a drain took off the line: a bogus header (FF FF FD 05) or a packet cut off
    before a whole late status stopped the count, and that status went uncounted."""
    from firmware_interface.port import _status_ids

    whole = _sdk_status(9, b"\x01\x02")
    cut = _sdk_status(4, b"\x10\x20\x30\x40")[:9]
    bad_crc = whole[:-1] + bytes([whole[-1] ^ 0xFF])
    assert _status_ids(whole) == [9]
    assert _status_ids(b"\xff\xff\xfd\x05" + whole) == [9]
    assert _status_ids(cut + whole) == [9]
    assert _status_ids(bad_crc + cut + whole + whole) == [9, 9]
