"""The servo-bus emulator: a :class:`~firmware_interface.bus.Bus` behind a pseudo-terminal.

Run as a process (``python -m firmware_interface.emulator`` or ``payload hw emulate``): it
opens a pty in raw mode, prints the slave's path as the first line of stdout and serves
until interrupted. ``dynamixel_sdk``'s PortHandler opens that path like a USB adapter (a
pty accepts any baud rate; the emulator itself delays every reply by its wire time).

Tests start it with :class:`EmulatorProcess`, which also opens a control channel (JSON
lines on a socket pair) to read the servos' control tables and state from the emulator's
side and to inject faults while it runs.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import socket
import subprocess
import sys
import time
import tty
from types import TracebackType
from typing import Any

from firmware_interface.bus import Bus
from firmware_interface.faults import FaultSpecError, parse_fault
from firmware_interface.servo_dynamics import plants_from_spec
from payload.cliutil import OneLineParser
from payload.errors import PayloadError

TICK_S = 0.005  # dynamics and watchdog update period while idle [s]
SPIN_S = 0.0  # spin this long before a due reply instead of sleeping [s]


class _Server:
    def __init__(self, bus: Bus, control: socket.socket | None) -> None:
        self.bus = bus
        self.control = control
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        tty.setraw(self.master)
        os.set_blocking(self.master, False)
        self.port = os.ttyname(self.slave)
        self.pending: list[tuple[float, bytes]] = []
        self.ctl_buf = b""

    def serve(self) -> None:
        fds = [self.master] + ([self.control] if self.control is not None else [])
        while True:
            now = time.monotonic()
            due = self.pending[0][0] if self.pending else now + TICK_S
            wait = max(0.0, min(due, now + TICK_S) - now - SPIN_S)
            readable, _, _ = select.select(fds, [], [], wait)
            now = time.monotonic()
            if self.master in readable:
                self._read_bus(now)
            if self.control is not None and self.control in readable:
                if not self._read_control():
                    return
            self._send_due()
            self.bus.advance(time.monotonic())

    def _read_bus(self, now: float) -> None:
        try:
            data = os.read(self.master, 65536)
        except BlockingIOError:
            return
        except OSError:  # no reader on the slave side: keep serving
            time.sleep(TICK_S)
            return
        self.pending += self.bus.feed(data, now)

    def _send_due(self) -> None:
        while self.pending:
            due, raw = self.pending[0]
            while time.monotonic() < due:
                if due - time.monotonic() > SPIN_S:
                    return
            self.pending.pop(0)
            try:
                os.write(self.master, raw)
            except OSError:
                pass

    def _read_control(self) -> bool:
        assert self.control is not None
        chunk = self.control.recv(65536)
        if not chunk:
            return False
        self.ctl_buf += chunk
        while b"\n" in self.ctl_buf:
            line, self.ctl_buf = self.ctl_buf.split(b"\n", 1)
            # what the host wrote on the bus before it asked is taken in first: its state
            # then answers for every packet sent before the question (a reply-less sync
            # write, the torque-off at a close, was answered as not yet there under load)
            if select.select([self.master], [], [], 0)[0]:
                self._read_bus(time.monotonic())
            try:
                reply = control(self.bus, json.loads(line))
            except Exception as exc:  # report to the caller, keep serving
                reply = {"error": f"{type(exc).__name__}: {exc}"}
            self.control.sendall(json.dumps(reply).encode() + b"\n")
        return True


def control(bus: Bus, req: dict[str, Any]) -> dict[str, Any]:
    """Answer one control request (``op``: table(s), servos, fault, clear, stats, power, load).

    ``power`` power-cycles every servo; ``load`` sets the external load on servos'
    outputs (``ma``: servo ID -> holding current [mA], signed in the tick direction).
    """
    op = req.get("op")
    bus.advance(time.monotonic(), force=True)
    if op == "table":
        return {"table": bytes(bus.servos[int(req["id"])].table).hex()}
    if op == "tables":
        return {str(i): bytes(s.table).hex() for i, s in bus.servos.items()}
    if op == "servos":
        return {
            str(i): {
                "pos": s.physical,
                "count": s.pos,
                "vel": s.vel,
                "current": s.current,
                "torque": s.torque,
                "hw_error": s.hw_error,
                "last_rx": s.last_rx,
                "watchdog_trip": s.watchdog_trip,
                "reboots": s.reboots,
                "blocked": s.blocked,
                "power_ups": s.power_ups,
                "load_ma": s.load_ma,
            }
            for i, s in bus.servos.items()
        }
    if op == "fault":
        bus.apply(parse_fault(str(req["spec"])))
        return {"ok": True}
    if op == "power":
        bus.power_cycle()
        return {"ok": True}
    if op == "load":
        for k, v in dict(req["ma"]).items():
            bus.servos[int(k)].load_ma = float(v)
        return {"ok": True}
    if op == "cpu":
        return {"cpu_s": time.process_time()}
    if op == "clear":
        bus.clear_faults()
        return {"ok": True}
    if op == "stats":
        st = bus.stats
        return {"packets": st.packets, "crc_errors": st.crc_errors, "dropped": st.dropped,
                "corrupted": st.corrupted, "replies": st.replies}  # fmt: skip
    raise ValueError(f"unknown control op {op!r}")


def bus_spec(servos: str | None, servo_params: str | None = None) -> dict[str, Any]:
    """IDs at the design's home posture, the rail's and the stage's hard stops (the
    design's travel ends), the baud rate of a map file (default map) and each servo's
    plant: the design's servo model moving its joint's load, with the overrides of a
    servo-parameters file (:func:`~firmware_interface.servo_dynamics.
    load_plant_overrides`) applied."""
    from firmware_interface.servo_dynamics import (
        apply_overrides,
        design_plants,
        load_plant_overrides,
    )
    from firmware_interface.servo_map import load_servo_map, posture_ticks, travel_ticks
    from payload.design.params import load_design
    from payload.design.servo import kind_of

    overrides = load_plant_overrides(servo_params) if servo_params else {}  # checked first
    design = load_design()
    smap = load_servo_map(servos, design)
    kinds = {s.id: kind_of(s.joint) for s in smap.servos}
    plants = apply_overrides(design_plants(design, kinds), kinds, overrides, str(servo_params))
    return {
        "positions": posture_ticks(smap, design, "stowed"),  # as the payload powers up
        "baud": smap.baud,
        "stops": travel_ticks(smap, design),
        "plants": {str(i): p.to_dict() for i, p in plants.items()},
    }


def make_bus(spec: dict[str, Any], faults: list[str], seed: int = 0) -> Bus:
    """A bus from :func:`bus_spec` with the faults applied."""
    parsed = [parse_fault(f) for f in faults]  # validate before opening anything
    positions = {int(k): int(v) for k, v in spec["positions"].items()}
    for text, f in zip(faults, parsed):
        if f.id is not None and f.id not in positions:  # a typo's fault would do nothing
            ids = ", ".join(map(str, sorted(positions)))
            raise FaultSpecError(f"fault {text!r}: no servo {f.id} on this bus (IDs {ids})")
    stops = {int(k): (float(v[0]), float(v[1])) for k, v in spec.get("stops", {}).items()}
    bus = Bus(positions, int(spec["baud"]), seed=seed, now=time.monotonic(), stops=stops,
              plants=plants_from_spec(spec))  # fmt: skip
    for f in parsed:
        bus.apply(f)
    return bus


class EmulatorLinkError(PayloadError):
    """The path ``hw emulate --device`` names cannot be made a link to the pty."""


def serve(
    spec: dict[str, Any],
    faults: list[str],
    control_fd: int | None = None,
    seed: int = 0,
    link: str | None = None,
) -> None:
    """Build the bus, print the port path (first stdout line) and serve until interrupted.

    ``link``: a path made a symbolic link to the pty for the time it serves (the device
    path a client is given: ``hw emulate --device DEV``), printed instead of the pty's;
    never made over anything that exists (:class:`FileExistsError`), removed at the end.
    """
    bus = make_bus(spec, faults, seed)
    ctl = socket.socket(fileno=control_fd) if control_fd is not None else None
    server = _Server(bus, ctl)
    if link is not None:
        try:
            os.symlink(server.port, link)
        except OSError as exc:  # there already, a folder not writable: one line
            raise EmulatorLinkError(f"{link}: cannot link it to the pty ({exc.strerror})") from None
    try:
        sys.stdout.write((link or server.port) + "\n")
        sys.stdout.flush()
        server.serve()
    finally:
        if link is not None and os.path.islink(link) and os.readlink(link) == server.port:
            os.unlink(link)


def main(argv: list[str] | None = None) -> int:
    ap = OneLineParser(prog="python -m firmware_interface.emulator", allow_abbrev=False)
    ap.add_argument("--servos", help="servo map TOML (default: the packaged map)")
    ap.add_argument("--fault", action="append", default=[], help="fault spec (repeatable)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--servo-params", help="servo parameters JSON (default: the design's)")
    ap.add_argument("--control-fd", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--bus", help=argparse.SUPPRESS)  # JSON from bus_spec (saves the imports)
    args = ap.parse_args(argv)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    spec = json.loads(args.bus) if args.bus else bus_spec(args.servos, args.servo_params)
    try:
        serve(spec, args.fault, args.control_fd, args.seed)
    except KeyboardInterrupt:
        return 0
    return 0


class EmulatorProcess:
    """The emulator in its own process, with a control channel (context manager).

    Args:
        servos: Servo map file (default map).
        faults: Fault specs applied from the start.
        seed: Seed of the fault dice.
        positions: Servo ID -> physical position at power-up [ticks] (default: the
            design's stowed posture, curled in the bays, as the payload powers up).
        servo_params: Servo-parameters file the servos' plants take (hidden parameters).
    """

    def __init__(
        self,
        servos: str | None = None,
        faults: list[str] | None = None,
        seed: int = 0,
        positions: dict[int, int] | None = None,
        servo_params: str | None = None,
    ) -> None:
        spec = bus_spec(servos, servo_params)
        spec["positions"].update(positions or {})
        for f in faults or []:
            parse_fault(f)
        ours, theirs = socket.socketpair()
        cmd = [sys.executable, "-m", "firmware_interface.emulator", "--seed", str(seed),
               "--control-fd", str(theirs.fileno()), "--bus", json.dumps(spec)]  # fmt: skip
        for f in faults or []:
            cmd += ["--fault", f]
        # a session of its own: a terminal's Ctrl-C goes to the command's process group,
        # and an emulator that took it too ended before the command's close could turn the
        # servos' torque off ("could not turn the torque off"); the command stops it, and it
        # ends on its own when the command's end of the control socket closes
        self.proc = subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            pass_fds=(theirs.fileno(),),
            start_new_session=True,
        )
        theirs.close()
        self._sock = ours
        self._file = ours.makefile("rb")
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline().decode().strip()
        if not line:
            err = self.proc.stderr.read().decode() if self.proc.stderr else ""
            raise RuntimeError(f"emulator did not start: {err.strip().splitlines()[-1:]}")
        self.port = line

    def request(self, **req: Any) -> dict[str, Any]:
        """One control request (see :func:`control`)."""
        self._sock.sendall(json.dumps(req).encode() + b"\n")
        reply = json.loads(self._file.readline())
        if "error" in reply:
            raise RuntimeError(reply["error"])
        return reply

    def table(self, dxl_id: int) -> bytes:
        """Servo ``dxl_id``'s control table as the emulator holds it."""
        return bytes.fromhex(self.request(op="table", id=dxl_id)["table"])

    def tables(self) -> dict[int, bytes]:
        """Every servo's control table, read at one instant."""
        return {int(k): bytes.fromhex(v) for k, v in self.request(op="tables").items()}

    def servos(self) -> dict[int, dict[str, Any]]:
        return {int(k): v for k, v in self.request(op="servos").items()}

    def fault(self, spec: str) -> None:
        self.request(op="fault", spec=spec)

    def clear(self) -> None:
        self.request(op="clear")

    def power_cycle(self) -> None:
        """Every servo off and on (RAM defaults, multi-turn counts lost, EEPROM kept)."""
        self.request(op="power")

    def load(self, ma: dict[int, float]) -> None:
        """External loads on servo outputs, as holding current [mA] (signed in ticks)."""
        self.request(op="load", ma={str(k): v for k, v in ma.items()})

    def stats(self) -> dict[str, Any]:
        return self.request(op="stats")

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._file.close()
        self._sock.close()
        for f in (self.proc.stdout, self.proc.stderr):
            if f is not None:
                f.close()

    def __enter__(self) -> EmulatorProcess:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


if __name__ == "__main__":
    sys.exit(main())
