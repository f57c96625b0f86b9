"""``payload hw emulate|scan|check|run`` and ``payload bench hw``."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from payload.errors import PayloadError


class HwUsageError(PayloadError):
    """Bad command-line input for the hardware commands."""


def _map(args: argparse.Namespace) -> Any:
    from firmware_interface.servo_map import load_servo_map

    return load_servo_map(args.servos)


def _cmd_emulate(args: argparse.Namespace) -> int:
    from firmware_interface.emulator import bus_spec, serve

    serve(bus_spec(args.servos), args.fault, seed=args.seed)
    return 0


def _cmd_scan(args: argparse.Namespace) -> int:
    from firmware_interface.driver import DynamixelDriver
    from payload.cli import emit_json

    smap = _map(args)
    with DynamixelDriver(args.port, smap, latency_timer_ms=args.latency_ms) as drv:
        found = drv.scan()
    known = {s.id: s.joint for s in smap.servos}
    servos = [
        {"id": i, "model_number": m, "firmware": fw, "joint": known.get(i)}
        for i, (m, fw) in sorted(found.items())
    ]
    missing = [{"id": i, "joint": j} for i, j in known.items() if i not in found]
    if args.json:
        emit_json({"port": args.port, "servos": servos, "missing": missing})
    else:
        for s in servos:
            print(f"ID {s['id']:3d}  model {s['model_number']}  firmware {s['firmware']}  "
                  f"{s['joint'] or '-'}")  # fmt: skip
        for s in missing:
            print(f"ID {s['id']:3d}  not answering ({s['joint']})")
    return 0


def check(port: str, smap: Any, latency_ms: float = 16.0) -> dict[str, Any]:
    """Bring-up and health of every servo: ``{"ok", "servos", "errors"}``."""
    from firmware_interface.driver import DynamixelDriver
    from firmware_interface.errors import DynamixelError, MissingServoError

    errors: list[str] = []
    servos = []
    with DynamixelDriver(port, smap, latency_timer_ms=latency_ms) as drv:
        present = list(smap.ids)
        try:
            drv.bring_up()
        except MissingServoError as exc:
            errors += [f"servo {i} ({j}): not answering" for i, j in zip(exc.ids, exc.joints)]
            present = [i for i in smap.ids if i not in exc.ids]
        except DynamixelError as exc:
            errors.append(str(exc))
        for i in present:
            try:
                h = drv.read_health(i)
            except DynamixelError as exc:
                errors.append(str(exc))
                continue
            servos.append({"id": i, "joint": h.joint, "model_number": h.model_number,
                           "hardware_error": h.hardware_error, "temperature_c": h.temperature_c,
                           "voltage_v": h.voltage_v})  # fmt: skip
            if h.hardware_error:
                errors.append(f"servo {i} ({h.joint}): hardware error {', '.join(h.bits)}")
    return {"ok": not errors, "servos": servos, "errors": errors}


def _cmd_check(args: argparse.Namespace) -> int:
    from payload.cli import CheckFailed, command_project, emit_json

    command_project(args)  # the servo map is validated against this project's design
    report = check(args.port, _map(args), args.latency_ms)
    if args.json:
        emit_json(report)
    else:
        for s in report["servos"]:
            print(f"ID {s['id']:3d} {s['joint']:<11s} model {s['model_number']}  "
                  f"error {s['hardware_error']}  {s['temperature_c']:.0f} C  "
                  f"{s['voltage_v']:.1f} V")  # fmt: skip
    if not report["ok"]:
        if args.json:
            print(f"payload: check failed: {'; '.join(report['errors'])}", file=sys.stderr)
            return 1
        raise CheckFailed("; ".join(report["errors"]))
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from firmware_interface.driver import DynamixelDriver
    from firmware_interface.run import run_hardware_trial
    from payload.cli import command_project, emit_json

    project = command_project(args)
    source = args.source
    if source[0] == "webxr":
        raise HwUsageError(
            "--source webxr: the live interface drives the hardware through "
            "`payload teleop serve --driver hardware`"
        )
    if source[0] != "replay" or len(source) != 2:
        raise HwUsageError("--source must be 'replay FILE' or 'webxr'")
    replay = Path(source[1])
    if not replay.is_file():
        raise HwUsageError(f"--source replay: {replay} is not a file")
    out = Path(args.out) if args.out else project.runs_dir / f"hw-{time.strftime('%Y%m%d-%H%M%S')}"
    if (out / "log.mcap").exists():
        raise HwUsageError(f"--out {out}: already holds a recording; choose another folder")
    from payload.profiles import SAFE, resolve

    prof, overrides = resolve(
        args.controller,
        SAFE,
        retarget_budget=args.retarget_budget,
        retarget_collisions=args.retarget_collisions,
    )
    with DynamixelDriver(args.port, _map(args), latency_timer_ms=args.latency_ms) as drv:
        drv.bring_up()
        result = run_hardware_trial(drv, replay, out, max_time=args.max_time,
                                    pace=not args.no_pace, controller=(prof.name, overrides),
                                    budget=prof.retarget_budget,
                                    collisions=prof.retarget_collisions)  # fmt: skip
    result["out"] = str(out)
    if args.json:
        emit_json(result)
    else:
        print(f"{result['steps']} steps recorded in {out}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from firmware_interface.bench import bench_hw
    from payload.cli import emit_json

    if args.cycles < 1:
        raise HwUsageError(f"--cycles must be at least 1, got {args.cycles}")
    result = bench_hw(args.port, args.cycles, args.servos, args.latency_ms)
    if args.json:
        emit_json(result)
    else:
        print(f"{result['cycles']} cycles at {result['baud']} baud: mean "
              f"{result['cycle_mean_us']:.0f} us, p99 {result['cycle_p99_us']:.0f} us, wire "
              f"{result['wire_us']:.0f} us ({result['ratio_to_wire']:.2f}x), "
              f"{result['retries']} retries, load {result['load_1min']:.2f}")  # fmt: skip
        if result.get("guard_us") is not None:
            print(f"collision guard: {result['guard_us']:.0f} us a command, "
                  f"{result['guard_cpu_us']:.0f} us CPU (in every cycle)")  # fmt: skip
    return 0


def _latency(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--latency-ms",
        type=float,
        default=16.0,
        help="reply timeout allowance per packet [ms] (the SDK's LATENCY_TIMER)",
    )


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    hw = sub.add_parser("hw", help="the Dynamixel hardware and its emulator")
    hws = hw.add_subparsers(dest="hw_command", required=True, metavar="WHAT")

    p = hws.add_parser("emulate", help="serve an emulated servo bus on a pty (prints its path)")
    p.add_argument("--servos", metavar="MAP", help="servo map TOML (default: the packaged map)")
    p.add_argument(
        "--fault",
        metavar="SPEC",
        action="append",
        default=[],
        help="missing:ID, corrupt:P, latency:3ms, drop:P, error:ID:BIT, block:ID",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the fault dice")
    p.set_defaults(func=_cmd_emulate)

    for name, fn, text in (
        ("scan", _cmd_scan, "IDs, models and firmware on the bus"),
        ("check", _cmd_check, "bring-up and health of every servo (exit 1 when not ok)"),
    ):
        p = hws.add_parser(name, help=text)
        p.add_argument("--port", required=True, help="serial device or emulator pty")
        p.add_argument("--servos", metavar="MAP", help="servo map TOML")
        p.add_argument("--json", action="store_true", help="print one JSON object")
        _latency(p)
        p.set_defaults(func=fn)

    p = hws.add_parser("run", help="the 50 Hz teleoperation loop on the hardware")
    p.add_argument("--port", required=True, help="serial device or emulator pty")
    p.add_argument(
        "--source",
        nargs="+",
        required=True,
        metavar="SRC",
        help="'replay FILE' (a hands.jsonl) or 'webxr'",
    )
    p.add_argument("--servos", metavar="MAP", help="servo map TOML")
    p.add_argument("--out", help="trial folder (default runs/hw-<time>)")
    p.add_argument("--max-time", type=float, default=240.0, help="session cap [s]")
    p.add_argument("--no-pace", action="store_true", help=argparse.SUPPRESS)
    from payload.profiles import PROFILES, SAFE

    p.add_argument(
        "--controller",
        choices=tuple(PROFILES),
        default=None,
        help=f"controller profile (default {SAFE}: real servos): 'safe' models "
        "self-collision (the pads of a pair excepted); 'paper' is the paper's controller",
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
        help="model self-collision in the pair solves (default: the --controller profile's)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    _latency(p)
    p.set_defaults(func=_cmd_run)

    p = groups["bench"].add_parser("hw", help="sync write + fast sync read cycle vs wire time")
    p.add_argument("--port", help="serial device (default: start an emulator at 4 Mbaud)")
    p.add_argument("--cycles", type=int, default=2000)
    p.add_argument("--servos", metavar="MAP", help="servo map TOML")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    _latency(p)
    p.set_defaults(func=_cmd_bench)
