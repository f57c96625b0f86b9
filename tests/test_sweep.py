"""Design sweeps: the grid, the edited design files, and a two-point sweep on a Dask
LocalCluster whose figures equal the same commands run by hand in each point."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import tomllib
from conftest import DESIGN, ROOT, replace_once

from payload.cli import main
from payload.design import load_design
from payload.sweep import POINT_FIELDS, SweepError, edit_design, parse_set
from payload.sweep.grid import check_axes, grid


def test_parse_set_lists_and_ranges():
    a = parse_set("finger.lengths.distal=0.040:0.050:3")
    assert a.key == "finger.lengths.distal"
    np.testing.assert_allclose(a.values, np.linspace(0.040, 0.050, 3), rtol=0, atol=1e-15)
    assert a.values[1] == 0.045  # no last-bit noise in the folder's design files
    assert parse_set("rail.travel=0.04, 0.05").values == (0.04, 0.05)
    assert parse_set("rail.travel=0.04:0.04:1").values == (0.04,)
    for bad, why in [
        ("rail.travel", "KEY=V1"),
        ("rail.travel=", "KEY=V1"),
        ("rail.travel=a,b", "not a number"),
        ("rail.travel=0.1:0.2", "A:B:N"),
        ("rail.travel=0.1:0.2:x", "integer"),
        ("rail.travel=0.1:0.2:0", "N must be >= 1, got 0"),
        # one value of two: 0.2 was dropped without a word
        ("rail.travel=0.1:0.2:1", r"0.1 alone \(N = 1\): give N >= 2 to reach 0.2"),
        ("rail.travel=0.1,0.1", "twice"),
        ("rail.travel=nan", "finite"),
    ]:
        with pytest.raises(SweepError, match=why):
            parse_set(bad)


def test_grid_is_every_combination_last_key_fastest(design):
    axes = [parse_set("rail.travel=0.04,0.05"), parse_set("finger.lengths.distal=1,2,3")]
    points = grid(axes)
    assert len(points) == 6
    assert points[:2] == [
        {"rail.travel": 0.04, "finger.lengths.distal": 1.0},
        {"rail.travel": 0.04, "finger.lengths.distal": 2.0},
    ]
    check_axes(axes, design)
    for key, why in [
        ("finger.lengths.thumb", "not a design key"),
        ("finger.lengths", "not a number"),
        ("finger.limits.pip", "not a number"),
    ]:
        with pytest.raises(SweepError, match=why):
            check_axes([parse_set(f"{key}=1,2")], design)
    with pytest.raises(SweepError, match="given twice"):
        check_axes([parse_set("rail.travel=1"), parse_set("rail.travel=2")], design)


def test_edit_design_changes_only_the_values_and_keeps_comments():
    text = DESIGN.read_text()
    out = edit_design(text, {"finger.lengths.distal": 0.04, "rail.travel": 0.041})
    want = tomllib.loads(text)
    want["finger"]["lengths"]["distal"] = 0.04
    want["rail"]["travel"] = 0.041
    assert tomllib.loads(out) == want
    changed = [(a, b) for a, b in zip(text.splitlines(), out.splitlines()) if a != b]
    assert len(changed) == 2 and len(text.splitlines()) == len(out.splitlines())
    assert all(b.split("#")[1:] == a.split("#")[1:] for a, b in changed)  # comments kept


def test_bad_sweep_input_exits_2_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["sweep", "--set", "finger.lengths.thumb=1,2", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "finger.lengths.thumb: not a design key" in err and "\n" not in err
    assert not out.exists()  # nothing made for a sweep that never started
    # a typo names the key it was, as the design file's loader does
    assert main(["sweep", "--set", "finger.lenghts.distal=0.04", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("not a design key (did you mean finger.lengths.distal?)"), err
    # each point's trials run seeds S to S + N - 1: past 2^63 - 1, refused before the
    # points (it was each point's error, after its build, envelope and reach)
    argv = ["sweep", "--set", "rail.travel=0.04", "--trials", "2", "--seed", str(2**63 - 1)]
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert f"at most {2**63 - 2} for 2 trials (their seeds run to {2**63}," in err
    assert "\n" not in err
    assert not out.exists()
    out.mkdir()
    (out / "sweep.json").write_text("{}")
    assert main(["sweep", "--set", "rail.travel=0.04", "--out", str(out)]) == 2
    assert (out / "sweep.json").read_text() == "{}"  # recorded data never overwritten
    capsys.readouterr()
    (out / "sweep.json").unlink()
    (out / "sweep.md").write_text("my notes")  # an earlier sweep's report, or the user's
    assert main(["sweep", "--set", "rail.travel=0.04", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert f"--out {out}: already holds sweep.md; choose another folder" in err
    assert "\n" not in err
    assert (out / "sweep.md").read_text() == "my notes"
    # a folder of the design reports (a project's analyses/): the sweep's point projects
    # and table were written among them
    reports = tmp_path / "analyses"
    reports.mkdir()
    shutil.copy(ROOT / "analyses" / "envelope.json", reports)
    assert main(["sweep", "--set", "rail.travel=0.04", "--out", str(reports)]) == 2
    err = capsys.readouterr().err.strip()
    assert "already holds envelope.json" in err and "\n" not in err
    assert [p.name for p in reports.iterdir()] == ["envelope.json"]


def test_bad_sweep_input_leaves_no_numbered_folder_in_the_project(tmp_path, capsys):
    """Without --out a sweep claims runs/sweep-NNNN; bad input found after that (a key
    the design does not have, an invalid design) leaves no empty folder behind, nor uses
    up a number."""
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    argv = ["--project", str(project.root), "sweep", "--set", "finger.lengths.thumb=1,2"]
    assert main(argv) == 2
    assert "not a design key" in capsys.readouterr().err
    text = project.design_path.read_text()
    project.design_path.write_text(replace_once(text, "middle = 0.0361 ", "middle = 0.005 "))
    assert main([*argv[:-1], "rail.travel=0.04,0.05"]) == 2
    assert "finger.lengths.middle" in capsys.readouterr().err
    assert not list(project.runs_dir.glob("sweep-*"))


@pytest.mark.slow
def test_two_point_sweep_equals_the_commands_by_hand(tmp_path, capsys):
    """One point fits, one (proximal link 150 mm longer) does not; each point's figures
    are those of `payload report envelope|reach` run by hand in its project."""
    proximal = load_design(DESIGN).finger.lengths.proximal
    long = round(proximal + 0.150, 6)
    out = tmp_path / "sweep"
    argv = ["sweep", "--set", f"finger.lengths.proximal={proximal},{long}"]
    argv += ["--samples", "2000", "--workers", "2", "--out", str(out), "--json"]
    assert main(argv) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["keys"] == ["finger.lengths.proximal"]
    assert [p["params"] for p in data["points"]] == [
        {"finger.lengths.proximal": proximal},
        {"finger.lengths.proximal": long},
    ]
    assert json.loads((out / "sweep.json").read_text())["points"] == data["points"]
    for p in data["points"]:
        assert list(p)[: len(POINT_FIELDS)] == list(POINT_FIELDS)
        assert p["valid"] is True and p["error"] is None and p["trials"] is None
    assert [p["fits"] for p in data["points"]] == [True, False]
    assert (out / "sweep.md").read_text().count("| **no** |") == 1
    assert (out / "sweep_finger_lengths_proximal.png").stat().st_size > 10_000

    md = (out / "sweep.md").read_text()
    (header,) = [ln for ln in md.splitlines() if ln.startswith("| # |")]
    head = [c.strip() for c in header.strip("|").split("|")]
    for p in data["points"]:
        root = Path(p["project"])
        design = tomllib.loads((root / "cad" / "design.toml").read_text())
        assert design["finger"]["lengths"]["proximal"] == p["params"]["finger.lengths.proximal"]
        hand = tmp_path / f"by-hand-{root.name}"
        assert main(["--project", str(root), "build", "--check"]) == 0
        capsys.readouterr()
        by_hand = ["--project", str(root), "--json", "--out", str(hand)]
        code = main(["report", "envelope", "--no-search", *by_hand])
        env = json.loads(capsys.readouterr().out)
        assert code == (0 if p["fits"] else 1)
        assert main(["report", "reach", "--samples", "2000", *by_hand]) == 0
        reach = json.loads(capsys.readouterr().out)
        assert (p["fits"], p["min_clearance_mm"]) == (env["fits"], env["min_clearance_mm"])
        # the least gap between two parts, as the report by hand has it (the sweep had none)
        assert p["min_self_clearance_mm"] == env["min_self_clearance_mm"] is not None
        (row,) = [ln for ln in md.splitlines() if ln.startswith(f"| {int(root.name[-3:])} |")]
        cells = dict(zip(head, (c.strip() for c in row.strip("|").split("|"))))
        assert cells["min self-clearance [mm]"] == f"{env['min_self_clearance_mm']:.2f}"
        # the reach report's verdict beside the envelope's (the sweep gave the envelope's)
        assert p["reach_passed"] == reach["passed"] is not None
        assert cells["reach check"] == ("passes" if reach["passed"] else "**fails**")
        assert p["below_vehicle_mm"] == reach["below_vehicle_mm"]
        assert p["span_max_mm"] == {k: reach["pairs"][k]["span_max_mm"] for k in "LR"}
        assert env["provenance"]["design_sha256"] == reach["provenance"]["design_sha256"]


@pytest.mark.slow
def test_a_sweep_runs_each_points_trials(tmp_path, capsys):
    """``--trials N`` runs the campaign in each point's project: the trial of a point with
    the design's own values is the one ``payload trial`` runs there by hand, to the last
    bit (its RMS deviation), and no trial raised (before, every one raised a TypeError and
    the sweep still exited 0 with 0 successes)."""
    travel = load_design(DESIGN).rail.travel
    out = tmp_path / "sweep"
    argv = ["sweep", "--set", f"rail.travel={travel}", "--trials", "1", "--samples", "2000"]
    assert main([*argv, "--workers", "1", "--out", str(out), "--json"]) == 0
    (point,) = json.loads(capsys.readouterr().out)["points"]
    hand = tmp_path / "by-hand"
    assert main(["--project", point["project"], "trial", "--out", str(hand), "--json"]) == 0
    by_hand = json.loads(capsys.readouterr().out)
    assert point["error"] is None
    assert point["trials"] == {
        "n": 1,
        "success": int(by_hand["success"]),
        "rms_mm_median": by_hand["rms_mm"],
        "duration_s_median": by_hand["duration_s"],
        "errors": 0,
    }


@pytest.mark.parametrize(
    ("option", "value", "says"),
    [
        ("--samples", "10", "--samples must be >= 1000, got 10"),
        ("--seed", "-1", "--seed must be >= 0, got -1"),
        ("--workers", "0", "--workers must be >= 1, got 0"),
    ],
)
def test_a_sweeps_reach_numbers_are_refused_as_the_reach_report_refuses_them(
    option, value, says, tmp_path, capsys
):
    """The sweep runs the reach analysis of every point: its numbers are refused with the
    words ``payload report reach`` uses for them, before any folder is made."""
    out = tmp_path / "s"
    assert main(["sweep", "--set", "rail.travel=0.04,0.05", option, value, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"payload: error: {says}"
    assert main(["report", "reach", option, value, "--out", str(tmp_path / "r")]) == 2
    assert capsys.readouterr().err.strip() == err
    assert not out.exists()


def test_a_sweep_of_invalid_designs_only_is_refused_and_runs_nothing(tmp_path, capsys):
    """Every value a unit slip: one line naming the first point's design error, exit 2,
    no folder made (it wrote a table of "invalid" rows and exited 0). A grid with one
    valid point among invalid ones is a sweep that maps a limit: it is not refused."""
    from payload.design.cli import new_project
    from payload.sweep.grid import parse_set
    from payload.sweep.run import plan

    project, _ = new_project(tmp_path / "p")
    out = tmp_path / "s"
    argv = ["--project", str(project.root), "sweep", "--set", "finger.lengths.distal=45,60"]
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "every point of the sweep is an invalid design" in err[0], err
    assert "finger.lengths.distal=45: finger.lengths.distal: 45 m: did you mean" in err[0]
    assert not out.exists() and not list(project.runs_dir.glob("sweep-*"))
    distal = load_design(project.design_path).finger.lengths.distal
    axes = [parse_set(f"finger.lengths.distal=45,{distal}")]
    assert len(plan(project, axes, tmp_path / "mixed")) == 2


@pytest.mark.parametrize(
    ("key", "unit"),
    [
        ("finger.lengths.distal", "m"),  # the table's doc: "... along the straight finger [m]"
        ("rail.travel", "m"),  # the field's doc: "carriage travel [m]"
        ("servo.kt", "N m/A"),
        ("finger.lengths", None),  # a table, not a value
        ("finger.lengths.nope", None),
    ],
)
def test_a_swept_keys_unit_is_the_one_its_design_doc_states(key, unit) -> None:
    """The sweep figures' axes name the swept key's unit, read from the design's own
    field and table docs (none invented where the docs state none)."""
    import dataclasses

    from payload.design.param_types import FingerLengths, Rail
    from payload.sweep.grid import key_unit

    assert key_unit(key) == unit
    # the docs it reads do say so
    assert FingerLengths.__doc__.rstrip().endswith("[m].")
    assert {f.name: f.metadata["doc"] for f in dataclasses.fields(Rail)}["travel"].endswith("[m]")


def test_a_sweep_without_a_terminal_says_each_point_as_it_ends(tmp_path, capsys):
    """No progress bar is drawn without a terminal (a pipe, a log, CI): each point's line
    goes to stderr as it ends, so a long sweep is not silent; stdout keeps the report."""
    out = tmp_path / "sweep"
    argv = ["sweep", "--set", "finger.lengths.distal=0.01,0.02,0.06", "--samples", "1000"]
    assert main([*argv, "--workers", "1", "--out", str(out)]) == 0
    got = capsys.readouterr()
    lines = [x for x in got.err.splitlines() if " done: point-" in x]
    # a 60 mm distal fits the bays but fails the envelope check (its tip runs into the
    # stage): the line says the check's verdict and what failed, as the envelope report
    # does (it said "fits" alone, then "FAILS (fits the bays)"); each line names its
    # point's folder, the table's row (the points may end in any order)
    *invalid, last = json.loads((out / "sweep.json").read_text())["points"]
    assert (last["valid"], last["fits"], last["passed"]) == (True, True, False)
    # an invalid design was never checked: its `passed` is null, as docs/design.md lists
    # it (the key was missing)
    assert [(p["valid"], p["passed"]) for p in invalid] == [(False, None), (False, None)]
    for p in invalid:  # and so were its other verdicts and figures: null, not missing
        assert p["reach_passed"] is None and p["min_self_clearance_mm"] is None
    assert lines[:2] == [
        "1/3 done: point-000 (finger.lengths.distal=0.01): invalid",
        "2/3 done: point-001 (finger.lengths.distal=0.02): invalid",
    ]
    assert main(["--project", str(out / "point-002"), "report", "envelope", "--json"]) == 1
    failures = json.loads(capsys.readouterr().out)["failures"]
    assert lines[2] == (
        "3/3 done: point-002 (finger.lengths.distal=0.06): envelope check FAILS: "
        + failures[0]
        + (f" (and {len(failures) - 1} more)" if failures[1:] else "")
    ), lines
    assert "done: point-" not in got.out and "# Design sweep" in got.out


def test_a_sweep_rows_note_counts_the_failures_it_leaves_out() -> None:
    """The table's note shows a point's first two failures; more were dropped without a
    word (a point with four collisions read as one with two)."""
    from payload.sweep.report import sweep_markdown

    failures = [f"part{i} and stage collide ({i}.0 mm deep, 1 mm^3)" for i in range(4)]
    point = {
        "params": {"finger.lengths.distal": 0.05}, "valid": True, "fits": True,
        "passed": False, "min_clearance_mm": 1.0, "below_vehicle_mm": 200.0, "error": None,
        "failures": failures,
    }  # fmt: skip
    text = sweep_markdown({"keys": ["finger.lengths.distal"], "points": [point]}, "cmd", [])
    (row,) = [line for line in text.splitlines() if line.startswith("| 0 |")]
    assert row.endswith(f"| {failures[0]}; {failures[1]} (and 2 more) |"), row
    assert "Generated by `cmd`: 1 point, each" in text  # it said "1 points"
    two = {**point, "failures": failures[:2]}
    text = sweep_markdown({"keys": ["finger.lengths.distal"], "points": [two]}, "cmd", [])
    assert "more)" not in text
