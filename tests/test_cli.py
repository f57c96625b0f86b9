"""The command line as a whole: no abbreviated options, a wrong option prints the
subcommand and one line, and bad input files give one line and exit 2."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT, replace_once

from payload.cli import COMMAND_MODULES, COMMANDS, GROUPS, build_parser, main, registered_commands
from payload.cliutil import DeprecatedAlias
from payload.schema import CONTROL_DT

STL = ROOT / "cad" / "meshes" / "finger_distal.stl"


def _parsers(parser: argparse.ArgumentParser, path: str = "payload"):
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _parsers(child, f"{path} {name}")


def test_no_parser_accepts_abbreviations() -> None:
    found = dict(_parsers(build_parser()))
    assert {"payload trial", "payload trials run", "payload report reach"} <= set(found)
    assert [path for path, p in found.items() if p.allow_abbrev] == []


def test_the_module_entry_points_accept_no_abbreviations(tmp_path, monkeypatch, capsys) -> None:
    """The two other parsers a user runs (``python -m payload.review.browser``, documented
    in docs/review.md, and ``python -m firmware_interface.emulator``, docs/hardware.md)
    refuse an abbreviated option with one line naming them, exit 2, before doing anything;
    the browser's missing page is one error too (was a Playwright traceback)."""
    from firmware_interface import emulator
    from payload.review import browser

    def never(*args, **kwargs):
        raise AssertionError("ran with an abbreviated option")

    monkeypatch.setattr(browser, "screenshot", never)
    monkeypatch.setattr(emulator, "serve", never)
    monkeypatch.setattr(emulator, "bus_spec", never)
    page = tmp_path / "review.html"
    page.write_text("<html></html>")
    cases = [
        (
            browser.main,
            ["--tim", "0", str(page), str(tmp_path / "x.png")],
            "(did you mean --time?)",
        ),
        (emulator.main, ["--see", "3"], "--see 3 (did you mean --seed?)"),
        (browser.main, [str(tmp_path / "none.html"), str(tmp_path / "x.png")], "no such file"),
    ]
    for entry, argv, word in cases:
        with pytest.raises(SystemExit) as info:
            entry(argv)
        assert info.value.code == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith("python -m ") and word in err[0], err


@pytest.mark.parametrize(
    ("argv", "line"),
    [
        (
            ["report", "reach", "--sample", "1000"],
            "payload report reach: error: unrecognized arguments: --sample 1000 (did you mean "
            "--samples?); see payload report reach --help",
        ),
        (
            ["trials", "run", "--n", "1", "--out", "x", "--work", "2"],
            "payload trials run: error: unrecognized arguments: --work 2 (did you mean "
            "--workers?); see payload trials run --help",
        ),
        (
            ["trial", "--sed", "3", "--outt", "x"],
            "payload trial: error: unrecognized arguments: --sed 3 --outt x (did you mean "
            "--seed for --sed, --out for --outt?); see payload trial --help",
        ),
        (
            ["trials", "summarize", "x", "--recomp"],
            "payload trials summarize: error: unrecognized arguments: --recomp (did you mean "
            "--recompute?); see payload trials summarize --help",
        ),
        (
            ["build", "--xyzzy"],
            "payload build: error: unrecognized arguments: --xyzzy; see payload build --help",
        ),
        (  # --set is required, and missing: the misspelling is what to say
            ["sweep", "--sett", "rail.travel=0.04"],
            "payload sweep: error: unrecognized arguments: --sett (did you mean --set?); see "
            "payload sweep --help",
        ),
        (  # near --out only by the two dashes they share
            ["trial", "--bogus"],
            "payload trial: error: unrecognized arguments: --bogus; see payload trial --help",
        ),
        (
            ["trail", "--seed", "3"],
            "payload: error: argument COMMAND: invalid choice: 'trail' (choose from 'new', "
            "'build', 'summary', 'report', 'review', 'bench', 'trial', 'trials', 'export', "
            "'sweep', 'teleop', 'hw') (did you mean 'trial'?); see payload --help",
        ),
        (
            ["trial", "--controller", "saf"],
            "payload trial: error: argument --controller: invalid choice: 'saf' (choose from "
            "'paper', 'safe') (did you mean 'safe'?); see payload trial --help",
        ),
        (
            ["trial", "--seed", "x"],
            "payload trial: error: argument --seed: invalid int value: 'x'; see payload trial "
            "--help",
        ),
    ],
)
def test_a_wrong_option_is_one_line_naming_the_subcommand(argv, line, capsys) -> None:
    """An option the parser refuses is one line, as every other bad input is (argparse
    printed the command's whole usage above it), naming the command, the closest option
    or choice it has (``--xyzzy`` is near none), and its help; exit 2."""
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err.splitlines()
    if "(choose from " in line:  # argparse quotes the choices or not, by Python version
        head, tail = line.split(" (choose from ")[0], line.split(") (did you mean")[1]
        assert len(err) == 1 and err[0].startswith(head + " (choose from "), err
        assert err[0].endswith(") (did you mean" + tail), err
    else:
        assert err == [line]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["summary", "--design", str(STL)], "not a text (UTF-8 TOML) file"),
        (["report", "envelope", "--design", str(STL)], "not a text (UTF-8 TOML) file"),
        (["trial", "--replay", str(STL)], "not a payload-hands recording"),
        (["trial", "--controller", "safe", "--zones", str(STL)], "not a text (UTF-8 JSON) file"),
        (["hw", "scan", "--device", "/dev/null", "--servos", str(STL)], "not a text (UTF-8"),
        (["bench", "retarget", "--hand", str(STL)], "not a text (UTF-8 TOML) file"),
        (["bench", "retarget", "--config", str(STL)], "not a text (UTF-8 TOML) file"),
    ],
)
def test_binary_input_files_give_one_line_and_exit_2(argv, message, capsys) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and str(STL) in err[0]


def test_replaying_a_json_file_that_is_not_a_hand_recording_says_so(tmp_path, capsys) -> None:
    """A trial's metrics.json (pretty-printed JSON) given to --replay: the line says the
    file is not a hand recording, not that its "header is not JSON"."""
    metrics = tmp_path / "metrics.json"
    metrics.write_text('{\n  "seed": 0,\n  "success": true\n}\n')
    assert main(["trial", "--replay", str(metrics), "--out", str(tmp_path / "t")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{metrics}: not a payload-hands recording" in err[0]
    assert "log.mcap" in err[0] and not (tmp_path / "t").exists()


def test_build_of_a_design_outside_a_project_writes_nothing(tmp_path: Path, capsys) -> None:
    variant = tmp_path / "variant.toml"
    variant.write_text((ROOT / "cad" / "design.toml").read_text())
    committed = {p: p.stat().st_mtime_ns for p in (ROOT / "urdf").iterdir()}
    assert main(["build", "--design", str(variant)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a design project's cad/design.toml" in err[0]
    assert {p: p.stat().st_mtime_ns for p in (ROOT / "urdf").iterdir()} == committed
    assert sorted(p.name for p in tmp_path.iterdir()) == ["variant.toml"]


def test_build_of_another_projects_design_writes_that_project(tmp_path: Path, capsys) -> None:
    project = tmp_path / "wide"
    (project / "cad").mkdir(parents=True)
    (project / "cad" / "design.toml").write_text((ROOT / "cad" / "design.toml").read_text())
    committed = {p: p.stat().st_mtime_ns for p in (ROOT / "urdf").iterdir()}
    assert main(["build", "--design", str(project / "cad" / "design.toml")]) == 0
    assert (project / "urdf" / "payload.urdf").read_bytes() == (
        ROOT / "urdf" / "payload.urdf"
    ).read_bytes()
    assert {p: p.stat().st_mtime_ns for p in (ROOT / "urdf").iterdir()} == committed


# -- the lazy registry -------------------------------------------------------------------
HEAVY = ("mujoco", "scipy", "casadi", "pinocchio", "fcl", "trimesh", "matplotlib", "dask")


def _imports_of(argv: list[str]) -> tuple[subprocess.CompletedProcess, set[str]]:
    """Run ``payload ARGV`` in a fresh interpreter; its output and the heavy modules its
    ``sys.modules`` holds at exit."""
    code = (
        "import sys, json, atexit\n"
        f"atexit.register(lambda: print(json.dumps([m for m in {HEAVY!r} if m in "
        "sys.modules]), file=sys.stderr))\n"
        "from payload.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code, *argv], capture_output=True, text=True, check=False
    )
    return res, set(json.loads(res.stderr.strip().splitlines()[-1]))


@pytest.mark.parametrize(
    "argv", [["--version"], ["--help"], ["bench", "--help"], ["report", "--help"]]
)
def test_version_and_help_import_no_numerical_library(argv: list[str]) -> None:
    res, heavy = _imports_of(argv)
    assert res.returncode == 0, res.stderr
    assert heavy == set(), heavy


def test_the_shared_trial_options_load_no_numpy() -> None:
    """The trial options every trial command shares quote the physics step and the control
    period from :mod:`payload.rates` (they typed 0.001 and 20 ms, since the schema that
    held them loads numpy): the options' module stays numpy-free, so `bench trial --help`
    loads none, and the help quotes the two clocks' values."""
    code = (
        "import sys\nimport payload.trials.setup_options\n"
        "from payload.cli import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit:\n"
        "    pass\nprint('numpy' in sys.modules, file=sys.stderr)\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code, "bench", "trial", "--help"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert res.stderr.strip().splitlines()[-1] == "False", res.stderr
    text = " ".join(res.stdout.split())
    assert "physics time step [s]: 0.001 (default, the paper's 1 kHz)" in text, text
    assert "divides the 20 ms control period, e.g. 0.002" in text, text


def test_help_lists_every_command_of_the_table_with_its_help() -> None:
    """Top level and every shared group list their commands (from the table, no module
    loaded), each with the help its module registers."""
    res, _ = _imports_of(["--help"])
    top = " ".join(res.stdout.split())
    for cmd in COMMANDS:
        first = cmd.path.split()[0]
        assert f" {first} " in top, first
        if first not in GROUPS:
            assert " ".join(cmd.help.split()) in top, cmd
    for group in GROUPS:
        listing = " ".join(_imports_of([group, "--help"])[0].stdout.split())
        for cmd in COMMANDS:
            words = cmd.path.split()
            if words[0] == group:
                assert f" {words[1]} {cmd.help}" in listing, cmd


def test_the_command_table_matches_what_the_modules_register() -> None:
    """Every module's register() adds exactly its table lines, with the same help, so
    ``payload --help`` (from the table) cannot drift from the commands (from the
    modules); and the full parser holds every table line."""
    for module in COMMAND_MODULES:
        table = {c.path: c.help for c in COMMANDS if c.module == module}
        assert registered_commands(module) == table, module
    found = {path.removeprefix("payload ") for path, _ in _parsers(build_parser())}
    assert {c.path for c in COMMANDS} <= found


@pytest.mark.parametrize(
    ("argv", "loaded", "not_loaded"),
    [
        (["build", "--help"], "payload.design.cli", "payload.trials.cli"),
        (["--project", ".", "bench", "sim", "--help"], "payload.sim.cli", "payload.trials.cli"),
        (["hw", "scan", "--help"], "firmware_interface.cli", "payload.envelope.cli"),
    ],
)
def test_a_command_loads_only_its_own_module(argv, loaded, not_loaded) -> None:
    code = (
        "import sys\nfrom payload.cli import main\ntry:\n    main(sys.argv[1:])\n"
        "except SystemExit:\n    pass\n"
        f"print({loaded!r} in sys.modules, {not_loaded!r} in sys.modules)\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code, *argv], capture_output=True, text=True, check=True
    )
    assert res.stdout.strip().splitlines()[-1] == "True False"


def test_no_command_module_imports_the_dispatcher() -> None:
    """Command modules take their helpers from payload.cliutil: none names payload.cli,
    at the top or inside a function (the dispatcher imports them, never the reverse)."""
    import ast

    for module in COMMAND_MODULES:
        path = ROOT / (module.replace(".", "/") + ".py")
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
                names += [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            assert "payload.cli" not in names, (module, node.lineno)


# -- one vocabulary ----------------------------------------------------------------------
FORBIDDEN = {"--serial", "--dev", "--tty", "--source", "--operator", "--input", "--recording"}
"""Spellings outside the vocabulary (docs/cli.md), allowed only as deprecated aliases."""


def test_every_option_has_help_and_speaks_the_vocabulary() -> None:
    """The whole tree (every subcommand, built through the registry): every option and
    positional has help text; ``--device`` is a serial device, ``--port`` a TCP port,
    ``--replay`` a recording, ``--out`` never required and shown as ``--out DIR`` (or
    ``FILE``), positionals in capitals as the usage lines write them; other spellings only
    as deprecated aliases of the vocabulary's."""
    problems = []
    for path, parser in _parsers(build_parser()):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                continue
            where = f"{path} {'/'.join(action.option_strings) or action.dest}"
            text = action.help or ""
            if text == argparse.SUPPRESS:
                continue  # hidden (tests, internal)
            if not text.strip():
                problems.append(f"{where}: no help")
            deprecated = isinstance(action, DeprecatedAlias)
            if deprecated and not text.startswith("deprecated spelling of --"):
                problems.append(f"{where}: a deprecated alias must say so and name the new one")
            for opt in action.option_strings:
                if opt in FORBIDDEN and not deprecated:
                    problems.append(f"{where}: {opt} is outside the vocabulary")
                if opt == "--port" and not deprecated and "TCP" not in text:
                    problems.append(f"{where}: --port is a TCP port")
                if opt == "--port" and deprecated and action.new != "--device":
                    problems.append(f"{where}: the old serial --port is an alias of --device")
                if opt == "--device" and "serial" not in text:
                    problems.append(f"{where}: --device is a serial device")
                if opt == "--replay" and "log.mcap" not in text:
                    problems.append(f"{where}: --replay should say which recordings it takes")
                if opt == "--out" and action.required:
                    problems.append(f"{where}: --out must be optional")
                if opt == "--out" and action.metavar not in ("DIR", "FILE"):
                    problems.append(f"{where}: shown as --out {action.metavar}, not DIR (a folder)")
            shown = action.metavar or action.dest
            if not action.option_strings and isinstance(shown, str) and shown != shown.upper():
                problems.append(f"{where}: a positional shown in lower case ({shown})")
    assert problems == []


@pytest.mark.parametrize(
    ("argv", "dest", "value", "warning"),
    [
        (["hw", "scan", "--port", "/dev/ttyUSB0"], "device", "/dev/ttyUSB0", "--port"),
        (["hw", "check", "--port", "/dev/pts/3"], "device", "/dev/pts/3", "--port"),
        (["bench", "hw", "--port", "/dev/pts/3"], "device", "/dev/pts/3", "--port"),
        (
            ["hw", "run", "--device", "D", "--source", "replay", "h.jsonl"],
            "source",
            None,
            "--source",
        ),
        (["trial", "--operator", "replay", "log.mcap"], "operator", None, "--operator"),
    ],
)
def test_old_spellings_still_parse_with_one_warning(argv, dest, value, warning, capsys) -> None:
    args, unknown = build_parser().parse_known_args(argv)
    assert unknown == []
    assert getattr(args, dest) == (value if value is not None else argv[-2:])
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"payload: warning: {warning} is deprecated")


def test_new_from_a_non_project_names_from(tmp_path: Path, capsys) -> None:
    assert main(["new", str(tmp_path / "p"), "--from", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--from {tmp_path}: not a design project" in err[0]
    assert "--project" not in err[0] and not (tmp_path / "p").exists()


def test_new_from_a_binary_design_is_one_line(tmp_path: Path, capsys) -> None:
    """``--from`` a project's mesh (a file inside a project), a project whose design
    file is binary, or one whose design holds an invalid value: one line naming it, exit
    2, no new folder (before: a UnicodeDecodeError traceback)."""
    binary = tmp_path / "binary"
    (binary / "cad").mkdir(parents=True)
    (binary / "cad" / "design.toml").write_bytes(STL.read_bytes())
    invalid = tmp_path / "invalid"
    (invalid / "cad").mkdir(parents=True)
    text = (ROOT / "cad" / "design.toml").read_text()
    (invalid / "cad" / "design.toml").write_text(text.replace("\ndistal = ", "\ndistal = -", 1))
    cases = [
        (STL, f"--from {STL}: not a text (UTF-8 TOML) file"),
        (binary, f"--from {binary / 'cad' / 'design.toml'}: not a text (UTF-8 TOML) file"),
        # an invalid value: the line names the design it is in (it named the key alone)
        (invalid, f"--from {invalid / 'cad' / 'design.toml'}: its design is not valid: "
                  "finger.lengths.distal: must be positive"),
    ]  # fmt: skip
    for source, message in cases:
        assert main(["new", str(tmp_path / "p"), "--from", str(source)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
        assert not (tmp_path / "p").exists()


@pytest.mark.parametrize(
    ("argv", "finite"),
    [
        (["bench", "recorder", "--seconds", "nan"], True),
        (["bench", "recorder", "--seconds", "inf"], True),
        (["bench", "filter", "--seconds", "inf"], True),
        (["bench", "teleop", "--seconds", "-1"], True),
        (["bench", "trial", "--seconds", "nan"], False),
        (["teleop", "serve", "--port", "0", "--seconds", "-5"], True),  # served, then ended
    ],
    ids=lambda v: " ".join(v) if isinstance(v, list) else str(v),
)
def test_a_duration_that_is_not_a_positive_number_is_one_line(argv, finite, monkeypatch, capsys):
    """NaN, infinity (where nothing ends the run by itself) and negative seconds: one line
    and exit 2 before anything runs (before: an OverflowError or ValueError traceback,
    ``bench teleop`` slept a negative time, ``bench trial --seconds nan`` ran a trial)."""
    import payload.teleop.bench
    import payload.trials.bench

    def never(*args, **kwargs):
        raise AssertionError("the bench ran")

    for module, name in (
        (payload.trials.bench, "run_trial_bench"),
        (payload.teleop.bench, "run_bench"),
        (payload.teleop.bench, "run_filter_bench"),
    ):
        monkeypatch.setattr(module, name, never)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    kind = "finite " if finite else ""
    want = f"--seconds must be a positive {kind}number of seconds, got {float(argv[-1])}"
    assert len(err) == 1 and want in err[0], err


def test_commands_run_without_mujoco_rendering_unless_the_user_asks(monkeypatch) -> None:
    """A command runs with ``MUJOCO_GL=disable`` (nothing renders with MuJoCo, whose
    import then skips GLFW; Dask workers inherit it), removed after the command; a
    user's own setting is kept."""

    import payload.cli as cli

    seen: list[str | None] = []
    command = argparse.Namespace(func=lambda args: seen.append(os.environ.get("MUJOCO_GL")))
    monkeypatch.setattr(cli, "_parse", lambda argv: command)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    assert main([]) == 0
    assert "MUJOCO_GL" not in os.environ
    monkeypatch.setenv("MUJOCO_GL", "egl")
    assert main([]) == 0
    assert seen == ["disable", "egl"]
    assert os.environ["MUJOCO_GL"] == "egl"


def test_a_closed_stdout_ends_the_command_quietly() -> None:
    """``payload ... | head``: the reader going away ends the command quietly, with the
    exit status of a tool that SIGPIPE ended (141) and no traceback."""
    code = (
        "import sys, payload.cli as cli\n"
        "def main():\n"
        "    for _ in range(100_000):\n"
        "        print('a line of the report')\n"
        "    return 0\n"
        "cli.main = main\n"
        "cli.run()\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.readline()
    proc.stdout.close()  # as `head -1` does
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141
    assert "Traceback" not in err and "BrokenPipeError" not in err, err
    # another pipe breaking (a socket, a child process) is an error like any other
    other = (
        "import payload.cli as cli\n"
        "cli.main = lambda: (_ for _ in ()).throw(BrokenPipeError())\n"
        "cli.run()\n"
    )
    done = subprocess.run([sys.executable, "-c", other], capture_output=True, timeout=60)
    assert done.returncode == 1 and b"BrokenPipeError" in done.stderr


def test_the_quick_exit_leaves_no_nanobind_leak_report() -> None:
    """``payload.cli.run`` freezes the heap before the interpreter's shutdown; manifold3d
    objects left in reference cycles (``report reach`` left some) must not be reported by
    nanobind as leaked at exit, dozens of lines on stderr."""
    code = (
        "import gc, manifold3d, payload.cli as cli\n"
        "gc.disable()  # the cycle is still garbage when the command returns\n"
        "class Holder: pass\n"
        "h = Holder(); h.me = h; h.solid = manifold3d.Manifold.cube([1.0, 1.0, 1.0])\n"
        "del h\n"
        "cli.main = lambda: 0\n"
        "cli.run()\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60)
    assert done.returncode == 0 and b"nanobind" not in done.stderr, done.stderr.decode()


def test_a_command_on_a_project_names_it_in_its_json(capsys, monkeypatch) -> None:
    """Every command that works on a design project carries ``"project"`` in its JSON
    (docs/cli.md), those that build their objects without it too (``bench filter`` here);
    the next command starts without the last one's project."""
    monkeypatch.chdir(ROOT)
    assert main(["bench", "filter", "--seconds", "0.3", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["project"] == str(ROOT.resolve()) and out["steps"] > 0
    from payload.cliutil import emit_json

    emit_json({"a": 1})  # outside a command: no project to name
    assert json.loads(capsys.readouterr().out) == {"a": 1}


def test_every_quick_bench_states_the_load_average_it_ran_at(capsys, monkeypatch) -> None:
    """Each bench's JSON carries ``load_average`` (the 1, 5 and 15 min averages at its
    end), as ``bench trial`` did: a figure is read beside the load (some said ``load`` in
    other shapes, some nothing). Checked against the kernel's own figures, read from
    /proc/loadavg after the run (Linux)."""

    monkeypatch.chdir(ROOT)
    for argv in (
        ["bench", "filter", "--seconds", "0.3"],
        ["bench", "recorder", "--seconds", "1"],
        ["bench", "sim", "--seconds", "0.2", "--no-progress"],
    ):
        assert main([*argv, "--json"]) == 0
        load = json.loads(capsys.readouterr().out)["load_average"]
        now = [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]
        assert len(load) == 3 and all(abs(a - b) < 1.0 for a, b in zip(load, now)), (argv, load)


def test_sigterm_stops_a_trial_as_ctrl_c_does(tmp_path: Path) -> None:
    """`kill` (SIGTERM) of a running `payload trial`: the recording is closed, reads
    complete and is marked aborted (before, the process died with the file never closed:
    cut short), the command says so in one line and exits 128 + 15."""
    import signal
    import time

    from payload.trials.reading import read_recording, unfinished_reason

    out = tmp_path / "t"
    code = "from payload.cli import run; run()"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, "trial", "--seed", "0", "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        preexec_fn=lambda: signal.signal(signal.SIGTERM, signal.SIG_DFL),
    )
    log = out / "log.mcap"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if log.is_file() and log.stat().st_size > 100_000:  # some steps flushed
            break
        time.sleep(0.05)
    assert proc.poll() is None, proc.communicate()[1]
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines()[-1] == (
        f"payload: terminated (SIGTERM); recording kept, marked aborted (not scored): {log}"
    )
    rec = read_recording(log)
    assert rec.complete and 0 < len(rec.t)
    assert unfinished_reason(rec.meta, rec.complete) == "aborted (Terminated: SIGTERM)"
    assert not (out / "metrics.json").exists()


def test_a_forked_worker_keeps_the_default_sigterm(tmp_path: Path) -> None:
    """`run()` turns SIGTERM into a clean stop in the command's process, but a forked
    worker (a multiprocessing pool's, which its pool ends with SIGTERM) keeps the default:
    with the handler inherited, `report reach`'s pool workers printed `Terminated`
    tracebacks on successful runs."""
    script = tmp_path / "fork.py"
    script.write_text(
        "import os, signal\n"
        "import payload.cli as cli\n"
        "def fake():\n"
        "    pid = os.fork()\n"
        "    if pid == 0:\n"
        "        os._exit(0 if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL else 1)\n"
        "    _, status = os.waitpid(pid, 0)\n"
        "    mine = signal.getsignal(signal.SIGTERM) is cli._terminate\n"
        "    print(os.waitstatus_to_exitcode(status), mine)\n"
        "    return 0\n"
        "cli.main = fake\n"
        "cli.run()\n"
    )
    out = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, cwd=ROOT, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["0", "True"]


@pytest.mark.parametrize("value", ["-1", "0", "nan"])
def test_a_trial_cap_that_is_not_a_positive_time_is_one_line(value, tmp_path, capsys) -> None:
    """``trial --max-time`` takes what ``hw run --max-time`` takes (``cliutil.check_seconds``
    with no upper bound): anything but a positive number of seconds is one line naming
    the option, exit 2, before any folder is made."""
    out = tmp_path / "t"
    assert main(["trial", "--max-time", value, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--max-time" in err[0] and "positive" in err[0], err
    assert not out.exists()


def test_a_trial_cut_off_by_its_cap_says_so(tmp_path, capsys) -> None:
    """A trial stopped by ``--max-time`` before the operator finished prints that, with
    the simulated time it ran (the control steps at t = 0 .. 1 s for a 1 s cap),
    and its ``metrics.json`` says what ended it."""
    out = tmp_path / "t"
    assert main(["trial", "--max-time", "1", "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "  success: no" in lines
    assert "  stopped by the --max-time cap after 1.0 s, before the operator finished" in lines
    metrics = json.loads((out / "metrics.json").read_text())
    assert (metrics["ended_by"], metrics["steps"]) == ("max_time", round(1.0 / CONTROL_DT) + 1)
    # a line names what the folder holds (a new user saw only "-> runs/trial-0001"), the
    # last what to do with it: commands that parse, on this folder
    head, folder = lines[-2].removeprefix("wrote ").rsplit(" in ", 1)
    assert folder == str(out) and sorted(head.split(", ")) == sorted(os.listdir(out))
    said = re.findall(r"`payload ([^`]+)`", lines[-1])
    # the replay; no export: the cap stopped it, and export leaves such a run out
    assert lines[-1].startswith("next: ") and len(said) == 1, lines[-1]
    for command in said:
        from payload.cli import _parse

        args = _parse(command.split())
        assert str(out) in command and args.command in ("review", "export"), command


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["trial", "--replay", "/dev/null"], ["--replay: /dev/null: not a regular file"]),
        (
            ["trial", "--base-filter", "--zones", "/no/such/zones.toml"],
            ["--zones: /no/such/zones.toml:"],
        ),
    ],
)
def test_a_trials_bad_file_option_names_the_option_and_what_is_wrong(argv, words, capsys):
    """A replay that exists but is no file (``/dev/null``) is not said to be missing; a
    zone file that cannot be read is named with its option: one line, exit 2."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and all(w in err[0] for w in words), err


def test_a_rich_table_to_a_closed_stdout_ends_as_any_output_does(monkeypatch) -> None:
    """The commands' rich tables (``payload summary``, the reports): a reader that went
    away raises ``BrokenPipeError``, which :func:`payload.cli.run` ends with 141 as above
    (rich's own answer was ``SystemExit(1)``: ``payload summary | head -1`` exited 1, the
    code of a failed check)."""
    from rich.table import Table

    from payload.console import console

    read, write = os.pipe()
    os.close(read)
    stream = os.fdopen(write, "w")
    monkeypatch.setattr(sys, "stdout", stream)
    table = Table("key", "value")
    table.add_row("a", "1")
    try:
        with pytest.raises(BrokenPipeError):
            console().print(table)
    finally:
        with contextlib.suppress(BrokenPipeError):  # what is left in its buffer
            stream.close()


def test_bench_start_only_naming_nothing_is_one_line(capsys) -> None:
    """``bench start --only ,`` names no measure: one line, exit 2 (it measured nothing and
    exited 0)."""
    assert main(["bench", "start", "--only", ","]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--only ',': names no measure (there are: version_s" in err


def test_a_commands_log_records_are_the_command_lines_own(monkeypatch, capsys) -> None:
    """A warning logged during a command (a kernel falling back, say) is one
    ``payload: warning:`` line, another library's names its logger, an error's traceback
    follows it; Python alone printed the bare message. Afterwards the root logger has
    the handlers it had."""
    import argparse
    import logging

    from payload import cli

    def command(args: argparse.Namespace) -> int:
        logging.getLogger("payload.teleop.pair_c").warning("finger chain: Python (%s)", "why")
        logging.getLogger("someone.else").warning("their note")
        try:
            raise ValueError("inner")
        except ValueError:
            logging.getLogger("payload.trials.runner").error("trial 3 aborted", exc_info=True)
        return 0

    before = logging.getLogger().handlers[:]
    monkeypatch.setattr(cli, "_parse", lambda argv: argparse.Namespace(func=command))
    assert cli.main([]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err[:3] == [
        "payload: warning: finger chain: Python (why)",
        "payload: warning: someone.else: their note",
        "payload: trial 3 aborted",
    ]
    assert err[3] == "Traceback (most recent call last):" and err[-1] == "ValueError: inner"
    assert logging.getLogger().handlers == before


def test_a_trial_of_a_design_that_does_not_stow_says_so(tmp_path, capsys) -> None:
    """A new user narrowed the bays to another vehicle's until the stowed payload stood
    out of them, then ran ``payload trial``: it ran and scored without a word that this
    payload could not be flown (only ``report envelope`` said so). The trial still runs (a
    simulation of the design as it is) but warns, naming the parts and millimetres the
    envelope report names; the design edited back, the warning goes (the cached answer
    follows the design)."""
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    design = project.design_path
    fitting = design.read_text()
    design.write_text(replace_once(fitting, "bay_size = [0.20, 0.10,", "bay_size = [0.20, 0.09,"))
    report = ["report", "envelope", "--project", str(project.root), "--no-search", "--json"]
    assert main([*report, "--out", str(tmp_path / "env")]) == 1
    out = json.loads(capsys.readouterr().out)
    mm = {p["name"]: p["protrusion_mm"] for p in out["parts"] if not p["inside"]}
    assert mm
    argv = ["trial", "--project", str(project.root), "--max-time", "0.2"]
    assert main([*argv, "--out", str(tmp_path / "t1")]) == 0
    err = [ln for ln in capsys.readouterr().err.splitlines() if "does not fit" in ln]
    assert len(err) == 1, err
    assert err[0].startswith(f"payload: warning: {design}: the stowed payload does not fit")
    named = re.findall(r"(\w+) protrudes ([0-9.]+) mm", err[0])
    assert len(named) == min(2, len(mm)), (named, mm)
    assert all(f"{mm[n]:.1f}" == v for n, v in named), (named, mm)
    assert "the trial ran all the same" in err[0]
    assert (tmp_path / "t1" / "metrics.json").is_file()
    # a campaign says it once, after its trials (a scheduler not reached is an error first)
    campaign = ["trials", "run", "--n", "1", "--workers", "0", "--max-time", "0.2"]
    assert main([*campaign, "--project", str(project.root), "--out", str(tmp_path / "c")]) == 0
    said = capsys.readouterr()
    err = [ln for ln in said.err.splitlines() if "does not fit" in ln]
    assert len(err) == 1 and err[0].endswith("the campaign ran all the same"), err
    # the last line says what to do next, on folders that are there
    last = said.out.splitlines()[-1]
    folders = re.findall(r"`payload (?:review|trials compare) ([^\s`]+)", last)
    assert last.startswith("next: ") and len(folders) == 2, last
    assert all(Path(f).is_dir() for f in folders) and "export" not in last, last  # capped
    design.write_text(fitting)
    assert main([*argv, "--out", str(tmp_path / "t2")]) == 0
    assert "does not fit" not in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "dest", "value"),
    [
        (["--samples", "2000", "report", "reach"], "samples", 2000),
        (["--force", "trial", "--seed", "2"], "force", True),
        (["--project", "p", "--seed=3", "trial"], "seed", 3),
        (["--project", "trial", "--json", "trial"], "json", True),  # a folder named trial
        (["--out", "trial", "trial"], "out", "trial"),  # its value a command's name
        (["report", "--samples", "2000", "reach"], "samples", 2000),  # inside a group
        (["hw", "--device", "/dev/ttyUSB9", "check"], "device", "/dev/ttyUSB9"),  # hw's own
        (["trials", "--n", "3", "run"], "n", 3),  # a subcommand the command registers itself
    ],
)
def test_a_commands_option_before_the_command_says_where_it_goes(argv, dest, value, capsys):
    """A new user's ``payload --samples 2000 report reach`` was refused as "argument
    COMMAND: invalid choice: '2000'" (argparse took the option's value for the command),
    and ``payload --force trial`` as "unrecognized arguments: --force (did you mean
    --force?)". Both say which option goes after the command and give the command line in
    order, one line, exit 2; that line parses, with the option's value."""
    from payload.cli import _parse

    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    (err,) = capsys.readouterr().err.splitlines()
    option = next(a for a in argv if a.startswith("-") and a != "--project")
    head = f"payload: error: {option.split('=')[0]} goes after the command: payload "
    assert err.startswith(head), err
    ordered = err.split(": payload ", 1)[1].split()
    assert str(getattr(_parse(ordered), dest)) == str(value)


@pytest.mark.parametrize(
    "argv",
    [
        ["--project", "trial", "trial", "--help"],  # a project folder named like a command
        ["--version"],
        ["-h"],
        ["report", "-h"],
    ],
)
def test_a_command_line_in_order_is_not_said_to_be_out_of_order(argv, capsys) -> None:
    """The check for a command's option before its name leaves alone what each level
    takes (``--project DIR`` anywhere, ``-h``, ``--version`` at the top); a misspelt
    command is argparse's to say ("invalid choice ... did you mean")."""
    from payload.cli import _option_before_command

    assert _option_before_command(argv) is None
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 0
    assert "goes after the command" not in capsys.readouterr().err
    assert _option_before_command(["trail", "--out", "trial"]) is None


def test_a_new_project_says_what_to_do_next(tmp_path, capsys) -> None:
    """``payload new`` said what it made and stopped; a new user did not know the next
    step. Its last line names the design file to edit and the command that checks it, in
    the project's folder, both of which are there."""
    root = tmp_path / "p"
    assert main(["new", str(root)]) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    match = re.fullmatch(r"next: edit (\S+), then run `payload report all` in (\S+)", last)
    assert match, last
    assert Path(match.group(1)).is_file() and Path(match.group(1)).name == "design.toml"
    assert Path(match.group(2)).resolve() == root.resolve()
    assert Path(match.group(1)).resolve().is_relative_to(root.resolve())


def test_a_project_made_inside_another_says_so(tmp_path, capsys) -> None:
    """``payload new`` inside a project made a nested project without a word: commands
    run in it then worked on the new one, those run beside it on the outer one. It says
    so, naming the outer project; made outside any project, it says nothing of it."""
    outer = tmp_path / "outer"
    assert main(["new", str(outer)]) == 0
    assert "note:" not in capsys.readouterr().out
    inner = outer / "analyses" / "variant"
    assert main(["new", str(inner)]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note:")]
    assert notes == [
        f"note: inside the project at {outer.resolve()}: commands run in {inner.resolve()} "
        f"work on the new project, those run outside it on {outer.resolve()}"
    ]
