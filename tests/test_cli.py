"""The command line as a whole: no abbreviated options, a wrong option prints the
subcommand's usage, and bad input files give one line and exit 2."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest
from conftest import ROOT

from payload.cli import build_parser, main

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


@pytest.mark.parametrize(
    ("argv", "usage"),
    [
        (["report", "reach", "--sample", "1000"], "usage: payload report reach"),
        (["trials", "run", "--n", "1", "--out", "x", "--work", "2"], "usage: payload trials run"),
        (["trial", "--sed", "3"], "usage: payload trial "),
        (["trials", "summarize", "x", "--recomp"], "usage: payload trials summarize"),
        (["build", "--chec"], "usage: payload build"),
    ],
)
def test_a_wrong_option_prints_the_subcommands_usage(argv, usage, capsys) -> None:
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(usage), err
    assert f"unrecognized arguments: {argv[-2] if argv[-1].isdigit() else argv[-1]}" in err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["summary", "--design", str(STL)], "not a text (UTF-8 TOML) file"),
        (["report", "envelope", "--design", str(STL)], "not a text (UTF-8 TOML) file"),
        (["trial", "--operator", "replay", str(STL)], "not a payload-hands recording"),
    ],
)
def test_binary_input_files_give_one_line_and_exit_2(argv, message, capsys) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and str(STL) in err[0]


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
