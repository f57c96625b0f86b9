"""Command line of the live Quest interface: ``payload teleop serve``, ``payload bench teleop``."""

from __future__ import annotations

import argparse
import logging
import sys
import threading
from pathlib import Path
from typing import Any

from payload.errors import PayloadError


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
        f"{status['state']:<11} clients={status['clients']} frames={status['frames']} "
        f"age={_ms(age['median'])}/{_ms(age['p99'])} ms "
        f"latency={_ms(lat['median'])}/{_ms(lat['p99'])} ms "
        f"overruns={status['loop_overruns']} dropped: {refused or 'none'}"
    )


def _status_printer(hub: Any, stop: threading.Event, interval: float) -> None:
    tty = sys.stderr.isatty()
    while not stop.wait(interval):
        line = status_line(hub.status(), hub.latency())
        sys.stderr.write(f"\r{line}\033[K" if tty else line + "\n")
        sys.stderr.flush()


def _check_record(record: Path | None) -> None:
    if record is None:
        return
    for name in ("log.mcap", "hands.jsonl", "metrics.json"):
        if (record / name).exists():
            raise TeleopCliError(
                f"--record {record}: {name} already exists (choose a new folder; recordings "
                "are never overwritten)"
            )
    if record.exists() and not record.is_dir():
        raise TeleopCliError(f"--record {record}: not a folder")


def _hardware_driver(device: str | None) -> Any:
    """The Dynamixel payload driver (``firmware_interface``), brought up on ``device``."""
    from firmware_interface import DynamixelDriver

    if not device:
        raise TeleopCliError("--driver hardware needs --device PORT (the servo bus's serial port)")
    driver = DynamixelDriver(device)
    try:
        driver.bring_up()
    except BaseException:
        driver.close()
        raise
    return driver


def _cmd_serve(args: argparse.Namespace) -> int:
    from payload.cli import command_project
    from payload.teleop.live import LiveHub
    from payload.teleop.server import TeleopServer, is_local, new_token
    from payload.teleop.tls import ensure_certificate, fingerprint, server_context

    command_project(args)  # the simulator and the retargeters read this project's models
    record = Path(args.record) if args.record else None
    _check_record(record)
    local = is_local(args.host)
    ssl_context, token = None, None
    if not local or args.tls:
        cert, key, made = ensure_certificate(args.host)
        ssl_context = server_context(cert, key)
        print(f"TLS certificate {'made' if made else 'kept'}: {cert}")
        print(f"  SHA-256 fingerprint {fingerprint(cert)}")
    if not local:
        token = new_token()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    from payload.trials.live import LiveSession

    hub = LiveHub()
    payload = _hardware_driver(args.device) if args.driver == "hardware" else None
    print("loading the simulator and the retargeters ...", flush=True)
    from payload.profiles import SAFE, resolve

    prof, overrides = resolve(
        args.controller,
        SAFE,
        retarget_budget=args.retarget_budget,
        retarget_collisions=args.retarget_collisions,
    )
    session = LiveSession(
        hub,
        record,
        payload=payload,
        collisions=prof.retarget_collisions,
        budget=prof.retarget_budget,
        controller=(prof.name, overrides),
    )
    server = TeleopServer(
        hub, args.host, args.port, ssl_context=ssl_context, token=token, scene=session.scene
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
    stop_status = threading.Event()
    printer = threading.Thread(
        target=_status_printer, args=(hub, stop_status, args.status_interval), daemon=True
    )
    printer.start()
    if args.seconds:
        threading.Timer(args.seconds, hub.stop.set).start()
    try:
        session.run()
    except KeyboardInterrupt:
        hub.stop.set()
        print("\nstopping", file=sys.stderr)
    finally:
        stop_status.set()
        server.stop()
        result = session.close()
    print("\n" + status_line(hub.status(), hub.latency()))
    if result is not None:
        print(f"recorded {record} ({result.get('steps')} steps)")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from payload.cli import emit_json
    from payload.teleop.bench import run_bench

    # the emulated operator's tracking drop-outs are part of the run, not news
    logging.getLogger("payload.teleop.safety").setLevel(logging.ERROR)
    result = run_bench(seconds=args.seconds)
    if args.json:
        emit_json(result)
        return 0
    print(f"emulated Quest 3 (iwer, headless Chromium), {result['frames']} frames")
    for key in ("frame_age_ms", "latency_ms"):
        v = result[key]
        print(f"  {key:<14} median {v['median']:6.2f}  p99 {v['p99']:6.2f}")
    print(f"  loop overruns {result['loop_overruns']} of {result['steps']} steps")
    print(f"  load average {result['load']}")
    return 0


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    teleop = sub.add_parser("teleop", help="the live Quest (WebXR) interface")
    tsub = teleop.add_subparsers(dest="teleop_command", required=True, metavar="WHAT")
    p = tsub.add_parser("serve", help="serve the WebXR page, its WebSocket and /status")
    p.add_argument("--driver", choices=("sim", "hardware"), default="sim")
    p.add_argument("--device", help="serial device of the servo bus (--driver hardware)")
    p.add_argument("--host", default="127.0.0.1", help="bind address (non-local needs TLS)")
    p.add_argument("--port", type=_port, default=8765)
    p.add_argument("--record", help="record the session as a trial into this folder")
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
        "--retarget-collisions",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="model self-collision in the pair solves (default: the --controller "
        "profile's); overrides the profile",
    )
    p.add_argument("--status-interval", type=float, default=1.0, help=argparse.SUPPRESS)
    p.add_argument("--seconds", type=float, default=0.0, help=argparse.SUPPRESS)
    p.set_defaults(func=_cmd_serve)

    b = groups["bench"].add_parser(
        "teleop", help="latency of the live interface through an emulated Quest 3"
    )
    b.add_argument("--seconds", type=float, default=20.0, help="teleoperation time to measure")
    b.add_argument("--json", action="store_true", help="print one JSON object")
    b.set_defaults(func=_cmd_bench)
