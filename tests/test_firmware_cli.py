"""``payload hw emulate|scan|check`` and ``payload bench hw`` against the emulator."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from typing import Any

import pytest
from conftest import reg, replace_once, spy_on_the_wire

from firmware_interface.control_table import BY_NAME
from firmware_interface.options import EMULATOR_LATENCY_MS, LATENCY_MS
from firmware_interface.servo_map import load_servo_map
from payload.cli import main

LAT = f"{EMULATOR_LATENCY_MS:g}"  # --latency-ms: the emulator's reply allowance


@pytest.fixture(scope="module")
def emulate():
    """``payload hw emulate`` in its own process, missing servo 7."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "payload.cli", "hw", "emulate", "--fault", "missing:7"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    port = proc.stdout.readline().strip()
    yield port
    proc.terminate()
    proc.wait(timeout=10)
    proc.stdout.close()
    proc.stderr.close()


def test_emulate_prints_the_port_path_first(emulate):
    assert emulate.startswith("/dev/") and os.path.exists(emulate)


def test_emulate_serves_on_the_device_path_it_is_given(tmp_path, capsys):
    """``hw emulate --device DEV`` (the CLI contract's spelling): DEV is made a link to
    the pty, printed first, scanned through like a device, and removed when the emulator
    stops; a DEV that exists is refused, one line, exit 2, left as it was."""
    dev = tmp_path / "ttyPAYLOAD"
    proc = subprocess.Popen(
        [sys.executable, "-m", "payload", "hw", "emulate", "--device", str(dev)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().strip() == str(dev)
        assert dev.is_symlink() and os.readlink(dev).startswith("/dev/pts/")
        assert main(["hw", "scan", "--device", str(dev), "--json", "--latency-ms", LAT]) == 0
        found = json.loads(capsys.readouterr().out)
        ids = [x["id"] for x in found["servos"]]
        assert ids == sorted(load_servo_map().ids) and found["missing"] == []
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        said = proc.stderr.read()
        proc.stdout.close()
        proc.stderr.close()
    assert not dev.exists() and not dev.is_symlink()
    # stopping is its normal end (as for `teleop serve`): "stopped", exit 0, not 143
    assert proc.returncode == 0 and said.strip().splitlines()[-1] == "stopped", said
    # a path no link can be made at (/proc takes none): one line, exit 2
    assert main(["hw", "emulate", "--device", "/proc/payload-ttyX"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "/proc/payload-ttyX: cannot link it to the pty" in err[0]
    dev.write_text("mine")
    assert main(["hw", "emulate", "--device", str(dev)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--device {dev}: exists" in err[0]
    assert dev.read_text() == "mine"


def test_scan_lists_ids_models_and_firmware(emulate, capsys):
    assert main(["hw", "scan", "--device", emulate, "--json", "--latency-ms", LAT]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [s["id"] for s in out["servos"]] == [i for i in range(1, 19) if i != 7]
    assert {s["model_number"] for s in out["servos"]} == {1240}
    assert out["missing"] == [{"id": 7, "joint": "B_pip"}]
    assert out["device"] == out["port"] == emulate  # "port": the field before --device


def test_scan_names_the_project_first_and_takes_the_old_port_with_a_warning(emulate, capsys):
    from payload.project import find_project

    assert main(["hw", "scan", "--port", emulate, "--latency-ms", LAT]) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert lines[0] == f"project: {find_project().root}"
    assert sum(ln.startswith("ID ") for ln in lines) == 18  # 17 answering, 7 missing
    warning = captured.err.strip().splitlines()
    assert len(warning) == 1 and "--port is deprecated here; use --device" in warning[0]


def test_hw_commands_without_a_device_say_so(capsys):
    assert main(["hw", "scan"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--device DEV is required" in err[0]


def test_a_device_that_is_not_there_is_one_line_with_the_systems_reason(tmp_path, capsys):
    """The reason is the system's own for opening that path (``os.strerror`` of the errno
    an ``open`` of it raises), said once (pyserial's message carried it twice)."""
    missing = tmp_path / "ttyUSB9"
    with pytest.raises(OSError) as opened:
        open(missing, "rb")  # the system's own answer for this path
    assert main(["hw", "scan", "--device", str(missing)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    reason = os.strerror(opened.value.errno)
    assert len(err) == 1 and f"{missing}: cannot open the serial port ({reason})" in err[0], err
    assert err[0].count(reason) == 1 and "Errno" not in err[0], err
    # a file that is there but no terminal (the system refuses a tty's ioctl: ENOTTY) is
    # said to be no serial device, not in pyserial's words ("Could not configure port")
    assert main(["hw", "scan", "--device", os.devnull]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"payload: error: {os.devnull}: cannot open the serial port (not a serial "
                   "device: give the USB adapter's, e.g. /dev/ttyUSB0)"], err  # fmt: skip


def test_check_fails_naming_the_missing_servo(emulate, capsys):
    assert main(["hw", "check", "--device", emulate, "--json", "--latency-ms", LAT]) == 1
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert report["ok"] is False and report["device"] == emulate  # the bus, as scan says it
    assert report["errors"] == ["servo 7 (B_pip): not answering"]
    assert "servo 7 (B_pip)" in captured.err
    ids = [s["id"] for s in report["servos"]]
    assert 7 not in ids and len(ids) == 17
    s = report["servos"][0]
    assert set(s) == {"id", "joint", "model_number", "hardware_error", "temperature_c",
                      "voltage_v"}  # fmt: skip
    assert s["model_number"] == 1240 and s["voltage_v"] == pytest.approx(5.0)


@contextlib.contextmanager
def _emulating(*faults: str) -> Iterator[str]:
    """``payload hw emulate [--fault F ...]`` in its own process; yields its port."""
    given = [arg for fault in faults for arg in ("--fault", fault)]
    proc = subprocess.Popen(
        [sys.executable, "-m", "payload.cli", "hw", "emulate", *given],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        yield proc.stdout.readline().strip()
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        proc.stdout.close()
        proc.stderr.close()


def test_a_passing_check_says_so(capsys):
    """`hw check` on a healthy bus listed the servos and ended without a word on the
    outcome; it now ends with one line saying it passed, counting the map's servos."""
    with _emulating() as port:
        assert main(["hw", "check", "--device", port, "--latency-ms", LAT]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    n = len(load_servo_map().ids)
    assert len([line for line in out if line.startswith("ID ")]) == n
    assert out[-1].startswith(f"check passed: {n} servos answering, the rail and the stage "), out


def test_check_says_a_servos_hardware_error_once(capsys):
    """A servo in overload from the start: the bring-up refuses it and its health read
    shows it; the report lists the fault once (it listed it twice) and exits 1, saying
    how to clear it as the other commands' refusals do (it did not)."""
    with _emulating("error:12:overload") as port:
        assert main(["hw", "check", "--device", port, "--json", "--latency-ms", LAT]) == 1
        said = capsys.readouterr()
        report = json.loads(said.out)
        # the bring-up homes the rail and the stage: said first, as `hw run` says it
        assert said.err.splitlines()[0] == (
            f"bringing up the servos on {port} and homing the rail and the stage ..."
        ), said.err
        # and, last, what to do about it: the error stays latched until a power cycle
        assert said.err.splitlines()[-1].endswith("then power-cycle the servos)"), said.err
        # the table names the bit (it printed "error  32"), and every other servo's none
        assert main(["hw", "check", "--device", port, "--latency-ms", LAT]) == 1
        rows = [x for x in capsys.readouterr().out.splitlines() if x.startswith("ID ")]
    flagged = [s for s in report["servos"] if s["hardware_error"]]
    assert [s["id"] for s in flagged] == [12]
    assert report["errors"] == [f"servo 12 ({flagged[0]['joint']}): hardware error overload"]
    assert len(rows) == len(report["servos"])
    for row in rows:
        named = "overload" if row.startswith("ID  12 ") else "none"
        assert row.endswith(f"  hardware error: {named}"), row


def test_check_names_every_fault_the_bring_up_found_once(capsys):
    """A missing servo, one of another model and two with latched errors: the check named
    the missing one and the two errors (their health rows) but not the other model (the
    bring-up stopped at the missing one); it now names each once, and its table has the
    missing servo's row (it had none)."""
    faults = ("error:3:overheating", "error:7:overload", "missing:9", "model:5:1060")
    with _emulating(*faults) as port:
        assert main(["hw", "check", "--device", port, "--json", "--latency-ms", LAT]) == 1
        report = json.loads(capsys.readouterr().out)
        assert main(["hw", "check", "--device", port, "--latency-ms", LAT]) == 1
        rows = [x for x in capsys.readouterr().out.splitlines() if x.startswith("ID ")]
    # a row per mapped servo, in the map's order, the missing one's too (as `hw scan`), and
    # the JSON's list of them (as `hw scan --json`'s)
    assert report["missing"] == [{"id": 9, "joint": "C_mcp_flex"}]
    assert [int(r.split()[1]) for r in rows] == list(range(1, 19)), rows
    assert rows[8] == "ID   9 C_mcp_flex  not answering", rows[8]
    assert report["errors"] == [
        "servo 9 (C_mcp_flex): not answering",
        "servo 5 (B_mcp_flex): model number 1060, not the servo map's 1240: another servo "
        "on this ID?",
        "servo 3 (A_pip): hardware error overheating",
        "servo 7 (B_pip): hardware error overload",
    ], report["errors"]


def test_check_reads_no_health_register_of_a_servo_of_another_model(monkeypatch, capsys):
    """Servo 5 answers as model 1060 with its overload bit set where an X-series servo
    keeps Hardware Error Status: `hw check` read its health registers anyway (another
    family's control table may hold anything there) and reported that bit as a hardware
    error; and the driver's close wrote Torque Enable = 0 (X-series address 64) to it
    and read it back. Now nothing but the scan (its ping, then Firmware Version) goes to
    it (the host's packets on the wire say so), its row says in words why it has no
    values, the other servos' rows are read, they get the torque-off, and the check still
    fails naming the model, exit 1."""
    from firmware_interface import protocol as P

    seen = spy_on_the_wire(monkeypatch)
    with _emulating("model:5:1060", "error:5:overload") as port:
        assert main(["hw", "check", "--device", port, "--json", "--latency-ms", LAT]) == 1
        report = json.loads(capsys.readouterr().out)
        assert main(["hw", "check", "--device", port, "--latency-ms", LAT]) == 1
        rows = [x for x in capsys.readouterr().out.splitlines() if x.startswith("ID ")]
    assert seen[5] == {(P.PING, None)}, sorted(seen[5], key=str)  # nothing else reached 5
    assert P.BROADCAST_ID not in seen, sorted(seen[P.BROADCAST_ID], key=str)
    # the spy sees the health reads and the close's torque-off of a servo of the map's model
    torque = BY_NAME["torque_enable"].address
    assert {(P.READ, BY_NAME["present_temperature"].address), (P.SYNC_WRITE, torque),
            (P.READ, torque)} <= seen[4], sorted(seen[4], key=str)  # fmt: skip
    why = "health registers not read: it is model 1060, not the map's 1240"
    assert report["errors"] == [
        "servo 5 (B_mcp_flex): model number 1060, not the servo map's 1240: another servo "
        "on this ID?"
    ], report["errors"]
    (row,) = [s for s in report["servos"] if s["id"] == 5]
    assert row == {"id": 5, "joint": "B_mcp_flex", "model_number": 1060, "hardware_error": None,
                   "temperature_c": None, "voltage_v": None, "not_read": why}  # fmt: skip
    others = [s for s in report["servos"] if s["id"] != 5]
    assert [s["id"] for s in others] == [i for i in load_servo_map().ids if i != 5]
    assert all(s["hardware_error"] == 0 and s["model_number"] == 1240 for s in others)
    assert len(rows) == len(report["servos"])
    assert next(x for x in rows if x.startswith("ID   5 ")).endswith(f"model 1060  {why}"), rows


@pytest.mark.parametrize(
    "argv, allowance",
    [
        (["hw", "run", "--emulator"], EMULATOR_LATENCY_MS),
        (["hw", "run", "--emulator", "--latency-ms", "20"], 20.0),
        (["hw", "run", "--device", "DEV"], LATENCY_MS),
        (["hw", "identify", "--emulator"], EMULATOR_LATENCY_MS),
        (["bench", "hw"], EMULATOR_LATENCY_MS),
        (["bench", "hw", "--latency-ms", "5"], 5.0),
    ],
)
def test_an_emulator_the_command_starts_gets_a_50_ms_reply_allowance(
    argv, allowance, tmp_path, monkeypatch, capsys
):
    """On an emulated bus it starts itself a command gave the driver the USB adapter's
    16 ms latency allowance, which the emulator on a loaded host does not meet; it now
    gives 50 ms unless --latency-ms says otherwise; a --device keeps the adapter's 16."""
    from firmware_interface import driver
    from payload.errors import RunAborted

    given = []

    def spy(device, smap, **kwargs):
        given.append(kwargs["latency_timer_ms"])
        raise RunAborted("the spy stops here")

    monkeypatch.setattr(driver, "DynamixelDriver", spy)
    hands = tmp_path / "hands.jsonl"
    hands.write_text("")
    extra = ["--replay", str(hands), "--out", str(tmp_path / "run")] if argv[1] == "run" else []
    assert main([*argv, *extra]) == 1
    assert given == [allowance]
    assert "the spy stops here" in capsys.readouterr().err


def test_check_fails_on_a_blocked_rail(capsys):
    """A blocked rail used to pass `hw check`: homing took the stalled shaft for the hard
    stop. The check now fails (exit 1) with the homing's refusal naming the rail, and
    every servo's health is still read and listed."""
    with _emulating("block:17") as port:
        assert main(["hw", "check", "--device", port, "--json", "--latency-ms", LAT]) == 1
        said = capsys.readouterr()
    report = json.loads(said.out)
    assert report["ok"] is False and len(report["errors"]) == 1, report["errors"]
    assert report["errors"][0].startswith("homing: rail ("), report["errors"]
    assert "the drive is jammed" in report["errors"][0]
    assert [s["id"] for s in report["servos"]] == sorted(load_servo_map().ids)
    assert "homing: rail (" in said.err.splitlines()[-1]


@pytest.mark.parametrize("spec", ["drop:7", "missing:99", "error:77:overload"])
def test_a_bad_fault_spec_is_one_line_and_exit_2(spec):
    """A spec that does not parse, and one naming a servo the bus does not have (a typo's
    fault would do nothing): one line naming it, exit 2, no bus served."""
    r = subprocess.run(
        [sys.executable, "-m", "payload.cli", "hw", "emulate", "--fault", spec],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().count("\n") == 0 and spec in r.stderr


def test_bench_hw_reports_the_cycle_against_the_wire_time(capsys):
    assert main(["bench", "hw", "--cycles", "40", "--json", "--latency-ms", LAT]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("cycles", "cycle_mean_us", "cycle_p99_us", "wire_us", "ratio_to_wire",
                "retries", "baud"):  # fmt: skip
        assert key in out
    assert out["cycles"] == 40 and out["baud"] == 4_000_000
    # 18 servos: sync write 7+1+4+18*5+2, fast sync read 7+1+4+18+2, reply 8+18*(2+10+2)
    n_bytes = (7 + 1 + 4 + 90 + 2) + (7 + 1 + 4 + 18 + 2) + (8 + 18 * 14)
    assert out["wire_us"] == pytest.approx(n_bytes * 10 / 4e6 * 1e6)
    assert out["ratio_to_wire"] == pytest.approx(out["cycle_mean_us"] / out["wire_us"])
    assert out["cycle_p99_us"] >= out["cycle_mean_us"] * 0.5 > 0
    # the driver's collision guard, part of every cycle: well inside the 20 ms of 50 Hz
    assert 0 < out["guard_cpu_us"] < 20_000 and out["guard_us"] > 0


def test_scan_of_a_bus_where_nobody_answers_fails(capsys):
    """``hw scan`` lists what answered; a bus where no servo does is a failed look (exit 1,
    one line), as ``hw check`` says of it."""
    import os

    master, slave = os.openpty()
    try:
        code = main(["hw", "scan", "--device", os.ttyname(slave)])
        out, err = capsys.readouterr()
        # and `hw check` says the same of it, not eighteen servos "not answering" in a row
        checked = main(["hw", "check", "--device", os.ttyname(slave)])  # nobody to wait for
        said = capsys.readouterr().err.strip().splitlines()
    finally:
        os.close(master)
        os.close(slave)
    assert code == 1 and "not answering" in out
    assert err.strip().splitlines()[-1].startswith("payload: check failed: no servo answered")
    assert said[0].startswith("bringing up the servos on "), said  # its stage, first
    assert checked == 1 and len(said) == 2 and "not answering" not in said[1], said
    assert said[1].startswith("payload: check failed: no servo answered on "), said


@pytest.mark.parametrize(
    "argv, named",
    [
        (["hw", "scan", "--latency-ms", "nan"], "--latency-ms"),
        (["hw", "check", "--latency-ms", "-5"], "--latency-ms"),
        (["hw", "identify", "--latency-ms", "inf"], "--latency-ms"),
        (["hw", "run", "--max-time", "-1"], "--max-time"),
        (["hw", "run", "--max-time", "nan"], "--max-time"),
    ],
)
def test_a_bad_number_is_one_line_before_the_bus_is_touched(argv, named, tmp_path, capsys):
    """A reply timeout that is NaN, infinite (a silent servo waited on forever) or
    negative, or a session cap that is not positive, is bad input: one line naming the
    option, exit 2, before any packet reaches the bus or any folder is made (``hw run
    --max-time -1`` used to home the payload, then fail on its own empty recording and
    leave it behind)."""
    from firmware_interface.emulator import EmulatorProcess

    out = tmp_path / "run"
    with EmulatorProcess() as emu:
        extra = ["--replay", __file__, "--out", str(out)] if argv[1] == "run" else []
        code = main([*argv, "--device", emu.port, *extra])
        assert emu.stats()["packets"] == {}  # the bus never heard from it
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith(f"payload: error: {named} ")
    assert not out.exists()


def test_emulate_serves_the_servos_of_the_project_given(tmp_path, monkeypatch, capsys):
    """``payload hw emulate --project DIR`` emulates DIR's servos (its ``[servo]`` model,
    its travel ends), from anywhere, and still prints the pty path as its first stdout
    line (no ``project:`` line before it). ``--project`` was accepted and ignored:
    outside a project it failed ("not inside a design project ... use --project DIR"),
    inside another it emulated that one's servos."""
    import re

    import firmware_interface.emulator as emulator

    root = tmp_path / "scratch"
    assert main(["new", str(root)]) == 0
    path = root / "cad" / "design.toml"
    text, n = re.subn(r"(?m)^armature = [0-9.eE+-]+", "armature = 3.5e-3", path.read_text())
    assert n == 1
    path.write_text(text)
    served = []
    monkeypatch.setattr(emulator, "serve", lambda spec, *a, **k: served.append(spec))
    monkeypatch.delenv("PAYLOAD_PROJECT", raising=False)
    monkeypatch.chdir(tmp_path)  # in no project
    capsys.readouterr()
    assert main(["hw", "emulate", "--project", str(root)]) == 0
    (spec,) = served
    # the unloaded abduction servo is the armature alone (the finger links beyond it
    # add their inertia about the abduction axis): every plant includes 3.5e-3
    assert min(p["inertia"] for p in spec["plants"].values()) >= 3.5e-3
    assert capsys.readouterr().out == ""  # serve() prints the pty path first


@pytest.mark.parametrize(
    "argv", [["hw", "scan"], ["hw", "check"], ["bench", "hw", "--cycles", "5"]]
)
def test_commands_whose_guard_reads_the_models_make_them_follow_the_design_first(
    argv, emulate, tmp_path, monkeypatch, capsys
):
    """The driver's collision guard reads the project's URDF, so every command that makes
    a driver applies the one rule for stale models (rebuild, saying so) before the guard
    is built: it never checks commands against the geometry of an earlier design."""
    import firmware_interface.driver as driver_module
    from payload.design import load_design, stale_files
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    text = project.design_path.read_text()
    project.design_path.write_text(replace_once(text, "distal = 0.045 ", "distal = 0.044 "))
    assert stale_files(load_design(project.design_path), project.root)
    capsys.readouterr()
    stale_at_guard = []
    real = driver_module.default_guard

    def guard():
        stale_at_guard.append(stale_files(load_design(project.design_path), project.root))
        return real()

    monkeypatch.setattr(driver_module, "default_guard", guard)
    device = [] if argv[0] == "bench" else ["--device", emulate]
    code = main(["--project", str(project.root), *argv, *device, "--latency-ms", LAT])
    out = capsys.readouterr().out.splitlines()
    assert code in (0, 1)  # hw check: servo 7 is missing on this bus
    assert out[0] == f"project: {project.root}"
    assert out[1].startswith("models: rebuilt ") and "urdf/payload.urdf" in out[1]
    assert stale_at_guard == [[]]


@pytest.mark.parametrize("late", ["latency:50ms", "latency:36ms"])
def test_check_never_passes_on_replies_that_come_after_their_timeout(late, capsys):
    """Replies later than the 34 ms reply timeout of a 16 ms latency timer: `hw check`
    passed on them with rows like "model 21248 ... 0 C 3689.6 V" (late replies taken as
    the answers to later reads). Now each row shown is what the emulator's tables hold,
    or the check fails, saying the replies came late."""
    from firmware_interface.control_table import VOLTAGE_UNIT_V
    from firmware_interface.emulator import EmulatorProcess

    with EmulatorProcess(faults=[late]) as emu:
        code = main(["hw", "check", "--device", emu.port, "--json", "--latency-ms", "16"])
        tables = emu.tables()
    out, err = capsys.readouterr()
    report = json.loads(out)
    for s in report["servos"]:  # a row shown is the emulator's (none is, below)
        t = tables[s["id"]]
        assert s["model_number"] == reg(t, "model_number") == 1240
        assert s["temperature_c"] == reg(t, "present_temperature")
        assert s["voltage_v"] == pytest.approx(reg(t, "present_input_voltage") * VOLTAGE_UNIT_V)
    # every reply is late (36 and 50 ms > 2 x 16 + 2 ms): the check fails, saying so
    assert code == 1 and not report["ok"] and report["servos"] == [], report
    # (which read meets them first depends on the host's load; each says the timeout)
    assert "34 ms reply timeout" in err, err


@pytest.mark.parametrize(
    ("fault", "named"),
    [("missing:7", "ID 7 ({})"), ("error:12:overload", "servo 12 ({}): hardware error")],
)
def test_bench_hw_says_it_homes_and_fails_a_bring_up_as_a_failed_start(fault, named, capsys):
    """`bench hw` on a bus with a servo missing or faulted: the notice that the rail and
    the stage are homed first, then `payload: aborted: ...` naming the servo, exit 1 (the
    hardware's state), not exit 2 (bad input), as every other hw command."""
    from firmware_interface.emulator import EmulatorProcess

    with EmulatorProcess(faults=[fault]) as emu:
        code = main(["bench", "hw", "--device", emu.port, "--cycles", "5", "--latency-ms", LAT])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1, err
    assert f"bringing up the servos on {emu.port} and homing the rail and the stage ..." in err
    assert err[-1].startswith(f"payload: aborted: bring-up on {emu.port} failed: "), err
    joint = load_servo_map().joint_of(int(fault.split(":")[1]))  # the servo the fault is on
    assert named.format(joint) in err[-1], err


def test_bench_hw_on_a_bus_where_nobody_answers_is_a_failed_start(capsys):
    import os

    master, slave = os.openpty()
    try:
        device = os.ttyname(slave)
        code = main(["bench", "hw", "--device", device, "--cycles", "5", "--latency-ms", "5"])
    finally:
        os.close(master)
        os.close(slave)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1, err
    assert err[-1] == (
        f"payload: aborted: no servo answered on {device} (power, wiring, baud rate, IDs?)"
    ), err


def _fault_at_homing(monkeypatch: Any, emu: Any, spec: str) -> None:
    """The emulator's fault ``spec`` starts as the bring-up's homing does (after the scan
    and the first reads)."""
    from firmware_interface.driver import DynamixelDriver

    home = DynamixelDriver.home

    def fault_then_home(drv: Any, *args: Any, **kwargs: Any) -> Any:
        emu.fault(spec)
        return home(drv, *args, **kwargs)

    monkeypatch.setattr(DynamixelDriver, "home", fault_then_home)


def test_check_names_a_servo_gone_silent_in_a_sync_read_without_blaming_latency(
    monkeypatch, capsys
):
    """Servo 5 goes silent after the scan, before the homing's sync reads: the plain sync
    read waits on it while servos 6..18 answer on time. Those replies were counted late,
    and `hw check` failed with "N replies came after the reply timeout (--latency-ms?)",
    every row hidden. Now it names servo 5, blames no latency, and shows the rows read
    (each as the emulator's own table holds it)."""
    from firmware_interface.emulator import EmulatorProcess

    with EmulatorProcess() as emu:
        _fault_at_homing(monkeypatch, emu, "missing:5")
        code = main(["hw", "check", "--device", emu.port, "--json", "--latency-ms", LAT])
        tables = emu.tables()
    out, err = capsys.readouterr()
    report = json.loads(out)
    assert code == 1 and not report["ok"]
    assert any("servo 5 (B_mcp_flex)" in e for e in report["errors"]), report["errors"]
    assert not any("latency" in e or "came after" in e for e in report["errors"]), err
    assert report["servos"], report  # the rows read before servo 5's own read failed
    # and after it: one silent servo does not end the look (the rows stopped at 5)
    assert max(s["id"] for s in report["servos"]) > 5, report["servos"]
    assert "no reply to the health read from servo 5 (B_mcp_flex)" in report["errors"]
    for s in report["servos"]:
        assert s["id"] != 5
        assert s["model_number"] == reg(tables[s["id"]], "model_number")


def test_check_on_a_bus_gone_silent_reads_two_servos_then_says_the_rest_were_not(
    monkeypatch, capsys
):
    """Every reply lost from the homing on (the emulator's drop fault at probability 1):
    the health reads stop after two lost in a row, in one line naming them and how many
    were left unread (each further read would wait out its retries)."""
    from firmware_interface.cli import SILENT_RUN
    from firmware_interface.driver import DynamixelDriver
    from firmware_interface.emulator import EmulatorProcess

    reads, read_health = [], DynamixelDriver.read_health
    with EmulatorProcess() as emu:
        _fault_at_homing(monkeypatch, emu, "drop:1")
        monkeypatch.setattr(
            DynamixelDriver, "read_health", lambda drv, i: reads.append(i) or read_health(drv, i)
        )
        code = main(["hw", "check", "--device", emu.port, "--json", "--latency-ms", LAT])
    report = json.loads(capsys.readouterr().out)
    assert code == 1 and report["servos"] == []
    assert len(reads) == SILENT_RUN == 2
    said = [e for e in report["errors"] if e.startswith("no reply to the health read")]
    smap = load_servo_map()
    first, second = smap.ids[0], smap.ids[1]
    assert said == [
        f"no reply to the health read from servos {first} ({smap.joint_of(first)}), "
        f"{second} ({smap.joint_of(second)}), and the {len(smap.ids) - 2} after it not read"
    ], report["errors"]


def test_check_of_a_device_that_goes_away_is_a_failed_check_not_bad_input(monkeypatch, capsys):
    """The serial device gone during the bring-up (unplugged; here the emulator ended):
    ``hw check`` said ``payload: error:`` and exit 2, bad input, where ``hw run`` and ``hw
    identify`` say the hardware's state (``aborted``, exit 1). A failed check, exit 1."""
    from firmware_interface.driver import DynamixelDriver
    from firmware_interface.emulator import EmulatorProcess

    home = DynamixelDriver.home
    with EmulatorProcess() as emu:

        def gone_then_home(drv, *args, **kwargs):
            emu.proc.kill()
            emu.proc.wait()
            return home(drv, *args, **kwargs)

        monkeypatch.setattr(DynamixelDriver, "home", gone_then_home)
        code = main(["hw", "check", "--device", emu.port, "--latency-ms", LAT])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1, err
    assert err[-1].startswith("payload: check failed: ") and "serial device" in err[-1], err
    # a device that cannot be opened at all is still bad input, as `hw scan` says it
    for device in (os.devnull, "/dev/ttyUSB-no-such"):
        assert main(["hw", "check", "--device", device, "--latency-ms", LAT]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith(f"payload: error: {device}: cannot open the serial port"), err


def test_hw_run_given_a_trials_folder_names_the_recording_in_it(tmp_path, capsys) -> None:
    """``hw run --replay runs/trial-0000`` said only "is not a file"; it says what the
    folder is and which file in it to give, as ``payload trial --replay`` does."""
    trial = tmp_path / "trial-0000"
    trial.mkdir()
    (trial / "log.mcap").write_bytes(b"")
    assert main(["hw", "run", "--emulator", "--replay", str(trial)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"payload: error: --replay: {trial}: is a folder, not a recording: give "
        f"{trial / 'log.mcap'}"
    ], err


def test_scan_ends_with_what_it_found_and_what_check_would_refuse(capsys):
    """``hw scan`` listed the IDs and stopped: a missing servo and one of another model on
    a mapped ID (model 1060, said without comment) read like a bus ready to run. Its last
    line counts the map's servos answering and names what ``hw check`` refuses (the look
    itself still exits 0, as documented); the other model's row says so."""
    with _emulating("missing:7", "model:5:1060") as port:
        assert main(["hw", "scan", "--device", port, "--latency-ms", LAT]) == 0
        lines = capsys.readouterr().out.splitlines()
    row = next(x for x in lines if x.startswith("ID   5 "))
    assert row == "ID   5  model 1060  firmware -  B_mcp_flex  (not the map's 1240)", row
    assert lines[-1] == (
        "17 of the map's 18 servos answering; 1 not answering, 1 of another model: "
        "`payload hw check` refuses this bus"
    ), lines


@pytest.mark.parametrize(
    "argv",
    [
        ["hw", "check"],
        ["hw", "scan"],
        ["bench", "hw", "--cycles", "1"],
        ["hw", "run", "--replay", "REPLAY"],
        ["hw", "identify"],
        ["teleop", "serve", "--driver", "hardware"],
    ],
)
def test_a_device_that_is_not_there_rebuilds_no_model_first(argv, tmp_path, capsys) -> None:
    """A new user's ``payload hw check --device /dev/ttyUSB0`` with no adapter plugged in,
    in a project whose design had changed, printed "models: rebuilt ..." and rewrote the
    project's models before "cannot open the serial port". The missing device is refused
    first, in the driver's words and the system's reason, and no model file changes."""
    import hashlib

    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    design = project.design_path
    design.write_text(replace_once(design.read_text(), "distal = 0.045 ", "distal = 0.047 "))
    models = sorted(p for p in project.root.rglob("*") if p.suffix in (".urdf", ".xml", ".stl"))
    before = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in models}
    missing = tmp_path / "ttyUSB9"
    with pytest.raises(OSError) as opened:
        open(missing, "rb")  # the system's own answer for this path
    replay = tmp_path / "hands.jsonl"
    replay.write_text("")
    argv = [str(replay) if a == "REPLAY" else a for a in argv]
    code = main([*argv, "--device", str(missing), "--project", str(project.root)])
    out, err = capsys.readouterr()
    assert code == 2, err
    reason = os.strerror(opened.value.errno)
    assert err.strip().splitlines() == [
        f"payload: error: {missing}: cannot open the serial port ({reason})"
    ], err
    assert "models: rebuilt" not in out
    assert {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in models} == before


def test_check_reads_no_health_register_of_another_model_after_a_bring_up_that_lost_replies(
    monkeypatch, capsys
) -> None:
    """A bring-up that stops on lost or late replies after its scan (a CommError) named no
    servo of another model, so `hw check` read servo 5's health registers anyway (model
    1060, another family's table) and could report a made-up hardware error. The scan's
    finding is used: servo 5 gets nothing but the scan and its row says why."""
    from firmware_interface import protocol as P
    from firmware_interface.driver import DynamixelDriver
    from firmware_interface.errors import CommError

    def scan_then_lose(drv) -> None:
        drv.scan()
        raise CommError("servo 9 (C_mcp_flex): no reply (lost after the scan)")

    monkeypatch.setattr(DynamixelDriver, "bring_up", scan_then_lose)
    seen = spy_on_the_wire(monkeypatch)
    with _emulating("model:5:1060", "error:5:overload") as port:
        assert main(["hw", "check", "--device", port, "--json", "--latency-ms", LAT]) == 1
        report = json.loads(capsys.readouterr().out)
    assert seen[5] == {(P.PING, None)}, sorted(seen[5], key=str)  # the scan's ping alone
    (row,) = [s for s in report["servos"] if s["id"] == 5]
    assert row["not_read"] == "health registers not read: it is model 1060, not the map's 1240"
    assert not any("hardware error" in e for e in report["errors"]), report["errors"]
    assert any("model number 1060" in e for e in report["errors"]), report["errors"]
