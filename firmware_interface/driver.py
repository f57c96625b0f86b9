"""``DynamixelDriver``: the payload's 18 XC330 servos behind the ``PayloadDriver`` protocol.

Built on ``dynamixel_sdk`` (PortHandler, PacketHandler 2.0, GroupSyncWrite, GroupSyncRead).
Bring-up follows the LEAP hand's: torque off, Return Delay Time, Operating Mode 5
(current-based position), Position P/I/D, Goal Current as the current cap (the design's
``servo.current_limit``), Bus Watchdog, goal = present position, torque on. Each cycle is
one sync write of the 18 goal positions (:meth:`send`) and one fast sync read of present
current, velocity and position (:meth:`read`, falling back to a plain sync read); every
``health_every`` reads, Hardware Error Status, Bus Watchdog, input voltage and
temperature are read too. A hardware error stops the payload safely (``hold``: every
servo holds where it is; ``torque_off``) and :meth:`recover` reboots the servo, restores
its settings and returns it to service.
"""

from __future__ import annotations

import logging
import time
from types import TracebackType

import numpy as np
from dynamixel_sdk import COMM_SUCCESS, GroupSyncRead, GroupSyncWrite, PacketHandler

from firmware_interface.control_table import ADDR, VELOCITY_UNIT_RPM, hw_error_names, to_signed
from firmware_interface.errors import (
    CommError,
    DynamixelError,
    HardwareFault,
    MissingServoError,
)
from firmware_interface.guard import CommandGuard, default_guard
from firmware_interface.health import Recovery, ServoHealth
from firmware_interface.port import SdkPort
from firmware_interface.servo_map import LINEAR_JOINTS, ServoMap, ServoSpec, load_servo_map
from payload.design.params import Design, load_design
from payload.schema import Health, PayloadCommand, PayloadState

log = logging.getLogger(__name__)

FEEDBACK_ADDR = ADDR["present_current"]  # 126: current (2), velocity (4), position (4)
FEEDBACK_LEN = 10
_FEEDBACK = np.dtype([("current", "<i2"), ("velocity", "<i4"), ("position", "<i4")])
GAINS = {"finger": (600, 0, 200), "abduction": (450, 0, 150), "linear": (600, 0, 200)}
"""Position P, I, D per servo kind (LEAP API values; abduction softer)."""


def _gains(spec: ServoSpec) -> tuple[int, int, int]:
    if spec.joint in LINEAR_JOINTS:
        return GAINS["linear"]
    return GAINS["abduction"] if spec.joint.endswith("mcp_abd") else GAINS["finger"]


class DynamixelDriver:
    """The hardware payload (see the module docstring).

    Args:
        port: Serial device (a USB adapter such as ``/dev/ttyUSB0``, or the emulator's pty).
        servo_map: The servo map (default: the packaged map for the design).
        design: The design (current cap, efforts); default: the project's.
        retries: Extra attempts of a failed read within one cycle.
        health_every: Read temperature, voltage and hardware errors every N reads.
        on_fault: ``hold`` or ``torque_off`` (default: the map's).
        fast: Use fast sync read (falls back to sync read when it fails).
        poll_timeout: Blocking read timeout given to the SDK's serial port [s]: the SDK
            polls a non-blocking port in a busy loop; a short blocking read returns as
            soon as the bytes it asks for are there, without spinning the CPU (0 keeps
            the SDK's busy polling).
        latency_timer_ms: Latency allowance of the reply timeout (SDK default 16 ms).
        guard: Check every command against the self-collision margins before it is sent
            (:mod:`firmware_interface.guard`): ``True`` (default) builds the guard for
            our hand, a :class:`~firmware_interface.guard.CommandGuard` is used as given,
            ``False`` sends commands unchecked (tests of the unit conversions).
    """

    def __init__(
        self,
        port: str,
        servo_map: ServoMap | None = None,
        *,
        design: Design | None = None,
        retries: int = 2,
        health_every: int = 10,
        on_fault: str | None = None,
        fast: bool = True,
        poll_timeout: float = 0.002,
        latency_timer_ms: float = 16.0,
        guard: bool | CommandGuard = True,
    ) -> None:
        self.design = design if design is not None else load_design()
        self.map = servo_map if servo_map is not None else load_servo_map(design=self.design)
        self.retries = retries
        self.health_every = max(1, health_every)
        self.on_fault = on_fault or self.map.on_fault
        self.fast = fast
        self.port = SdkPort(port, latency_timer_ms)
        self.packet = PacketHandler(2.0)
        self.ids = self.map.ids
        self.retry_count = 0
        self.fallbacks = 0
        self.reads = 0
        self.guard: CommandGuard | None = None
        if isinstance(guard, CommandGuard):
            self.guard = guard
        elif guard:
            self.guard = default_guard()
        self.fault: HardwareFault | None = None
        self.faults: list[HardwareFault] = []
        self.health: dict[int, ServoHealth] = {}
        self._stopped = False
        self._closed = True
        self._last_io = time.monotonic()
        self._present = np.zeros(len(self.ids), dtype=np.int64)
        s = self.design.servo
        self._kt = s.stall_torque / s.stall_current  # [N m / A]
        specs = self.map.servos
        self._direction = np.array([sp.direction for sp in specs], dtype=float)
        self._zero = np.array([sp.zero for sp in specs], dtype=float)
        self._units = np.array([sp.units_per_tick for sp in specs])
        self._lower = np.array([sp.lower for sp in specs])
        self._upper = np.array([sp.upper for sp in specs])
        # joint units per servo-shaft radian: 1 for the fingers, radius / gear for the drives
        self._ratio = np.array([sp.units_per_tick / (2 * np.pi / 4096) for sp in self.map.servos])
        try:
            if not self.port.openPort():
                raise DynamixelError(f"{port}: cannot open the serial port")
            if not self.port.setBaudRate(self.map.baud):
                raise DynamixelError(f"{port}: cannot set {self.map.baud} baud")
        except OSError as exc:
            raise DynamixelError(f"{port}: cannot open the serial port ({exc})") from exc
        self._closed = False
        if poll_timeout > 0 and getattr(self.port, "ser", None) is not None:
            self.port.ser.timeout = poll_timeout
        self._writer = GroupSyncWrite(self.port, self.packet, ADDR["goal_position"], 4)
        self._reader = GroupSyncRead(self.port, self.packet, FEEDBACK_ADDR, FEEDBACK_LEN)
        for i in self.ids:
            self._writer.addParam(i, [0, 0, 0, 0])
            self._reader.addParam(i)

    # -- low-level helpers -------------------------------------------------------------------
    def _name(self, dxl_id: int) -> str:
        return f"servo {dxl_id} ({self.map.joint_of(dxl_id)})"

    def _write(self, dxl_id: int, name: str, value: int) -> None:
        """Write one register and check the status (retried on a timeout or CRC error)."""
        addr = ADDR[name]
        size = {64: 1, 9: 1, 11: 1, 98: 1}.get(addr, 4 if addr in (116, 20) else 2)
        fn = {1: self.packet.write1ByteTxRx, 2: self.packet.write2ByteTxRx,
              4: self.packet.write4ByteTxRx}[size]  # fmt: skip
        for attempt in range(self.retries + 1):
            result, error = fn(self.port, dxl_id, addr, int(value) & ((1 << (8 * size)) - 1))
            if result == COMM_SUCCESS:
                if error & 0x7F:
                    raise DynamixelError(
                        f"{self._name(dxl_id)}: writing {name} = {value} failed: "
                        f"{self.packet.getRxPacketError(error)}"
                    )
                return
            if attempt < self.retries:
                self.retry_count += 1
        raise CommError(
            f"{self._name(dxl_id)}: writing {name}: {self.packet.getTxRxResult(result)}"
        )

    def _read_reg(self, dxl_id: int, address: int, size: int) -> int:
        fn = {1: self.packet.read1ByteTxRx, 2: self.packet.read2ByteTxRx,
              4: self.packet.read4ByteTxRx}[size]  # fmt: skip
        for attempt in range(self.retries + 1):
            value, result, _ = fn(self.port, dxl_id, address)
            if result == COMM_SUCCESS:
                return int(value)
            if attempt < self.retries:
                self.retry_count += 1
        raise CommError(f"{self._name(dxl_id)}: reading address {address}: "
                        f"{self.packet.getTxRxResult(result)}")  # fmt: skip

    # -- bring-up ----------------------------------------------------------------------------
    def scan(self) -> dict[int, tuple[int, int]]:
        """Ping every mapped ID: ID -> (model number, firmware version) of those answering."""
        found = {}
        for i in self.ids:
            for _ in range(self.retries + 1):
                model, result, _ = self.packet.ping(self.port, i)
                if result == COMM_SUCCESS:
                    fw = self._read_reg(i, ADDR["firmware_version"], 1)
                    found[i] = (int(model), fw)
                    break
        return found

    def bring_up(self) -> None:
        """Configure every servo and enable torque (LEAP hand's sequence, see the module).

        Raises:
            MissingServoError: Servos that did not answer, named by ID and joint.
            HardwareFault: A servo reports a hardware error at bring-up.
        """
        found = self.scan()
        missing = [i for i in self.ids if i not in found]
        if missing:
            raise MissingServoError(missing, [self.map.joint_of(i) for i in missing])
        for spec in self.map.servos:
            err = self._read_reg(spec.id, ADDR["hardware_error_status"], 1)
            if err:
                raise HardwareFault(spec.id, spec.joint, hw_error_names(err))
            self._configure(spec)
        self._arm_watchdog(self.ids)
        self._last_io = time.monotonic()
        if self.guard is not None:  # where the servos hold is the guard's last safe command
            self.guard.reset(self._direction * (self._present - self._zero) * self._units)

    def _arm_watchdog(self, ids: list[int]) -> None:
        """Bus Watchdog on, for all servos at once (after every servo is configured)."""
        g = GroupSyncWrite(self.port, self.packet, ADDR["bus_watchdog"], 1)
        for i in ids:
            g.addParam(i, [self.map.watchdog_ms // 20])
        result = g.txPacket()
        if result != COMM_SUCCESS:
            raise CommError(f"arming the Bus Watchdog: {self.packet.getTxRxResult(result)}")

    def _configure(self, spec: ServoSpec) -> None:
        i = spec.id
        self._write(i, "torque_enable", 0)
        self._write(i, "return_delay_time", self.map.return_delay)
        self._write(i, "operating_mode", 5)
        p, i_gain, d = _gains(spec)
        self._write(i, "position_p_gain", p)
        self._write(i, "position_i_gain", i_gain)
        self._write(i, "position_d_gain", d)
        self._write(i, "goal_current", self.map.current_limit_ma)
        self._write(i, "bus_watchdog", 0)
        present = to_signed(self._read_reg(i, ADDR["present_position"], 4), 4)
        self._present[self.ids.index(i)] = present
        self._write(i, "goal_position", present)
        self._write(i, "torque_enable", 1)

    # -- protocol ----------------------------------------------------------------------------
    def send(self, command: PayloadCommand) -> None:
        """Sync-write the 18 goal positions (limits applied before conversion).

        Ignored while the payload is stopped by a hardware fault (see :meth:`recover`).
        """
        self._check_open()
        if not isinstance(command, PayloadCommand):
            raise DynamixelError(f"send: expected a PayloadCommand, got {type(command).__name__}")
        values = np.clip(np.append(command.q, command.deploy), self._lower, self._upper)
        if self._stopped:
            return
        if self.guard is not None:  # the last line: no command inside a non-pad margin
            guarded = self.guard.filter(values)
            if guarded is None:
                return
            values = guarded
        ticks = np.rint(self._zero + self._direction * values / self._units).astype(np.int64)
        if self.map.watchdog_ms and time.monotonic() - self._last_io > self.map.watchdog_ms / 1e3:
            # silent for longer than the Bus Watchdog: servos that stopped refuse goals
            # until it is cleared, so re-arm them first
            self._rearm_watchdog()
        self._sync_write_goals(ticks)
        self._last_io = time.monotonic()

    def _rearm_watchdog(self) -> None:
        """Clear and re-arm the servos whose Bus Watchdog tripped (two sync writes)."""
        wd = self._group_read(ADDR["bus_watchdog"], 1)
        tripped = [i for i in self.ids if wd.getData(i, ADDR["bus_watchdog"], 1) == 0xFF]
        if not tripped:
            return
        log.warning("Bus Watchdog tripped on %s; re-arming",
                    ", ".join(self._name(i) for i in tripped))  # fmt: skip
        clear = GroupSyncWrite(self.port, self.packet, ADDR["bus_watchdog"], 1)
        for i in tripped:
            clear.addParam(i, [0])
        clear.txPacket()
        self._arm_watchdog(tripped)

    def _sync_write_goals(self, ticks: list[int]) -> None:
        raw = np.asarray(ticks, dtype="<i4").view(np.uint8).reshape(-1, 4).tolist()
        for i, b in zip(self.ids, raw):
            self._writer.changeParam(i, b)
        result = self._writer.txPacket()
        if result != COMM_SUCCESS:
            raise CommError(f"sync write of the goal positions: "
                            f"{self.packet.getTxRxResult(result)}")  # fmt: skip

    def _sync_read(self, group: GroupSyncRead, what: str) -> None:
        """Fast sync read with retries, then a plain sync read; raises CommError."""
        result = -1
        for attempt in range(self.retries + 1):
            result = group.fastSyncRead() if self.fast else group.txRxPacket()
            if result == COMM_SUCCESS:
                return
            if attempt < self.retries:
                self.retry_count += 1
        if self.fast:
            # fall back to a plain sync read: it names the servo that does not answer
            self.fallbacks += 1
            result = group.txRxPacket()
            if result == COMM_SUCCESS:
                return
        addr = group.start_address
        silent = [i for i in self.ids if not group.isAvailable(i, addr, group.data_length)]
        who = ", ".join(self._name(i) for i in silent) if silent else "the bus"
        raise CommError(f"reading {what} after {self.retries + 1} attempt(s): "
                        f"{self.packet.getTxRxResult(result)} ({who})")  # fmt: skip

    def _feedback(self) -> None:
        """One fast sync read (or a sync read) of current, velocity and position."""
        self._sync_read(self._reader, "feedback")

    def read(self) -> PayloadState:
        """Measured positions [rad, m], velocities and efforts, with health flags.

        Raises:
            CommError: The feedback could not be read within the retries.
        """
        self._check_open()
        self._feedback()
        stamp = self._last_io = time.monotonic()
        self.reads += 1
        # the group's raw bytes per servo: current int16, velocity int32, position int32
        raw = np.frombuffer(
            b"".join(bytes(self._reader.data_dict[i]) for i in self.ids), dtype=_FEEDBACK
        )
        cur = raw["current"].astype(float)
        vel = raw["velocity"].astype(float)
        pos = raw["position"].astype(np.int64)
        self._present = pos
        if self.reads % self.health_every == 0 or self.fault is not None:
            self.check_health()
        return self._state(pos, vel, cur, stamp)

    def _state(
        self, pos: np.ndarray, vel: np.ndarray, cur: np.ndarray, stamp: float
    ) -> PayloadState:
        q = self._direction * (pos - self._zero) * self._units
        w = vel * VELOCITY_UNIT_RPM * 2.0 * np.pi / 60.0  # servo shaft [rad/s]
        torque = cur * 1e-3 * self._kt  # [N m]
        dq = self._direction * w * self._ratio  # [rad/s or m/s]
        effort = self._direction * torque / self._ratio  # [N m or N]
        health = Health.OK
        if self.fault is not None:
            health |= Health.HARDWARE_ERROR
        if np.any(np.abs(cur) >= 0.98 * self.map.current_limit_ma):
            health |= Health.OVERLOAD
        lo, hi = self._lower[:-1], self._upper[:-1]
        if np.any((q[:-1] <= lo + 1e-4) | (q[:-1] >= hi - 1e-4)):
            health |= Health.LIMIT
        return PayloadState(q[:-1], float(q[-1]), stamp, dq[:-1], effort[:-1], health)

    # -- health, faults, recovery ------------------------------------------------------------
    def _group_read(self, address: int, size: int) -> GroupSyncRead:
        g = GroupSyncRead(self.port, self.packet, address, size)
        for i in self.ids:
            g.addParam(i)
        self._sync_read(g, f"address {address}")
        return g

    def read_health(self, dxl_id: int) -> ServoHealth:
        """One servo's health, read register by register (works with servos missing)."""
        return ServoHealth(
            dxl_id,
            self.map.joint_of(dxl_id),
            self._read_reg(dxl_id, ADDR["hardware_error_status"], 1),
            float(self._read_reg(dxl_id, ADDR["present_temperature"], 1)),
            self._read_reg(dxl_id, ADDR["present_input_voltage"], 2) * 0.1,
            self._read_reg(dxl_id, ADDR["bus_watchdog"], 1),
            self._read_reg(dxl_id, ADDR["model_number"], 2),
        )

    def check_health(self) -> dict[int, ServoHealth]:
        """Read Hardware Error Status, Bus Watchdog, input voltage and temperature.

        A hardware error stops the payload safely and is logged (see :meth:`safe_stop`).
        """
        err = self._group_read(ADDR["hardware_error_status"], 1)
        wd = self._group_read(ADDR["bus_watchdog"], 1)
        env = self._group_read(ADDR["present_input_voltage"], 3)
        out = {}
        for spec in self.map.servos:
            i = spec.id
            out[i] = ServoHealth(
                i,
                spec.joint,
                int(err.getData(i, 70, 1)),
                float(env.getData(i, 146, 1)),
                env.getData(i, 144, 2) * 0.1,
                int(wd.getData(i, 98, 1)),
            )
        self.health = out
        if any(h.watchdog == 0xFF for h in out.values()) and not self._stopped:
            self._rearm_watchdog()
        faulted = [h for h in out.values() if h.hardware_error]
        if faulted and (self.fault is None or not self._stopped):
            self._on_hardware_error(faulted)
        return out

    def _on_hardware_error(self, faulted: list[ServoHealth]) -> None:
        h = faulted[0]
        fault = HardwareFault(h.id, h.joint, hw_error_names(h.hardware_error),
                              others=[x.id for x in faulted[1:]])  # fmt: skip
        self.fault = fault
        self.faults.append(fault)
        log.error("payload stopped (%s): %s", self.on_fault, fault)
        self.safe_stop()

    def safe_stop(self) -> None:
        """Stop the payload: hold every servo where it is, or turn the torque off."""
        self._stopped = True
        if self.on_fault == "torque_off":
            g = GroupSyncWrite(self.port, self.packet, ADDR["torque_enable"], 1)
            for i in self.ids:
                g.addParam(i, [0])
            g.txPacket()
            return
        self._sync_write_goals([int(p) for p in self._present])

    def recover(self, timeout: float = 5.0) -> Recovery:
        """Reboot the faulted servo(s), restore their settings, return them to service.

        Returns:
            The servos rebooted and the time from the REBOOT to back in service.

        Raises:
            HardwareFault: The error is still there after the reboot (the cause persists).
            CommError: A servo did not come back within ``timeout``.
        """
        self._check_open()
        self.check_health() if self.fault is None else None
        ids = [h.id for h in self.health.values() if h.hardware_error]
        t0 = time.monotonic()
        for i in ids:
            self.packet.reboot(self.port, i)
        for i in ids:
            while True:
                _, result, _ = self.packet.ping(self.port, i)
                if result == COMM_SUCCESS:
                    break
                if time.monotonic() - t0 > timeout:
                    raise CommError(f"{self._name(i)}: did not answer within {timeout} s of REBOOT")
            err = self._read_reg(i, ADDR["hardware_error_status"], 1)
            if err:
                raise HardwareFault(i, self.map.joint_of(i), hw_error_names(err))
            self._configure(self.map.by_id(i))
        self._arm_watchdog(self.ids)
        if self.on_fault == "torque_off":
            for spec in self.map.servos:
                if spec.id not in ids:
                    present = to_signed(self._read_reg(spec.id, ADDR["present_position"], 4), 4)
                    self._write(spec.id, "goal_position", present)
                    self._write(spec.id, "torque_enable", 1)
        self._stopped = False
        self.fault = None
        seconds = time.monotonic() - t0
        log.info("recovered %s in %.3f s", ", ".join(self._name(i) for i in ids), seconds)
        return Recovery(tuple(ids), seconds)

    # -- lifetime ----------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise DynamixelError("the driver is closed")

    def close(self) -> None:
        """Leave the servos safe (hold where they are, then torque off) and close the port.

        Idempotent; never raises for a bus that stopped answering.
        """
        if self._closed:
            return
        try:
            g = GroupSyncWrite(self.port, self.packet, ADDR["torque_enable"], 1)
            for i in self.ids:
                g.addParam(i, [0])
            g.txPacket()
        except Exception as exc:  # the port may be gone: closing must still succeed
            log.warning("close: could not turn the torque off: %s", exc)
        finally:
            self._closed = True
            try:
                self.port.closePort()
            except Exception:
                pass

    def __enter__(self) -> DynamixelDriver:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
