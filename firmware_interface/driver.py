"""``DynamixelDriver``: the payload's 18 XC330 servos behind the ``PayloadDriver`` protocol.

Built on ``dynamixel_sdk`` (PortHandler, PacketHandler 2.0, GroupSyncWrite, GroupSyncRead).
Bring-up follows the LEAP hand's: torque off, Return Delay Time, Operating Mode 5
(current-based position), Position P/I/D per joint kind from the design's ``[servo.gains]``
(:mod:`payload.design.servo`), Goal Current as the current cap (the design's
``servo.current_limit``), Bus Watchdog, goal = present position, torque on. Each cycle is
one sync write of the 18 goal positions (:meth:`send`) and one fast sync read of present
current, velocity and position (:meth:`read`, falling back to a plain sync read); every
``health_every`` reads, Hardware Error Status, Bus Watchdog, input voltage and
temperature are read too. Every read also looks at each servo's status error byte: its
alert bit (bit 7) means a latched hardware error, and Hardware Error Status of those
servos is read in the same cycle, so the safe stop follows within one control period.
A hardware error stops the payload safely (``hold``: every servo holds where it is;
``torque_off``) and :meth:`recover` reboots the servo, restores its settings and returns
it to service. The rail and the stage are homed at bring-up and after a reboot of either
(:mod:`firmware_interface.homing`); until then :meth:`send` refuses every command.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator, Mapping
from types import TracebackType

import numpy as np
from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupSyncRead,
    GroupSyncWrite,
)

from firmware_interface import protocol as P
from firmware_interface.control_table import (
    ADDR,
    BY_ADDRESS,
    BY_NAME,
    CURRENT_UNIT_A,
    EMULATOR_MODEL_INFORMATION,
    RAD_PER_TICK,
    VELOCITY_UNIT_RPM,
    hw_error_names,
    to_signed,
)
from firmware_interface.deployment import fold_before_homing
from firmware_interface.errors import (
    BringUpFailed,
    CommError,
    DynamixelError,
    HardwareFault,
    MissingServoError,
    NotHomedError,
    WrongModelError,
    cannot_open,
)
from firmware_interface.fault_handling import FaultHandling
from firmware_interface.guard import CommandGuard, default_guard
from firmware_interface.health import ServoHealth
from firmware_interface.homing import home_linear
from firmware_interface.options import LATENCY_MS
from firmware_interface.port import AlertSyncRead, CheckedPacketHandler, SdkPort
from firmware_interface.servo_map import (
    LINEAR_JOINTS,
    ServoMap,
    ServoSpec,
    load_servo_map,
    travel_ticks,
)
from firmware_interface.shutdown import Shutdown
from payload.design.params import Design, load_design
from payload.design.servo import gains_of, kind_of
from payload.schema import Health, PayloadCommand, PayloadState

log = logging.getLogger(__name__)

FEEDBACK_ADDR = ADDR["present_current"]  # 126: current (2), velocity (4), position (4)
FEEDBACK_LEN = 10
_FEEDBACK = np.dtype([("current", "<i2"), ("velocity", "<i4"), ("position", "<i4")])


_LATE_HINT = ("the bus answers later than the driver allows (an adapter's latency timer "
              "above the one given: --latency-ms?)")  # fmt: skip


def late_words(n: int | None, allowance_ms: float, then: str, ids: list[int] | None = None) -> str:
    """How the hardware layer says that replies came after their timeout: ``n`` of them
    (None: some), the ``allowance_ms`` timeout, of ``ids`` (the first named before these
    words, the others after them), then ``then`` (what it means or what to try)."""
    many = "replies" if n is None else f"{n} repl{'y' if n == 1 else 'ies'}"
    return f"{many} came after the {allowance_ms:.0f} ms reply timeout{_also(ids or [])}: {then}"


def _also(ids: list[int]) -> str:
    return f" (also IDs {', '.join(map(str, ids[1:]))})" if len(ids) > 1 else ""


def bring_up_notice(device: str) -> str:
    """What a command says before :meth:`DynamixelDriver.bring_up` on ``device``: the
    servos are powered and the rail and the stage driven to their hard stops to home."""
    return f"bringing up the servos on {device} and homing the rail and the stage"


def nobody_answered(device: str) -> str:
    """What the commands say of a bus where no servo answers."""
    return f"no servo answered on {device} (power, wiring, baud rate, IDs?)"


LATCHED_REMEDY = (
    "a hardware error stays latched until the servo restarts: remove its cause (a blocked "
    "joint for overload, the supply for input_voltage, time to cool for overheating), then "
    "power-cycle the servos"
)
"""What to do about a latched hardware error (the e-Manual's Hardware Error Status:
cleared by a reboot only); ``hw check`` says it after the errors it read."""
LATCHED_HINT = f"{LATCHED_REMEDY}; `payload hw check` shows every servo's state"
"""What to do about a hardware error the bring-up found."""


@contextlib.contextmanager
def failed_start(device: str) -> Iterator[None]:
    """A hardware error inside (the bring-up, the drive home) as a failed start of the
    payload on ``device``: :class:`~firmware_interface.errors.BringUpFailed` (exit 1), in
    one line, a bus where no servo answers said as ``hw scan`` and ``hw check`` say it,
    not as eighteen missing IDs; the hardware's state, not the command line's input."""
    try:
        yield
    except DynamixelError as exc:
        everyone = isinstance(exc, MissingServoError) and exc.everyone
        why = nobody_answered(device) if everyone else f"bring-up on {device} failed: {exc}"
        if any(isinstance(f, HardwareFault) and f.bits != ["reset"] for f in (exc, *exc.also)):
            why += f" ({LATCHED_HINT})"
        raise BringUpFailed(why) from None


class DynamixelDriver(FaultHandling, Shutdown):
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
        latency_timer_ms: float = LATENCY_MS,
        guard: bool | CommandGuard = True,
    ) -> None:
        self.design = design if design is not None else load_design()
        self.map = servo_map if servo_map is not None else load_servo_map(design=self.design)
        self.retries = retries
        self.health_every = max(1, health_every)
        self.on_fault = on_fault or self.map.on_fault
        self.fast = fast
        self.port = SdkPort(port, latency_timer_ms)
        self.packet = CheckedPacketHandler()  # the SDK's, every status's length checked
        self.ids = self.map.ids
        self.heard: set[int] = set()  # servos that answered a scan
        # mapped IDs whose last answer to a scan gave another model number than the map's
        # (ID -> that number): no shutdown writes to them or reads them (_owed_torque_off)
        self.other_model: dict[int, int] = {}
        self._enabled: set[int] = set()  # servos the driver ever sent a torque enable
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
        self.homed: set[int] = set()
        self.device = port
        self.emulated = False  # the far end reports the emulator's Model Information
        # per trip: "t" (the host's monotonic clock [s]) and "unix_s" (the wall clock) when
        # the next command re-armed them, "servos", "silence_s" (the host's silence);
        # ``hw run`` adds "session_t", the session time [s] of that command
        self.watchdog_trips: list[dict] = []
        self.alerts = 0  # reads whose status carried an alert bit
        self._linear = [sp for sp in self.map.servos if sp.joint in LINEAR_JOINTS]
        self._stopped = False
        self._torque_on = False  # set once brought up: a servo then found torque off restarted
        self._reset: set[int] = set()
        self._closed = True
        self.torque_unconfirmed: list[int] = []  # servos close() could not confirm off
        self._last_io = time.monotonic()
        self._longest_gap = 0.0  # the host's longest bus silence since a check or an arming
        self._present = np.zeros(len(self.ids), dtype=np.int64)
        self._known: set[int] = set()  # servos whose present position has been read
        s = self.design.servo
        self._kt = s.kt  # [N m / A], output-side
        specs = self.map.servos
        self._direction = np.array([sp.direction for sp in specs], dtype=float)
        self._zero = np.array([sp.zero for sp in specs], dtype=float)
        self._units = np.array([sp.units_per_tick for sp in specs])
        self._lower = np.array([sp.lower for sp in specs])
        self._upper = np.array([sp.upper for sp in specs])
        # joint units per servo-shaft radian: 1 for the fingers, radius / gear for the drives
        self._ratio = np.array([sp.units_per_tick / RAD_PER_TICK for sp in self.map.servos])
        try:
            if not self.port.openPort():
                raise DynamixelError(cannot_open(port))
            if not self.port.setBaudRate(self.map.baud):
                raise DynamixelError(f"{port}: cannot set {self.map.baud} baud")
        except OSError as exc:
            # pyserial's error repeats the system's ("[Errno 2] could not open port P:
            # [Errno 2] No such file or directory: 'P'"): say the system's reason once
            cause = exc.__context__ if isinstance(exc.__context__, OSError) else exc
            reason = cause.strerror or str(cause)
            if "Inappropriate ioctl" in str(exc):  # ENOTTY from the port's configuration
                reason = "not a serial device: give the USB adapter's, e.g. /dev/ttyUSB0"
            raise DynamixelError(cannot_open(port, reason)) from exc
        self._closed = False
        if poll_timeout > 0 and getattr(self.port, "ser", None) is not None:
            self.port.ser.timeout = poll_timeout
        self._writer = GroupSyncWrite(self.port, self.packet, ADDR["goal_position"], 4)
        self._reader = AlertSyncRead(self.port, self.packet, FEEDBACK_ADDR, FEEDBACK_LEN)
        for i in self.ids:
            self._writer.addParam(i, [0, 0, 0, 0])
            self._reader.addParam(i)

    # -- low-level helpers -------------------------------------------------------------------
    def _name(self, dxl_id: int) -> str:
        return f"servo {dxl_id} ({self.map.joint_of(dxl_id)})"

    def _why(self, result: int, dxl_id: int | None = None) -> str:
        """A failed transaction's result in the driver's words (not the SDK's), with the
        replies that came after their timeout (from ``dxl_id``, or from any servo)."""
        if result == COMM_RX_TIMEOUT:
            words = "no reply"
        elif result == COMM_RX_CORRUPT:
            words = "a corrupt reply (bad CRC, or not the length asked for)"
        else:
            words = self.packet.getTxRxResult(result).removeprefix("[TxRxResult] ")
        self.port.settle()  # what is still on its way is counted as late
        late = self.port.late
        n = late.get(dxl_id, 0) if dxl_id is not None else sum(late.values())
        if n:
            words += f"; {self._late_words(n)}"
        return words

    def _late_words(self, n: int | None = None, ids: list[int] | None = None) -> str:
        """What the driver says of replies that came after their timeout: ``n`` of them
        (None: some), of ``ids`` (the first named before these words, the others after
        them), and what to try."""
        return late_words(n, self.port.reply_allowance_ms, _LATE_HINT, ids)

    def _write(self, dxl_id: int, name: str, value: int) -> None:
        """Write one register and check the status (retried on a timeout or CRC error)."""
        addr, size = ADDR[name], BY_NAME[name].size
        if name == "torque_enable" and value:  # sent: it may be on even if no reply came
            self._enabled.add(dxl_id)
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
        raise CommError(f"{self._name(dxl_id)}: writing {name} after {self.retries + 1} "
                        f"attempt(s): {self._why(result, dxl_id)}")  # fmt: skip

    def _read_reg(self, dxl_id: int, address: int, size: int) -> int:
        fn = {1: self.packet.read1ByteTxRx, 2: self.packet.read2ByteTxRx,
              4: self.packet.read4ByteTxRx}[size]  # fmt: skip
        for attempt in range(self.retries + 1):
            value, result, _ = fn(self.port, dxl_id, address)
            if result == COMM_SUCCESS:
                return int(value)
            if attempt < self.retries:
                self.retry_count += 1
        reg = BY_ADDRESS[address].name if address in BY_ADDRESS else f"address {address}"
        raise CommError(f"{self._name(dxl_id)}: reading {reg} after {self.retries + 1} "
                        f"attempt(s): {self._why(result, dxl_id)}")  # fmt: skip

    # -- bring-up ----------------------------------------------------------------------------
    def scan(self) -> dict[int, tuple[int, int | None]]:
        """Ping every mapped ID: ID -> (model number, firmware version) of those answering.

        Those answering as another model than the map's are kept in ``other_model`` (a
        servo not answering keeps what an earlier scan found of it); their firmware
        version is None: no register of another model's control table is read.

        Raises:
            CommError: A servo whose replies come, but after the reply timeout (not a
                missing servo: the bus's latency is above the driver's allowance).
        """
        found = {}
        for i in self.ids:
            for _ in range(self.retries + 1):
                model, result, _ = self.packet.ping(self.port, i)
                if result == COMM_SUCCESS:
                    ours = int(model) == self.map.model_number
                    fw = self._read_reg(i, ADDR["firmware_version"], 1) if ours else None
                    found[i] = (int(model), fw)
                    break
        self.heard.update(found)
        for i, (model, _) in found.items():
            if model != self.map.model_number:
                self.other_model[i] = model
            else:
                self.other_model.pop(i, None)
        late = [i for i in self.ids if i not in found and self._late(i)]
        if late:  # the count is the first servo's, named before it (the others after it)
            raise CommError(f"{self._name(late[0])}{_also(late)}: no reply to a ping, but "
                            f"{self._late_words(self._late(late[0]))}")  # fmt: skip
        return found

    def _late(self, dxl_id: int) -> int:
        """Replies of ``dxl_id`` that came after their timeout (the line drained first)."""
        self.port.settle()
        return self.port.late.get(dxl_id, 0)

    def bring_up(self) -> None:
        """Configure every servo and enable torque (LEAP hand's sequence, see the module).

        Every servo is looked at before any is configured: the error raised names every
        servo at fault, its type the first kind found of missing, another model, a
        hardware error (the others in its ``also``).

        Raises:
            MissingServoError: Servos that did not answer, named by ID and joint.
            WrongModelError: A servo that is not the map's model (named).
            HardwareFault: A servo reports a hardware error at bring-up (``also``: the
                other servos that do).
            CommError: Replies lost, corrupt or late after the retries.
        """
        late = dict(self.port.late)
        found = self.scan()
        faults: list[DynamixelError] = []  # the most severe kind first
        missing = [i for i in self.ids if i not in found]
        if missing:
            joints = [self.map.joint_of(i) for i in missing]
            everyone = len(missing) == len(self.ids)
            faults.append(MissingServoError(missing, joints, everyone=everyone))
        wrong = {i for i in found if i in self.other_model}
        faults += [WrongModelError(i, self.map.joint_of(i), found[i][0], self.map.model_number)
                   for i in self.ids if i in wrong]  # fmt: skip
        came = [i for i in self.ids if self._late(i) > late.get(i, 0)]
        if came:  # a bus whose replies come late: a later one could answer the wrong read,
            # so no error bits are read; the late replies are said with the rest
            faults.append(CommError(f"{self._name(came[0])}: {self._late_words(ids=came)}"))
        else:  # each servo's latched error bits (another model's register there is not them)
            lost: list[DynamixelError] = []  # a read that failed: said after the faults found
            for spec in self.map.servos:
                if spec.id in found and spec.id not in wrong:
                    try:
                        err = self._read_reg(spec.id, ADDR["hardware_error_status"], 1)
                    except CommError as exc:
                        lost.append(exc)
                        continue
                    if err:
                        faults.append(HardwareFault(spec.id, spec.joint, hw_error_names(err)))
            faults += lost
        if faults:
            raise faults[0].joined(faults[1:])
        info = self._read_reg(self.ids[0], ADDR["model_information"], 4)
        self.emulated = info == EMULATOR_MODEL_INFORMATION
        for spec in self.map.servos:
            self._configure(spec)
        fold_before_homing(self)  # fingers out of the bays: folded first (or refused)
        for spec in self._linear:  # the rail to its stowed end, then the stage up
            self.home([spec])
        self._arm_watchdog(self.ids)
        self._torque_on = True
        self._last_io = time.monotonic()
        if self.guard is not None:  # where the servos hold is the guard's last safe command
            self.guard.reset(self._direction * (self._present - self._zero) * self._units)

    def home(self, specs: list[ServoSpec] | None = None) -> dict[int, int]:
        """Home the rail and the stage (default both): a current-limited move to the stowed
        hard stop, Homing Offset set from it (see :mod:`firmware_interface.homing`).

        Returns:
            ID -> the Homing Offset written [ticks].

        Raises:
            HomingError: A servo did not reach its stop in time.
        """
        specs = self._linear if specs is None else specs
        for sp in specs:
            self.homed.discard(sp.id)
        spans = {i: hi - lo for i, (lo, hi) in travel_ticks(self.map, self.design).items()}

        def feedback() -> tuple[np.ndarray, np.ndarray]:
            raw = self._feedback_raw()
            return raw["current"].astype(float), raw["position"].astype(np.int64)

        offsets = home_linear(self._write, self._read_reg, feedback, self.ids, specs, spans,
                              self.map.current_limit_ma)  # fmt: skip
        self.homed.update(sp.id for sp in specs)
        log.info("homed %s", ", ".join(f"{self._name(i)} (offset {h})" for i, h in offsets.items()))
        return offsets

    def present_ticks(self) -> np.ndarray:
        """One feedback read's Present Positions, raw [ticks], map order: homed or not
        (the fingers' are absolute within their one turn, the rail's and the stage's
        known only once homed)."""
        self._check_open()
        pos = self._feedback_raw()["position"].astype(np.int64)
        self._present = pos
        self._known.update(self.ids)
        return pos.copy()

    def goal_ticks(self, ticks: Mapping[int, int]) -> None:
        """One sync write of raw goal positions to some servos (ID -> ticks), homed or
        not, neither clipped to the joints' limits nor guarded: for motions checked
        elsewhere (:func:`firmware_interface.deployment.fold_before_homing`)."""
        self._check_open()
        goals = np.array([ticks.get(i, 0) for i in self.ids], dtype=np.int64)
        self._sync_write_goals(goals, [i for i in self.ids if i in ticks])
        self._last_io = time.monotonic()

    def set_watchdog(self, armed: bool) -> None:
        """Arm (the map's period) or disarm the Bus Watchdog of every servo: a session
        disarms it while it sets up (no 50 Hz traffic yet) and arms it once its loop runs."""
        self._arm_watchdog(self.ids, armed)

    def _arm_watchdog(self, ids: list[int], armed: bool = True) -> None:
        """Bus Watchdog on, for all servos at once (after every servo is configured)."""
        g = GroupSyncWrite(self.port, self.packet, ADDR["bus_watchdog"], 1)
        for i in ids:
            g.addParam(i, [self.map.watchdog_ms // 20 if armed else 0])
        result = g.txPacket()
        if result != COMM_SUCCESS:
            raise CommError(f"arming the Bus Watchdog: {self._why(result)}")
        if armed:  # a later trip: only a silence from here on could have caused it
            self._longest_gap = 0.0

    def _configure(self, spec: ServoSpec) -> None:
        i = spec.id
        self._write(i, "torque_enable", 0)
        self._write(i, "return_delay_time", self.map.return_delay)
        self._write(i, "operating_mode", int(self.design.servo.operating_mode))
        p, i_gain, d = gains_of(self.design, kind_of(spec.joint))
        self._write(i, "position_p_gain", p)
        self._write(i, "position_i_gain", i_gain)
        self._write(i, "position_d_gain", d)
        self._write(i, "goal_current", self.map.current_limit_ma)
        self._write(i, "bus_watchdog", 0)
        present = to_signed(self._read_reg(i, ADDR["present_position"], 4), 4)
        self._present[self.ids.index(i)] = present
        self._known.add(i)
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
        if self._stopped:  # nothing goes out (a reset servo is homed again by recover())
            return
        unhomed = [sp.joint for sp in self._linear if sp.id not in self.homed]
        if unhomed:
            raise NotHomedError(f"{' and '.join(unhomed)} not homed: bring_up() homes them")
        values = np.clip(np.append(command.q, command.deploy), self._lower, self._upper)
        if self.guard is not None:  # the last line: no command inside a non-pad margin
            guarded = self.guard.filter(values)
            if guarded is None:
                return
            values = guarded
        ticks = np.rint(self._zero + self._direction * values / self._units).astype(np.int64)
        # a failed reply's drain first: the silence it adds may trip the Bus Watchdog
        self.port.settle()
        silence = self._silence_until(time.monotonic())
        if self.map.watchdog_ms and silence > self.map.watchdog_ms / 1e3:
            # silent for longer than the Bus Watchdog: servos that stopped refuse goals
            # until it is cleared, so re-arm them first
            self._rearm_watchdog(silence)
        self._sync_write_goals(ticks)
        self._last_io = time.monotonic()

    def _silence_until(self, now: float) -> float:
        """The host's silence on the bus until ``now`` [s], kept as the longest since the
        last health check or arming of the watchdog (what a trip found later is put down to)."""
        silence = now - self._last_io
        self._longest_gap = max(self._longest_gap, silence)
        return silence

    def _rearm_watchdog(self, silence: float) -> None:
        """Clear and re-arm the servos whose Bus Watchdog tripped (two sync writes);
        ``silence``: the host's longest silence on the bus that could have tripped it [s]
        (recorded with the trip; shorter than the watchdog's time when the host was never
        silent that long and the far end missed or delayed its packets)."""
        wd = self._group_read(ADDR["bus_watchdog"], 1)
        tripped = [i for i in self.ids if wd.getData(i, ADDR["bus_watchdog"], 1) == 0xFF]
        if not tripped:
            return
        limit_ms = self.map.watchdog_ms
        host = not limit_ms or silence * 1e3 >= limit_ms
        self.watchdog_trips.append(
            {
                "t": time.monotonic(),
                "unix_s": round(time.time(), 3),
                "servos": tripped,
                "silence_s": round(silence, 4),
                "host_silent_long_enough": host,
            }
        )
        if host:
            log.warning("Bus Watchdog tripped on %d servo(s) after %.0f ms of host silence: "
                        "they held still until now; re-arming", len(tripped),
                        silence * 1e3)  # fmt: skip
        else:
            log.warning("Bus Watchdog tripped on %d servo(s) although the host was silent "
                        "for at most %.0f ms (its time: %d ms): the bus or the servos missed "
                        "or delayed packets; they held still until now; re-arming",
                        len(tripped), silence * 1e3, limit_ms)  # fmt: skip
        clear = GroupSyncWrite(self.port, self.packet, ADDR["bus_watchdog"], 1)
        for i in tripped:
            clear.addParam(i, [0])
        clear.txPacket()
        self._arm_watchdog(tripped)

    def _sync_write_goals(self, ticks: list[int], ids: list[int] | None = None) -> None:
        """One sync write of the goal positions ``ticks`` (one per mapped servo, in the
        map's order) to the servos ``ids`` (default: every mapped servo; none: no write)."""
        raw = np.asarray(ticks, dtype="<i4").view(np.uint8).reshape(-1, 4).tolist()
        writer = self._writer
        if ids is None or ids == self.ids:
            for i, b in zip(self.ids, raw):
                writer.changeParam(i, b)
        elif not ids:
            return
        else:  # some of them: a group of their own
            writer = GroupSyncWrite(self.port, self.packet, ADDR["goal_position"], 4)
            for i, b in zip(self.ids, raw):
                if i in ids:
                    writer.addParam(i, b)
        result = writer.txPacket()
        if result != COMM_SUCCESS:
            raise CommError(f"sync write of the goal positions: {self._why(result)}")

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
        # a plain sync read reads the servos in turn and stops at the first that does not
        # answer: name that one (the group's own isAvailable is False for all of them then)
        silent = getattr(group, "silent_id", None)
        if silent is None:  # the SDK's group: the first servo it holds no data of
            n = group.data_length
            silent = next((i for i in self.ids if len(group.data_dict.get(i, [])) != n), None)
        who = f"{self._name(silent)} did not answer" if silent is not None else "the bus"
        raise CommError(f"reading {what} after {self.retries + 1} attempt(s): "
                        f"{self._why(result, silent)} ({who})")  # fmt: skip

    def _feedback(self) -> None:
        """One fast sync read (or a sync read) of current, velocity and position."""
        self._sync_read(self._reader, "feedback")

    def _feedback_raw(self) -> np.ndarray:
        """One feedback read as a record array (current, velocity, position), shape (n,)."""
        self._feedback()
        now = time.monotonic()
        self._silence_until(now)
        self._last_io = now
        return np.frombuffer(
            b"".join(bytes(self._reader.data_dict[i]) for i in self.ids), dtype=_FEEDBACK
        )

    def read(self) -> PayloadState:
        """Measured positions [rad, m], velocities and efforts, with health flags.

        Raises:
            CommError: The feedback could not be read within the retries.
        """
        self._check_open()
        # the group's raw bytes per servo: current int16, velocity int32, position int32
        raw = self._feedback_raw()
        stamp = self._last_io
        self.reads += 1
        cur = raw["current"].astype(float)
        vel = raw["velocity"].astype(float)
        pos = raw["position"].astype(np.int64)
        self._present = pos
        self._known.update(self.ids)
        alerted = [i for i in self.ids if self._reader.errors.get(i, 0) & P.ALERT]
        if alerted:
            self.alerts += 1
        if self.reads % self.health_every == 0 or self.fault is not None:
            self.check_health()
        elif alerted and not self._stopped:
            self._check_alerted(alerted)
        return self._state(pos, vel, cur, stamp)

    def _state(
        self, pos: np.ndarray, vel: np.ndarray, cur: np.ndarray, stamp: float
    ) -> PayloadState:
        q = self._direction * (pos - self._zero) * self._units
        w = vel * VELOCITY_UNIT_RPM * 2.0 * np.pi / 60.0  # servo shaft [rad/s]
        torque = cur * CURRENT_UNIT_A * self._kt  # [N m]
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

    # -- lifetime ----------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise DynamixelError("the driver is closed")

    def __enter__(self) -> DynamixelDriver:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
