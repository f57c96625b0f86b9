"""The command line's entry points: ``payload --version`` and ``python -m payload``."""

from __future__ import annotations

import math
import subprocess
import sys
from importlib.metadata import version

from payload.cli import main


def test_version_matches_installed_distribution(capsys) -> None:
    try:
        main(["--version"])
    except SystemExit as exc:
        assert exc.code == 0
    out = capsys.readouterr().out.strip()
    assert out == f"payload {version('astrobee-payload')}"


def test_python_dash_m_runs_the_same_cli() -> None:
    res = subprocess.run(
        [sys.executable, "-m", "payload", "--version"], capture_output=True, text=True, check=False
    )
    assert res.returncode == 0
    assert res.stdout.strip() == f"payload {version('astrobee-payload')}"
    bad = subprocess.run(
        [sys.executable, "-m", "payload", "no-such-command"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert bad.returncode == 2
    assert "invalid choice" in bad.stderr


def test_summary_tables_keep_one_line_per_row_and_their_units_when_piped(design_dict) -> None:
    res = subprocess.run(
        [sys.executable, "-m", "payload", "summary"], capture_output=True, text=True, check=True
    )
    lines = res.stdout.splitlines()
    lo, hi = design_dict["finger"]["limits"]["mcp_flex"]
    for finger in "ABCD":
        row = [ln for ln in lines if f" {finger}_mcp_flex " in ln]
        assert len(row) == 1, row
        # the limits stand on the joint's own line, in degrees, from the design file
        assert f"{math.degrees(lo):.1f} deg" in row[0]
        assert f"{math.degrees(hi):.1f} deg" in row[0]
    header = next(ln for ln in lines if "posture" in ln)
    for col in ("x [mm]", "y [mm]", "z [mm]", "size [mm]"):
        assert col in header
    # a wrapped row would leave a continuation line with an empty first cell
    assert not [ln for ln in lines if ln.startswith("│ ") and ln[2:12].strip() == ""]


def test_every_command_module_registers_its_commands() -> None:
    from payload.cli import COMMAND_MODULES, build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    # the contract's top-level commands (docs/cli.md), each from its own module
    for command in ("build", "summary", "new", "sweep", "trial", "trials", "teleop", "review"):
        assert command in sub.choices, command
    for group, what in (("bench", "retarget"), ("bench", "sim"), ("bench", "trial")):
        inner = next(a for a in sub.choices[group]._actions if a.dest == f"{group}_command")
        assert what in inner.choices
    assert "hw" in sub.choices and len(COMMAND_MODULES) == len(set(COMMAND_MODULES))
