"""``payload hw emulate|scan|check|run`` and ``payload bench hw``.

The serial device is ``--device`` (``--port``, its earlier spelling here, is kept for one
release as a deprecated alias); ``hw run`` replays ``--replay FILE`` (``--source replay
FILE``, its earlier spelling, likewise).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from firmware_interface.errors import missing_device
from firmware_interface.options import (
    LATENCY_MS,
    add_latency,
    add_servo_map,
    latency_of,
    latency_problem,
)
from payload.cliutil import (
    CheckFailed,
    add_deprecated,
    add_device,
    add_json,
    add_replay,
    check_seconds,
    command_project,
    emit_json,
    load_average,
    need_device,
    out_folder,
    replay_file,
    results_folder,
    say_stage,
)
from payload.errors import PayloadError, counted
from payload.folders import HANDS, RECORDING, other_results
from payload.trials.setup_options import MAX_TRIAL_S

if TYPE_CHECKING:
    from firmware_interface.errors import WrongModelError


class HwUsageError(PayloadError):
    """Bad command-line input for the hardware commands."""


def _check_numbers(args: argparse.Namespace) -> None:
    """The numeric options, before anything is opened, moved or written (one line, exit 2).

    Raises:
        HwUsageError: ``--latency-ms`` not a finite number >= 0 (a NaN or infinite reply
            timeout would wait forever on a silent servo).
        UsageError: ``--max-time`` not a positive number of seconds
            (:func:`payload.cliutil.check_seconds`).
    """
    problem = latency_problem(getattr(args, "latency_ms", None))
    if problem is not None:
        raise HwUsageError(problem)
    check_seconds("--max-time", getattr(args, "max_time", None), cap=True)


def _models_follow(args: argparse.Namespace) -> None:
    """The one rule for stale models (docs/design-loop.md): the project's generated models
    rebuilt if they no longer match its design, saying so. Every command that makes a
    driver applies it: the driver's collision guard reads the project's URDF."""
    project = command_project(args)
    from payload.design import models_follow_design

    models_follow_design(project.design_path, project.root, json=getattr(args, "json", False))


def _map(args: argparse.Namespace) -> Any:
    from firmware_interface.servo_map import load_servo_map

    return load_servo_map(args.servos)


def _cmd_emulate(args: argparse.Namespace) -> int:
    from firmware_interface.emulator import bus_spec, serve

    # the servos of this project's design; the pty path (or --device's) is the first line
    command_project(args, announce=False)
    link = args.device
    if link is not None:
        path = Path(link)
        what = "exists" if path.is_symlink() or path.exists() else None
        if what is None and not path.absolute().parent.is_dir():
            what = "is not in a folder that exists"
        if what is not None:
            raise HwUsageError(
                f"--device {link}: {what} (the emulator links a new path to its pty)"
            )
    try:  # its normal end, as for `teleop serve` and `review` (docs/cli.md): exit 0
        serve(bus_spec(args.servos, args.servo_params), args.fault, seed=args.seed, link=link)
    except KeyboardInterrupt:  # Ctrl-C, and SIGTERM or SIGHUP (payload.errors.Terminated)
        pass
    print("stopped", file=sys.stderr)
    return 0


def _cmd_scan(args: argparse.Namespace) -> int:
    _check_numbers(args)
    from firmware_interface.driver import DynamixelDriver, nobody_answered

    command_project(args)  # the servo map's joints are this project's
    device = need_device(args)
    _device_there(args)
    smap = _map(args)
    _models_follow(args)
    from firmware_interface.errors import DynamixelError

    with DynamixelDriver(device, smap, latency_timer_ms=args.latency_ms) as drv:
        try:
            found = drv.scan()
        except DynamixelError as exc:  # replies that come too late: the bus's state
            raise CheckFailed(str(exc)) from None
    known = {s.id: s.joint for s in smap.servos}
    servos = [
        {"id": i, "model_number": m, "firmware": fw, "joint": known.get(i)}
        for i, (m, fw) in sorted(found.items())
    ]
    missing = [{"id": i, "joint": j} for i, j in known.items() if i not in found]
    # a mapped ID answering as another model: `hw check` refuses it (WrongModelError)
    other = set(drv.other_model)
    if args.json:
        # "port": the device's field name before --device (kept: JSON fields are never renamed)
        emit_json({"device": device, "port": device, "servos": servos, "missing": missing})
    else:
        for s in servos:
            note = f"  (not the map's {smap.model_number})" if s["id"] in other else ""
            fw = "-" if s["firmware"] is None else s["firmware"]  # another model's: unread
            print(f"ID {s['id']:3d}  model {s['model_number']}  firmware {fw}  "
                  f"{s['joint'] or '-'}{note}")  # fmt: skip
        for s in missing:
            print(f"ID {s['id']:3d}  not answering ({s['joint']})")
        if servos:  # a look, not a check: what it found, and what `hw check` would refuse
            print(_scan_summary(servos, missing, other, smap))
    if not servos:  # listed; but a bus where no servo answers is a failed look, as in check
        raise CheckFailed(nobody_answered(device))
    return 0


def _scan_summary(
    servos: list[dict[str, Any]], missing: list[dict[str, Any]], other: set[int], smap: Any
) -> str:
    """``hw scan``'s last line: how many of the map's servos answered, and those that
    ``hw check`` would refuse (``missing``, ``other``: the IDs of another model)."""
    mapped = [s for s in servos if s["joint"] is not None]
    head = f"{len(mapped)} of the map's {len(smap.ids)} servos answering"
    if not (missing or other):
        return head
    said = [f"{len(missing)} not answering"] if missing else []
    said += [f"{len(other)} of another model"] if other else []
    return f"{head}; {', '.join(said)}: `payload hw check` refuses this bus"


SILENT_RUN = 2
"""Health reads lost in a row, after a bring-up that lost replies, that end ``hw check``'s
look: a bus that stopped answering, not one servo (each read waits out its retries)."""


def check(
    port: str, smap: Any, latency_ms: float = LATENCY_MS, say: Callable[[str], None] | None = None
) -> dict[str, Any]:
    """Bring-up and health of every servo: ``{"ok", "servos", "errors"}``. The bring-up
    homes the rail and the stage (they move to their hard stops): ``say`` is told first.
    A servo of another model than the map's gets a row without health values (none of
    its registers is read, :func:`_unread_row`)."""
    from firmware_interface.driver import (
        DynamixelDriver,
        bring_up_notice,
        late_words,
        nobody_answered,
    )
    from firmware_interface.errors import (
        CommError,
        DynamixelError,
        HardwareFault,
        MissingServoError,
        WrongModelError,
    )

    errors: list[str] = []
    servos = []
    missing: list[dict[str, Any]] = []  # mapped servos that did not answer (as `hw scan`'s)
    other: dict[int, WrongModelError] = {}  # servos of another model: no register read
    lost = False  # the bring-up lost replies: the health reads' losses are said in one line
    silent: list[str] = []  # servos whose health read was lost after that
    with DynamixelDriver(port, smap, latency_timer_ms=latency_ms) as drv:
        present = list(smap.ids)
        try:
            if say is not None:
                say(bring_up_notice(port))
            drv.bring_up()
        except DynamixelError as exc:
            lost = isinstance(exc, CommError)
            for fault in (exc, *exc.also):  # every servo the bring-up found at fault, once
                if isinstance(fault, WrongModelError):
                    other[fault.id] = fault
                if isinstance(fault, MissingServoError):
                    present = [i for i in smap.ids if i not in fault.ids]
                    if not present:  # the bus, not the servos: as `hw scan` says it
                        errors.append(nobody_answered(port))
                    else:
                        missing = [{"id": i, "joint": j} for i, j in zip(fault.ids, fault.joints)]
                        errors += [f"servo {m['id']} ({m['joint']}): not answering"
                                   for m in missing]  # fmt: skip
                # a latched error bit is each faulted servo's health read's to say (below),
                # once; a reset (torque off with no error bit) is not in the health read
                elif not isinstance(fault, HardwareFault) or fault.bits == ["reset"]:
                    errors.append(fault.alone)
        for i, model in drv.other_model.items():  # its scan saw them, though the bring-up
            if i not in other:  # stopped before saying so (replies lost or late)
                other[i] = WrongModelError(i, smap.joint_of(i), model, smap.model_number)
                errors.append(other[i].alone)
        run = 0  # health reads lost in a row
        for k, i in enumerate(present):
            if i in other:  # another family may keep other registers at these addresses
                servos.append(_unread_row(other[i]))
                continue
            try:
                h = drv.read_health(i)
            except DynamixelError as exc:
                if not (lost and isinstance(exc, CommError)):
                    errors.append(str(exc))
                    continue
                silent.append(f"{i} ({smap.joint_of(i)})")
                run += 1
                if run >= SILENT_RUN and k + 1 < len(present):
                    # the bus, not a servo: the rest would each wait out their retries
                    silent.append(f"and the {len(present) - k - 1} after it not read")
                    break
                continue
            run = 0
            servos.append({"id": i, "joint": h.joint, "model_number": h.model_number,
                           "hardware_error": h.hardware_error, "temperature_c": h.temperature_c,
                           "voltage_v": h.voltage_v})  # fmt: skip
            if h.hardware_error:
                errors.append(str(HardwareFault(i, h.joint, list(h.bits))))  # its own words
        if silent:
            servo = "servo" if len(silent) == 1 else "servos"
            errors.append(f"no reply to the health read from {servo} {', '.join(silent)}")
        drv.port.settle()
        late = sum(drv.port.late.values())
        allowance = drv.port.reply_allowance_ms
    if late:  # a late reply can be taken as the answer to a later read of the same length
        errors.append(late_words(late, allowance, "no value read on this bus is shown "
                                 "(--latency-ms?)"))  # fmt: skip
        servos = []
    return {"ok": not errors, "servos": servos, "errors": errors, "missing": missing}


def _unread_row(fault: WrongModelError) -> dict[str, Any]:
    """``hw check``'s row of a servo of another model than the map's (``fault``, as the
    bring-up refused it): its model number from its ping, no health value (another
    model's control table may hold other registers at the X series' health addresses, so
    none is read), and ``not_read`` saying why."""
    return {"id": fault.id, "joint": fault.joint, "model_number": fault.model,
            "hardware_error": None, "temperature_c": None, "voltage_v": None,
            "not_read": f"health registers not read: it is model {fault.model}, "
                        f"not the map's {fault.expected}"}  # fmt: skip


def _cmd_check(args: argparse.Namespace) -> int:
    _check_numbers(args)
    command_project(args)  # the servo map is validated against this project's design
    device, smap = need_device(args), _map(args)
    _device_there(args)
    _models_follow(args)
    from firmware_interface.errors import CommError

    try:
        report = {"device": device, **check(device, smap, args.latency_ms, say_stage)}
    except CommError as exc:  # the open device failed (gone): its state, exit 1; one that
        # cannot be opened (a typo, not a serial device) stays bad input, exit 2
        report = {"device": device, "ok": False, "servos": [], "errors": [str(exc)], "missing": []}
    if args.json:
        emit_json(report)
    else:
        from firmware_interface.control_table import hw_error_names

        rows = {s["id"]: s for s in report["servos"]}
        silent = {m["id"] for m in report["missing"]}
        for i, joint in ((sp.id, sp.joint) for sp in smap.servos):  # the map's order
            if i not in rows:  # a row for a missing servo too, as `hw scan` has
                if i in silent:
                    print(f"ID {i:3d} {joint:<11s} not answering")
                continue
            s = rows[i]  # the error bits by name (the e-Manual's), not a number
            head = f"ID {s['id']:3d} {s['joint']:<11s} model {s['model_number']}  "
            if "not_read" in s:  # a servo of another model: why its values are not shown
                print(head + s["not_read"])
                continue
            bits = ", ".join(hw_error_names(s["hardware_error"])) or "none"
            print(f"{head}{s['temperature_c']:3.0f} C  {s['voltage_v']:.1f} V  "
                  f"hardware error: {bits}")  # fmt: skip
    if not report["ok"]:
        from firmware_interface.driver import LATCHED_REMEDY

        said = "; ".join(report["errors"])
        if any(s.get("hardware_error") for s in report["servos"]):
            said += f" ({LATCHED_REMEDY})"
        if args.json:
            print(f"payload: check failed: {said}", file=sys.stderr)
            return 1
        raise CheckFailed(said)
    if not args.json:  # a passing check says so, as a failing one does
        print(f"check passed: {len(report['servos'])} servos answering, the rail and the "
              "stage homed (each moved off its stop and back), no hardware error")  # fmt: skip
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    _check_numbers(args)
    project = command_project(args)
    replay = _replay_of(args)
    # a run never writes among other results, nor into a file
    out_folder(args.out, holding=other_results())
    _emulated_or_device(args)
    _models_follow(args)  # the input checked first: a refusal rebuilds nothing
    with results_folder(args.out, project, "hw") as out:
        result = _run_hardware(args, out, replay)  # a bus that did not answer: no folder left
    result["out"] = str(out)
    if args.json:
        emit_json(result)
        return 0
    from payload.trials.summary import print_trial_summary

    far = "the emulator" if result["emulator"] else "hardware"
    print(f"hw run ({far} on {result['device']}), {counted(result['steps'], 'step')} -> {out}")
    print(f"  Bus Watchdog: {result['watchdog']['effect']}")
    unconfirmed = result.get("torque_off_unconfirmed")
    if unconfirmed:  # close() sent the torque-off but could not read it back from these
        who = f"servo{'s' if len(unconfirmed) > 1 else ''} {', '.join(map(str, unconfirmed))}"
        print(f"  ended: {_ended(result)}; torque off sent, not confirmed on {who}: "
              "check them before handling the hand")  # fmt: skip
    else:
        print(f"  ended: {_ended(result)}; every servo's torque turned off")
    stowed = {True: "stowed", None: "left deployed (--stay-deployed)"}
    print(f"  payload: {stowed.get(result.get('stowed'), 'not stowed (see the warning above)')}")
    if result.get("loop_overruns"):  # the servos ran behind the recording's control rate
        from payload.rates import CONTROL_DT

        print(f"  fell behind {1 / CONTROL_DT:g} Hz: {result['loop_overruns']} of "
              f"{result['steps']} steps ended after their {1e3 * CONTROL_DT:g} ms period (a "
              "slow bus or a busy host; docs/hardware.md)")  # fmt: skip
    # the world and the CTB's placement are the recording's; the controller profile and
    # the retargeting this session's own (real servos in the loop: `safe` by default)
    print_trial_summary(result, f" (world and CTB placement from {replay.name})")
    return 0


def _ended(result: dict[str, Any]) -> str:
    """What ended an ``hw run`` session, with the time it ran (its ``ended_by``)."""
    from payload.schema import CONTROL_DT, ENDED_BY_CAP, ENDED_BY_SOURCE

    ran = f"{result.get('steps', 0) * CONTROL_DT:.1f} s in"
    if result.get("ended_by") == ENDED_BY_CAP:
        return f"the session-length cap (--max-time), {ran}"
    if result.get("ended_by") == ENDED_BY_SOURCE:
        return f"the replayed recording's end, {ran}"
    return f"the session's end, {ran}"


def _run_hardware(args: argparse.Namespace, out: Path, replay: Path) -> dict[str, Any]:
    """``hw run``'s session on the bus (``--device``, or an emulator started here)."""
    from firmware_interface.driver import DynamixelDriver
    from firmware_interface.run import run_hardware_trial
    from payload.profiles import SAFE, resolve_args

    prof, overrides = resolve_args(args, SAFE)
    with contextlib.ExitStack() as stack:
        emu = None
        if args.emulator:
            from firmware_interface.emulator import EmulatorProcess

            emu = stack.enter_context(EmulatorProcess(args.servos))
        device = emu.port if emu is not None else need_device(args)
        latency = latency_of(args.latency_ms, emu is not None)
        drv = stack.enter_context(DynamixelDriver(device, _map(args), latency_timer_ms=latency))
        result = run_hardware_trial(drv, replay, out, max_time=args.max_time,
                                    pace=not args.no_pace, emulator=emu,
                                    base_filter=prof.base_filter,
                                    controller=(prof.name, overrides),
                                    budget=prof.retarget_budget,
                                    collisions=prof.retarget_collisions,
                                    progress=not args.json and sys.stderr.isatty(),
                                    say=say_stage,
                                    stow_after=not args.stay_deployed)  # fmt: skip
    # the driver is closed: the servos whose torque off it could not read back, recorded
    from payload.trials.scoring import write_metrics

    result["torque_off_unconfirmed"] = list(drv.torque_unconfirmed)
    write_metrics(out, result)
    return result


def _device_there(args: argparse.Namespace) -> None:
    """A ``--device`` path that is not there is refused in the driver's words before any
    work, the models' rebuild included (it was said only after the project's models had
    been regenerated). A path that is there but cannot be opened is the driver's to say.

    Raises:
        HwUsageError: The path does not exist.
    """
    if (missing := missing_device(getattr(args, "device", None))) is not None:
        raise HwUsageError(missing)


def _emulated_or_device(args: argparse.Namespace) -> None:
    """One bus: ``--device DEV`` (a path that is there) or ``--emulator`` (started by the
    command).

    Raises:
        HwUsageError: Both or neither; ``--servo-params`` without ``--emulator``; a
            device that is not there.
    """
    if (getattr(args, "device", None) is None) == (not args.emulator):
        raise HwUsageError("give either --device DEV or --emulator")
    _device_there(args)
    if getattr(args, "servo_params", None) is not None and not args.emulator:
        raise HwUsageError(
            "--servo-params sets an emulated bus's servos: give it with --emulator (or to "
            "`payload hw emulate`)"
        )


def _replay_of(args: argparse.Namespace) -> Path:
    """The recording ``hw run`` replays: ``--replay FILE``, or the deprecated ``--source``.

    Raises:
        HwUsageError: None, both, a ``--source`` other than ``replay FILE``, or no file.
    """
    source = getattr(args, "source", None)
    if source is not None and args.replay is not None:
        raise HwUsageError("--replay and --source (its deprecated spelling): give one")
    if source is not None:
        if source[0] == "webxr":
            raise HwUsageError(
                "--source webxr: the live interface drives the hardware through "
                "`payload teleop serve --driver hardware`"
            )
        if source[0] != "replay" or len(source) != 2:
            raise HwUsageError("--source must be 'replay FILE' (use --replay FILE)")
        given, name = source[1], "--source replay"
    elif args.replay is not None:
        given, name = args.replay, "--replay"
    else:
        raise HwUsageError(f"--replay FILE is required (a trial's {RECORDING} or a {HANDS})")
    return replay_file(name, Path(given))


def _cmd_bench(args: argparse.Namespace) -> int:
    _check_numbers(args)
    from firmware_interface.bench import bench_hw

    if args.cycles < 1:
        raise HwUsageError(f"--cycles must be >= 1, got {args.cycles}")
    command_project(args)  # the servo map is checked against this project's design
    _device_there(args)
    _models_follow(args)
    result = bench_hw(args.device, args.cycles, args.servos, args.latency_ms, say_stage)
    if args.json:
        emit_json({**result, "load_average": load_average()})
    else:
        print(f"{result['cycles']} cycles at {result['baud']} baud: mean "
              f"{result['cycle_mean_us']:.0f} us, p99 {result['cycle_p99_us']:.0f} us, wire "
              f"{result['wire_us']:.0f} us ({result['ratio_to_wire']:.2f}x), "
              f"{result['retries']} retries, load {result['load_1min']:.2f}")  # fmt: skip
        if result.get("guard_us") is not None:
            print(f"collision guard: {result['guard_us']:.0f} us a command, "
                  f"{result['guard_cpu_us']:.0f} us CPU (in every cycle)")  # fmt: skip
    return 0


def _cmd_identify(args: argparse.Namespace) -> int:
    _check_numbers(args)
    from firmware_interface.driver import DynamixelDriver
    from firmware_interface.identify import identify, write_servo_values

    command_project(args)  # the design whose servo model is fitted (and --write written)
    smap = _map(args)
    known = {s.joint for s in smap.servos}
    unknown = [j for j in args.joints or [] if j not in known]
    if unknown:
        raise HwUsageError(
            f"--joints: no servo drives {', '.join(unknown)} (the servo map's joints: "
            f"{', '.join(s.joint for s in smap.servos)})"
        )
    _emulated_or_device(args)
    if args.write and args.emulator:  # the emulator's values are the design's (or FILE's)
        raise HwUsageError(
            "--write puts an identification into the design: one of an emulated bus gives "
            "back the emulator's values, not your servos' (identify the hardware with "
            "--device DEV to write)"
        )
    _models_follow(args)
    with contextlib.ExitStack() as stack:
        emu = None
        if args.emulator:
            from firmware_interface.emulator import EmulatorProcess

            emu = stack.enter_context(EmulatorProcess(args.servos, servo_params=args.servo_params))
        device = emu.port if emu is not None else need_device(args)
        latency = latency_of(args.latency_ms, emu is not None)
        drv = stack.enter_context(DynamixelDriver(device, smap, latency_timer_ms=latency))
        # --write on a --device that turns out to be the emulator: refused before any servo
        # moves (its values are the emulator's, not the servos' the design describes)
        refuse = "--write takes real servos' values, not written" if args.write else None
        report = identify(drv, args.joints, say=say_stage, refuse_emulated=refuse)
        design_file = drv.design.source
    report["device"] = device
    report["emulator"] = emu is not None
    report["written"] = None
    if args.write:
        write_servo_values(design_file, report["suggested"])
        report["written"] = design_file
    if args.json:
        emit_json(report)
        return 0
    for s in report["servos"]:
        f = s["fit"]
        print(f"{s['joint']:>10} (ID {s['id']}): J {f['inertia']:.3e} kg m^2, "
              f"b {f['viscous']:.4f} N m s/rad, c {f['coulomb']:.4f} N m, kt {f['kt']:.3f} N m/A, "
              f"R {f['resistance']:.2f} ohm; residual {f['residual']['dynamics']:.1%} "
              f"(dynamics), {f['residual']['voltage']:.1%} (voltage)")  # fmt: skip
    for k, v in report["suggested"].items():
        print(f"servo.{k}: design {report['design'][k]:.6g}, suggested {v:.6g}")
    print(f"written to {report['written']}" if report["written"] else
          "(not written: --write puts the suggested values into the design)")  # fmt: skip
    return 0


def _emulator_option(p: argparse.ArgumentParser, text: str) -> None:
    p.add_argument("--emulator", action="store_true", help=text)


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    from firmware_interface.control_table import HW_ERROR_BITS  # the fault help's names
    from firmware_interface.faults import FAULT_FORMS

    hw = sub.add_parser("hw", help="the Dynamixel hardware and its emulator")
    hws = hw.add_subparsers(dest="hw_command", required=True, metavar="WHAT")

    p = hws.add_parser("emulate", help="serve an emulated servo bus on a pty (prints its path)")
    add_servo_map(p, "servo map TOML (default: the packaged map)")
    p.add_argument(
        "--fault",
        metavar="SPEC",
        action="append",
        default=[],
        help=f"{', '.join(FAULT_FORMS)} (BIT one of {', '.join(HW_ERROR_BITS)}; docs/hardware.md)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the fault dice")
    add_device(
        p,
        "the serial device path to serve the bus on too (a new link to the pty, removed "
        "when it stops), printed instead of the pty's",
    )
    p.add_argument(
        "--servo-params",
        metavar="FILE",
        help="JSON of servo plant values overriding the design's, by ID, joint kind or '*' "
        "(hidden parameters for `hw identify`; docs/servo.md)",
    )
    p.set_defaults(func=_cmd_emulate)

    for name, fn, text in (
        ("scan", _cmd_scan, "IDs, models and firmware on the bus"),
        ("check", _cmd_check, "bring-up and health of every servo (exit 1 when not ok)"),
    ):
        p = hws.add_parser(name, help=text)
        add_device(p, "serial device of the servo bus or an emulator's pty (required)",
                   old_port=True)  # fmt: skip
        add_servo_map(p)
        add_json(p)
        add_latency(p)
        p.set_defaults(func=fn)

    p = hws.add_parser(
        "identify",
        help="fit each servo's armature, friction and torque constant from step and chirp "
        "responses (moves every named joint across its range)",
    )
    add_device(p, "serial device of the servo bus or an emulator's pty (or --emulator)")
    _emulator_option(p, "start an emulated bus here instead of --device")
    p.add_argument(
        "--servo-params",
        metavar="FILE",
        help="with --emulator: the emulated servos' plant values (as `hw emulate --servo-params`)",
    )
    add_servo_map(p)
    p.add_argument("--joints", nargs="+", metavar="JOINT", help="joints to identify (default all)")
    p.add_argument("--write", action="store_true",
                   help="write the suggested [servo] values into the design file")  # fmt: skip
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_latency(p, emulator="with --emulator")
    p.set_defaults(func=_cmd_identify)

    p = hws.add_parser("run", help="the 50 Hz teleoperation loop on the hardware")
    add_device(p, "serial device of the servo bus or an emulator's pty (or --emulator)",
               old_port=True)  # fmt: skip
    _emulator_option(
        p, "start an emulated bus here instead of --device (it takes the grasp's load)"
    )
    add_replay(p, "the recorded hands to replay (required): a trial's log.mcap or a hands.jsonl")
    add_deprecated(p, "--source", "--replay FILE", "source", nargs="+", metavar="SRC",
                   help="'replay FILE'")  # fmt: skip
    add_servo_map(p)
    p.add_argument("--out", help="trial folder (default: a new runs/hw-NNNN in the project)")
    p.add_argument(
        "--max-time",
        type=float,
        default=MAX_TRIAL_S,
        metavar="S",
        help="session cap [s] (default %(default)g)",
    )
    p.add_argument(
        "--no-pace",
        action="store_true",
        help="send each step as soon as the last exchange ends instead of at the replay's "
        "50 Hz (for the emulator and tests; a host stall over 100 ms trips the servos' "
        "watchdog, docs/hardware.md)",
    )
    p.add_argument(
        "--stay-deployed",
        action="store_true",
        help="leave the payload deployed when the session ends (default: stowed, the "
        "deployment's reverse)",
    )
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
    p.add_argument(
        "--base-filter",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the base safety filter on the simulated vehicle (default: the --controller "
        "profile's, on in 'safe')",
    )
    add_json(p)
    add_latency(p, emulator="with --emulator")
    p.set_defaults(func=_cmd_run)

    p = groups["bench"].add_parser("hw", help="sync write + fast sync read cycle vs wire time")
    add_device(p, "serial device of the servo bus (default: start an emulator at 4 Mbaud)",
               old_port=True)  # fmt: skip
    p.add_argument(
        "--cycles", type=int, default=2000, help="write/read cycles to time (default 2000)"
    )
    add_servo_map(p)
    add_json(p)
    add_latency(p, emulator="on the emulator it starts without --device")
    p.set_defaults(func=_cmd_bench)
