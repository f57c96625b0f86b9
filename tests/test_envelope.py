"""Envelope report: bay model, containment and clearance, self-collision, posture search,
deployment sweep, CLI. Numbers are checked against closed forms of known geometry."""

from __future__ import annotations

import copy
import hashlib
import json
import math
import subprocess
import sys
from pathlib import Path

import manifold3d as m3d
import numpy as np
import pytest
import tomli_w
from conftest import DESIGN, ROOT, replace_once

from payload.design import build_tree, design_from_dict
from payload.design.solids import SEGMENTS
from payload.envelope import (
    PayloadGeometry,
    Vehicle,
    VehicleError,
    analyse_envelope,
    load_design_and_vehicle,
    vehicle_from_dict,
    with_bay_size,
)
from payload.envelope.fit import (
    box_solid,
    check_stowed,
    deployment_sweep,
    envelope_margin,
    finger_links,
    fit_solid,
    search_stowed_posture,
    self_contacts,
    with_finger_posture,
)
from payload.envelope.fit_results import TIGHT_CLEARANCE
from payload.envelope.vehicle import BAY_ASSUMPTION
from payload.project import SOURCES

VEHICLE = Vehicle()
LO, HI = VEHICLE.bay_lower, VEHICLE.bay_upper


def run_cli(*args: str) -> subprocess.CompletedProcess:
    main = "import sys; from payload.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run(
        [sys.executable, "-c", main, *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )


def geometry_of(data: dict) -> PayloadGeometry:
    return PayloadGeometry(build_tree(design_from_dict(data)))


CURLED = [1.5708, 0.0, 1.5708, 1.5708]
"""Every finger joint but the abduction at a right angle (the first default stowed posture)."""


@pytest.fixture(scope="module")
def geom(design) -> PayloadGeometry:
    """The default design as committed."""
    return PayloadGeometry(build_tree(design))


@pytest.fixture(scope="module")
def stowed(geom):
    return check_stowed(geom, VEHICLE, geom.tree.posture("stowed"))


@pytest.fixture(scope="module")
def curled_geom(design_dict) -> PayloadGeometry:
    """The default design with LEAP's 50.3 mm distal link, stowed curled at right angles."""
    data = copy.deepcopy(design_dict)
    data["finger"]["lengths"]["distal"] = 0.0503
    data["stowed"].update(finger=CURLED, rail=0.0, stage=0.0)
    return geometry_of(data)


@pytest.fixture(scope="module")
def curled(curled_geom):
    return check_stowed(curled_geom, VEHICLE, curled_geom.tree.posture("stowed"))


# ----------------------------------------------------------------- the bay model


def test_default_bays_are_the_facts_assumption_and_are_named_as_one():
    assert VEHICLE.bay_size == (0.20, 0.10, 0.10)
    assert np.allclose(LO, [-0.1, -0.05, -0.1]) and np.allclose(HI, [0.1, 0.05, 0.0])
    assert VEHICLE.bottom_z == pytest.approx(-0.1)
    assert "not public" in VEHICLE.assumption and "200 x 100 x 100 mm" in VEHICLE.assumption


def test_body_boxes_are_the_body_minus_the_open_bays():
    boxes = VEHICLE.body_boxes()
    total = sum(float(np.prod(hi - lo)) for lo, hi in boxes)
    assert total == pytest.approx(0.32**3 - 0.2 * 0.1 * 0.1, rel=1e-12)
    # disjoint: their union has the summed volume
    union = box_solid(*boxes[0])
    for lo, hi in boxes[1:]:
        union = union + box_solid(lo, hi)
    assert union.volume() == pytest.approx(total, rel=1e-9)
    assert VEHICLE.body_solid().volume() == pytest.approx(total, rel=1e-9)


def test_vehicle_table_in_the_design_file_replaces_the_assumption(tmp_path, design_dict):
    data = copy.deepcopy(design_dict)
    data["vehicle"] = {"bay_size": [0.21, 0.11, 0.12]}
    path = tmp_path / "design.toml"
    path.write_bytes(tomli_w.dumps(data).encode())
    design, vehicle = load_design_and_vehicle(path)
    assert design.finger.lengths.distal == pytest.approx(design_dict["finger"]["lengths"]["distal"])
    assert vehicle.bay_size == (0.21, 0.11, 0.12)
    assert vehicle.bottom_z == pytest.approx(-0.12)
    assert "210.0 x 110.0 x 120.0 mm" in vehicle.assumption
    # the packaged design's table (what a project's design without one gets) has the
    # class's defaults, its own words for the assumption aside
    import dataclasses

    import tomllib

    from payload.project import default_design_text

    packaged = vehicle_from_dict(tomllib.loads(default_design_text())["vehicle"])
    assert dataclasses.replace(packaged, assumption=BAY_ASSUMPTION) == Vehicle(source="<memory>")
    assert vehicle_from_dict({}).assumption == BAY_ASSUMPTION


@pytest.mark.parametrize(
    ("table", "where"),
    [
        ({"bay_size": [0.2, 0.1]}, "vehicle.bay_size"),
        ({"bay_size": [0.2, -0.1, 0.1]}, "vehicle.bay_size"),
        ({"bay_size": [0.4, 0.1, 0.1]}, "vehicle.bay_size"),
        ({"body_size": [0.32, 0.32, 0.05]}, "vehicle.bay_size"),
        ({"body_offset": [0.1, 0.0]}, "vehicle.bay_size"),
        ({"bay_sise": [0.2, 0.1, 0.1]}, "vehicle.bay_sise"),
        ({"assumption": 3}, "vehicle.assumption"),
    ],
)
def test_bad_vehicle_tables_name_the_parameter(table, where):
    with pytest.raises(VehicleError) as err:
        vehicle_from_dict(table)
    assert err.value.parameter == where


def test_bay_size_override_is_validated_and_named():
    v = with_bay_size(VEHICLE, [0.3, 0.1, 0.1])
    assert v.bay_size == (0.3, 0.1, 0.1) and "command line" in v.assumption
    with pytest.raises(VehicleError, match="--bay-size"):
        with_bay_size(VEHICLE, [0.3, 0.0, 0.1])


def test_a_bay_size_typed_in_mm_is_named_as_the_option_with_the_sizes_meant():
    """``--bay-size 200 100 100`` (mm where metres are meant) named the design file's
    ``vehicle.bay_size`` and gave no hint: the error names the option, and the sizes it
    suggests are accepted as they are printed; a size too large in metres gets no hint."""
    import re

    typed = [1e3 * v for v in VEHICLE.bay_size]
    with pytest.raises(VehicleError) as err:
        with_bay_size(VEHICLE, typed)
    assert err.value.parameter == "--bay-size"
    meant = re.search(
        r"did you mean .* = --bay-size ([0-9.e-]+) ([0-9.e-]+) ([0-9.e-]+)\?", str(err.value)
    )
    assert meant, str(err.value)
    accepted = with_bay_size(VEHICLE, [float(v) for v in meant.groups()])
    assert accepted.bay_size == pytest.approx(VEHICLE.bay_size)
    with pytest.raises(VehicleError) as err:
        with_bay_size(VEHICLE, [2 * VEHICLE.body_size[0], *VEHICLE.bay_size[1:]])
    assert err.value.parameter == "--bay-size" and "did you mean" not in str(err.value)


# ----------------------------------------------------------------- known boxes


def box(lo, hi) -> m3d.Manifold:
    return box_solid(np.asarray(lo), np.asarray(hi))


def test_a_box_inside_has_the_exact_clearance_to_every_wall():
    lo, hi = np.array([-0.05, -0.02, -0.07]), np.array([0.08, 0.03, -0.01])
    fit = fit_solid("box", box(lo, hi), VEHICLE)
    gaps = [
        lo[0] - LO[0],
        HI[0] - hi[0],
        lo[1] - LO[1],
        HI[1] - hi[1],
        lo[2] - LO[2],
        HI[2] - hi[2],
    ]
    assert (
        fit.inside and fit.protrusion == 0.0 and fit.outside_volume == pytest.approx(0, abs=1e-15)
    )
    assert np.allclose(fit.wall_clearance, gaps, atol=1e-9)
    assert fit.clearance == pytest.approx(min(gaps), abs=1e-9)  # 0.01 m to the +z wall
    assert fit.wall == VEHICLE.walls[int(np.argmin(gaps))]


def test_a_box_wholly_outside_reports_its_farthest_point():
    # below the bays and beyond the +x wall: the far corner is 50 mm down and 30 mm out
    lo, hi = np.array([0.05, -0.01, -0.15]), np.array([0.13, 0.01, -0.12])
    fit = fit_solid("box", box(lo, hi), VEHICLE)
    assert not fit.inside
    assert fit.protrusion == pytest.approx(math.hypot(0.03, 0.05), abs=1e-9)
    assert fit.clearance == pytest.approx(-fit.protrusion)
    assert fit.wall == "-z (bottom face)"
    assert fit.outside_volume == pytest.approx(np.prod(hi - lo), rel=1e-9)


def test_a_box_straddling_a_wall_reports_the_protrusion_and_the_volume_outside():
    lo, hi = np.array([-0.03, -0.02, -0.12]), np.array([0.01, 0.02, -0.08])
    fit = fit_solid("box", box(lo, hi), VEHICLE)
    assert not fit.inside and fit.protrusion == pytest.approx(0.02, abs=1e-9)
    assert fit.wall == "-z (bottom face)"
    assert fit.outside_volume == pytest.approx(0.04 * 0.04 * 0.02, rel=1e-9)
    # one micrometre out is out; touching the wall is in with zero clearance
    assert not fit_solid("b", box([0, 0, -0.05], [0.05, 0.050001, -0.01]), VEHICLE).inside
    touching = fit_solid("b", box([0, 0, -0.05], [0.1, 0.05, -0.01]), VEHICLE)
    assert touching.inside and touching.clearance == pytest.approx(0.0, abs=1e-9)


def test_a_mounted_part_measures_clearance_to_the_other_five_walls():
    fit = fit_solid("plate", box([-0.09, -0.04, -0.004], [0.09, 0.04, 0.0]), VEHICLE, True)
    assert fit.inside and math.isnan(fit.wall_clearance[5])
    assert fit.clearance == pytest.approx(0.01, abs=1e-9)


# ----------------------------------------------------------------- the default design


def test_default_design_fits_the_bays_by_the_closed_form_clearance(design, stowed):
    a, mnt = design.array, design.mounting
    # the stage's brackets and the carriage reach side_gap/2 + depth/2 across y
    y_clear = VEHICLE.bay_size[1] / 2 - (a.side_gap / 2 + design.finger.section.depth / 2)
    parts = {p.name: p for p in stowed.parts}
    assert stowed.fits
    assert parts["stage"].clearance == pytest.approx(y_clear, abs=1e-7)
    assert parts["carriage"].clearance == pytest.approx(y_clear, abs=1e-7)
    assert stowed.min_clearance == min(p.clearance for p in stowed.parts) <= y_clear + 1e-7
    assert parts["base"].mounted and parts["base"].clearance == pytest.approx(
        (VEHICLE.bay_size[1] - mnt.plate_width) / 2, abs=1e-7
    )


def test_curled_fingers_sit_at_the_closed_form_height_above_the_bottom_face(design, curled):
    a, st, mnt = design.array, design.stage, design.mounting
    z_mcp = -(mnt.plate_thickness + st.stowed_gap + st.plate_thickness) - a.finger_drop
    bottom = z_mcp - design.finger.section.depth / 2  # the curled knuckle's underside
    parts = {p.name: p for p in curled.parts}
    # (1.5708 rad is 3.7 urad past a right angle: 0.1 um over a link)
    assert parts["A_proximal"].wall_clearance[4] == pytest.approx(bottom - LO[2], abs=1e-6)
    assert curled.fits


def test_the_figure_title_of_parts_that_fit_but_collide_says_fails(curled):
    """The curled design's parts fit the bays and collide: its verdict fails, and the
    figure's title says so rather than "fits"."""
    from payload.envelope.envelope_figure import figure_title

    assert curled.fits and curled.self_collision
    title = figure_title(curled)
    assert "(FAILS: the parts fit the bays but collide" in title
    assert title.endswith("self-collision: yes)")


def test_the_figure_title_of_a_blocked_deployment_says_fails(stowed):
    """Parts that fit without colliding but whose deployment sweep is not clear: the
    verdict fails, and so does the title."""
    import dataclasses

    from payload.envelope.envelope_figure import figure_title

    assert stowed.passed and figure_title(stowed).startswith(
        "Stowed payload in the two lower bays (fits;"
    )
    blocked = dataclasses.replace(
        stowed, sweep=stowed.sweep._replace(clear=False, vehicle_clear=False)
    )
    assert blocked.fits and not blocked.self_collision and not blocked.passed
    assert "(FAILS: the parts fit the bays but the deployment path is not clear;" in (
        figure_title(blocked)
    )


def test_curled_distal_pads_run_into_their_own_brackets_by_the_closed_form_depth(
    design, curled_geom, curled
):
    assert curled.self_collision
    pairs = {frozenset((c.a, c.b)) for c in curled.collisions}
    assert pairs == {
        frozenset(p)
        for p in (
            ("stage", "A_distal"),
            ("stage", "C_distal"),
            ("carriage", "B_distal"),
            ("carriage", "D_distal"),
        )
    }
    tips = curled_geom.tree.frame_positions(curled.q)
    a = design.array
    inner_face = a.side_gap / 2 - design.finger.section.depth / 2  # bracket face toward -y
    depth = tips["A_tip"][1] + design.finger.pad.radius - inner_face
    for c in curled.collisions:
        assert -c.distance == pytest.approx(depth, abs=1e-4)  # pad tessellation
        assert c.overlap_volume > 0
    assert curled.sweep.vehicle_clear and not curled.sweep.clear
    assert not curled.passed
    assert curled.failures()[0].startswith(f"stage and A_distal collide ({depth * 1e3:.1f} mm deep")


def test_adjacent_links_are_the_only_pairs_left_out(geom):
    excluded = {frozenset(p) for p in geom.excluded_pairs()}
    assert len(excluded) == len(geom.tree.joints) == 18
    n = len(geom.links)
    assert len(geom.pairs) == n * (n - 1) // 2 - 18
    assert not excluded & {frozenset(p) for p in geom.pairs}


def test_self_contacts_agree_with_exact_mesh_volumes(curled_geom, curled):
    """Convex signed distance < 0 exactly where the exact solids share volume."""
    poses = curled_geom.poses(curled.q)
    for c in curled.self_contacts[:30]:
        vol = curled_geom.overlap_volume(c.a, c.b, poses)
        assert (vol > 1e-12) == (c.distance < -1e-6), (c, vol)


def test_a_lengthened_finger_fails_naming_its_links_and_the_protrusion(design_dict, tmp_path):
    data = copy.deepcopy(design_dict)
    data["finger"]["lengths"]["distal"] = 0.09
    g = geometry_of(data)
    check = check_stowed(g, VEHICLE, g.tree.posture("stowed"))
    parts = {p.name: p for p in check.parts}
    tips = g.tree.frame_positions(check.q)
    r = data["finger"]["pad"]["radius"]
    for finger, sign in (("A", 1), ("B", 1), ("C", -1), ("D", -1)):
        p = parts[f"{finger}_distal"]
        # the curled distal points back across the bay: its pad pole is the farthest point,
        # less at most the sagitta of the tessellated sphere when no vertex sits at the pole
        expected = sign * tips[f"{finger}_tip"][1] + r - HI[1]
        sagitta = r * (1 - math.cos(math.pi / SEGMENTS))
        assert not p.inside
        assert expected - sagitta - 1e-9 <= p.protrusion <= expected + 1e-9
        assert p.wall == ("+y (left)" if sign > 0 else "-y (right)")
    assert {n for n, p in parts.items() if not p.inside} == {f"{f}_distal" for f in "ABCD"}
    # the command fails (exit 1) naming the links and the millimetres
    path = tmp_path / "long.toml"
    path.write_bytes(tomli_w.dumps(data).encode())
    res = run_cli(
        "report",
        "envelope",
        "--design",
        str(path),
        "--no-search",
        "--json",
        "--out",
        str(tmp_path / "out"),
    )
    assert res.returncode == 1
    mm = f"{parts['A_distal'].protrusion * 1e3:.1f} mm"
    assert "A_distal protrudes " + mm in res.stderr and len(res.stderr.strip().splitlines()) == 1
    out = json.loads(res.stdout)
    assert out["fits"] is False
    bad = {p["name"]: p for p in out["parts"] if not p["inside"]}
    assert set(bad) == {"A_distal", "B_distal", "C_distal", "D_distal"}
    assert bad["C_distal"]["clearance_mm"] == pytest.approx(
        -parts["C_distal"].protrusion * 1e3, abs=0.01
    )


# ----------------------------------------------------------------- deployment sweep


def test_the_sweep_finds_the_first_contact_at_the_closed_form_travel(geom, stowed, design):
    q = with_finger_posture(stowed.q, [0.0, 0.0, 0.0, 0.0])  # straight fingers, stage free
    tips = geom.tree.frame_positions(q)
    lowest = min(tips[f"{f}_tip"][2] for f in "ABCD") - geom.tree.design.finger.pad.radius
    # a thin plate 31.3 mm below the pads, under finger A only
    x = geom.tree.joint_map["A_mcp_flex"].xyz[0]
    top = lowest - 0.0313
    plate = ("plate", np.array([x - 0.004, 0.03, top - 0.0005]), np.array([x + 0.004, 0.04, top]))
    sweep = deployment_sweep(geom, VEHICLE, q, contacts=[], extra=[plate])
    assert not sweep.vehicle_clear and "plate" in sweep.between
    assert sweep.first_contact == pytest.approx(0.0313, abs=2e-4)  # pad tessellation
    clear = deployment_sweep(geom, VEHICLE, q, contacts=[])
    assert clear.vehicle_clear and clear.certified
    a = design.array  # closest: the straight knuckles and the brackets, across y
    y_clear = VEHICLE.bay_size[1] / 2 - (a.side_gap / 2 + design.finger.section.depth / 2)
    assert clear.min_distance == pytest.approx(y_clear, abs=1e-6)


def test_narrower_bays_block_the_deployment_at_stage_zero(curled_geom, curled):
    narrow = with_bay_size(VEHICLE, [0.2, 0.097, 0.1])
    check = check_stowed(curled_geom, narrow, curled.q)
    assert not check.fits and not check.sweep.vehicle_clear
    assert check.sweep.first_contact == pytest.approx(0.0, abs=1e-9)
    assert -check.min_clearance == pytest.approx(0.0005, abs=1e-7)


# ----------------------------------------------------------------- posture search


def test_posture_search_beats_random_postures_and_reports_its_own_clearance(curled_geom, curled):
    geom, stowed = curled_geom, curled
    result = search_stowed_posture(geom, VEHICLE, stowed.q, grid=4, starts=2)
    limits = np.array(
        [
            [geom.tree.joint_map[f"A_{j}"].lower, geom.tree.joint_map[f"A_{j}"].upper]
            for j in ("mcp_flex", "mcp_abd", "pip", "dip")
        ]
    )
    assert np.all(limits[:, 0] <= result.finger) and np.all(result.finger <= limits[:, 1])
    # recompute the objective independently: fingers' wall clearances and pair distances
    q = with_finger_posture(stowed.q, result.finger)
    check = check_stowed(geom, VEHICLE, q)
    fingers = set(finger_links(geom))
    walls = min(p.clearance for p in check.parts if p.name in fingers)
    pairs = min(c.distance for c in check.self_contacts if {c.a, c.b} & fingers)
    assert result.clearance == pytest.approx(min(walls, pairs), abs=1e-6)
    rng = np.random.default_rng(3)
    for _ in range(60):
        x = rng.uniform(limits[:, 0], limits[:, 1])
        poses = geom.poses(with_finger_posture(stowed.q, x))
        margin = envelope_margin(geom, poses, VEHICLE, finger_links(geom))[0]
        d = min(geom.link_distance(a, b, poses) for a, b in geom.pairs if {a, b} & fingers)
        assert min(margin, d) <= result.clearance + 1e-9


def test_a_shorter_distal_link_stows_with_the_searched_posture(design_dict):
    """The design change proposed in the envelope report: distal 45 mm, posture searched."""
    data = copy.deepcopy(design_dict)
    data["finger"]["lengths"]["distal"] = 0.045
    data["stowed"]["finger"] = [1.66, 0.0, 1.398, 1.805]
    g = geometry_of(data)
    check = check_stowed(g, VEHICLE, g.tree.posture("stowed"))
    assert check.passed, check.failures()
    assert check.min_clearance == pytest.approx(0.001, abs=1e-6)
    assert check.min_self_clearance.distance > 0.0005


def test_analysis_runs_the_search_only_when_asked_or_when_the_posture_fails(curled_geom):
    a = analyse_envelope(curled_geom, VEHICLE, search=False)
    assert a.search is None and not a.passed
    contacts = self_contacts(curled_geom, curled_geom.poses(a.given.q))
    assert [(c.a, c.b) for c in contacts[:4]] == [(c.a, c.b) for c in a.given.self_contacts[:4]]


# ----------------------------------------------------------------- CLI


def test_report_envelope_json_and_files(tmp_path, stowed):
    out = tmp_path / "analyses"
    res = run_cli("report", "envelope", "--json", "--out", str(out))
    obj = json.loads(res.stdout)
    assert len(res.stdout.strip().splitlines()) == 1
    for key in (
        "fits",
        "min_clearance_mm",
        "parts",
        "self_collision",
        "deploy_path_clear",
        "assumptions",
    ):
        assert key in obj
    assert {"name", "inside", "clearance_mm"} <= set(obj["parts"][0])
    assert obj["fits"] is stowed.fits
    assert obj["min_clearance_mm"] == pytest.approx(stowed.min_clearance * 1e3, abs=0.01)
    assert obj["self_collision"] is stowed.self_collision
    assert obj["deploy_path_clear"] is stowed.sweep.clear
    assert any("ASSUMPTION" in s and "not public" in s for s in obj["assumptions"])
    # exit 0 when every check passes, else 1 with one line naming the first failure
    if obj["passed"]:
        assert res.returncode == 0 and obj["stowed_search"] is None
    else:
        assert res.returncode == 1 and len(res.stderr.strip().splitlines()) == 1
        assert res.stderr.startswith("payload: check failed: stowed payload: " + obj["failures"][0])
        assert obj["stowed_search"]["finger"] and "passed" in obj["stowed_search"]["check"]
    for name in ("envelope.md", "envelope.png", "envelope.json"):
        assert (out / name).stat().st_size > 0
    md = (out / "envelope.md").read_text()
    assert "ASSUMPTION (bay size)" in md and f"{stowed.tightest.clearance * 1e3:.1f} mm" in md
    assert json.loads((out / "envelope.json").read_text())["fits"] is stowed.fits


def test_report_envelope_with_a_bay_override_and_bad_input(tmp_path):
    res = run_cli("report", "envelope", "--bay-size", "0.2", "-0.1", "0.1", "--out", str(tmp_path))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        "payload: error: --bay-size: every size must be positive (got -0.1)"
    ]
    res = run_cli("report", "envelope", "--design", str(tmp_path / "missing.toml"))
    assert res.returncode == 2 and "cannot read design file" in res.stderr


def test_generated_envelope_report_is_committed_and_names_the_assumption():
    md = ROOT / "analyses" / "envelope.md"
    data = json.loads((ROOT / "analyses" / "envelope.json").read_text())
    assert "ASSUMPTION" in md.read_text()
    assert data["design"] == "cad/design.toml" and Path(DESIGN).exists()


def _report(project, capsys, *extra):
    from payload.cli import main

    code = main(["--project", str(project), "report", "envelope", "--no-search", *extra])
    out = capsys.readouterr()
    return code, out.out.splitlines(), out.err.strip().splitlines()


def _edit_design(path, old, new):
    text = path.read_text()
    path.write_text(replace_once(text, old, new))
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_the_report_follows_the_design_through_two_edits(tmp_path, capsys):
    """edit -> report envelope -> edit -> report envelope in a new project (issue 30)."""
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    design, out = project.design_path, project.analyses_dir
    names = ("envelope.md", "envelope.json", "envelope.png")
    # edit 1: a shorter distal link still stows
    sha1 = _edit_design(design, "distal = 0.045 ", "distal = 0.044 ")
    code, lines, err = _report(project.root, capsys)
    assert code == 0 and err == []
    assert lines[0] == f"project: {project.root}"
    assert lines[1].startswith("models: rebuilt ") and "urdf/payload.urdf" in lines[1]
    assert lines[2].startswith("verdict: fits: every part inside the bays, min clearance")
    first = json.loads((out / "envelope.json").read_text())
    assert first["passed"] is True and first["provenance"]["design_sha256"] == sha1
    assert not (out / "envelope.prev.json").exists()
    # the same design again: the files are left as they are
    stamp = {n: (out / n).stat().st_mtime_ns for n in names}
    code, lines, _ = _report(project.root, capsys)
    assert code == 0 and lines[1].startswith("verdict: fits") and "report unchanged" in lines[-1]
    # the files kept are named (a new user's `make demo` named only the timings')
    assert all(str(out / n) in lines[-1] for n in names), lines[-1]
    assert {n: (out / n).stat().st_mtime_ns for n in names} == stamp
    # a comment only: the figures stand, but the report names the design it follows
    design.write_text(design.read_text() + "# a note\n")
    sha_note = hashlib.sha256(design.read_bytes()).hexdigest()
    code, lines, _ = _report(project.root, capsys)
    noted = json.loads((out / "envelope.json").read_text())
    assert code == 0 and noted["provenance"]["design_sha256"] == sha_note
    assert {k: v for k, v in noted.items() if k != "provenance"} == {
        k: v for k, v in first.items() if k != "provenance"
    }
    assert "changed since envelope.prev.json: the design file only" in "\n".join(lines)
    first = noted
    # edit 2: a distal link 15 mm longer runs into the stage when curled
    sha2 = _edit_design(design, "distal = 0.044 ", "distal = 0.060 ")
    code, lines, err = _report(project.root, capsys)
    assert code == 1 and lines[2].startswith("verdict: FAILS: ") and "_distal" in lines[2]
    assert len(err) == 1 and err[0].startswith("payload: check failed: stowed payload: ")
    second = json.loads((out / "envelope.json").read_text())
    assert second["provenance"]["design_sha256"] == sha2 and second["passed"] is False
    md = (out / "envelope.md").read_text()
    assert "**The stowed configuration fails the envelope check.**" in md
    assert json.loads((out / "envelope.prev.json").read_text()) == first
    change = next(x for x in lines if x.startswith("changed since envelope.prev.json: "))
    assert "passes yes -> no" in change and "deployment path clear yes -> no" in change
    assert lines[-1].startswith("wrote ") and str(out / "envelope.prev.json") in lines[-1]
    # the models followed the design too
    assert run_cli("build", "--check", "--project", str(project.root)).returncode == 0


def test_a_projects_reports_cite_sources_the_reader_can_open(tmp_path, capsys):
    """A project outside the checkout has no docs/sources.md: its reports (the default
    design's assumption, the CTB features' sources) cited one all the same. Every
    citation now is a link that, read from the report's folder, opens the workbench's
    file (its section kept); the checkout's own report cites it as before."""
    import re

    from payload.cli import main
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    assert not (project.root / SOURCES).exists()
    sources = (ROOT / SOURCES).resolve()
    for args in (["envelope", "--no-search"], ["reach", "--samples", "2000"]):
        assert main(["--project", str(project.root), "report", *args]) == 0
        # the terminal's assumption line names the file a reader can open from anywhere
        said = [x for x in capsys.readouterr().out.splitlines() if Path(SOURCES).name in x]
        paths = [Path(p) for p in re.findall(r"\((/[^)#]*sources\.md)", " ".join(said))]
        assert said and paths and all(p.resolve() == sources for p in paths), said
        assert not [x for x in said if f"({SOURCES}" in x], said
    for name, cited in (("envelope.md", 1), ("reach.md", 3)):
        md = project.analyses_dir / name
        text = md.read_text()
        links = re.findall(r"\[[^\]]*\]\(([^)#]*)(#[^)]*)?\)", text)
        opened = [t for t, _ in links if (md.parent / t).resolve() == sources]
        assert len(opened) >= cited, (name, links)
        rest = re.sub(r"\[[^\]]*\]\([^)]*\)", "", text)
        assert Path(SOURCES).name not in rest, name  # no citation left that opens nothing
    checkout = tmp_path / "checkout"
    assert main(["report", "envelope", "--no-search", "--out", str(checkout)]) == 0
    [line] = [x for x in (checkout / "envelope.md").read_text().splitlines() if "sources" in x]
    assert f"({SOURCES})" in line and "workbench" not in line


def test_another_designs_report_needs_an_out_and_never_replaces_the_projects(tmp_path, capsys):
    """``report envelope|reach --design F`` with F not the project's own design (outside any
    project, or another file inside it) would write F's report over the project's in
    analyses/ (which follows the project's design): one line, exit 2, nothing written;
    a bad F still says what is wrong with it."""
    from payload.cli import main

    root = tmp_path / "p"
    (root / "cad").mkdir(parents=True)
    (root / "cad" / "design.toml").write_bytes(Path(DESIGN).read_bytes())
    elsewhere = tmp_path / "loose" / "other.toml"
    elsewhere.parent.mkdir()
    elsewhere.write_bytes(Path(DESIGN).read_bytes())
    inside = root / "variants" / "other.toml"
    inside.parent.mkdir()
    inside.write_bytes(Path(DESIGN).read_bytes())
    for what in ("envelope", "reach"):
        for design in (elsewhere, inside):
            argv = ["--project", str(root), "report", what, "--design", str(design)]
            assert main(argv) == 2
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and f"--design {design} is not the project's design" in err[0]
            assert "give --out DIR" in err[0]
            # nor with --out naming the project's own analyses/ (the default's folder)
            assert main([*argv, "--out", str(root / "analyses")]) == 2
            assert "is not the project's design" in capsys.readouterr().err
    assert not (root / "analyses").exists()
    broken = tmp_path / "loose" / "broken.toml"
    broken.write_text("[finger\n")
    assert main(["--project", str(root), "report", "envelope", "--design", str(broken)]) == 2
    err = capsys.readouterr().err
    assert "is not the project's design" not in err and str(broken) in err


def test_write_stowed_writes_the_proposal_into_the_stowed_table_and_nothing_else(geom, tmp_path):
    """``--write-stowed``: only ``[stowed] finger`` and its comment change, and the design
    then loads with the proposed posture (the proposal here is checked by check_stowed)."""
    import argparse
    import dataclasses

    from payload.design import load_design
    from payload.envelope.cli_runs import _write_stowed
    from payload.envelope.fit_results import PostureSearch

    design = tmp_path / "design.toml"
    design.write_bytes(DESIGN.read_bytes())
    finger = (1.65, 0.0, 1.40, 1.80)  # near the committed posture
    suggested = check_stowed(
        geom, VEHICLE, with_finger_posture(geom.tree.posture("stowed"), finger)
    )
    assert suggested.passed, suggested.failures()
    analysis = dataclasses.replace(
        analyse_envelope(geom, VEHICLE, search=False),
        search=PostureSearch(finger, suggested.min_clearance, "test", 1, 0.0),
        suggested=suggested,
    )
    args = argparse.Namespace(design=str(design))
    line = _write_stowed(args, analysis)
    assert line == f"wrote [stowed] finger = {list(finger)} into {design}"
    before, after = DESIGN.read_text().splitlines(), design.read_text().splitlines()
    changed = [(a, b) for a, b in zip(before, after) if a != b]
    assert len(before) == len(after) and len(changed) == 1
    assert changed[0][0].startswith("finger = [1.66, 0.0, 1.398, 1.805]")
    assert changed[0][1].startswith("finger = [1.65, 0.0, 1.4, 1.8]  # written by `payload report")
    assert "--write-stowed" in changed[0][1] and "min clearance" in changed[0][1]
    assert load_design(design).stowed.finger == finger
    assert _write_stowed(args, analysis) == f"{design} already holds the proposed posture"


def test_report_all_runs_everything_and_leads_with_one_verdict(tmp_path, capsys):
    from payload.cli import main
    from payload.design import load_design
    from payload.design.summary import summarize

    out = tmp_path / "analyses"
    code = main(["report", "all", "--samples", "2000", "--out", str(out)])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("project: ") and lines[1].startswith("verdict: ")
    assert sum(x.startswith("verdict: ") for x in lines) == 3  # overall, envelope, reach
    assert lines.index("-- envelope") < lines.index("-- reach") < lines.index("-- design summary")
    # the bay-size assumption both reports rest on, said once, before them
    said = [i for i, x in enumerate(lines) if x.startswith("assumption: ")]
    assert len(said) == 1 and said[0] < lines.index("-- envelope"), lines
    env = json.loads((out / "envelope.json").read_text())
    reach = json.loads((out / "reach.json").read_text())
    grasps = all(any(g["closes"] for g in p["grasp"]) for p in reach["pairs"].values())
    passed = env["passed"] and grasps and reach["below_vehicle_mm"] > 0
    assert code == (0 if passed else 1)
    assert lines[1].startswith("verdict: passes" if passed else "verdict: FAILS")
    # --json: one object holding the three parts and the verdict
    assert main(["report", "all", "--samples", "2000", "--out", str(out), "--json"]) == code
    data = json.loads(capsys.readouterr().out)
    assert data["passed"] is passed and data["models"] == {"rebuilt": []}
    assert data["envelope"]["passed"] == env["passed"] and data["reach"]["pairs"].keys() == {
        "L",
        "R",
    }
    assert data["summary"]["dof"] == summarize(load_design(DESIGN))["dof"]


def test_a_reach_run_with_other_settings_says_so_before_its_figures() -> None:
    """``report reach --samples 1000`` after a 100,000-sample report: the changed line
    names the sample count first (the figures moved with it, not with the design); a
    rerun with the same settings names figures only."""
    from payload.envelope.verdict import headline_changes

    before = {"samples": 100000, "seed": 0, "below_vehicle_mm": 202.52}
    after = {"samples": 1000, "seed": 0, "below_vehicle_mm": 201.42}
    line = headline_changes("reach", before, after)
    assert line == (
        "changed since reach.prev.json: run with other settings (samples 100000 -> 1000); "
        "fingertips below the vehicle 202.52 mm -> 201.42 mm"
    )
    same = headline_changes("reach", {**before, "samples": 1000}, after)
    assert (
        same == "changed since reach.prev.json: fingertips below the vehicle 202.52 mm -> 201.42 mm"
    )


def test_an_out_holding_another_designs_report_or_other_files_is_refused(tmp_path, capsys):
    """``--out`` into another project's analyses/ (its report of its own design) or into a
    folder holding files that are no report (a hand-written ``envelope.md``, a JSON
    without provenance): one line, exit 2, every file as it was, unless ``--force``. A
    report written there names the project it came from, so it is recognised as its
    own on the next run."""
    from payload.cli import main
    from payload.design.cli import new_project

    a, _ = new_project(tmp_path / "a")
    b, _ = new_project(tmp_path / "b")
    _edit_design(b.design_path, "distal = 0.045 ", "distal = 0.044 ")
    assert _report(b.root, capsys)[0] == 0
    theirs = {p.name: p.read_bytes() for p in b.analyses_dir.iterdir()}
    code, _, err = _report(a.root, capsys, "--out", str(b.analyses_dir))
    assert code == 2 and len(err) == 1
    assert err[0] == (
        f"payload: error: --out {b.analyses_dir}: already holds envelope.json, the report of "
        f"{b.design_path}, not of {a.design_path}; pass --force to replace it or choose "
        "another --out"
    )
    assert {p.name: p.read_bytes() for p in b.analyses_dir.iterdir()} == theirs
    other = tmp_path / "otherres"
    other.mkdir()
    (other / "envelope.md").write_text("my notes\n")
    code, _, err = _report(a.root, capsys, "--out", str(other))
    assert code == 2 and len(err) == 1 and "holds envelope.md, not a report of " in err[0]
    # nor the reach report, refused before it samples anything
    (other / "reach.md").write_text("my notes\n")
    argv = ["--project", str(a.root), "report", "reach", "--samples", "1000", "--out", str(other)]
    assert main(argv) == 2
    assert "holds reach.md, not a report of " in capsys.readouterr().err
    (other / "envelope.json").write_text('{"mine": 1}\n')
    code, _, err = _report(a.root, capsys, "--out", str(other))
    assert code == 2 and "holds envelope.json, not a report (no provenance" in err[0]
    assert (other / "envelope.md").read_text() == "my notes\n"
    assert (other / "envelope.json").read_text() == '{"mine": 1}\n'
    assert sorted(p.name for p in other.iterdir()) == ["envelope.json", "envelope.md", "reach.md"]
    # --force replaces them; the report then names its project and is its own next time
    code, lines, _ = _report(a.root, capsys, "--out", str(other), "--force")
    assert code == 0 and lines[-1].startswith("wrote ")
    prov = json.loads((other / "envelope.json").read_text())["provenance"]
    assert prov["project"] == str(a.root) and prov["design"] == "cad/design.toml"
    assert Path(prov["project"], prov["design"]) == a.design_path
    code, lines, _ = _report(a.root, capsys, "--out", str(other))
    assert code == 0 and "report unchanged" in lines[-1]
    # the project's own analyses/ (no project in its files' provenance) is its own too
    assert _report(b.root, capsys)[0] == 0
    assert "project" not in json.loads((b.analyses_dir / "envelope.json").read_text())["provenance"]


def test_wall_labels_name_the_least_clearance_over_every_part(design_dict):
    """envelope.png's wall labels against envelope.json's per-part clearances (python-fcl,
    per wall): with the sides 90 mm apart some parts stick out sideways, and each other
    wall's label still shows the least clearance over every part, inside or not (the
    stage, outside, is the nearest to the mount face at 6.0 mm; the knuckles, outside, to
    the bottom face at 5.1 mm)."""
    from matplotlib.figure import Figure

    from payload.envelope.drawing import AXES
    from payload.envelope.envelope_figure import _annotate_clearances
    from payload.envelope.report_json import envelope_json

    data = copy.deepcopy(design_dict)
    data["array"]["side_gap"] = 0.090
    analysis = analyse_envelope(geometry_of(data), VEHICLE, search=False)
    parts = envelope_json(analysis)["parts"]
    assert not all(p["inside"] for p in parts)
    fig = Figure()
    seen = set()
    for axis, ax in enumerate(fig.subplots(1, 3)):
        _annotate_clearances(ax, analysis.given, VEHICLE, axis)
        walls = [w for w in range(6) if w // 2 in AXES[axis]]
        texts = [t.get_text() for t in ax.texts]
        assert len(texts) == len(walls)
        for w, text in zip(walls, texts):
            wall = VEHICLE.walls[w]
            out = [p for p in parts if not p["inside"] and p["wall"] == wall]
            if out:
                # (which part and how far, wall by wall: the test below)
                name, mm = text.removesuffix(" mm out").split(": ")
                far = max(p["protrusion_mm"] for p in out)
                assert float(mm) == pytest.approx(far, abs=0.051), (wall, text)
                assert name in {p["name"] for p in parts if not p["inside"]}, (wall, text)
                continue
            values = {p["name"]: p["wall_clearance_mm"][w] for p in parts}
            least = min(v for v in values.values() if v is not None)
            mm, name = text.removesuffix(")").split(" mm (")
            assert float(mm) == pytest.approx(least, abs=0.051), (wall, text)
            assert values[name] == pytest.approx(least, abs=0.01), (wall, text)
            seen.add((wall, text))
    assert ("+z (mount)", "6.0 mm (stage)") in seen
    assert any(w.startswith("-z") and t.startswith("5.1 mm (") for w, t in seen), seen


def test_wall_labels_say_no_clearance_on_a_wall_a_part_crosses(geom):
    """In bays 180 x 100 x 85 mm the base and the stage cross the forward wall, but the
    bottom face more: envelope.png labelled the forward wall "0.00 mm (base)" in black,
    which reads as safe. Each wall a part crosses, found here from the posed meshes against
    the bay box wall by wall, is now labelled in red with the part reaching farthest
    beyond it; no other wall is."""
    from matplotlib.colors import same_color
    from matplotlib.figure import Figure

    from payload.envelope.drawing import AXES, FAIL_COLOUR
    from payload.envelope.envelope_figure import _annotate_clearances

    bays = with_bay_size(VEHICLE, [0.18, 0.10, 0.085])
    analysis = analyse_envelope(geom, bays, search=False)
    poses = geom.poses(analysis.given.q)
    lo, hi = bays.bay_lower, bays.bay_upper
    beyond = {}  # part -> how far beyond each wall, -x .. +z [m]
    for n in geom.links:
        v = geom.mesh_vertices[n] @ poses[n][:3, :3].T + poses[n][:3, 3]
        beyond[n] = np.concatenate([(lo - v).max(axis=0), (v - hi).max(axis=0)])[[0, 3, 1, 4, 2, 5]]
    crossing = {w: [n for n in beyond if beyond[n][w] > 1e-6] for w in range(6)}
    assert {"base", "stage"} <= set(crossing[1])  # the forward wall
    assert all(int(np.argmax(beyond[n])) != 1 for n in ("base", "stage"))  # crossed less
    fig = Figure()
    for axis, ax in enumerate(fig.subplots(1, 3)):
        _annotate_clearances(ax, analysis.given, bays, axis)
        walls = [w for w in range(6) if w // 2 in AXES[axis]]
        assert len(ax.texts) == len(walls)
        for w, t in zip(walls, ax.texts):
            text = t.get_text()
            if not crossing[w]:
                assert not same_color(t.get_color(), FAIL_COLOUR) and "out" not in text, text
                continue
            far = max(crossing[w], key=lambda n: beyond[n][w])
            assert same_color(t.get_color(), FAIL_COLOUR), text
            name, mm = text.removesuffix(" mm out").split(": ")
            assert name == far, (bays.walls[w], text)
            assert float(mm) == pytest.approx(beyond[far][w] * 1e3, abs=0.051), text


def test_the_search_line_prints_no_negative_zero() -> None:
    """A search angle that rounds to zero from below printed "-0.0000" (the design file
    already got 0.0)."""
    from types import SimpleNamespace

    from payload.envelope.cli_runs import _search_line

    search = SimpleNamespace(finger=[1.66006, -1e-6, -0.0, 1.80481], clearance=1.06e-3,
                             limited_by="A_knuckle / +y (left) wall")  # fmt: skip
    passing = SimpleNamespace(passed=True, tight=False)
    line = _search_line(SimpleNamespace(search=search, suggested=passing))
    assert line.startswith("stowed-posture search: proposes finger [1.6601, 0.0000, 0.0000, 1.80")


# ----------------------------------------------------------------- tight fits, one formatting


def test_a_clearance_prints_two_decimals_under_1_mm_and_one_from_1_mm() -> None:
    """The CLI said 0.06 mm where envelope.md, envelope.png and the review said 0.1 mm:
    one formatting of a clearance now, two decimals under 1 mm."""
    from payload.envelope.fit_results import clearance_text

    assert clearance_text(0.06e-3) == "0.06 mm"
    assert clearance_text(0.5e-3) == "0.50 mm"
    assert clearance_text(-0.3e-3) == "-0.30 mm"
    assert clearance_text(0.996e-3) == "1.0 mm"  # rounds to 1 mm: one decimal
    assert clearance_text(1.06e-3) == "1.1 mm"
    assert clearance_text(6e-3) == "6.0 mm"


@pytest.fixture(scope="module")
def narrow_fit(design, geom):
    """The default design in bays 1.4 mm narrower across y (the stage's and the
    carriage's side, 1.0 mm from each wall): 0.3 mm to the y walls, still a pass."""
    a = design.array
    reach_y = a.side_gap / 2 + design.finger.section.depth / 2  # closed form: 49.0 mm
    narrow = with_bay_size(VEHICLE, [0.2, 2 * (reach_y + 0.3e-3), 0.1])
    return analyse_envelope(geom, narrow, search=False)


def test_a_pass_under_the_tight_clearance_is_said_tight_in_every_verdict(narrow_fit):
    """A stowed fit with 0.3 mm to a wall (under the review's 0.5 mm, a printed part's
    tolerance) passed as plainly as one with 10 mm: it still passes (exit 0), but the
    terminal's, ``report all``'s, envelope.md's and the figure's verdicts say it is
    tight, and the JSON lists what is."""
    from types import SimpleNamespace

    from payload.envelope.cli import _all_verdict
    from payload.envelope.envelope_figure import figure_title
    from payload.envelope.markdown import envelope_markdown
    from payload.envelope.report_json import envelope_json
    from payload.envelope.verdict import envelope_verdict

    a = narrow_fit
    assert a.passed, a.given.failures()
    parts = {p.name: p for p in a.given.parts}
    assert parts["stage"].clearance == pytest.approx(0.3e-3, abs=1e-7)  # the closed form
    line = envelope_verdict(a)
    assert line.startswith("verdict: fits, tight: every part inside the bays, min clearance 0.30")
    assert "under 0.50 mm" in line and "stage 0.30 mm to the" in line
    reach = SimpleNamespace(  # a reach that passes: only the envelope's words are asked
        workspaces=[], below_vehicle=0.1, samples=1,
        pairs=[SimpleNamespace(name="L", grasps=[
            SimpleNamespace(closes=True, feature=SimpleNamespace(thickness=0.003, name="strap"))
        ])],
    )  # fmt: skip
    both = _all_verdict(a, reach)
    assert both.startswith("verdict: passes: the stowed payload fits, tight (min clearance 0.30 mm")
    assert "under 0.50 mm" in both
    md = envelope_markdown(a, "payload report envelope", "envelope.png")
    assert "**0.30 mm** of clearance" in md and "**A tight fit:**" in md
    assert "under 0.50 mm" in md.split("## Parts")[0]
    assert "(fits, tight: under 0.50 mm; min clearance 0.30 mm;" in figure_title(a.given)
    data = envelope_json(a)
    assert data["passed"] is True and data["tight_clearance_mm"] == 0.5
    tight = {t["part"]: t["clearance_mm"] for t in data["tight"] if "part" in t}
    # every part the JSON measures under 0.5 mm from a wall, and only those
    assert tight == {p["name"]: p["clearance_mm"] for p in data["parts"]
                     if p["inside"] and p["clearance_mm"] < 0.5}  # fmt: skip
    assert tight["stage"] == tight["carriage"] == pytest.approx(0.3, abs=0.01)


def test_a_stowed_fit_with_room_to_spare_is_not_tight_and_a_close_unfolding_is_said(stowed, geom):
    """The committed design: 1.0 mm at its tightest, links 1.06 mm apart stowed: its stowed
    fit is not tight (the figure's title and the JSON's tight parts keep their words). On
    the way to home, though, B_distal passes 0.22 mm from the carriage (the unfolding's
    proof finds it; a dense sweep of that pair's distance along the line, 4,000
    postures, agrees to 0.005 mm): the verdict says so after "deployment path clear"."""
    from payload.envelope.deployment import unfolding_postures
    from payload.envelope.envelope_figure import figure_title
    from payload.envelope.report_json import envelope_json
    from payload.envelope.verdict import envelope_verdict

    a = analyse_envelope(geom, VEHICLE, search=False)
    assert a.passed and stowed.min_clearance >= 0.5e-3
    said = envelope_verdict(a)
    assert said.startswith("verdict: fits: every part inside the bays, min clearance 1.0 mm ")
    assert "tight" not in figure_title(a.given) and envelope_json(a)["tight"] == []
    u = a.given.unfolding
    dense = unfolding_postures(a.given.q, geom.tree.posture("home"), 4000)
    least = min(geom.link_distance(*u.between, geom.poses(q)) for q in dense)
    assert set(u.between) == {"carriage", "B_distal"}
    assert least - 1e-9 <= u.min_distance <= least + 5e-6 and u.min_distance < TIGHT_CLEARANCE
    assert said.endswith(
        f"deployment path clear (tight: {u.between[0]} / {u.between[1]} "
        f"{u.min_distance * 1e3:.2f} mm apart as the fingers unfold)"
    )


def test_links_closer_than_the_tight_clearance_make_a_tight_fit_too(design_dict):
    """A distal link of 46 mm stows in the packaged posture 1.0 mm from every wall, but
    its pad passes 0.28 mm under the stage: tight, said, and still a pass (a home posture
    with the fingers curled: straightening, this distal would brush the carriage)."""
    from payload.envelope.report_json import envelope_json
    from payload.envelope.verdict import envelope_verdict

    data = copy.deepcopy(design_dict)
    data["finger"]["lengths"]["distal"] = 0.046
    data["home"]["finger"] = data["stowed"]["finger"]
    g = geometry_of(data)
    a = analyse_envelope(g, VEHICLE, search=False)
    assert a.passed and a.given.min_clearance == pytest.approx(0.001, abs=1e-6)
    # a second route to the links' distances: the pairwise check on the posed links
    near = {
        frozenset((c.a, c.b)): c.distance
        for c in self_contacts(g, g.poses(a.given.q))
        if c.distance < 0.5e-3
    }
    assert near  # (0.28 mm: stage / A_distal and its three mirror images)
    listed = {frozenset(t["links"]) for t in envelope_json(a)["tight"] if "links" in t}
    assert listed == set(near)
    line = envelope_verdict(a)
    closest = min(near, key=near.get)
    assert line.startswith("verdict: fits, tight: ") and "min clearance 1.0 mm" in line
    assert f"{near[closest] * 1e3:.2f} mm apart" in line


def test_the_search_line_is_a_proposal_that_names_write_stowed() -> None:
    """A failing design's line said "...; passes" under "verdict: FAILS": nothing said the
    search only proposes a posture, nor that --write-stowed applies it."""
    from types import SimpleNamespace

    from payload.envelope.cli_runs import _search_line

    search = SimpleNamespace(finger=[1.6723, -0.2085, 1.3891, 1.8479], clearance=0.06e-3,
                             limited_by="stage / C_distal")  # fmt: skip
    passing = SimpleNamespace(search=search, suggested=SimpleNamespace(passed=True, tight=True))
    line = _search_line(passing)
    assert line.startswith("stowed-posture search: proposes finger [1.6723, -0.2085, 1.3891, "
                           "1.8479] rad, min clearance 0.06 mm (stage / C_distal)")  # fmt: skip
    assert "not applied" in line and "`payload report envelope --write-stowed`" in line
    assert "tight (under 0.50 mm)" in line and "; passes" not in line
    written = _search_line(passing, writing=True)  # --write-stowed's own line follows
    assert "not applied" not in written and written.endswith("; it passes, tight (under 0.50 mm)")
    why = "stage and C_distal collide (0.1 mm deep, 2 mm^3)"
    suggested = SimpleNamespace(passed=False, tight=False, failures=lambda: [why, "another"])
    failing = SimpleNamespace(search=search, suggested=suggested)
    assert "--write-stowed" not in _search_line(failing)
    assert _search_line(failing).endswith(f"; it fails too: {why}")  # its first failure


def test_the_reports_search_section_calls_a_passing_posture_a_proposal(geom):
    import dataclasses

    from payload.envelope.fit_results import PostureSearch
    from payload.envelope.markdown import envelope_markdown

    finger = (1.65, 0.0, 1.40, 1.80)
    q = with_finger_posture(geom.tree.posture("stowed"), finger)
    suggested = check_stowed(geom, VEHICLE, q)
    assert suggested.passed, suggested.failures()
    analysis = dataclasses.replace(
        analyse_envelope(geom, VEHICLE, search=False),
        search=PostureSearch(finger, suggested.min_clearance, "test", 1, 0.0),
        suggested=suggested,
    )
    section = envelope_markdown(analysis, "payload report envelope", "envelope.png")
    section = section.split("## Stowed-posture search")[1].split("## Method")[0]
    assert "A proposal only" in section and "`payload report envelope --write-stowed`" in section


def test_the_design_files_distal_comment_states_the_bound_that_holds(design_dict):
    """The comment said the curled distal stows up to 47.5 mm; with the packaged posture
    47 mm collides. The lengths it names now: the longest that stows in the packaged
    posture does, the one it says collides does."""
    import re

    text = DESIGN.read_text()
    comment = text.split("\ndistal = ", 1)[1].split("\n[", 1)[0]
    up_to = re.search(r"posture below up to (\d+\.\d) mm", comment)
    collides = re.search(r"(\d+\.\d) mm collides", comment)
    assert up_to and collides, comment
    for mm, passes in ((float(up_to[1]), True), (float(collides[1]), False)):
        data = copy.deepcopy(design_dict)
        data["finger"]["lengths"]["distal"] = mm / 1e3
        g = geometry_of(data)
        check = check_stowed(g, VEHICLE, g.tree.posture("stowed"))
        assert check.stows is passes, (mm, check.failures())  # (unfolding: the home's too)
        if not passes:
            assert check.self_collision and any("_distal" in f for f in check.failures())


def _unfolding_contacts(geom, check, per_posture: int) -> dict[tuple[str, str], int]:
    """MuJoCo's contacts (the collision model of the convex pieces and the vehicle body)
    along the fingers and the rail going straight from ``check``'s stowed posture to home
    with the stage down, sampled ``per_posture`` times as finely as the check was."""
    from payload.design.tree import ALL_JOINTS
    from payload.envelope.collisions import CollisionModel

    stowed, home = check.q, geom.tree.posture("home")
    n = per_posture * check.unfolding.samples
    rows = [
        [home[j] if j == "stage" else (1 - s) * stowed[j] + s * home[j] for j in ALL_JOINTS]
        for s in np.linspace(0.0, 1.0, n + 1)
    ]
    return CollisionModel(geom, VEHICLE).check(np.array(rows)).pair_counts()


def _unfolding_case(design_dict, home_finger, distal, postures: int):
    """The design with ``home_finger`` and ``distal`` (None: the packaged), its stowed
    check, and the pairs and the vehicle hits MuJoCo's collision model finds along its
    unfolding sampled at about ``postures`` postures, less the pairs colliding stowed."""
    data = copy.deepcopy(design_dict)
    if home_finger is not None:
        data["home"]["finger"] = list(home_finger)
    if distal is not None:
        data["finger"]["lengths"]["distal"] = distal
    g = geometry_of(data)
    check = check_stowed(g, VEHICLE, g.tree.posture("stowed"))
    contacts = _unfolding_contacts(g, check, -(-postures // check.unfolding.samples))
    stowed_pairs = {frozenset((c.a, c.b)) for c in check.collisions}
    pairs = {frozenset(p) for p in contacts if "vehicle" not in p} - stowed_pairs
    hits = {n for p in contacts if "vehicle" in p for n in p if n != "vehicle"}
    return g, check, pairs, hits


def test_the_unfolding_rates_bound_every_links_point_speed(geom):
    """:func:`unfolding_rates` bounds how fast each link's points move along a straight
    joint-space line (the proof of the unfolding rests on it): on random lines between
    postures within the joints' limits, no convex piece's vertex, nor a point on a pad's
    true sphere, moves faster, by finite differences of the posed points, than its link's
    bound; the carriage, carried by the rail alone, moves exactly at its bound (the
    rail's change)."""
    from payload.envelope.deployment import unfolding_rates

    rng = np.random.default_rng(3)
    joints = [j for j in geom.tree.joints if j.kind != "fixed" and j.name != "stage"]
    down = geom.tree.posture("home")["stage"]
    worst = 0.0
    for _ in range(6):
        a = {j.name: rng.uniform(j.lower, j.upper) for j in joints} | {"stage": down}
        b = {j.name: rng.uniform(j.lower, j.upper) for j in joints} | {"stage": down}
        rate = unfolding_rates(geom, a, b)
        n = 400
        line = [{k: (1 - s) * a[k] + s * b[k] for k in a} for s in np.linspace(0, 1, n + 1)]
        poses = [geom.poses(q) for q in line]
        for link in geom.links:
            local = [geom.hull_vertices(link, np.eye(4))]  # and points of the true spheres
            for piece in geom.pieces[link]:  # (a pad's mesh vertices lie inside its sphere)
                if piece.sphere is not None:
                    u = rng.normal(size=(64, 3))
                    u /= np.linalg.norm(u, axis=1, keepdims=True)
                    local.append(piece.sphere[0] + piece.sphere[1] * u)
            local = np.vstack(local)
            pts = np.array([p[link][:3, :3] @ local.T + p[link][:3, 3:4] for p in poses])
            pts = pts.transpose(0, 2, 1)
            speed = np.linalg.norm(np.diff(pts, axis=0), axis=2).max() * n
            assert speed <= rate[link] * (1 + 1e-9) + 1e-12, (link, speed, rate[link])
            worst = max(worst, speed / rate[link] if rate[link] > 0 else 0.0)
        assert rate["carriage"] == pytest.approx(abs(b["rail"] - a["rail"]), rel=1e-12)
    assert worst == pytest.approx(1.0, rel=1e-9)  # the carriage's: a bound, and a tight one


def test_an_unfolding_not_proved_clear_fails_and_says_why(geom, monkeypatch):
    """A line the proof cannot settle (here: its halving stopped at once, the stretches
    too long to prove) is not clear: the verdict fails naming it, the figure's title says
    the path is not clear, and the hardware's deployment gate refuses the design (it read
    the failures, which had no phrase for it: the gate let it through, the verdict read
    "FAILS: ")."""
    import payload.envelope.deployment as deployment
    from payload.envelope.envelope_figure import figure_title
    from payload.envelope.verdict import envelope_verdict

    monkeypatch.setattr(deployment, "PROOF_MIN_MOTION_M", 1.0)
    a = analyse_envelope(geom, VEHICLE, search=False)
    u = a.given.unfolding
    assert not u.certified and not u.collisions and not u.hits and not u.clear
    said = "deployment: the fingers' unfolding could not be proved contact-free"
    assert a.given.failures() == [said] and not a.passed
    assert envelope_verdict(a) == f"verdict: FAILS: {said}"
    assert "the deployment path is not clear" in figure_title(a.given)
    from firmware_interface.deployment import deployment_cleared
    from firmware_interface.errors import DynamixelError

    with pytest.raises(DynamixelError, match="could not be proved contact-free"):
        deployment_cleared(geom.tree.design)


@pytest.mark.parametrize(
    ("home_finger", "distal"),
    [((0.0, -0.3, 0.0, 0.0), None), (None, 0.060), (None, None)],  # None: the packaged
)
def test_the_unfolding_proof_finds_between_coarse_postures_what_mujoco_finds_densely(
    design_dict, home_finger, distal, monkeypatch
):
    """The unfolding's postures are 1 degree apart, and a contact between two of them was
    not looked for. With the postures 30 degrees and 20 mm apart (four postures on these
    lines, between which every contact is missed: checked here), the proof of the line
    between them still finds the pairs and the vehicle hits MuJoCo's collision model finds
    along the same line sampled at 416 postures, less the pairs colliding stowed; the
    packaged design's line is proved clear."""
    import payload.envelope.deployment as deployment

    monkeypatch.setattr(deployment, "UNFOLD_STEP_RAD", math.radians(30.0))
    monkeypatch.setattr(deployment, "UNFOLD_STEP_M", 0.02)
    g, check, pairs, hits = _unfolding_case(design_dict, home_finger, distal, 416)
    u = check.unfolding
    assert u.samples <= 4 and u.certified
    stowed_pairs = {frozenset((c.a, c.b)) for c in check.collisions}
    assert {frozenset((c.a, c.b)) for c in u.collisions} == pairs
    assert {h.link for h in u.hits} == hits
    collided, deepest = {}, {}  # the four postures alone
    kept = [p for p in g.pairs if frozenset(p) not in stowed_pairs]
    body, moving = deployment._obstacles(g, VEHICLE), [n for n in g.links if n != g.root]
    for q in deployment.unfolding_postures(check.q, g.tree.posture("home"), u.samples):
        deployment._examine(g, q, kept, body, moving, collided, deepest)
    assert not collided and not deepest
    if home_finger is None and distal is None:
        assert not pairs and not hits and u.clear and u.min_distance > 0
    else:
        assert (pairs or hits) and not u.clear


@pytest.mark.parametrize(
    ("home_finger", "distal"),
    [((0.0, -0.3, 0.0, 0.0), None), (None, 0.060), (None, None)],  # None: the packaged
)
def test_the_fingers_unfolding_is_checked_as_mujocos_collision_model_finds_it(
    design_dict, home_finger, distal
):
    """The envelope check lowered the stage with the fingers stowed and stopped there: a
    design whose fingers pass through each other (a home posture abducted -0.3 rad) or
    into the vehicle body (60 mm distal links) on their way from stowed to home passed
    it. The deployment's second half is checked: the link pairs and the vehicle hits it
    names are those MuJoCo's collision model finds along the same motion sampled four
    times as finely, less the pairs already colliding stowed (the stowed check's); the
    packaged design's unfolding is clear."""
    _, check, pairs, hits = _unfolding_case(design_dict, home_finger, distal, 416)
    assert {frozenset((c.a, c.b)) for c in check.unfolding.collisions} == pairs
    assert {h.link for h in check.unfolding.hits} == hits
    said = [f for f in check.failures() if "as the fingers unfold" in f]
    assert len(said) == len(pairs) + len(hits)
    if home_finger is None and distal is None:  # the packaged design
        assert not pairs and not hits and check.passed and check.deploy_clear
    else:
        assert (pairs or hits) and not check.passed and not check.deploy_clear


def test_the_design_review_words_a_tight_clearance_as_the_report_does(narrow_fit):
    """The review said "tightest stage 0.3 mm" where the CLI said 0.30 mm."""
    from payload.review.design_view import legend, title
    from payload.review.project import ProjectFiles

    files = ProjectFiles(DESIGN, ROOT / "urdf" / "payload.urdf", ROOT / "urdf" / "payload.xml")
    _, verdict = title(files, narrow_fit.given)
    assert verdict == "stowed fit: pass; tightest stage 0.30 mm"
    said = [text for _, text in legend({}, reach=False) if text.startswith("tight:")]
    assert said == ["tight: under 0.50 mm to a bay wall or another link (none here)"]


def _drawn_envelope_figure(geom, analysis, monkeypatch, tmp_path):
    """envelope.png of ``analysis`` as :func:`envelope_figure` lays it out and saves it."""
    from matplotlib.figure import Figure

    from payload.envelope.envelope_figure import envelope_figure

    saved = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *args, **kw: saved.append(fig))
    envelope_figure(geom, analysis, tmp_path / "envelope.png")
    (fig,) = saved
    return fig


def _section_patches(fig) -> list[tuple[str, list[tuple[float, ...]], list[tuple[float, ...]]]]:
    """Per section panel: its title, the extents [mm] of its patches filled amber, and of
    its other patches."""
    from matplotlib.colors import to_rgb

    from payload.envelope.drawing import TIGHT_COLOUR

    def extents(patch) -> tuple[float, ...]:
        b = patch.get_path().get_extents(patch.get_patch_transform())
        return tuple(round(float(x), 2) for x in (b.x0, b.y0, b.x1, b.y1))

    out = []
    for ax in fig.axes:
        if "section" in ax.get_title():
            amber = [np.allclose(p.get_facecolor()[:3], to_rgb(TIGHT_COLOUR)) for p in ax.patches]
            drawn = [extents(p) for p in ax.patches]
            out.append((
                ax.get_title(),
                [e for e, is_amber in zip(drawn, amber) if is_amber],
                [e for e, is_amber in zip(drawn, amber) if not is_amber],
            ))  # fmt: skip
    return out


@pytest.mark.parametrize("case", ["walls", "links", "neither"])
def test_envelope_png_draws_the_tight_parts_amber_and_says_so(
    case, narrow_fit, geom, design_dict, monkeypatch, tmp_path
):
    """envelope.png said "fits, tight" in its title but drew nothing tight: the tight
    parts (0.30 mm from a narrowed bay's walls) and the tight pair's links (a 46 mm distal
    0.28 mm under the stage) are now filled amber, the review's colour, in every section
    panel, silhouette and section, and the legend says what amber means; the committed
    design, with room to spare, has no amber and no such entry. Each silhouette is matched
    to its link by the extents of the posed solid (its bounding box seen along the panel's
    axis): every tight link's is amber, every other link's is not, and the amber patches
    left over are at most one section per tight link."""
    from collections import Counter

    from payload.envelope.drawing import AXES
    from payload.envelope.report_json import envelope_json

    if case == "walls":
        g, a = geom, narrow_fit
    elif case == "links":
        data = copy.deepcopy(design_dict)
        data["finger"]["lengths"]["distal"] = 0.046
        # straightening, this distal would brush the carriage: the fingers stay curled
        data["home"]["finger"] = data["stowed"]["finger"]
        g = geometry_of(data)
        a = analyse_envelope(g, VEHICLE, search=False)
    else:
        g, a = geom, analyse_envelope(geom, VEHICLE, search=False)
    assert a.passed
    # what is tight, read from the JSON the report writes
    listed = envelope_json(a)["tight"]
    tight = {t["part"] for t in listed if "part" in t}
    tight |= {n for t in listed if "links" in t for n in t["links"]}
    assert bool(tight) == (case != "neither")
    fig = _drawn_envelope_figure(g, a, monkeypatch, tmp_path)
    poses = g.poses(a.given.q)
    panels = _section_patches(fig)
    assert len(panels) == 3
    sections = 0
    for (title, amber, other), axis in zip(panels, (0, 1, 2)):
        h, v = AXES[axis]
        seen = {True: Counter(), False: Counter()}
        for name in g.links:
            box = np.array(g.posed_solid(name, poses[name]).bounding_box()) * 1e3
            along = (box[h], box[v], box[3 + h], box[3 + v])
            seen[name in tight][tuple(round(float(x), 2) for x in along)] += 1
        for drawn, silhouettes in ((amber, seen[True]), (other, seen[False])):
            rest = Counter(drawn)
            rest.subtract(silhouettes)
            assert min(rest.values(), default=0) >= 0, (title, rest)  # every one drawn
        sections += len(amber) - len(tight)
        assert len(amber) - len(tight) <= len(tight), title
    assert (sections > 0) == (case != "neither")  # tight sections are cut somewhere
    said = [t.get_text() for t in fig.legends[0].get_texts() if t.get_text().startswith("tight")]
    expected = {
        "walls": ["tight: under 0.50 mm to a bay wall"],
        "links": ["tight: under 0.50 mm to another link"],
        "neither": [],
    }
    assert said == expected[case]


@pytest.mark.parametrize(
    ("distal", "bays"), [(0.050, [0.2, 0.0986, 0.1]), (0.046, [0.18, 0.10, 0.085])]
)
def test_a_failing_link_is_never_drawn_amber(
    distal, bays, design_dict, monkeypatch, tmp_path
) -> None:
    """envelope.png filled every tight link amber, failing or not, while the review drew a
    failing link red or magenta: a 50 mm distal in bays 98.6 mm across collides with the
    stage and the carriage, which are tight to the walls; a 46 mm distal in bays
    180 x 100 x 85 mm is tight under the stage, which is outside. A failing link (outside
    the bays, colliding, as the report's JSON lists them, or hit deploying) is now never
    amber in the figure or the review; the other tight links still are, and the legend
    says amber only for them."""
    from payload.envelope.drawing import AXES, TIGHT_COLOUR
    from payload.envelope.report_json import envelope_json
    from payload.review.design_view import part_colours
    from payload.review.model import PayloadModel
    from payload.review.scene import hex_colour

    data = copy.deepcopy(design_dict)
    data["finger"]["lengths"]["distal"] = distal
    # the fingers stay curled at home: the stowed roles alone (straightening, B's and D's
    # distal would brush the carriage, and in the front view a link of finger B has the
    # box of its finger A twin)
    data["home"]["finger"] = data["stowed"]["finger"]
    g = geometry_of(data)
    a = analyse_envelope(g, with_bay_size(VEHICLE, bays), search=False)
    j = envelope_json(a)
    failing = {p["name"] for p in j["parts"] if not p["inside"]}
    failing |= {n for c in j["self_collisions"] for n in c["links"]}
    if not a.given.sweep.vehicle_clear:
        failing |= set(a.given.sweep.between) & set(g.links)
    unfolding = j["deploy_path"]["unfolding"]  # as the fingers unfold to home
    failing |= {n for c in unfolding["collisions"] for n in c["links"]}
    failing |= {h["link"] for h in unfolding["vehicle_hits"]}
    tight = {t["part"] for t in j["tight"] if "part" in t}
    tight |= {n for t in j["tight"] if "links" in t for n in t["links"]}
    assert tight & failing and tight - failing  # failing and tight, and tight only
    fig = _drawn_envelope_figure(g, a, monkeypatch, tmp_path)
    poses = g.poses(a.given.q)
    for (title, amber, _), axis in zip(_section_patches(fig), (0, 1, 2)):
        h, v = AXES[axis]
        for name in g.links:
            box = np.array(g.posed_solid(name, poses[name]).bounding_box()) * 1e3
            along = tuple(round(float(x), 2) for x in (box[h], box[v], box[3 + h], box[3 + v]))
            assert (along in amber) == (name in tight - failing), (title, name)
    said = [t.get_text() for t in fig.legends[0].get_texts() if t.get_text().startswith("tight")]
    assert len(said) == 1
    model = PayloadModel(ROOT / "urdf" / "payload.urdf")  # the same links as the design's
    colours = part_colours(model, a.given)
    amber = {n for n, c in colours.items() if c == hex_colour(TIGHT_COLOUR)}
    assert amber == tight - failing


def test_the_review_draws_a_tight_pairs_links_amber_as_envelope_png_does(design_dict) -> None:
    """envelope.png draws both links of a tight pair amber (a 46 mm distal 0.28 mm under
    the stage), but the design review coloured only the parts tight to a bay wall and
    named only those in its legend: a pair-only tight design looked roomy there. The review
    now colours every link the report's JSON lists as tight, and its legend's amber means
    a bay wall or another link."""
    from payload.envelope.drawing import TIGHT_COLOUR
    from payload.envelope.report_json import envelope_json
    from payload.review.design_view import legend, part_colours
    from payload.review.model import PayloadModel
    from payload.review.scene import hex_colour

    data = copy.deepcopy(design_dict)
    data["finger"]["lengths"]["distal"] = 0.046
    data["home"]["finger"] = data["stowed"]["finger"]  # no straightening past the carriage
    g = geometry_of(data)
    a = analyse_envelope(g, VEHICLE, search=False)
    listed = envelope_json(a)["tight"]
    pairs = {n for t in listed if "links" in t for n in t["links"]}
    walls = {t["part"] for t in listed if "part" in t}
    assert a.passed and pairs - walls, listed  # a pair is tight beyond any wall
    colours = part_colours(PayloadModel(ROOT / "urdf" / "payload.urdf"), a.given)
    amber = {n for n, c in colours.items() if c == hex_colour(TIGHT_COLOUR)}
    assert amber == pairs | walls
    said = [text for _, text in legend(colours, reach=False) if text.startswith("tight:")]
    assert said == ["tight: under 0.50 mm to a bay wall or another link"]


def test_envelope_png_and_the_review_say_the_same_of_red_and_magenta(geom, monkeypatch, tmp_path):
    """envelope.png's legend said "outside the envelope" and "self-collision" where the
    design review's said "fails: outside the bays or hits the vehicle" and "fails: collides
    with another link": the same colours in other words. Each colour envelope.png's legend
    shows in red or magenta now reads as the review's row of that colour does."""
    from matplotlib.colors import to_hex

    from payload.envelope.drawing import COLLISION_COLOUR, FAIL_COLOUR
    from payload.review.design_view import legend

    fig = _drawn_envelope_figure(geom, analyse_envelope(geom, VEHICLE, search=False),
                                 monkeypatch, tmp_path)  # fmt: skip
    handles = fig.legends[0].legend_handles
    texts = [t.get_text() for t in fig.legends[0].get_texts()]
    by_edge = {to_hex(h.get_edgecolor()): t for h, t in zip(handles, texts)}
    review = {colour.lower(): text for colour, text in legend({}, reach=False)}
    for colour in (FAIL_COLOUR, COLLISION_COLOUR):
        ours, theirs = by_edge[to_hex(colour)], review[to_hex(colour)]
        assert theirs.removeprefix("fails: ").startswith(ours), (ours, theirs)
