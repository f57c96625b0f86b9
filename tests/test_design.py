"""The parametric design: validation, solids, tree, URDF/MJCF export, build --check."""

from __future__ import annotations

import copy
import math
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import manifold3d as m3d
import mujoco
import numpy as np
import pinocchio as pin
import pytest
import tomli_w
import tomllib
import trimesh
import yourdfpy
from conftest import DESIGN, MJCF, ROOT, SCENE, URDF, hand_file, replace_once

from payload.design import (
    ALL_JOINTS,
    FINGER_JOINTS,
    FINGERS,
    build_tree,
    design_from_dict,
    generate,
    load_design,
    stale_files,
    write,
)
from payload.design.solids import SEGMENTS
from payload.errors import DesignError
from payload.project import default_design_text


def pin_q(model: pin.Model, values: dict[str, float]) -> np.ndarray:
    q = pin.neutral(model)
    for name, v in values.items():
        q[model.joints[model.getJointId(name)].idx_q] = v
    return q


def mj_values(model: mujoco.MjModel, qpos: np.ndarray) -> dict[str, float]:
    return {model.joint(j).name: float(qpos[model.jnt_qposadr[j]]) for j in range(model.njnt)}


# ---------------------------------------------------------------- models agree


def test_fingertip_and_distal_frames_agree_between_pinocchio_and_mujoco():
    pmodel = pin.buildModelFromUrdf(str(URDF))
    pdata = pmodel.createData()
    mmodel = mujoco.MjModel.from_xml_path(str(MJCF))
    mdata = mujoco.MjData(mmodel)
    rng = np.random.default_rng(1)
    lo, hi = mmodel.jnt_range[:, 0], mmodel.jnt_range[:, 1]
    worst = 0.0
    for _ in range(250):
        mdata.qpos[:] = rng.uniform(lo, hi)
        mujoco.mj_kinematics(mmodel, mdata)
        pin.framesForwardKinematics(pmodel, pdata, pin_q(pmodel, mj_values(mmodel, mdata.qpos)))
        for f in FINGERS:
            for kind in ("tip", "distal"):
                name = f"{f}_{kind}"
                a = pdata.oMf[pmodel.getFrameId(name)].translation
                b = mdata.site(name).xpos
                worst = max(worst, float(np.abs(a - b).max()))
    assert worst < 1e-6


def test_frames_agree_with_the_trees_own_forward_kinematics(design):
    tree = build_tree(design)
    pmodel = pin.buildModelFromUrdf(str(URDF))
    pdata = pmodel.createData()
    rng = np.random.default_rng(2)
    for _ in range(20):
        q = {j.name: rng.uniform(j.lower, j.upper) for j in tree.actuated}
        pin.framesForwardKinematics(pmodel, pdata, pin_q(pmodel, q))
        mine = tree.frame_positions(q)
        for name, p in mine.items():
            np.testing.assert_allclose(pdata.oMf[pmodel.getFrameId(name)].translation, p, atol=1e-9)


def test_joint_limits_in_urdf_and_mjcf_equal_the_design(design):
    expected = {}
    for f in FINGERS:
        for j in FINGER_JOINTS:
            lim = design.finger.limit(j)
            expected[f"{f}_{j}"] = (lim.lower, lim.upper)
    expected["rail"] = (0.0, design.rail.travel)
    expected["stage"] = (0.0, design.stage.travel)
    assert set(expected) == set(ALL_JOINTS)

    robot = yourdfpy.URDF.load(str(URDF), load_meshes=False)
    pmodel = pin.buildModelFromUrdf(str(URDF))
    mmodel = mujoco.MjModel.from_xml_path(str(MJCF))
    for name, (lo, hi) in expected.items():
        uj = robot.joint_map[name]
        assert (uj.limit.lower, uj.limit.upper) == pytest.approx((lo, hi), abs=1e-12)
        idx = pmodel.joints[pmodel.getJointId(name)].idx_q
        assert pmodel.lowerPositionLimit[idx] == pytest.approx(lo, abs=1e-12)
        assert pmodel.upperPositionLimit[idx] == pytest.approx(hi, abs=1e-12)
        assert tuple(mmodel.joint(name).range) == pytest.approx((lo, hi), abs=1e-12)
        act = mmodel.actuator(name)
        assert tuple(act.ctrlrange) == pytest.approx((lo, hi), abs=1e-12)
    assert mmodel.nu == 18


def test_mjcf_follows_menagerie_conventions():
    mmodel = mujoco.MjModel.from_xml_path(str(MJCF))
    visual = [g for g in range(mmodel.ngeom) if mmodel.geom_group[g] == 2]
    collision = [g for g in range(mmodel.ngeom) if mmodel.geom_group[g] == 3]
    assert visual and collision
    assert all(mmodel.geom_contype[g] == 0 and mmodel.geom_conaffinity[g] == 0 for g in visual)
    assert mmodel.key("home").id >= 0
    # every actuator is a position servo on its own joint
    for a in range(mmodel.nu):
        assert mmodel.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT
        assert mmodel.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_AFFINE


def test_servos_carry_the_derived_gains_per_joint_kind(design):
    """MuJoCo's affine bias of each actuator is -kp q - kv qdot with the servo model's kp
    and kv for the joint's kind (finger flexion, abduction, rail, stage)."""
    from payload.design.servo import joint_servo, kind_of

    mmodel = mujoco.MjModel.from_xml_path(str(MJCF))
    for a in range(mmodel.nu):
        js = joint_servo(design, kind_of(mmodel.actuator(a).name))
        kp, kv = -mmodel.actuator_biasprm[a, 1], -mmodel.actuator_biasprm[a, 2]
        assert (kp, kv) == pytest.approx((js.kp, js.kv), rel=1e-5)
        j = mmodel.actuator_trnid[a, 0]
        assert mmodel.dof_armature[mmodel.jnt_dofadr[j]] == pytest.approx(js.armature, rel=1e-5)
    # the force it adds: a joint moving at 2 rad/s onto its set point feels -kp e - kv qdot
    d = mujoco.MjData(mmodel)
    a = mmodel.actuator("A_mcp_flex").id
    js = joint_servo(design, "finger")
    j = mmodel.actuator_trnid[a, 0]
    d.qpos[mmodel.jnt_qposadr[j]] = 0.3
    d.qvel[mmodel.jnt_dofadr[j]] = 2.0
    d.ctrl[a] = 0.25
    mujoco.mj_forward(mmodel, d)
    expected = js.kp * (0.25 - 0.3) - js.kv * 2.0
    assert d.actuator_force[a] == pytest.approx(expected, rel=1e-5)


def test_a_design_written_before_the_servo_model_still_loads(design_dict):
    """The per-joint servo keys of older design files are ignored with a warning, and a
    [servo] table without the new keys takes the packaged default's."""
    data = copy.deepcopy(design_dict)
    data["finger"].update(kp=3.0, kv=0.01, damping=0.03, frictionloss=0.001, armature=8e-4)
    data["rail"].update(kp=3000.0, damping=40.0)
    for key in ("kt", "gains", "armature"):
        del data["servo"][key]
    with pytest.warns(DeprecationWarning, match="finger.damping"):
        old = design_from_dict(data)
    assert old.servo == design_from_dict(design_dict).servo


def test_the_pinch_pre_shape_has_one_source(design_dict, tmp_path):
    """The simulator's scripted pinch and the retargeter's rest posture both read the
    design's ``[pinch]``; a design file written before it existed takes the packaged
    default's; a value outside the joint limits is refused by name."""
    from payload.retarget.hand import load_hand
    from payload.sim.config import WorldConfig
    from payload.sim.grasp import pinch_grasp

    data = copy.deepcopy(design_dict)
    data["pinch"]["finger"] = [-0.3, 0.05, 0.0, 1.0]
    path = tmp_path / "design.toml"
    path.write_text(tomli_w.dumps(data))
    changed = design_from_dict(data)
    assert pinch_grasp(changed, WorldConfig(ctb=None)).open == (-0.3, 0.05, 0.0, 1.0)
    for pair in load_hand(hand_file(tmp_path, URDF, path)).pairs.values():
        assert pair.rest == (-0.3, 0.05, 0.0, 1.0) * 2
    del data["pinch"]
    assert design_from_dict(data).pinch == load_design(DESIGN).pinch
    data["pinch"] = {"finger": [-0.3, 0.0, 0.0, 9.0]}
    with pytest.raises(DesignError, match=r"pinch\.finger.*dip"):
        design_from_dict(data)
    # an older file whose own limits exclude the packaged default is told to add [pinch]
    del data["pinch"]
    data["finger"]["limits"]["dip"] = [0.0, 0.8]
    with pytest.raises(DesignError, match=r"^pinch: missing.*add a \[pinch\] table"):
        design_from_dict(data)


# ---------------------------------------------------------------- mass properties


def test_masses_and_inertias_are_physical():
    pmodel = pin.buildModelFromUrdf(str(URDF))
    for inertia in pmodel.inertias[1:]:
        assert inertia.mass > 0
        eig = np.linalg.eigvalsh(inertia.inertia)
        assert eig.min() > 0
        a, b, c = sorted(eig)
        assert a + b >= c * (1 - 1e-9), "triangle inequality on principal moments"


def test_total_mass_equals_sum_of_parts(design):
    """Independent of trimesh: manifold3d's own volumes, densities and the servo count."""
    tree = build_tree(design)
    expected = 0.0
    n_servos = 0
    for link in tree.links:
        if link.body is None:
            continue
        expected += sum(p.solid.volume() * p.density for p in link.body.parts)
        n_servos += len(link.body.servos)
    assert n_servos == 18  # 16 finger joints, the rail and the stage
    expected += n_servos * design.servo.mass
    mmodel = mujoco.MjModel.from_xml_path(str(MJCF))
    robot = yourdfpy.URDF.load(str(URDF), load_meshes=False)
    urdf_total = sum(link.inertial.mass for link in robot.link_map.values() if link.inertial)
    assert urdf_total == pytest.approx(expected, rel=1e-8)
    assert mmodel.body_subtreemass[0] == pytest.approx(expected, rel=1e-8)
    assert tree.total_mass() == pytest.approx(expected, rel=1e-8)


def test_knuckle_mass_matches_closed_form(design):
    """Box plus the half of the 32-gon cylinder outside it, plus the abduction servo."""
    tree = build_tree(design)
    f = design.finger
    w, d, length = f.section.width, f.section.depth, f.lengths.knuckle
    r = d / 2
    polygon_area = SEGMENTS / 2 * r * r * math.sin(2 * math.pi / SEGMENTS)
    volume = w * d * length + 0.5 * polygon_area * w
    expected = volume * design.materials.finger + design.servo.mass
    assert tree.link_map["A_knuckle"].mass.mass == pytest.approx(expected, rel=1e-6)


# ---------------------------------------------------------------- meshes


def test_committed_meshes_are_watertight():
    meshes = sorted((ROOT / "cad" / "meshes").glob("*.stl"))
    assert len(meshes) == 7
    for path in meshes:
        mesh = trimesh.load(path, force="mesh")
        assert mesh.is_watertight, path.name
        assert mesh.volume > 0, path.name
        # a second library agrees that it is a valid 2-manifold
        solid = m3d.Manifold(
            m3d.Mesh(
                vert_properties=np.asarray(mesh.vertices, dtype=np.float32),
                tri_verts=np.asarray(mesh.faces, dtype=np.uint32),
            )
        )
        assert solid.status() == m3d.Error.NoError, path.name


def test_urdf_loads_with_meshes_in_yourdfpy():
    robot = yourdfpy.URDF.load(str(URDF))
    assert len(robot.actuated_joint_names) == 18
    assert robot.scene is not None
    assert len(robot.scene.geometry) >= 7


# ---------------------------------------------------------------- simulation


def test_scene_compiles_and_steps_with_random_controls_without_warnings():
    model = mujoco.MjModel.from_xml_path(str(SCENE))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    rng = np.random.default_rng(3)
    lo, hi = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
    steps = round(1.0 / model.opt.timestep)
    for i in range(steps):
        if i % 100 == 0:
            data.ctrl[:] = rng.uniform(lo, hi)
        mujoco.mj_step(model, data)
    assert np.all(np.isfinite(data.qpos))
    assert all(w.number == 0 for w in data.warning), [w.number for w in data.warning]


# ---------------------------------------------------------------- parametric change


def _regenerate(design_data: dict, tmp_path: Path) -> pin.Model:
    design = design_from_dict(design_data, source="test")
    write(design, tmp_path)
    return pin.buildModelFromUrdf(str(tmp_path / "urdf" / "payload.urdf"))


def test_lengthening_the_proximal_link_moves_the_fingertip_by_that_amount(design_dict, tmp_path):
    delta = 0.007
    data = copy.deepcopy(design_dict)
    base = _regenerate(data, tmp_path / "a")
    data["finger"]["lengths"]["proximal"] += delta
    longer = _regenerate(data, tmp_path / "b")
    rng = np.random.default_rng(4)
    for _ in range(10):
        values = {"rail": 0.01, "stage": 0.05}
        for f in FINGERS:
            for j, v in zip(FINGER_JOINTS, rng.uniform(-0.3, 1.0, size=4)):
                values[f"{f}_{j}"] = float(v)
        dbase, dlong = base.createData(), longer.createData()
        pin.framesForwardKinematics(base, dbase, pin_q(base, values))
        pin.framesForwardKinematics(longer, dlong, pin_q(longer, values))
        for f in FINGERS:
            tip = base.getFrameId(f"{f}_tip")
            moved = dlong.oMf[tip].translation - dbase.oMf[tip].translation
            # the proximal link's direction: the proximal frame's -z axis in the payload frame
            prox = dbase.oMf[base.getFrameId(f"{f}_proximal")].rotation
            np.testing.assert_allclose(moved, -delta * prox[:, 2], atol=1e-12)
            assert np.linalg.norm(moved) == pytest.approx(delta, abs=1e-12)


def test_straight_finger_length_is_the_sum_of_its_links(design):
    tree = build_tree(design)
    q = tree.posture("home")
    q.update({f"{f}_{j}": 0.0 for f in FINGERS for j in FINGER_JOINTS})
    pos = tree.link_poses(q)
    tips = tree.frame_positions(q)
    L = design.finger.lengths
    for f in FINGERS:
        mcp = pos[f"{f}_knuckle"][:3, 3]
        assert mcp[2] - tips[f"{f}_tip"][2] == pytest.approx(
            L.knuckle + L.proximal + L.middle + L.distal, abs=1e-12
        )


# ---------------------------------------------------------------- validation


def _edit(data: dict, path: str, value) -> dict:
    out = copy.deepcopy(data)
    *parents, leaf = path.split(".")
    node = out
    for key in parents:
        node = node[key]
    if value is _DELETE:
        del node[leaf]
    else:
        node[leaf] = value
    return out


_DELETE = object()

INVALID = [
    ("finger.lengths.proximal", -0.01, "finger.lengths.proximal", "positive"),
    ("finger.lengths.distal", 0.0, "finger.lengths.distal", "positive"),
    ("finger.limits.pip", [1.0, 0.5], "finger.limits.pip", "lower limit"),
    ("rail.travel", 0.2, "rail.travel", "longer than the rail"),
    ("finger.section.width", 0.015, "servo.width", "does not fit"),
    ("finger.section.depth", 0.02, "servo.height", "does not fit"),
    ("finger.lengths.knuckle", 0.02, "servo.length", "does not fit"),
    ("finger.lengths.bogus", 0.02, "finger.lengths.bogus", "unknown key (expected one of"),
    ("finger.lengths.distl", 0.02, "finger.lengths.distl", "unknown key (did you mean distal?"),
    ("stage.travel", _DELETE, "stage.travel", "missing key"),
    ("materials.finger", "heavy", "materials.finger", "expected a number"),
    ("stage.travel", 0.2, "stage.travel", "guide columns"),
]


@pytest.mark.parametrize(("path", "value", "named", "reason"), INVALID)
def test_invalid_designs_are_rejected_naming_the_parameter(design_dict, path, value, named, reason):
    with pytest.raises(DesignError) as info:
        design_from_dict(_edit(design_dict, path, value))
    assert info.value.parameter == named
    assert reason in str(info.value)


@pytest.mark.parametrize(
    ("path", "toml", "named", "says"),
    [
        ("finger.lengths.distal", "true", "finger.lengths.distal", "expected a number, got true"),
        ("finger.lengths.distal", '"45 mm"', "finger.lengths.distal", 'got "45 mm"'),
        ("finger.limits.pip", "[0, false]", "finger.limits.pip", "got [0, false]"),
        ("vehicle.mass", "true", "vehicle.mass", "expected a number, got true"),
        ("vehicle.mass", "-9.5", "vehicle.mass", "must be a positive, finite number (got -9.5)"),
        ("vehicle.bay_size", "[0.2, true, 0.1]", "vehicle.bay_size", "got [0.2, true, 0.1]"),
        ("vehicle.inertia", "[0.15, 0, 0.16]", "vehicle.inertia",
         "every principal moment of inertia must be positive (got 0"),
    ],
)  # fmt: skip
def test_a_wrong_value_is_named_as_the_design_file_spells_it(tmp_path, path, toml, named, says):
    """What a design file holds is quoted in TOML (``true``, ``"45 mm"``), not Python's
    ``True`` and ``'45 mm'``; a mass is not called a size. The file is written and read
    as a designer's is."""
    lines = Path(DESIGN).read_text().splitlines()  # a designer's file: comments and all
    *parents, key = path.split(".")
    table = "[" + ".".join(parents) + "]"
    start = next(i for i, line in enumerate(lines) if line.split("#")[0].strip() == table)
    at = next(i for i in range(start + 1, len(lines)) if lines[i].split("=")[0].strip() == key)
    assert not any(line.startswith("[") for line in lines[start + 1 : at])  # in the table
    lines[at] = f"{key} = {toml}"
    design = tmp_path / "design.toml"
    design.write_text("\n".join(lines) + "\n")
    with pytest.raises(DesignError) as info:
        load_design(design)
    assert info.value.parameter == named
    assert says in str(info.value), str(info.value)
    if "size" not in path:  # an inertia or a mass is not called a size (the message said)
        assert "size" not in str(info.value), str(info.value)


def test_cli_prints_one_line_and_exits_2_on_an_invalid_design(design_dict, tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(tomli_w.dumps(_edit(design_dict, "finger.lengths.middle", -0.002)))
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "payload.cli",
            "build",
            "--design",
            str(bad),
            "--root",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1
    assert "finger.lengths.middle" in lines[0] and "positive" in lines[0]


# ---------------------------------------------------------------- plausibility (issue 30)

PLAUSIBILITY = [  # edit, the parameter named, what the one line must say
    ("finger.lengths.distal", 45, "finger.lengths.distal", "45 m: did you mean 45 mm = 0.045?"),
    ("finger.lengths.middle", 0.005, "finger.lengths.middle", "cannot hold the servos"),
    ("finger.lengths.proximal", 0.005, "finger.lengths.proximal", "cannot hold the servos"),
    ("servo.mass", 23, "servo.mass", "23 kg: did you mean 23 g = 0.023? (23 kg is heavier"),
    ("rail.length", 0.5, "rail.length", "longer than the vehicle"),
    ("finger.offsets.tip", 0.05, "finger.offsets.tip", "outside its link"),
    ("finger.lengths.distal", 0.012, "finger.lengths.distal", "cannot hold the DIP servo"),
    ("finger.lengths.proximal", 1e-6, "finger.lengths.proximal", "0.001 mm cannot hold"),
    # a thousandth of the packaged value: the slip the other way, named before the bounds
    # it breaks further on (a section this thin put the tip offset "outside its link")
    ("finger.lengths.proximal", 2.45e-5, "finger.lengths.proximal",
     "2.45e-05 m = 0.0245 mm is about a thousandth of its packaged value (24.5 mm): did you "
     "mean 0.0245?"),
    ("finger.section.depth", 2.8e-5, "finger.section.depth", "(28.0 mm): did you mean 0.028?"),
    ("servo.length", 3.4e-5, "servo.length", "(34.0 mm): did you mean 0.034?"),
    ("finger.pad.thickness", 3e-6, "finger.pad.thickness", "(3.0 mm): did you mean 0.003?"),
    ("servo.mass", 2.3e-5, "servo.mass", "0.023 g is about a thousandth of its packaged value "
     "(23 g): did you mean 0.023? (the design file is in kg)"),
    # the vehicle's own sizes, which the bounds above are taken from; angles in degrees
    ("vehicle.bay_size", [200, 100, 100], "vehicle.bay_size",
     "[200, 100, 100] m: did you mean [200, 100, 100] mm = [0.2, 0.1, 0.1]?"),
    ("vehicle.mass", 9583.8, "vehicle.mass", "9583.8 kg: did you mean 9583.8 g = 9.5838?"),
    ("finger.limits.mcp_flex", [-18, 127.8], "finger.limits.mcp_flex",
     "[-18, 127.8] rad: did you mean [-0.314, 2.231] (degrees given)?"),
    ("home.rail", 25, "home.rail", "25 m: did you mean 25 mm = 0.025?"),
    # a pad modulus in MPa (the silicone's 1 MPa typed as 1.0), or far beyond any pad's
    ("finger.pad.modulus", 1.0, "finger.pad.modulus",
     "1 Pa is softer than any pad material (1000 to 1e+10 Pa, a gel to a hard plastic): did "
     "you mean 1 MPa = 1e+06? (the design file is in Pa)"),
    ("finger.pad.modulus", 2e11, "finger.pad.modulus", "2e+11 Pa is stiffer than any pad"),
]  # fmt: skip


@pytest.mark.parametrize(("path", "value", "named", "says"), PLAUSIBILITY)
def test_an_implausible_design_gives_one_line_naming_the_parameter_and_exit_2(
    design_dict, tmp_path, capsys, path, value, named, says
):
    from payload.cli import main

    bad = tmp_path / "bad.toml"
    bad.write_text(tomli_w.dumps(_edit(design_dict, path, value)).replace("45.0", "45"))
    assert main(["build", "--design", str(bad), "--root", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"payload: error: {named}: ")
    assert says in err[0]
    assert not (tmp_path / "out").exists()


def test_an_exact_fit_fits_and_a_micrometre_more_does_not(design_dict):
    """The rail's travel plus its carriage exactly the rail's length fits (0.054 + 0.05
    is 0.10400000000000001 in binary and was refused as longer than 0.104); a micrometre
    more does not. The guide columns on the plate and the distal link's least length
    compare the same way."""
    rail = design_dict["rail"]
    typed = round(rail["length"] - rail["carriage_length"], 6)  # the decimal one types
    assert typed + rail["carriage_length"] > rail["length"]  # the rounding that bit (premise)
    design_from_dict(_edit(design_dict, "rail.travel", typed))
    with pytest.raises(DesignError, match="longer than the rail"):
        design_from_dict(_edit(design_dict, "rail.travel", typed + 1e-6))


def test_a_retargeting_margin_in_mm_is_a_unit_slip(design_dict):
    """``retarget.collision_margin = 2`` (meant 2 mm) built silently: it is a length like
    the design's others, refused with the slip named."""
    with pytest.raises(DesignError, match=r"2 m: did you mean 2 mm = 0\.002\?"):
        design_from_dict(_edit(design_dict, "retarget.collision_margin", 2))


def test_a_coordinate_offset_or_gap_near_zero_is_no_unit_slip(design_dict):
    """The "thousandth of its default" slip is a size's (a field that must be positive):
    a coordinate, an offset or a gap may be zero, and a value near it (a thousandth of its
    default, of either sign) builds as zero does; a sweep across zero had holes at
    +-0.0002 (array.a_x, default -0.066)."""
    for path in ("array.a_x", "finger.offsets.tip", "stage.stowed_gap"):
        default = design_dict
        for part in path.split("."):
            default = default[part]
        for value in (0.0, default / 1000, abs(default) / 500):
            design_from_dict(_edit(design_dict, path, value))
    with pytest.raises(DesignError, match="about a thousandth"):  # a size, the same ratio
        design_from_dict(_edit(design_dict, "servo.length", design_dict["servo"]["length"] / 1e3))


def test_the_bounds_come_from_the_design_itself(design_dict):
    """A link exactly one servo width long holds its servos, a hair shorter does not; a
    bigger servo raises the bound; a bigger vehicle admits a longer part."""
    width = design_dict["servo"]["width"]
    design_from_dict(_edit(design_dict, "finger.lengths.middle", width))
    with pytest.raises(DesignError, match="cannot hold"):
        design_from_dict(_edit(design_dict, "finger.lengths.middle", width * 0.99))
    wider = _edit(_edit(design_dict, "servo.width", 0.022), "finger.lengths.middle", 0.021)
    with pytest.raises(DesignError, match=r"22\.0 mm between the axes"):
        design_from_dict(wider)
    long_rail = _edit(design_dict, "rail.length", 0.33)
    with pytest.raises(DesignError, match="Astrobee's body is 320 mm"):
        design_from_dict(long_rail)
    design_from_dict(_edit(long_rail, "vehicle", {"body_size": [0.4, 0.4, 0.4]}))


def _packaged(dotted: str) -> Any:
    """A value of the packaged default design (``payload new``'s)."""
    value: Any = tomllib.loads(default_design_text())
    for part in dotted.split("."):
        value = value[part]
    return value


def _meant(message: str) -> Any:
    """The value a refusal's "did you mean X?" suggests, read as a design file reads it."""
    found = re.search(
        r"did you mean (?:.* = )?(\[[^\]]*\]|[-0-9.e]+)(?: \(degrees given\))?\?", message
    )
    assert found, message
    return tomllib.loads(f"x = {found.group(1)}")["x"]


@pytest.mark.parametrize("key", ["body_size", "bay_size", "mass", "inertia"])
@pytest.mark.parametrize("factor", [1000, 1 / 1000])
def test_a_unit_slip_in_the_vehicle_table_names_the_packaged_value_meant(design_dict, key, factor):
    """``vehicle.body_size = [320, 320, 320]`` (mm typed for metres) built, and every other
    bound, taken from the vehicle, let a 45 m finger through after it; a thousandth of a
    size (a conversion made twice) named another parameter. Both are refused first, naming
    the vehicle's key, and what they suggest is the packaged value and builds."""
    packaged = _packaged(f"vehicle.{key}")
    typed = [v * factor for v in packaged] if isinstance(packaged, list) else packaged * factor
    with pytest.raises(DesignError) as info:
        design_from_dict(_edit(design_dict, f"vehicle.{key}", typed))
    assert info.value.parameter == f"vehicle.{key}", str(info.value)
    assert ("about a thousandth" in str(info.value)) == (factor < 1), str(info.value)
    meant = _meant(str(info.value))
    assert meant == pytest.approx(packaged)
    design_from_dict(_edit(design_dict, f"vehicle.{key}", meant))


def test_a_vehicle_slip_is_named_before_the_bounds_it_would_widen(design_dict):
    """A vehicle a thousand times too large admitted a 45 m finger and a 23 kg servo; the
    vehicle is named, whatever else the file holds. The bay size the file's refusal
    suggests is the one ``--bay-size`` suggests for the same sizes."""
    from payload.design.vehicle import Vehicle, with_bay_size

    big_body = _edit(design_dict, "vehicle.body_size", [320, 320, 320])
    with pytest.raises(DesignError) as info:
        design_from_dict(_edit(big_body, "finger.lengths.distal", 45))
    assert info.value.parameter == "vehicle.body_size"
    heavy = _edit(design_dict, "vehicle.mass", 1000 * _packaged("vehicle.mass"))
    with pytest.raises(DesignError) as info:
        design_from_dict(_edit(heavy, "servo.mass", 23))
    assert info.value.parameter == "vehicle.mass"
    typed = [200, 100, 100]
    with pytest.raises(DesignError) as file_said:
        design_from_dict(_edit(design_dict, "vehicle.bay_size", typed))
    with pytest.raises(DesignError) as option_said:
        with_bay_size(Vehicle(), typed)
    option = re.search(r"--bay-size ([0-9. ]+)\?", str(option_said.value))
    assert option, str(option_said.value)
    assert _meant(str(file_said.value)) == [float(v) for v in option.group(1).split()]


@pytest.mark.parametrize("joint", FINGER_JOINTS)
def test_joint_limits_in_degrees_are_refused_with_the_radians_meant(design_dict, joint):
    """``mcp_flex = [-18, 127.8]`` built, and the summary showed -1031.3 deg .. 7322.4 deg:
    no finger joint turns more than a turn, and a limit beyond one was typed in degrees."""
    typed = [round(math.degrees(v), 1) for v in _packaged(f"finger.limits.{joint}")]
    with pytest.raises(DesignError) as info:
        design_from_dict(_edit(design_dict, f"finger.limits.{joint}", typed))
    assert info.value.parameter == f"finger.limits.{joint}"
    assert "(degrees given)" in str(info.value)
    assert _meant(str(info.value)) == pytest.approx([math.radians(v) for v in typed], abs=5e-4)


def test_a_limit_within_a_turn_is_no_degrees_slip(design_dict):
    """The line is one turn: a limit just inside it is radians (and refused, if at all, for
    something else), just outside it is degrees."""
    design_from_dict(_edit(design_dict, "finger.limits.mcp_abd", [-6.28, 6.28]))
    with pytest.raises(DesignError, match=r"\(degrees given\)"):
        design_from_dict(_edit(design_dict, "finger.limits.mcp_abd", [-6.29, 6.29]))


@pytest.mark.parametrize(
    ("posture", "degrees"),
    [
        ("stowed.finger", None),  # the packaged stowed posture, in degrees
        ("pinch.finger", None),
        ("home.finger", [0, 0, 30, 10]),  # the packaged home posture is straight: zeros
    ],
)
def test_a_posture_in_degrees_is_refused_with_the_radians_meant(design_dict, posture, degrees):
    """``stowed.finger = [95, 0, 80.1, 103.4]`` said "95.0 rad is outside its limits" with
    no word of the degrees it was typed in."""
    typed = degrees or [round(math.degrees(v), 1) for v in _packaged(posture)]
    with pytest.raises(DesignError) as info:
        design_from_dict(_edit(design_dict, posture, typed))
    assert info.value.parameter == posture
    assert "(degrees given)" in str(info.value) and "is outside finger.limits." in str(info.value)
    meant = _meant(str(info.value))
    assert meant == pytest.approx([math.radians(v) for v in typed], abs=5e-4)
    design_from_dict(_edit(design_dict, posture, meant))


def test_a_posture_joint_outside_its_limits_names_them(design_dict) -> None:
    """A new user's ``stowed.finger`` with a DIP of 3.0 rad was refused as "dip = 3.0 rad
    is outside its limits", with no word of what they are: the refusal names the design's
    own limits and where they are set."""
    lower, upper = design_dict["finger"]["limits"]["dip"]
    posture = [*_packaged("stowed.finger")[:3], upper + 0.5]
    with pytest.raises(DesignError) as info:
        design_from_dict(_edit(design_dict, "stowed.finger", posture))
    assert info.value.parameter == "stowed.finger"
    assert f"dip = {upper + 0.5} rad is outside finger.limits.dip [{lower}, {upper}]" in str(
        info.value
    ), info.value


@pytest.mark.parametrize("position", ["home.rail", "home.stage"])
def test_a_posture_position_in_mm_is_refused_with_the_metres_meant(design_dict, position):
    """``home.rail = 25`` said "25.0 m is outside [0, 0.05]"; it names the slip, and a
    position just past its travel (no slip) is refused without a hint."""
    packaged = _packaged(position)
    with pytest.raises(DesignError) as info:
        design_from_dict(_edit(design_dict, position, 1000 * packaged))
    assert info.value.parameter == position
    assert _meant(str(info.value)) == pytest.approx(packaged)
    travel = _packaged(position.replace("home", "").strip(".") + ".travel")
    with pytest.raises(DesignError) as info:
        design_from_dict(_edit(design_dict, position, 1.2 * travel))
    assert "outside" in str(info.value) and "did you mean" not in str(info.value)


def test_an_empty_design_file_says_it_is_empty(tmp_path, capsys):
    from payload.cli import main

    for text in ("", "# nothing but a comment\n"):
        empty = tmp_path / "design.toml"
        empty.write_text(text)
        assert main(["summary", "--design", str(empty)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(
            f"payload: error: {empty}: the design file is empty"
        )


def test_unreadable_and_malformed_files_are_design_errors(tmp_path):
    with pytest.raises(DesignError, match="cannot read"):
        load_design(tmp_path / "missing.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("[finger\nlength = ")
    with pytest.raises(DesignError, match="not valid TOML"):
        load_design(broken)
    # the committed design saved with a byte-order mark (as some Windows editors save):
    # named as such, not "Invalid statement (at line 1, column 1)"
    marked = tmp_path / "bom.toml"
    marked.write_bytes(b"\xef\xbb\xbf" + DESIGN.read_bytes())
    with pytest.raises(DesignError, match="starts with a byte-order mark"):
        load_design(marked)


# ---------------------------------------------------------------- build


def test_generation_is_deterministic(design):
    _, first = generate(design)
    _, second = generate(load_design(DESIGN))
    assert first == second


def test_build_check_passes_on_the_committed_files(design):
    assert stale_files(design, ROOT) == []
    proc = subprocess.run(
        [sys.executable, "-m", "payload.cli", "build", "--check"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr


def test_build_check_fails_after_a_design_edit(design_dict, tmp_path):
    edited = tmp_path / "edited.toml"
    edited.write_text(tomli_w.dumps(_edit(design_dict, "finger.lengths.middle", 0.040)))
    proc = subprocess.run(
        [sys.executable, "-m", "payload.cli", "build", "--check", "--design", str(edited)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1
    stale = lines[0].split("stale: ")[1].split(" (")[0].split(", ")
    assert set(stale) == {"urdf/payload.urdf", "urdf/payload.xml", "cad/meshes/finger_middle.stl"}
    # a design that is not the project's: `payload build` would not make its models match
    # (it builds the project's own), so the line does not tell to run it
    assert "run `payload build`" not in lines[0]
    assert lines[0].endswith(
        "it is not a project's design, and the project's models follow its own "
        "cad/design.toml: give it a project of its own to build it)"
    ), lines[0]


def test_stale_extra_mesh_is_reported(design, tmp_path):
    write(design, tmp_path)
    assert stale_files(design, tmp_path) == []
    (tmp_path / "cad" / "meshes" / "old_part.stl").write_bytes(b"x")
    (tmp_path / "urdf" / "payload.urdf").write_text("edited")
    assert stale_files(design, tmp_path) == ["urdf/payload.urdf", "cad/meshes/old_part.stl"]


def test_build_says_which_meshes_it_removed(tmp_path, capsys):
    """``payload build`` removes the meshes no part of the design makes (a renamed or
    dropped part's) and says so; a build with none to remove says nothing of it."""
    from payload.cli import main

    root = tmp_path / "p"
    (root / "cad").mkdir(parents=True)
    (root / "cad" / "design.toml").write_bytes(Path(DESIGN).read_bytes())
    assert main(["build", "--project", str(root)]) == 0
    assert "removed" not in capsys.readouterr().out
    (root / "cad" / "meshes" / "old_part.stl").write_bytes(b"x")
    assert main(["build", "--project", str(root)]) == 0
    out = capsys.readouterr().out
    assert "removed cad/meshes/old_part.stl (no part of the design makes it)" in out
    assert not (root / "cad" / "meshes" / "old_part.stl").exists()


def test_build_says_how_many_files_it_wrote_and_leaves_matching_ones_alone(tmp_path, capsys):
    """A first build writes every file; a second finds them all matching the design and
    says it wrote none (their modification times unchanged); a damaged model is the one
    file the next build writes."""
    from payload.cli import main

    root = tmp_path / "p"
    (root / "cad").mkdir(parents=True)
    (root / "cad" / "design.toml").write_bytes(Path(DESIGN).read_bytes())
    assert main(["build", "--project", str(root)]) == 0
    made = sorted(p for p in root.rglob("*") if p.is_file() and p.name != "design.toml")
    first = capsys.readouterr().out
    assert f"wrote {len(made)} of {len(made)} files under {root}" in first

    def stamps() -> dict[Path, tuple[int, int]]:  # a rewrite renames a new file into place
        return {p: (p.stat().st_ino, p.stat().st_mtime_ns) for p in made}

    before = stamps()
    assert main(["build", "--project", str(root)]) == 0
    assert f"the {len(made)} generated files under {root} already match" in capsys.readouterr().out
    assert stamps() == before
    (root / "urdf" / "payload.urdf").write_text("edited")
    assert main(["build", "--project", str(root)]) == 0
    out = capsys.readouterr().out
    assert f"wrote 1 of {len(made)} files under {root}" in out
    assert f"the other {len(made) - 1} already matched it" in out
    assert "<robot" in (root / "urdf" / "payload.urdf").read_text()


# ---------------------------------------------------------------- stale models (issue 30)

MODEL_READERS = {  # every command that reads the generated models -> its handler
    "report envelope": ("payload.envelope.cli_runs", "run_envelope"),
    "report reach": ("payload.envelope.cli_runs", "run_reach"),
    "report all": ("payload.envelope.cli", "_cmd_all"),
    "review": ("payload.review.cli", "_cmd_review"),
    "trial": ("payload.trials.cli", "_cmd_trial"),
    "trials run": ("payload.trials.cli", "_cmd_trials_run"),
    "bench retarget": ("payload.retarget.cli", "_cmd_bench"),
    "bench sim": ("payload.sim.cli", "_cmd_bench_sim"),
    "bench trial": ("payload.trials.bench_cli", "_cmd_bench_trial"),
    "bench start": ("payload.trials.bench_cli", "_cmd_bench_start"),  # its starts read them
    "bench teleop": ("payload.teleop.cli", "bench"),
    "teleop serve": ("payload.teleop.cli", "serve"),
    "sweep": ("payload.sweep.cli", "_cmd_sweep"),
    "hw run": ("firmware_interface.cli", "_cmd_run"),
    "hw scan": ("firmware_interface.cli", "_cmd_scan"),  # the driver's guard reads the URDF
    "hw check": ("firmware_interface.cli", "_cmd_check"),
    "hw identify": ("firmware_interface.cli", "_cmd_identify"),
    "bench hw": ("firmware_interface.cli", "_cmd_bench"),
    "bench filter": ("payload.teleop.cli", "bench_filter"),  # flies the project's MJCF
    "bench reach": ("payload.envelope.cli", "_cmd_bench_reach"),
}
MODEL_FREE = {  # every other command, and why the rule is not its
    "new": "makes a project (its models built by its own build)",
    "build": "is the rule itself: it regenerates the models",
    "summary": "reads the design file, not the models",
    "bench recorder": "writes synthetic steps, no model",
    "trials summarize": "reads recordings and metrics",
    "trials compare": "reads recordings and metrics",
    "trials convert": "rewrites schema-1 recordings; its world refuses a stale model",
    "export lerobot": "reads recordings",
    "hw emulate": "serves the design's servo model, not the generated models",
}


def test_every_command_is_a_model_reader_or_says_why_not():
    """A command added without a place in either table fails here (the hardware commands
    once read a stale URDF unnoticed, because nothing listed them)."""
    import argparse

    from payload.cli import build_parser

    def leaves(parser: argparse.ArgumentParser, path: str = ""):
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            yield path.strip()
        for action in subs:
            for name, child in action.choices.items():
                yield from leaves(child, f"{path} {name}")

    commands = set(leaves(build_parser()))
    assert not set(MODEL_READERS) & set(MODEL_FREE)
    assert commands == set(MODEL_READERS) | set(MODEL_FREE)


def test_every_command_reading_the_models_applies_the_one_rule():
    import importlib
    import inspect

    for command, (module, name) in MODEL_READERS.items():
        source = inspect.getsource(getattr(importlib.import_module(module), name))
        assert "models_follow_design(" in source or "_models_follow(" in source, command


def test_stale_models_are_rebuilt_saying_so(tmp_path, capsys):
    from payload.design import models_follow_design, stale_files
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    assert models_follow_design(project.design_path, project.root) == []
    assert capsys.readouterr().out == ""  # models that match: nothing to say
    text = project.design_path.read_text()
    project.design_path.write_text(replace_once(text, "middle = 0.0361 ", "middle = 0.0400 "))
    expected = stale_files(load_design(project.design_path), project.root)
    assert expected  # the edit made the models stale
    assert models_follow_design(project.design_path, project.root, json=True) == expected
    out = capsys.readouterr()
    assert out.out == ""  # --json: stdout keeps its one object; the line goes to stderr
    assert out.err.startswith("models: rebuilt ") and expected[0] in out.err
    assert stale_files(load_design(project.design_path), project.root) == []
    # an invalid design rebuilds nothing: the models stay those of the last valid design
    before = {p: p.read_bytes() for p in project.urdf_dir.iterdir()}
    project.design_path.write_text(replace_once(text, "middle = 0.0361 ", "middle = 0.005 "))
    with pytest.raises(DesignError, match=r"finger\.lengths\.middle"):
        models_follow_design(project.design_path, project.root)
    assert {p: p.read_bytes() for p in project.urdf_dir.iterdir()} == before

    # a mesh no part makes (one put there by hand) is removed, and the line says removed,
    # not rebuilt, with the rebuilt files on a line of their own
    project.design_path.write_text(text)
    mine = project.root / "cad" / "meshes" / "my_bracket.stl"
    mine.write_text("solid mine\n")
    rebuilt = stale_files(load_design(project.design_path), project.root)
    assert "cad/meshes/my_bracket.stl" in rebuilt and len(rebuilt) > 1
    models_follow_design(project.design_path, project.root)
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and lines[0].startswith("models: rebuilt ")
    assert "my_bracket" not in lines[0]
    assert lines[1].startswith("models: removed cad/meshes/my_bracket.stl (no part of ")
    assert not mine.exists()


def test_bench_filter_flies_models_that_follow_the_design(tmp_path, capsys, monkeypatch):
    """``bench filter`` builds the world from the project's MJCF: stale models are rebuilt
    (saying so) before the world is built, not flown with the new design's servos."""
    import payload.teleop.bench as teleop_bench
    from payload.cli import main
    from payload.design import stale_files
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    text = project.design_path.read_text()
    project.design_path.write_text(replace_once(text, "middle = 0.0361 ", "middle = 0.0400 "))
    capsys.readouterr()
    seen = []

    def bench(seconds):
        seen.append(stale_files(load_design(project.design_path), project.root))
        return {"steps": 1, "active_steps": 0, "median_us": 1.0, "p99_us": 1.0,
                "constraints": 0, "load": [0.0, 0.0, 0.0]}  # fmt: skip

    monkeypatch.setattr(teleop_bench, "run_filter_bench", bench)
    assert main(["--project", str(project.root), "bench", "filter", "--seconds", "1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"project: {project.root}" and lines[1].startswith("models: rebuilt ")
    assert seen == [[]]


def test_part_mass_properties_from_the_cache_are_trimeshs_own(design):
    """The cached figures equal trimesh's computed afresh, first run and cached run alike."""
    from payload.design.solids import part_props
    from payload.design.tree import build_tree

    tree = build_tree(design)
    parts = [p for link in tree.links if link.body is not None for p in link.body.parts][:4]
    for part in parts:
        tm = trimesh.Trimesh(
            vertices=np.asarray(part.solid.to_mesh().vert_properties)[:, :3].astype(float),
            faces=np.asarray(part.solid.to_mesh().tri_verts).astype(np.int64),
            process=False,
        )
        for _ in range(2):  # computed (and kept), then read from the cache
            props = part_props(part)
            assert props.mass == tm.volume * part.density
            assert np.array_equal(props.com, tm.center_mass)
            assert np.array_equal(props.inertia, tm.moment_inertia * part.density)


def test_fresh_models_skip_the_rebuild_and_any_edit_is_rebuilt(tmp_path, design_dict, monkeypatch):
    """The fingerprint spares the rebuild only while every generated file is unchanged."""
    import payload.design.build as build
    from payload.design.follow import models_follow_design

    path = tmp_path / "cad" / "design.toml"
    path.parent.mkdir(parents=True)
    design_dict = copy.deepcopy(design_dict)
    path.write_text(tomli_w.dumps(design_dict))
    assert "urdf/payload.urdf" in models_follow_design(path, tmp_path)
    calls = []
    real = build.follow_design
    monkeypatch.setattr(build, "follow_design", lambda *a, **k: calls.append(1) or real(*a, **k))
    assert models_follow_design(path, tmp_path) == [] and calls == []  # fingerprint: fresh
    urdf = tmp_path / "urdf" / "payload.urdf"
    urdf.write_text(urdf.read_text() + " ")
    assert models_follow_design(path, tmp_path) == ["urdf/payload.urdf"] and len(calls) == 1
    stray = tmp_path / "cad" / "meshes" / "stray.stl"
    stray.write_bytes(b"")
    assert models_follow_design(path, tmp_path) == ["cad/meshes/stray.stl"] and len(calls) == 2
    assert not stray.exists()
    design_dict["finger"]["lengths"]["distal"] = 0.044
    path.write_text(tomli_w.dumps(design_dict))
    rebuilt = models_follow_design(path, tmp_path)
    assert "urdf/payload.urdf" in rebuilt and len(calls) == 3
