"""The live Quest interface's command-line parts: options, terminal status line, serving.

``payload teleop serve`` and ``payload bench teleop`` are registered by
:mod:`payload.trials.live_cli`, which composes the live session (a trial-layer
:class:`~payload.trials.live.LiveSession`) and hands it to :func:`serve` and
:func:`bench` here as a factory: this package never imports the trials above it.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from firmware_interface.options import add_latency, add_servo_map
from payload.cliutil import (
    add_device,
    add_json,
    check_seconds,
    command_project,
    drop_log_lines,
    emit_json,
    out_folder,
    say_stage,
)
from payload.errors import STOP_SIGNALS, PayloadError
from payload.folders import other_results

SessionFactory = Callable[..., Any]
"""Makes the live session: ``(hub, record, payload=..., collisions=...)``, an object with
``scene``, ``steps``, ``run()`` and ``close()`` (:class:`payload.trials.live.LiveSession`)."""


def _load_text(load: list[float]) -> str:
    """The 1, 5 and 15 min load averages as a line says them (``0.97, 1.64, 1.59``)."""
    return ", ".join(f"{v:.2f}" for v in load)


class TeleopCliError(PayloadError):
    """Bad arguments to a teleop command."""


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"port {value} outside 0..65535")
    return value


def _ms(v: float | None) -> str:
    return "-" if v is None or v != v else f"{v:.1f}"


def status_line(status: dict[str, Any], lat: dict[str, float]) -> str:
    """One line for the terminal: ``/status`` and the XR frame -> command latency."""
    d = status["dropped"]
    age = status["frame_age_ms"]
    refused = " ".join(f"{k}={v}" for k, v in d.items() if v)
    return (
        f"{status['state']:<11} [{status.get('driver', 'simulator')}] "
        f"clients={status['clients']} frames={status['frames']} "
        f"age={_ms(age['median'])}/{_ms(age['p99'])} ms "
        f"latency={_ms(lat['median'])}/{_ms(lat['p99'])} ms "
        f"overruns={status['loop_overruns']} dropped: {refused or 'none'}"
    )


@contextlib.contextmanager
def _press_twice_to_abandon(record: Path | None) -> Iterator[None]:
    """While the server stops and the session is closed and scored (a second or so), a
    Ctrl-C (or a SIGTERM or SIGHUP the command stops on as on Ctrl-C) says what it would
    cost and only a second one stops."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    presses = []
    previous = {}

    def on_interrupt(signum: int, frame: Any) -> None:
        presses.append(signum)
        if len(presses) > 1:
            handler = previous[signum]
            if callable(handler) and signum != signal.SIGINT:
                handler(signum, frame)  # the command's own stop (payload.cli's)
            raise KeyboardInterrupt
        print(
            "\nscoring the session: Ctrl-C again stops without its metrics.json and figures",
            file=sys.stderr,
        )

    for signum in (signal.SIGINT, *STOP_SIGNALS):
        handler = signal.getsignal(signum)
        if signum == signal.SIGINT or callable(handler):  # not where ignored or default
            previous[signum] = signal.signal(signum, on_interrupt)
    try:
        yield
    except KeyboardInterrupt:
        if record is not None:
            print(
                f"stopped before scoring: metrics.json and the figures of {record} were "
                "not written",
                file=sys.stderr,
            )
        raise
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


_STDERR = threading.RLock()
"""Held while the status line or a log record is written to stderr (never interleaved)."""


class _BesideStatusLine(logging.StreamHandler):
    """Log records on stderr, each on a line of its own: on a terminal the status line
    (:func:`_status_printer`, redrawn in place) is cleared first, so a warning does not
    run on from it; the next status redraws below the record. The workbench's messages
    name their part ("teleop safety: ..."); another library's record is prefixed with its
    logger's name."""

    OURS = logging.Formatter("%(levelname)s %(message)s")
    THEIRS = logging.Formatter("%(levelname)s %(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        mine = record.name == "payload" or record.name.startswith("payload.")
        return (self.OURS if mine else self.THEIRS).format(record)

    def emit(self, record: logging.LogRecord) -> None:
        with _STDERR:
            if self.stream.isatty():
                self.stream.write("\r\033[K")
            super().emit(record)


STATUS_LOG_S = 10.0
"""Without a terminal (a log, a pipe), the status line is written when the session's state
or its operator changes, else this often [s]: a line a second filled the log."""


def _status_printer(hub: Any, stop: threading.Event, interval: float) -> None:
    tty = sys.stderr.isatty()
    said: tuple[Any, ...] | None = None
    said_at = -math.inf
    while not stop.wait(interval):
        status = hub.status()
        line = status_line(status, hub.latency())
        if not tty:
            now, what = time.monotonic(), (status.get("state"), status.get("operator"))
            if what == said and now - said_at < STATUS_LOG_S:
                continue
            said, said_at = what, now
        with _STDERR:
            sys.stderr.write(f"\r{line}\033[K" if tty else line + "\n")
            sys.stderr.flush()


def _check_record(record: Path | None) -> None:
    if record is None:
        return
    # a file on the way, a folder that cannot be made or written in, any command's results
    # (a trial's recordings are never replaced): one line now, not a traceback once the
    # operator has calibrated
    out_folder(record, "--record", holding=other_results())


def _check_bus_options(args: argparse.Namespace) -> None:
    """``--device``, ``--emulator``, ``--servos`` and ``--latency-ms`` go with ``--driver
    hardware`` (one bus: a device or the emulator); one line, exit 2, before anything."""
    from firmware_interface.errors import missing_device
    from firmware_interface.options import latency_problem

    if args.driver != "hardware":
        given = {"--device": args.device, "--emulator": args.emulator or None,
                 "--servos": args.servos, "--latency-ms": args.latency_ms,
                 "--stay-deployed": args.stay_deployed or None}  # fmt: skip
        for option, value in given.items():
            if value is not None:
                shown = option if value is True else f"{option} {value}"
                raise TeleopCliError(f"{shown}: only with --driver hardware")
        return
    if args.device and args.emulator:
        raise TeleopCliError("--device and --emulator: give one bus")
    if not args.device and not args.emulator:
        raise TeleopCliError(
            "--driver hardware needs --device DEV (the servo bus's serial device), or --emulator"
        )
    problem = latency_problem(args.latency_ms)
    if problem is not None:
        raise TeleopCliError(problem)
    if (missing := missing_device(args.device)) is not None:  # before the models' rebuild
        raise TeleopCliError(missing)


def _hardware_driver(args: argparse.Namespace, smap: Any, stack: contextlib.ExitStack) -> Any:
    """The Dynamixel payload driver (``firmware_interface``) on ``--device`` (or on an
    emulator started here, stopped with ``stack``), with the servo map ``smap`` and
    ``--latency-ms``, brought up (the rail and the stage homed), at the design's home
    posture where the simulated session starts, its Bus Watchdog disarmed until the
    session's loop runs (the simulator and the retargeters load for seconds first)."""
    from firmware_interface import DynamixelDriver
    from firmware_interface.options import latency_of
    from firmware_interface.run import ready_at_home

    device = args.device
    if args.emulator:
        from firmware_interface.emulator import EmulatorProcess

        device = stack.enter_context(EmulatorProcess(args.servos)).port
    latency = latency_of(args.latency_ms, args.emulator)
    driver = DynamixelDriver(device, smap, latency_timer_ms=latency)
    try:  # the servos move: said first, on stderr (stdout names the page), as `hw run` does
        ready_at_home(driver, say_stage)
    except BaseException:
        driver.close()
        raise
    return driver


def serve(
    args: argparse.Namespace,
    make_session: SessionFactory,
    report: Callable[[dict[str, Any]], None] | None = None,
) -> int:
    """``payload teleop serve``: the live page driving the session ``make_session`` makes."""
    from payload.profiles import SAFE, resolve_args
    from payload.teleop.live import LiveHub
    from payload.teleop.server import TeleopServer, check_address, is_local, new_token
    from payload.teleop.tls import (
        CA_NAME,
        CERT_NAME,
        config_dir,
        ensure_certificate,
        fingerprint,
        server_context,
    )

    # every check of the command line before the long set-up (the models, the simulator)
    _check_bus_options(args)
    link_delay = None
    if args.link_delay is not None:
        from payload.teleop.link import parse_link_delay

        link_delay = parse_link_delay(args.link_delay)
    prof, overrides = resolve_args(args, SAFE)
    desktop = None
    if args.desktop:
        from payload.teleop.emulate import EmulationError, find_iwer

        try:
            desktop = find_iwer()
        except EmulationError as exc:
            raise TeleopCliError(f"--desktop: {exc}") from None
    record = Path(args.record) if args.record else None
    _check_record(record)
    if (args.cert is None) != (args.key is None):
        raise TeleopCliError("--cert and --key go together (a certificate and its key)")
    for option, given in (("--cert", args.cert), ("--key", args.key)):
        path = None if given is None else Path(given)
        if path is not None and (path.is_dir() or not path.exists()):
            what = "a folder, not a PEM file" if path.is_dir() else "no such file"
            raise TeleopCliError(f"{option} {given}: {what}")  # the rest: the TLS load says
    check_address(args.host, args.port)
    if args.seconds:  # the hidden time limit (tests, scripts); 0: none
        check_seconds("--seconds", args.seconds)
    project = command_project(args)  # the simulator and the retargeters read its models
    from payload.design import models_follow_design

    models_follow_design(project.design_path, project.root)  # the one rule for stale models
    smap = None
    if args.driver == "hardware":  # a bad --servos map: one line, before anything is made
        from firmware_interface.servo_map import load_servo_map

        smap = load_servo_map(args.servos)
    local = is_local(args.host)
    ssl_context, token = None, None
    if args.cert is not None:
        cert, key = Path(args.cert), Path(args.key)
        ssl_context = server_context(cert, key)
        print(f"TLS certificate (yours): {cert}")
        print(f"  SHA-256 fingerprint {fingerprint(cert)}")
    elif not local or args.tls:
        # "again" only when the headset may have trusted an earlier one (not on a first run)
        earlier = any((config_dir() / name).exists() for name in (CERT_NAME, CA_NAME))
        cert, key, made = ensure_certificate(args.host)
        ssl_context = server_context(cert, key)
        print(f"TLS certificate {'made' if made else 'kept'}: {cert}")
        print(f"  SHA-256 fingerprint {fingerprint(cert)}")
        new = f" (new: install it on the headset{' again' if earlier else ''})" if made else ""
        print(f"  the headset trusts it through the CA {cert.parent / CA_NAME}{new}")
    if not local:
        token = new_token()
    drop_log_lines()  # the records go beside the status line instead
    logging.basicConfig(level=logging.WARNING, handlers=[_BesideStatusLine(sys.stderr)])
    hub = LiveHub()
    bus = contextlib.ExitStack()  # the emulator of --emulator, stopped last
    try:
        payload = _hardware_driver(args, smap, bus) if smap is not None else None
    except BaseException:
        bus.close()
        raise
    try:
        if payload is not None:
            hub.driver = f"hardware on {payload.device}" + (
                " (emulator)" if payload.emulated else ""
            )
        print("loading the simulator and the retargeters ...", flush=True)
        session = make_session(
            hub,
            record,
            payload=payload,
            collisions=prof.retarget_collisions,
            budget=prof.retarget_budget,
            controller=(prof.name, overrides),
            base_filter=prof.base_filter,
            link_delay=link_delay,
        )
        server = TeleopServer(
            hub,
            args.host,
            args.port,
            ssl_context=ssl_context,
            token=token,
            scene=session.scene,
            desktop=desktop,
        ).start()
        if args.host in ("0.0.0.0", "::"):
            from payload.teleop.tls import lan_addresses

            for addr in lan_addresses():
                print(f"serving the live Quest page on {server.url(addr)}")
        else:
            print(f"serving the live Quest page on {server.url()}")
        if token:
            print(f"session token: {token}")
        if local:
            print(f"Quest over USB: adb reverse tcp:{server.port} tcp:{server.port}, then open it")
        if record is not None:
            print(f"recording each session's steps into {record} (scored when you stop)")
        stop_status = threading.Event()
        printer = threading.Thread(
            target=_status_printer, args=(hub, stop_status, args.status_interval), daemon=True
        )
        printer.start()
        if args.seconds:  # a daemon: Ctrl-C before it fires must not wait for it
            timer = threading.Timer(args.seconds, hub.stop.set)
            timer.daemon = True
            timer.start()
        interrupted, ended = False, False
        try:
            session.run()
            ended = True
        except KeyboardInterrupt:
            interrupted = ended = True
            hub.stop.set()
            print("\nstopping", file=sys.stderr)
        finally:
            stop_status.set()
            try:
                if ended and payload is not None and not args.stay_deployed:
                    from firmware_interface.deployment import stow_after_session

                    # before the session closes the driver; a Ctrl-C stops the motion only
                    stow_after_session(payload, say_stage)
            finally:
                with _press_twice_to_abandon(record):
                    server.stop()
                    result = session.close()
        if interrupted:  # the session closed (and scored): the command's normal end
            print("stopped", file=sys.stderr)
        print("\n" + status_line(hub.status(), hub.latency()))
        if result is not None:
            print(f"recorded {record} ({result.get('steps')} steps)")
            if report is not None:  # what the scoring found and wrote (the trials' words)
                report(result)
        elif record is not None:  # asked for, and no session ran: said, not left to guess
            print(
                f"nothing recorded in {record}: no session was recorded (a session is recorded "
                "once its calibration is done)"
            )
        return 0
    finally:
        with bus:
            if payload is not None:  # torque off, if stopped before the session closed it
                payload.close()


def bench(args: argparse.Namespace, make_session: SessionFactory) -> int:
    """``payload bench teleop``: the emulated Quest against the session ``make_session``
    makes."""
    from payload.teleop.bench import run_bench

    check_seconds("--seconds", args.seconds)
    project = command_project(args)  # the session flies this project's models
    from payload.design import models_follow_design

    models_follow_design(project.design_path, project.root, json=args.json)
    # the emulated operator's tracking drop-outs are part of the run, not news
    logging.getLogger("payload.teleop.safety").setLevel(logging.ERROR)
    result = run_bench(make_session, seconds=args.seconds)
    if args.json:
        emit_json(result)
        return 0
    print(f"emulated Quest 3 (iwer, headless Chromium), {result['frames']} frames")
    for key in ("frame_age_ms", "latency_ms"):
        v = result[key]
        print(f"  {key:<14} median {_ms(v['median']):>6}  p99 {_ms(v['p99']):>6}")
    print(f"  loop overruns {result['loop_overruns']} of {result['steps']} steps")
    print(f"  load average {_load_text(result['load'])}")
    return 0


def bench_filter(args: argparse.Namespace) -> int:
    """``payload bench filter``: the base safety filter's cost per step."""
    from payload.teleop.bench import run_filter_bench

    check_seconds("--seconds", args.seconds)
    project = command_project(args)  # the stack it flies is this project's
    from payload.design import models_follow_design

    models_follow_design(project.design_path, project.root, json=args.json)
    result = run_filter_bench(seconds=args.seconds)
    if args.json:
        emit_json(result)
        return 0
    print(
        f"base safety filter, {result['steps']} steps ({result['active_steps']} acting): "
        f"median {result['median_us']:.0f} us, p99 {result['p99_us']:.0f} us, at most "
        f"{result['constraints']} constraints; load average {_load_text(result['load'])}"
    )
    return 0


def serve_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``payload teleop serve``."""
    p.add_argument(
        "--driver",
        choices=("sim", "hardware"),
        default="sim",
        help="what the page drives: the simulator alone (default), or the Dynamixel "
        "payload on --device beside the simulated scene",
    )
    add_device(p, "serial device of the servo bus (--driver hardware)")
    p.add_argument(
        "--emulator",
        action="store_true",
        help="with --driver hardware: drive an emulated servo bus started here (as `payload "
        "hw emulate` serves one), instead of --device",
    )
    add_servo_map(p, "servo map TOML (--driver hardware; default: the packaged map)")
    add_latency(p, "; --driver hardware", emulator="with --emulator")
    p.add_argument(
        "--stay-deployed",
        action="store_true",
        help="with --driver hardware: leave the payload deployed when the server stops "
        "(default: stowed, the deployment's reverse)",
    )
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="bind address (default 127.0.0.1); any other is served over TLS with a "
        "session token, on a certificate the workbench makes and keeps unless --cert is "
        "given (docs/live.md)",
    )
    p.add_argument(
        "--port",
        type=_port,
        default=8765,
        help="TCP port the page, its WebSocket and /status are served on (default 8765; "
        "0: any free port)",
    )
    p.add_argument("--record", metavar="DIR", help="record the session as a trial into this folder")
    p.add_argument("--tls", action="store_true", help="use TLS on a local bind too")
    from payload.profiles import PROFILES, SAFE

    p.add_argument(
        "--controller",
        choices=tuple(PROFILES),
        default=None,
        help=f"controller profile (default {SAFE}: real servos and a person in the loop): "
        "'safe' models self-collision (every link pair keeps the design's margin, the two "
        "pads of a pair excepted) and filters the base; 'paper' is the paper's controller",
    )
    p.add_argument(
        "--retarget-budget",
        choices=("paper", "converged"),
        default=None,
        help="retargeting budget per pair solve (default: the --controller profile's)",
    )
    p.add_argument(
        "--desktop",
        action="store_true",
        help="also serve the desktop mode: an emulated headset driven by the keyboard "
        "(iwer from node_modules)",
    )
    p.add_argument("--cert", help="your TLS certificate (PEM) instead of the made one")
    p.add_argument("--key", help="the key of --cert (PEM)")
    p.add_argument(
        "--retarget-collisions",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="model self-collision in the pair solves (default: the --controller "
        "profile's); overrides the profile",
    )
    p.add_argument(
        "--base-filter",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the base safety filter between the base channel and the vehicle, keeping the "
        "vehicle, payload and bag off the station (default: the --controller profile's, on "
        "in 'safe')",
    )
    p.add_argument(
        "--link-delay",
        default=None,
        metavar="S[:JITTER]",
        help="a delayed ground link: hand frames reach the robot and its state reaches the "
        "page S seconds late (each message +-JITTER, uniform); default none",
    )
    p.add_argument("--status-interval", type=float, default=1.0, help=argparse.SUPPRESS)
    p.add_argument("--seconds", type=float, default=0.0, help=argparse.SUPPRESS)


def bench_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``payload bench teleop``."""
    p.add_argument(
        "--seconds",
        type=float,
        default=20.0,
        help="teleoperation time to measure (default %(default)g)",
    )
    add_json(p)


def bench_filter_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``payload bench filter``."""
    p.add_argument(
        "--seconds", type=float, default=8.0, help="simulated seconds per scenario (default 8)"
    )
    add_json(p)
