"""``payload hw identify`` against the emulator holding hidden servo parameters."""

from __future__ import annotations

import json

import pytest

from firmware_interface.identify import write_servo_values
from firmware_interface.options import EMULATOR_LATENCY_MS
from payload.cli import main
from payload.design import load_design

HIDDEN = {"kt": 0.45, "resistance": 3.3, "viscous": 0.0105, "coulomb": 0.015}
HIDDEN_INERTIA = 0.0032  # [kg m^2] finger flexion servo with its load


def test_identify_recovers_hidden_emulator_parameters_within_10_percent(tmp_path, capsys):
    """The emulator's finger servos hold kt, R, friction and inertia 13-35 % off the
    design's; identify, through the driver on the pty of the emulator it starts
    (``--emulator --servo-params``), recovers each within 10 %."""
    design = load_design()
    for key, value in HIDDEN.items():
        assert abs(value / getattr(design.servo, key) - 1) > 0.1, key  # really hidden
    params = tmp_path / "hidden.json"
    params.write_text(json.dumps({"*": HIDDEN, "finger": {"inertia": HIDDEN_INERTIA}}))
    # the emulator's own reply allowance, --emulator's default (EMULATOR_LATENCY_MS)
    code = main(["hw", "identify", "--emulator", "--servo-params", str(params), "--joints",
                 "A_mcp_flex", "--json"])  # fmt: skip
    assert code == 0
    said = capsys.readouterr()
    report = json.loads(said.out)
    (servo,) = report["servos"]
    assert report["emulator"] is True and report["device"].startswith("/dev/pts/")
    # each stage said as it starts, on stderr (a whole bus takes minutes, each joint moving)
    lines = said.err.splitlines()
    stages = [
        f"bringing up the servos on {report['device']} and homing the rail and the stage ...",
        f"servo 1 of 1: A_mcp_flex (ID {servo['id']}), steps and a chirp across its range ...",
    ]
    assert all(line in lines for line in stages), said.err
    assert [lines.index(line) for line in stages] == sorted(lines.index(x) for x in stages)
    got = servo["fit"]
    for key, value in HIDDEN.items():
        assert got[key] == pytest.approx(value, rel=0.10), key
    assert got["inertia"] == pytest.approx(HIDDEN_INERTIA, rel=0.10)
    assert got["residual"]["voltage"] < 0.2 and got["residual"]["dynamics"] < 0.3
    assert report["written"] is None  # nothing written without --write
    assert report["suggested"]["kt"] == got["kt"]


def test_write_servo_values_keeps_comments_and_refuses_unknown_keys(tmp_path):
    path = tmp_path / "design.toml"
    path.write_text("[servo]\nkt = 0.517  # [N m/A] datasheet\n[other]\nkt = 1.0\n")
    write_servo_values(path, {"kt": 0.45})
    assert path.read_text() == "[servo]\nkt = 0.45  # [N m/A] datasheet\n[other]\nkt = 1.0\n"
    with pytest.raises(ValueError, match="no resistance"):
        write_servo_values(path, {"resistance": 3.0})


def test_a_bad_servo_params_file_is_refused_in_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"finger": {"kt": 0.0}}))
    assert main(["hw", "emulate", "--servo-params", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "finger.kt: expected a number > 0" in err
    bad.write_text(json.dumps({"*": {"stiffness": 1.0}}))
    assert main(["hw", "emulate", "--servo-params", str(bad)]) == 2
    assert "*.stiffness: unknown" in capsys.readouterr().err
    # a unit slip (kt in mN m/A): refused, it drove the emulated shaft past its registers
    assert load_design().servo.kt == 0.517  # the datasheet's 0.93 N m / 1.80 A
    bad.write_text(json.dumps({"*": {"kt": 450}}))
    assert main(["hw", "emulate", "--servo-params", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "*.kt: 450 is 870 times the design's 0.517" in err
    # each layer is weighed against the design, not the layer before it: 0.2 for all and
    # 2.5 for servo 12 are each within ten times 0.517 (12.5 times 0.2 was refused)
    from firmware_interface.emulator import bus_spec

    bad.write_text(json.dumps({"*": {"kt": 0.2}, "12": {"kt": 2.5}}))
    plants = bus_spec(None, str(bad))["plants"]
    assert plants["12"]["kt"] == 2.5 and plants["1"]["kt"] == 0.2


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--device", "/dev/null", "--emulator"], "give either --device DEV or --emulator"),
        ([], "give either --device DEV or --emulator"),
        (["--device", "/dev/null", "--servo-params", "p.json"], "give it with --emulator"),
        (["--emulator", "--write"], "not your servos' (identify the hardware"),
    ],
)
def test_identify_takes_one_bus(extra: list[str], message: str, capsys) -> None:
    """A device and an emulator, neither, or an emulated servo's values for a real bus:
    one line and exit 2 before anything is opened."""
    assert main(["hw", "identify", *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and message in err, err


def test_identify_refuses_a_bad_servo_params_file_before_starting_a_bus(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"finger": {"kt": 0.0}}))
    args = ["hw", "identify", "--emulator", "--servo-params", str(bad), "--joints", "A_pip"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"{bad}: finger.kt: expected a number > 0" in err, err


def test_identify_write_on_a_device_that_is_the_emulator_is_refused(tmp_path, capsys):
    """``--write`` is refused with ``--emulator``; given the emulator's device path as
    ``--device``, identify wrote the emulator's values into the design. The bus says it is
    the emulator (its servos' Model Information): refused after the bring-up, before any
    servo moves, the design file as it was."""
    from firmware_interface.emulator import EmulatorProcess

    project = tmp_path / "proj"
    assert main(["new", str(project)]) == 0
    design = project / "cad" / "design.toml"
    before = design.read_bytes()
    capsys.readouterr()
    with EmulatorProcess() as emu:
        argv = ["hw", "identify", "--device", emu.port, "--write", "--joints", "A_pip",
                "--project", str(project), "--latency-ms", f"{EMULATOR_LATENCY_MS:g}"]  # fmt: skip
        assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (
        f"payload: error: {emu.port} answers as the emulator: --write takes real servos' "
        "values, not written"
    ), err
    assert design.read_bytes() == before
