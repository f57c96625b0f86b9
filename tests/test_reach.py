"""Reach report: shared kinematics, spans, rail spacing, collisions, grasp witnesses, CLI.

Numbers are checked against a second library (Pinocchio on the URDF, python-fcl),
brute force over a coarse grid, or closed forms of the design."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
import time

import numpy as np
import pinocchio as pin
import pytest
from conftest import ROOT, URDF
from scipy import optimize

from payload.design import (
    ALL_JOINTS,
    FINGER_JOINTS,
    FINGERS,
    build_tree,
    design_from_dict,
    design_to_dict,
    load_design,
)
from payload.envelope import PayloadGeometry, Vehicle
from payload.envelope.geometry import box_geometry, signed_distance
from payload.envelope.reach import (
    PAIRS,
    CollisionModel,
    GraspFeature,
    analyse_reach,
    design_kinematics,
    finger_link_names,
    fingertips,
    opposition,
    rail_spacing,
    sample_configurations,
    span_range,
    workspace,
)
from payload.envelope.sampling import frame_positions
from payload.retarget import PairKinematics, pair_range

VEHICLE = Vehicle()


def run_cli(*args: str) -> subprocess.CompletedProcess:
    main = "import sys; from payload.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run(
        [sys.executable, "-c", main, *args], capture_output=True, text=True, cwd=ROOT, timeout=300
    )


@pytest.fixture(scope="module")
def tree(design):
    return build_tree(design)


@pytest.fixture(scope="module")
def geom(tree) -> PayloadGeometry:
    return PayloadGeometry(tree)


@pytest.fixture(scope="module")
def small(geom):
    """A small analysis (serial collision checks) shared by several tests."""
    return analyse_reach(geom, VEHICLE, samples=4000, seed=7, workers=1)


def pin_q(model: pin.Model, values: dict[str, float]) -> np.ndarray:
    q = pin.neutral(model)
    for name, v in values.items():
        q[model.joints[model.getJointId(name)].idx_q] = v
    return q


# ----------------------------------------------------------------- shared kinematics


@pytest.fixture(scope="module")
def model(tree):
    return design_kinematics(tree)


def test_fingertips_on_the_shared_kinematics_match_the_trees_own(tree, model):
    rng = np.random.default_rng(11)
    q = sample_configurations(tree, 300, rng, stage=None)
    q[:, -1] = rng.uniform(0, tree.joint_map["stage"].upper, len(q))
    tips = fingertips(model.kin, q)
    worst = 0.0
    for i, row in enumerate(q):
        ref = tree.frame_positions(dict(zip(ALL_JOINTS, row)))  # the tree's own numpy FK
        for k, f in enumerate(FINGERS):
            worst = max(worst, float(np.abs(tips[i, k] - ref[f"{f}_tip"]).max()))
    assert worst < 1e-9


def test_the_reach_model_is_the_committed_urdfs(tree, model):
    """The design's generated model is the one the retargeter loads (urdf/payload.urdf)."""
    committed = pin.buildModelFromUrdf(str(URDF))
    data = committed.createData()
    q = sample_configurations(tree, 50, np.random.default_rng(3))
    frames = [f"{f}_{k}" for f in FINGERS for k in ("tip", "distal")]
    ours = frame_positions(model.kin, q, frames)
    for i, row in enumerate(q):
        pin.framesForwardKinematics(committed, data, pin_q(committed, dict(zip(ALL_JOINTS, row))))
        for k, name in enumerate(frames):
            ref = data.oMf[committed.getFrameId(name)].translation
            assert np.abs(ours[i, k] - ref).max() < 1e-9


def test_the_reach_model_follows_the_given_design_not_the_project(design):
    """A --design with another pad radius, distal length, pinch pre-shape and pad link: its
    own URDF, pads, rest posture (the span range's posture family rests on it) and pad link,
    also when the design was built in memory (no file to read them from)."""
    data = design_to_dict(design)
    data["finger"]["pad"]["radius"] = 0.012
    data["finger"]["lengths"]["distal"] += 0.005
    data["pinch"]["finger"] = [-0.25, 0.05, 0.1, 0.8]
    data["retarget"]["pad_link"] = "middle"
    other = build_tree(design_from_dict(data))
    model = design_kinematics(other)
    assert all(pk.desc.tip_radius == 0.012 for pk in model.pairs.values())
    for pk in model.pairs.values():
        assert pk.desc.rest == (-0.25, 0.05, 0.1, 0.8) * 2
        np.testing.assert_array_equal(pk.rest, [-0.25, 0.05, 0.1, 0.8] * 2)
        assert pk.hand.pad_link == "middle"
    q = sample_configurations(other, 5, np.random.default_rng(4))
    tips = fingertips(model.kin, q)
    for i, row in enumerate(q):
        ref = other.frame_positions(dict(zip(ALL_JOINTS, row)))
        assert np.abs(tips[i, 0] - ref["A_tip"]).max() < 1e-9


# ----------------------------------------------------------------- spans


def grid(tree, finger: str, n: int) -> np.ndarray:
    axes = [
        np.linspace(tree.joint_map[f"{finger}_{j}"].lower, tree.joint_map[f"{finger}_{j}"].upper, n)
        for j in FINGER_JOINTS
    ]
    return np.array(list(itertools.product(*axes)))


def tree_tips(tree, finger: str, rows: np.ndarray) -> np.ndarray:
    """Fingertips by the tree's own (unbatched numpy) kinematics, rail and stage at 0."""
    out = [
        tree.frame_positions({f"{finger}_{j}": v for j, v in zip(FINGER_JOINTS, row)})[
            f"{finger}_tip"
        ]
        for row in rows
    ]
    return np.array(out)


def front(tree, finger: str, rest: np.ndarray, tips: np.ndarray) -> np.ndarray:
    """How far each tip lies in front of the finger's MCP along its rest direction [m]."""
    origin = tree.link_poses()[tree.joint_map[f"{finger}_mcp_flex"].child][:3, 3]
    axis = tree_tips(tree, finger, rest[None])[0] - origin
    return (tips - origin) @ (axis / np.linalg.norm(axis))


@pytest.mark.parametrize("pair", ["L", "R"])
def test_span_range_is_pair_ranges_and_holds_against_the_trees_kinematics(tree, geom, model, pair):
    """283.5 mm (the old reach figure) is the maximum over the bare joint box: finger 1
    curled back through the vehicle, the base and the stage. pair_range's 281.5 mm keeps
    each fingertip in front of its MCP, and its witness touches nothing."""
    span = span_range(model.pairs[pair])
    own = pair_range(PairKinematics(pair=pair))  # the retargeter's, on the committed URDF
    assert span.maximum == pytest.approx(own.span_max, abs=1e-9)
    assert span.minimum == pytest.approx(own.span_min_kinematic, abs=1e-9)
    # independently: a 6^4 grid per finger on the tree's own kinematics
    f1, f2 = PAIRS[pair]
    rest = np.array(load_design().pinch.finger)  # the retargeter's rest posture, per finger
    assert np.array_equal(PairKinematics(pair=pair).rest, np.tile(rest, 2))
    g1, g2 = grid(tree, f1, 6), grid(tree, f2, 6)
    p1, p2 = tree_tips(tree, f1, g1), tree_tips(tree, f2, g2)
    ok1, ok2 = front(tree, f1, rest, p1) >= 0, front(tree, f2, rest, p2) >= 0
    d = np.linalg.norm(p1[:, None, :] - p2[None, :, :], axis=2)
    allowed = d[np.ix_(ok1, ok2)].max()
    # the grid is a subset of the allowed set (its corner is pair_range's witness)
    assert span.maximum - 1e-3 <= allowed <= span.maximum + 1e-9
    # with finger 1 behind its MCP, a local search on the tree's kinematics from the
    # grid's farthest such pair finds the old 283.5 mm
    behind = np.where(~ok1[:, None], d, -1.0)
    i, j = np.unravel_index(int(np.argmax(behind)), d.shape)
    limits = [tree.joint_map[f"{f}_{n}"] for f in (f1, f2) for n in FINGER_JOINTS]

    def neg(x: np.ndarray) -> float:
        return -float(
            np.linalg.norm(tree_tips(tree, f2, x[None, 4:]) - tree_tips(tree, f1, x[None, :4]))
        )

    res = optimize.minimize(
        neg,
        np.concatenate([g1[i], g2[j]]),
        method="L-BFGS-B",
        bounds=[(lim.lower, lim.upper) for lim in limits],
    )
    x = res.x
    assert -res.fun == pytest.approx(0.28352, abs=5e-5) and -res.fun > span.maximum + 1e-3
    assert front(tree, f1, rest, tree_tips(tree, f1, x[None, :4]))[0] < -0.05
    # that posture collides; pair_range's does not (rail at home, stage deployed)
    check = CollisionModel(geom, VEHICLE)
    own_links = finger_link_names(tree, f1) + finger_link_names(tree, f2)
    others = [n for g in FINGERS if g not in (f1, f2) for n in finger_link_names(tree, g)]
    cols = [ALL_JOINTS.index(f"{f}_{j}") for f in (f1, f2) for j in FINGER_JOINTS]

    def free(q8: np.ndarray) -> bool:
        row = np.zeros(len(ALL_JOINTS))
        row[ALL_JOINTS.index("rail")] = tree.design.home.rail
        row[ALL_JOINTS.index("stage")] = tree.joint_map["stage"].upper
        row[cols] = q8
        return check.pair_free(row, own_links, others)

    assert not free(x) and free(span.q_max)


def test_rail_spacing_is_the_closed_form_range(design, model):
    lo, hi = rail_spacing(model.kin)
    assert lo == pytest.approx(design.array.pair_spacing, abs=1e-12)
    assert hi == pytest.approx(design.array.pair_spacing + design.rail.travel, abs=1e-12)


def test_workspace_hull_volume_of_a_known_box():
    rng = np.random.default_rng(0)
    corners = np.array(list(itertools.product([0.0, 0.02], [0.0, 0.03], [-0.05, 0.0])))
    pts = np.vstack([corners, rng.uniform([0, 0, -0.05], [0.02, 0.03, 0], (500, 3))])
    w = workspace("A", pts, bottom_z=-0.01)
    assert w.hull_volume == pytest.approx(0.02 * 0.03 * 0.05, rel=1e-12)
    assert w.below_vehicle == pytest.approx(0.04) and np.allclose(w.upper, [0.02, 0.03, 0])


# ----------------------------------------------------------------- collisions


def test_mujoco_contacts_agree_with_fcl_signed_distances(geom, tree):
    model = CollisionModel(geom, VEHICLE)
    rng = np.random.default_rng(5)
    q = sample_configurations(tree, 120, rng)
    contacts = model.check(q)
    names = contacts.body_names
    found = {
        (int(i), names[a] if a else "vehicle", names[b])
        for i, a, b in zip(contacts.index, contacts.body_a, contacts.body_b)
    }
    vehicle = [box_geometry(lo, hi) for lo, hi in VEHICLE.body_boxes()]
    disagreements = 0
    for i, row in enumerate(q):
        poses = geom.poses(dict(zip(ALL_JOINTS, row)))
        for a, b in geom.pairs:
            d = geom.link_distance(a, b, poses)
            key = (i, a, b) if names.index(a) < names.index(b) else (i, b, a)
            if (d < -5e-5 and key not in found) or (d > 5e-5 and key in found):
                disagreements += 1
        for link in geom.links:
            d = min(
                signed_distance(o, v)
                for o in geom.piece_objects(link, poses[link])
                for v in vehicle
            )
            if (d < -5e-5) != ((i, "vehicle", link) in found) and abs(d) > 5e-5:
                disagreements += 1
    assert disagreements == 0
    assert contacts.self_collision().any() and contacts.vehicle_contact().any()


def test_forked_workers_find_the_same_contacts(geom, tree):
    model = CollisionModel(geom, VEHICLE)
    q = sample_configurations(tree, 12_000, np.random.default_rng(9))
    one, two = model.check(q, workers=1), model.check(q, workers=2)
    for field in ("index", "body_a", "body_b"):
        assert np.array_equal(getattr(one, field), getattr(two, field))
    # the ranges come back in any order; the rows are sorted by (sample, body a, body b)
    order = np.lexsort((two.body_b, two.body_a, two.index))
    assert np.array_equal(order, np.arange(len(order)))


def test_contact_ranges_in_any_order_give_the_sorted_rows(geom, tree):
    """Ranges checked apart and joined in any order give the rows of one whole check,
    sorted by (sample, body a, body b) as a lexsort of them puts them."""
    model = CollisionModel(geom, VEHICLE)
    q = sample_configurations(tree, 1200, np.random.default_rng(4))
    bounds = [0, 150, 400, 401, 900, 1200]
    parts = [(a, b, model._check_range(q, a, b)) for a, b in itertools.pairwise(bounds)]
    shuffled = [parts[i] for i in np.random.default_rng(1).permutation(len(parts))]
    assert [a for a, _, _ in shuffled] != bounds[:-1]
    got = model._contacts(len(q), shuffled)
    whole = model._contacts(len(q), [(0, len(q), model._check_range(q, 0, len(q)))])
    rows = np.column_stack([got.index, got.body_a, got.body_b])
    assert np.array_equal(rows, np.column_stack([whole.index, whole.body_a, whole.body_b]))
    assert np.array_equal(rows, rows[np.lexsort((rows[:, 2], rows[:, 1], rows[:, 0]))])
    assert np.all(got.body_a < got.body_b)
    assert len(rows) > len(q)  # most samples touch something: a real ordering problem


def test_contact_rows_are_every_body_pair_mujoco_reports_per_sample(geom, tree):
    """The compiled overlap check against MuJoCo's own collision (``mj_collision`` one
    sample at a time, as MuJoCo runs by default: native GJK/EPA, multi-point CCD): the
    same body pairs touch in every sample, none more, none fewer."""
    import collections

    import mujoco

    model = CollisionModel(geom, VEHICLE)
    q = sample_configurations(tree, 3000, np.random.default_rng(21))
    contacts = model.check(q)
    m, d = model.model, model.data
    assert m.opt.disableflags == 0  # MuJoCo's defaults
    expected = set()
    for i, row in enumerate(q):
        for name, v in zip(ALL_JOINTS, row):
            d.qpos[m.jnt_qposadr[m.joint(name).id]] = v
        mujoco.mj_kinematics(m, d)
        mujoco.mj_collision(m, d)
        for g1, g2 in d.contact.geom:
            a, b = sorted((int(m.geom_bodyid[g1]), int(m.geom_bodyid[g2])))
            expected.add((i, a, b))
    got = list(zip(contacts.index.tolist(), contacts.body_a.tolist(), contacts.body_b.tolist()))
    assert len(got) == len(set(got)) and set(got) == expected
    assert len(expected) > 2 * len(q)  # most samples touch: many decisions compared
    names = ["vehicle", *contacts.body_names[1:]]
    counts = collections.Counter((names[a], names[b]) for _, a, b in expected)
    assert contacts.pair_counts() == dict(counts)


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _hulls_meet(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether conv(a) and conv(b) share a point: a linear program (SciPy's HiGHS),
    lambda, mu >= 0, sum 1 each, sum lambda_i a_i = sum mu_j b_j."""
    na, nb = len(a), len(b)
    eq = np.zeros((5, na + nb))
    eq[:3, :na], eq[:3, na:] = a.T, -b.T
    eq[3, :na], eq[4, na:] = 1.0, 1.0
    res = optimize.linprog(np.zeros(na + nb), A_eq=eq, b_eq=[0, 0, 0, 1, 1], bounds=(0, None))
    return res.status == 0


def _overlap(verts, rads, rots, origins) -> bool:
    from payload.envelope.overlap import overlap

    (v1, v2), (r1, r2), (p1, p2) = verts, rots, origins
    both = np.concatenate([v1, v2])
    guess = (r1 @ v1.mean(0) + p1) - (r2 @ v2.mean(0) + p2)
    return bool(
        overlap(
            both, 0, len(v1), rads[0], r1.ravel(), p1, len(v1), len(v2), rads[1], r2.ravel(), p2,
            *guess, np.empty((4, 3)),
        )
    )  # fmt: skip


def test_overlap_of_random_polytopes_is_a_linear_programs_answer():
    """GJK's answer for random convex polytopes (4 to 60 points, rotated and moved) against
    the feasibility of a linear program; pairs whose answer changes when the offset
    is scaled by 1 +- 1e-6 (grazing) are left out."""
    rng = np.random.default_rng(3)
    tested = {True: 0, False: 0}
    for _ in range(400):
        v1 = rng.normal(size=(int(rng.integers(4, 60)), 3)) * rng.uniform(0.005, 0.03, 3)
        v2 = rng.normal(size=(int(rng.integers(4, 60)), 3)) * rng.uniform(0.005, 0.03, 3)
        r1, r2 = _rotation(rng), _rotation(rng)
        p1 = rng.uniform(-0.01, 0.01, 3)
        offset = rng.normal(size=3) * 0.03

        def world(v, r, p):
            return v @ r.T + p

        truth = [
            _hulls_meet(world(v1, r1, p1), world(v2, r2, p1 + offset * s))
            for s in (1 - 1e-6, 1.0, 1 + 1e-6)
        ]
        if len(set(truth)) > 1:
            continue
        got = _overlap((v1, v2), (0.0, 0.0), (r1, r2), (p1, p1 + offset))
        assert got == truth[1]
        tested[got] += 1
    assert min(tested.values()) > 100  # both answers well represented


def test_overlap_at_grazing_depths_is_the_closed_form():
    """A ball sunk into, or held off, a rotated box's face, edge or corner by 2 nm to
    1 um: GJK's answer is the closed form's at every depth (a sliver simplex near the
    contact must neither stall into "apart" nor call a 2 nm gap a contact)."""
    rng = np.random.default_rng(11)
    half = np.array([0.02, 0.01, 0.005])
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=3))) * half
    for gap in (-1e-6, -1e-7, -1e-8, -2e-9, 2e-9, 1e-8, 1e-7, 1e-6):
        for _ in range(1500):
            r_box, radius = _rotation(rng), float(rng.uniform(0.002, 0.02))
            local = rng.uniform(-1.5, 1.5, 3) * half  # outside: nearest a face, edge or corner
            near = np.clip(local, -half, half)
            out = local - near
            if not np.any(out):
                continue
            centre = r_box @ (near + out / np.linalg.norm(out) * (radius + gap))
            verts, radii = (corners, np.zeros((1, 3))), (0.0, radius)
            got = _overlap(verts, radii, (r_box, np.eye(3)), (np.zeros(3), centre))
            assert got == (gap < 0), (gap, radius)


def test_the_checked_pairs_are_those_mujoco_collides(tmp_path):
    """``_mujoco_filters`` against MuJoCo itself on a scene where every geom overlaps every
    other: a free body, a body welded to it, a hinge chain (parent filter), an excluded
    pair, a geom of another contype and static geoms (world, a body welded to the world):
    the body pairs MuJoCo reports touching are exactly those the check would test."""
    import mujoco

    from payload.envelope.collisions import _mujoco_filters

    ball = '<geom type="sphere" size="0.1"/>'
    xml = f"""<mujoco><worldbody>{ball}
      <body name="static">{ball}</body>
      <body name="free"><freejoint/>{ball}<body name="welded">{ball}</body></body>
      <body name="a"><joint type="hinge"/>{ball}
        <body name="b"><joint type="hinge"/>{ball}
          <body name="c"><joint type="hinge"/>{ball}</body></body></body>
      <body name="other"><joint type="slide"/><geom type="sphere" size="0.1" contype="2"
        conaffinity="2"/></body>
      <body name="d"><joint type="slide"/>{ball}</body>
    </worldbody><contact><exclude body1="a" body2="d"/></contact></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    seen = {tuple(sorted(m.geom_bodyid[g].tolist())) for g in d.contact.geom}
    tested = {
        tuple(sorted((int(m.geom_bodyid[g1]), int(m.geom_bodyid[g2]))))
        for g1, g2 in itertools.combinations(range(m.ngeom), 2)
        if _mujoco_filters(m, g1, g2)
    }
    assert tested == seen
    name = {m.body(b).name: b for b in range(m.nbody)}
    assert (name["a"], name["c"]) in seen  # grandparent: not filtered
    for x, y in [("world", "static"), ("free", "welded"), ("a", "b"), ("a", "d")]:
        assert tuple(sorted((name[x], name[y]))) not in seen
    assert not any(name["other"] in pair for pair in seen)


def test_overlap_of_a_sphere_and_a_box_is_the_closed_form():
    """A ball (one vertex and a radius) against a rotated box: they meet when the
    ball's centre, in the box's frame, is within the radius of the box (clamped point)."""
    rng = np.random.default_rng(8)
    half = np.array([0.02, 0.01, 0.005])
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=3))) * half
    tested = {True: 0, False: 0}
    for _ in range(600):
        r_box, p_box = _rotation(rng), rng.uniform(-0.01, 0.01, 3)
        radius = float(rng.uniform(0.002, 0.02))
        centre = p_box + rng.normal(size=3) * 0.02
        local = r_box.T @ (centre - p_box)
        gap = np.linalg.norm(local - np.clip(local, -half, half)) - radius
        if abs(gap) < 1e-7:
            continue
        got = _overlap(
            (corners, np.zeros((1, 3))), (0.0, radius), (r_box, _rotation(rng)), (p_box, centre)
        )
        assert got == (gap < 0)
        tested[got] += 1
    assert min(tested.values()) > 100


@pytest.mark.parametrize("pair", ["L", "R"])
def test_grasp_screening_fk_matches_pinocchio(tree, model, pair):
    from payload.envelope.grasp import pair_tips, symmetric_samples

    rows = np.vstack(
        [
            symmetric_samples(tree, pair, 200, np.random.default_rng(3)),
            sample_configurations(tree, 200, np.random.default_rng(4))[:, :8],
        ]
    )
    fast = pair_tips(model.kin, tree, pair, rows, batch=True)
    pino = pair_tips(model.kin, tree, pair, rows)
    for a, b in zip(fast, pino):
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_the_reach_models_urdf_lives_with_it_so_the_span_range_is_cached(tree):
    import gc
    from pathlib import Path

    from payload.retarget.range_cache import disk_key

    dk = design_kinematics(tree)
    urdf = Path(dk.kin.urdf)
    assert urdf.is_file()
    keys = {
        disk_key(pk, 0, False, []) for pk in (dk.pairs["L"], design_kinematics(tree).pairs["L"])
    }
    assert len(keys) == 1  # the same design, the same key: a second report reads the range
    del dk
    gc.collect()
    assert not urdf.exists()


def test_the_span_ranges_cache_key_follows_the_code_the_range_is_measured_with(tree, monkeypatch):
    """A change to the features, forward kinematics or self-collision code a pair range is
    computed with is a new key: the range is computed anew, not read from an old cache."""
    import inspect

    from payload import kinematics
    from payload.retarget import (
        collision,
        collision_distance,
        collision_geometry,
        features,
        range_cache,
        symbolic,
    )

    pk = design_kinematics(tree).pairs["L"]
    base = range_cache.disk_key(pk, 0, False, [])
    source = inspect.getsource
    for changed in (features, symbolic, kinematics, collision, collision_distance,
                    collision_geometry):  # fmt: skip

        def edited(obj, changed=changed):
            return source(obj) + ("\n# edited" if obj is changed else "")

        monkeypatch.setattr(range_cache.inspect, "getsource", edited)
        assert range_cache.disk_key(pk, 0, False, []) != base, changed.__name__
    monkeypatch.setattr(range_cache.inspect, "getsource", source)
    assert range_cache.disk_key(pk, 0, False, []) == base


# ----------------------------------------------------------------- the analysis


def test_reach_figures_against_closed_forms(design, tree, small):
    st, mnt, a = design.stage, design.mounting, design.array
    L, off = design.finger.lengths, design.finger.offsets
    z_mcp = -(mnt.plate_thickness + st.stowed_gap + st.plate_thickness) - st.travel - a.finger_drop
    length = L.knuckle + L.proximal + L.middle + L.distal
    straight = VEHICLE.bottom_z - (z_mcp - length)
    assert small.home_below_vehicle == pytest.approx(straight, abs=1e-12)
    # deepest: the knuckle, proximal and middle links straight down and the DIP turning the
    # distal's own tip vector (the pad sits off its axis by offsets.tip) straight down; the
    # whole MCP-to-tip vector turned down (hypot(length, tip)) is 0.28 mm short of it
    assert off.mcp_abd == off.pip == off.dip == 0.0  # the closed form's premise
    deepest = VEHICLE.bottom_z - (z_mcp - (length - L.distal + np.hypot(L.distal, off.tip)))
    q = tree.posture("home")
    q.update({f"A_{j}": 0.0 for j in FINGER_JOINTS}, stage=st.travel)
    q["A_dip"] = -np.arctan2(off.tip, L.distal)
    assert tree.joint_map["A_dip"].lower <= q["A_dip"] <= tree.joint_map["A_dip"].upper
    # the tree's own kinematics attains it, and no sampled fingertip goes deeper
    assert VEHICLE.bottom_z - tree.frame_positions(q)["A_tip"][2] == pytest.approx(
        deepest, abs=1e-12
    )
    assert deepest - 0.01 < small.below_vehicle <= deepest + 1e-12
    r = design.finger.pad.radius
    for p in small.pairs:
        assert p.pad_contact == pytest.approx(2 * r)
        assert p.span_min == pytest.approx(max(p.span.minimum, 2 * r))
        assert p.span_min <= p.free_span[0] + 1e-12 and p.free_span[1] <= p.span.maximum + 1e-12
    assert 0.0 < small.collision_free_fraction < 1.0
    assert small.contacts.n == small.samples == 4000


def test_grasp_witnesses_hold_up_under_an_independent_check(design, tree, geom, small):
    r = design.finger.pad.radius
    vehicle = [box_geometry(lo, hi) for lo, hi in VEHICLE.body_boxes()]
    fresh = build_tree(design)  # the unbatched kinematics, built anew
    closed = 0
    for p in small.pairs:
        f1, f2 = p.fingers
        own = finger_link_names(tree, f1) + finger_link_names(tree, f2)
        for g in p.grasps:
            if not g.closes:
                continue
            closed += 1
            # the witness as deployed: stage at its full travel, rail at home
            q = {"rail": design.home.rail, "stage": design.stage.travel}
            q.update(zip([f"{f}_{j}" for f in (f1, f2) for j in FINGER_JOINTS], g.q))
            tips = fresh.frame_positions(q)
            p1, p2 = tips[f"{f1}_tip"], tips[f"{f2}_tip"]
            assert np.linalg.norm(p2 - p1) == pytest.approx(g.feature.thickness + 2 * r, abs=1e-4)
            assert g.span == pytest.approx(np.linalg.norm(p2 - p1), abs=1e-9)
            side = 1.0 if tree.joint_map[f"{f2}_mcp_flex"].xyz[1] > 0 else -1.0
            assert opposition(p1[None], p2[None], side)[0] <= np.radians(30) + 1e-9
            assert g.angle == pytest.approx(opposition(p1[None], p2[None], side)[0], abs=1e-6)
            # depth: the higher pad's top (tip z plus the pad radius) below the bottom face
            depth = VEHICLE.bottom_z - (max(p1[2], p2[2]) + r)
            assert g.depth == pytest.approx(depth, abs=1e-9)
            assert depth >= -1e-9
            poses = geom.poses(q)
            checked = [*own, "base", "stage", "carriage"]
            for link in own:
                for other in checked:
                    if other != link and frozenset((link, other)) not in geom.adjacent:
                        assert geom.link_distance(link, other, poses) > -5e-5, (link, other)
                d = min(
                    signed_distance(o, v)
                    for o in geom.piece_objects(link, poses[link])
                    for v in vehicle
                )
                assert d > -5e-5
    assert closed >= 2  # the thin CTB straps close for both pairs


def test_bad_sample_counts_and_thicknesses_are_refused(geom):
    from payload.envelope.reach import ReachError

    with pytest.raises(ReachError, match="at least 1000"):
        analyse_reach(geom, VEHICLE, samples=10)
    with pytest.raises(ReachError, match="thickness"):
        analyse_reach(geom, VEHICLE, samples=1000, features=[GraspFeature("bad", -0.001, "test")])


# ----------------------------------------------------------------- CLI


def test_report_reach_json_fields_and_files(tmp_path):
    out = tmp_path / "analyses"
    res = run_cli(
        "report", "reach", "--samples", "2000", "--thickness", "0.004", "--json", "--out", str(out)
    )
    assert res.returncode == 0, res.stderr
    assert len(res.stdout.strip().splitlines()) == 1
    obj = json.loads(res.stdout)
    assert obj["samples"] == 2000 and obj["seconds"] > 0
    for pair in ("L", "R"):
        assert obj["pairs"][pair]["span_min_mm"] <= obj["pairs"][pair]["span_max_mm"]
    assert obj["rail_spacing_mm"] == {"min": 62.0, "max": 112.0}
    assert obj["below_vehicle_mm"] > 150 and 0 < obj["collision_free_fraction"] < 1
    assert any("given thickness 4.0 mm" == g["feature"] for g in obj["pairs"]["L"]["grasp"])
    assert any("ASSUMPTION" in a for a in obj["assumptions"])
    # the verdict, as the envelope's JSON gives `passed`: what the exit code says
    assert obj["passed"] is (res.returncode == 0) is True
    assert obj["verdict"].startswith("grasps: pair L closes down to")
    for name in ("reach.md", "reach.png", "reach.json"):
        assert (out / name).stat().st_size > 0
    assert "ASSUMPTION (bay size)" in (out / "reach.md").read_text()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--samples", "10"], "payload: error: --samples must be >= 1000, got 10"),
        (["--thickness", "-0.01"], "payload: error: --thickness must be between 0 and 1 m"),
        (  # a thickness in mm: the unit slip named, as the design file's are
            ["--thickness", "25"],
            "payload: error: --thickness must be between 0 and 1 m, got 25.0: did you mean "
            "25 mm = 0.025?",
        ),
        (["--bay-size", "0.2", "0.1", "0"], "payload: error: --bay-size: every size must be"),
    ],
)
def test_report_reach_bad_input_is_one_line_exit_2(tmp_path, args, message):
    res = run_cli("report", "reach", *args, "--out", str(tmp_path))
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(message)


def test_bench_reach_compares_the_checks_and_times_the_report_elsewhere():
    """``bench reach``: the compiled check and MuJoCo's collision agree row for row on
    the same samples (counted independently: MuJoCo's rows read contact by contact), and
    the timed report goes to a temporary folder, never the project's analyses/."""
    committed = {f.name: f.read_bytes() for f in (ROOT / "analyses").glob("reach.*")}
    r = run_cli("bench", "reach", "--samples", "1000", "--check-samples", "300", "--runs", "1",
                "--json")  # fmt: skip
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["identical"] and out["rows_only_overlap"] == out["rows_only_mujoco"] == 0
    assert out["rows"] > 300 and out["overlap_us"] > 0 and out["mujoco_us"] > 0
    assert len(out["report_wall_s"]) == len(out["report_cpu_s"]) == 1
    assert out["within_aim"] is None  # the aim is for 100,000 samples
    assert {f.name: f.read_bytes() for f in (ROOT / "analyses").glob("reach.*")} == committed
    bad = run_cli("bench", "reach", "--check-samples", "0")
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--check-samples" in bad.stderr


def test_generated_reach_report_is_committed():
    data = json.loads((ROOT / "analyses" / "reach.json").read_text())
    assert data["samples"] >= 100_000 and data["design"] == "cad/design.toml"
    assert (ROOT / "analyses" / "reach.png").exists()
    assert "ASSUMPTION" in (ROOT / "analyses" / "reach.md").read_text()


def test_batched_fingertips_match_pinocchio_on_the_generated_urdf(design) -> None:
    """The numpy forward kinematics over samples against Pinocchio, one sample at a time,
    on the generated URDF (joints and tip links as the URDF names them)."""
    from payload.envelope.batch_fk import fingertips_batch, frame_positions_batch
    from payload.envelope.sampling import sample_configurations

    tree = build_tree(design)
    q = sample_configurations(tree, 300, np.random.default_rng(7))
    q[:100, -1] = np.random.default_rng(8).uniform(0, tree.joint_map["stage"].upper, 100)
    got = fingertips_batch(tree, q)
    model = pin.buildModelFromUrdf(str(URDF))
    data = model.createData()
    idx = [model.joints[model.getJointId(j)].idx_q for j in ALL_JOINTS]
    tips = [model.getFrameId(f"{f}_tip") for f in "ABCD"]
    for i, row in enumerate(q):
        qp = pin.neutral(model)
        qp[idx] = row
        pin.framesForwardKinematics(model, data, qp)
        want = np.array([data.oMf[t].translation for t in tips])
        np.testing.assert_allclose(got[i], want, atol=1e-12)
    assert np.ptp(got[:, 0, 2]) > 0.05  # the samples move the tips (not a constant)
    with pytest.raises(KeyError, match="no frame named X_tip"):
        frame_positions_batch(tree, q, ["X_tip"])


def test_a_compile_of_the_check_is_said_and_left_out_of_the_reports_time(monkeypatch, capsys):
    """A check that takes longer than COMPILING_AFTER_S to load (as Numba's compile after
    a change to its code does) is said on stderr once, and its seconds are returned for
    the report's time to leave out; a quick load says nothing, then or later, and
    returns 0."""
    from payload.envelope import cli_runs, overlap

    monkeypatch.setattr(cli_runs, "COMPILING_AFTER_S", 0.2)  # the test's own, shorter wait
    slow = cli_runs.COMPILING_AFTER_S + 1.0
    monkeypatch.setattr(overlap, "compile_check", lambda: time.sleep(slow))
    took = cli_runs._load_check()
    assert capsys.readouterr().err == cli_runs.COMPILING_LINE + "\n"
    assert took >= slow
    monkeypatch.setattr(overlap, "compile_check", lambda: None)
    assert cli_runs._load_check() == 0.0
    time.sleep(cli_runs.COMPILING_AFTER_S + 0.2)  # no notice comes after the load ended
    assert capsys.readouterr().err == ""


def test_report_reach_starts_its_time_after_the_checks_load(monkeypatch, tmp_path):
    """``report reach`` moves its report's start past the seconds the check's load
    returns: a load that says it took a minute puts the start a minute after the
    command's own (the report is stopped there)."""
    from payload.cli import main
    from payload.envelope import cli_runs, report

    class Stop(BaseException):
        pass

    starts = []

    def write_reach(*args, t_start, **kwargs):
        starts.append(t_start)
        raise Stop

    load_s = 60.0  # the check's load, as a first compile reports it
    monkeypatch.setattr(cli_runs, "_load_check", lambda: load_s)
    monkeypatch.setattr(report, "write_reach", write_reach)
    before = time.perf_counter()
    with pytest.raises(Stop):
        main(["report", "reach", "--samples", "1000", "--json", "--out", str(tmp_path)])
    assert before + load_s <= starts[0] <= time.perf_counter() + load_s


def test_a_design_whose_fingers_almost_never_move_free_fails_with_a_report(tmp_path, capsys):
    """Links 49 mm deep (the default 28 mm) leave fingers A, B and D free in 2 of 2,000
    samples: too few for a workspace is a result about the design and the sampling (exit
    1, the report written, saying why and to sample more), not bad input (exit 2); the
    pairs' line says how many features it checked."""
    from payload.cli import main
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    text = project.design_path.read_text()
    project.design_path.write_text(text.replace("\ndepth = 0.028 ", "\ndepth = 0.049 ", 1))
    code = main(["--project", str(project.root), "report", "reach", "--samples", "2000"])
    out = capsys.readouterr()
    assert code == 1, out.err
    data = json.loads((project.analyses_dir / "reach.json").read_text())
    assert data["passed"] is False and data["samples"] == 2000
    # the fingers the verdict names are those the JSON counts under 4 free samples
    few = {f: round(w["reachable_fraction"] * 2000) for f, w in data["fingers"].items()}
    assert {f for f, n in few.items() if n < 4} == {"A", "B", "D"}
    err = out.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("payload: check failed: reach: fingers A (2), ")
    assert "sample more (--samples)" in err[0]
    lines = out.out.splitlines()
    assert lines[2].startswith("verdict: FAILS: fingers A (2), B (2), D (2) moved free in ")
    assert "sample more (--samples)" in (project.analyses_dir / "reach.md").read_text()
    for pair in ("L", "R"):
        checked = len(data["pairs"][pair]["grasp"])
        assert not any(g["closes"] for g in data["pairs"][pair]["grasp"])
        assert any(
            x.startswith(f"pair {pair}: ")
            and x.endswith(f"closes on none of the {checked} features checked")
            for x in lines
        ), lines


def test_the_reach_change_line_names_a_flipped_verdict_first() -> None:
    """The reach report records ``passed`` and its change line names it, as the
    envelope's does ("passes yes -> no")."""
    from payload.envelope.verdict import headline_changes

    before = {"samples": 2000, "seed": 0, "passed": True, "below_vehicle_mm": 202.5}
    after = {**before, "passed": False, "below_vehicle_mm": 197.3}
    assert headline_changes("reach", before, after) == (
        "changed since reach.prev.json: passes yes -> no; "
        "fingertips below the vehicle 202.50 mm -> 197.30 mm"
    )


def test_the_pairs_grasp_markers_sit_on_rows_of_their_own(small, geom) -> None:
    """reach.png's span panel: each pair's marker for a feature at the same thickness
    is drawn at another height (pair L's no longer hidden under pair R's), both inside
    the panel's lower edge."""
    from matplotlib.figure import Figure

    from payload.envelope.reach_figure import _span_panel

    fig = Figure()
    ax = fig.subplots()
    _span_panel(ax, small, geom.tree.design.finger.pad.radius)
    fig.canvas.draw()
    marks: dict[float, list[tuple[str, float]]] = {}
    for line in ax.get_lines():
        if line.get_marker() in ("^", "x") and len(line.get_xdata()) == 1:
            x, y = ax.transData.inverted().transform(
                line.get_transform().transform((line.get_xdata()[0], line.get_ydata()[0]))
            )
            marks.setdefault(round(float(x), 6), []).append((line.get_marker(), float(y)))
    features = len(small.pairs[0].grasps)
    assert len(marks) == features  # one thickness per feature, a marker per pair
    bottom, top = ax.get_ylim()
    for ys in marks.values():
        assert len(ys) == 2
        (_, y_l), (_, y_r) = ys  # drawn pair L first
        rows = [ax.transData.transform((0, y))[1] for y in (y_l, y_r)]
        assert rows[1] - rows[0] > 10  # pixels: more than a 7-point marker apart, R above L
        assert bottom <= y_l < y_r < top


@pytest.fixture
def reach_png(small, geom, monkeypatch, tmp_path):
    """reach.png of the small analysis as :func:`reach_figure` lays it out and saves it,
    drawn (the figure kept as it is saved); and its span panel."""
    from matplotlib.figure import Figure

    from payload.envelope.reach_figure import reach_figure

    saved = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *args, **kw: saved.append(fig))
    reach_figure(geom, small, tmp_path / "reach.png", points=200)
    (fig,) = saved
    fig.canvas.draw()
    (ax,) = [ax for ax in fig.axes if ax.get_title().startswith("pair spans")]
    return fig, ax


def test_the_side_and_front_views_show_the_whole_bay_envelope(reach_png) -> None:
    """reach.png's side and front views: the bay envelope (VEHICLE's bays in z, the dashed
    box) lies inside each view; its top edge was cut off (the view stopped 80 mm above the
    vehicle's bottom face, below the bays' top)."""
    fig, _ = reach_png
    views = [ax for ax in fig.axes if ax.get_title().startswith(("side view", "front view"))]
    assert len(views) == 2
    top, bottom = VEHICLE.bay_upper[2] * 1e3, VEHICLE.bay_lower[2] * 1e3
    for ax in views:
        lo, hi = ax.get_ylim()
        assert lo < bottom and hi > top, (ax.get_title(), lo, hi)


def _along(xy: np.ndarray, n: int = 50) -> np.ndarray:
    """Points along the polyline through ``xy`` (display coordinates), ``n`` a segment."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    return np.vstack([a + t * (b - a) for a, b in itertools.pairwise(xy)] or [xy])


def test_the_span_panels_legend_covers_no_data(reach_png) -> None:
    """reach.png's span panel: its legend lies over no histogram bar (each bin read back
    from the drawn step outlines as the bar from 0 to its count) and no line or marker
    (it covered the top of the histograms and the span lines)."""
    from matplotlib.transforms import Bbox

    fig, ax = reach_png
    legend = ax.get_legend()
    assert legend is not None
    box = legend.get_window_extent(fig.canvas.get_renderer())
    bars = 0
    for patch in ax.patches:  # the histograms: outlines through (edge, count) corners
        xy = patch.get_path().vertices
        for (x0, y0), (x1, y1) in itertools.pairwise(xy):
            if y0 == y1 > 0 and x1 != x0:  # the top of a bin
                corners = ax.transData.transform([(min(x0, x1), 0.0), (max(x0, x1), y0)])
                bars += 1
                assert not box.overlaps(Bbox(corners)), (x0, x1, y0)
    assert bars >= 40  # both pairs' histograms were read
    for line in ax.get_lines():
        xy = _along(line.get_transform().transform(line.get_xydata()))
        assert not any(box.contains(x, y) for x, y in xy), line.get_label()


def test_the_pairs_span_ranges_are_told_apart(reach_png, small) -> None:
    """reach.png's span panel: each pair's span range is one line from its narrowest to
    its widest span, and the two pairs' lines, which span the same range here, lie apart
    (pair L's was hidden under pair R's)."""
    fig, ax = reach_png
    lo, hi = (small.pairs[0].span_min, small.pairs[0].span.maximum)
    assert all(
        (p.span_min, p.span.maximum) == pytest.approx((lo, hi), abs=1e-3) for p in small.pairs
    )  # the premise: equal ranges, which two lines at the same place would hide
    spans = {
        p.name: [x for x in ax.get_lines() if x.get_label().startswith(f"pair {p.name}: span")]
        for p in small.pairs
    }
    assert [len(lines) for lines in spans.values()] == [1, 1]
    renderer = fig.canvas.get_renderer()
    extents = [spans[n][0].get_window_extent(renderer) for n in ("L", "R")]
    assert not extents[0].overlaps(extents[1]), extents
    for p in small.pairs:
        x = np.asarray(spans[p.name][0].get_xdata(), dtype=float)
        assert x.min() == pytest.approx(p.span_min * 1e3)
        assert x.max() == pytest.approx(p.span.maximum * 1e3)


def test_the_span_panel_names_each_ctb_feature_beside_its_markers(reach_png, small) -> None:
    """reach.png's span panel: the CTB features' markers said nothing of which feature
    each was (reach.md had to be read). A legend beside the panel names them, one entry
    per feature, left to right as the marker columns stand, each at the separation its
    markers are drawn at and with a marker per pair as its row draws it (a triangle where
    the pair closes on it, a cross where not); it covers no data and not the panel's
    other legend."""
    from matplotlib.legend import Legend
    from matplotlib.lines import Line2D
    from matplotlib.offsetbox import DrawingArea, HPacker, TextArea

    fig, ax = reach_png
    renderer = fig.canvas.get_renderer()
    # the markers drawn in the rows: separation [mm] -> markers, pair by pair (L first)
    drawn: dict[float, list[str]] = {}
    for line in ax.get_lines():
        if line.get_marker() in ("^", "x") and len(line.get_xdata()) == 1:
            drawn.setdefault(round(float(line.get_xdata()[0]), 6), []).append(line.get_marker())
    features = [g.feature for g in small.pairs[0].grasps]
    assert len(drawn) == len(features) >= 6  # CTB_FEATURES
    # each legend entry: its text and the markers of its handle
    legends = [c for c in ax.get_children() if isinstance(c, Legend)]
    entries = []
    for legend in legends:
        for row in legend.findobj(HPacker):
            kids = row.get_children()
            if (
                len(kids) == 2
                and isinstance(kids[0], DrawingArea)
                and isinstance(kids[1], TextArea)
            ):
                marks = [m.get_marker() for m in kids[0].findobj(Line2D)]
                entries.append((kids[1].get_text(), [m for m in marks if m in ("^", "x")]))
    named = [(text, marks) for text, marks in entries if any(f.name in text for f in features)]
    assert [next(f.name for f in features if f.name in text) for text, _ in named] == [
        f.name for f in sorted(features, key=lambda f: f.thickness)
    ]  # each once, in the markers' order
    for (text, marks), x in zip(named, sorted(drawn)):
        assert text.startswith(f"{x:.1f} mm: "), (text, x)
        assert marks == drawn[x], (text, marks, drawn[x])
        want = ["^" if g.closes else "x" for p in small.pairs for g in p.grasps
                if g.feature.name in text]  # fmt: skip
        assert marks == want, text
    # beside the panel: over no bar, line or marker, and apart from the other legend
    boxes = [legend.get_window_extent(renderer) for legend in legends]
    assert len(boxes) == 2 and not boxes[0].overlaps(boxes[1])
    panel = ax.get_window_extent(renderer)
    assert all(box.x0 > panel.x1 for box in boxes)


def test_the_span_panels_legends_stay_apart_with_given_thicknesses(
    geom, monkeypatch, tmp_path
) -> None:
    """With the 6 CTB features and 8 ``--thickness`` values the span legend (anchored at
    the panel's top, growing down) and the features' (anchored at its bottom, growing up)
    overlapped; the features' now stands under the other's measured box, titled "grasp
    features", and both lie inside the figure."""
    from matplotlib.figure import Figure
    from matplotlib.legend import Legend

    from payload.envelope.grasp import CTB_FEATURES, GraspFeature
    from payload.envelope.reach_figure import reach_figure

    given = [GraspFeature(f"given thickness {t:.1f} mm", t * 1e-3, "command line")
             for t in (2, 4, 6, 8, 12, 16, 24, 32)]  # fmt: skip
    features = [*CTB_FEATURES, *given]
    assert len(features) == 14
    a = analyse_reach(geom, VEHICLE, samples=2000, seed=7, workers=1, features=features)
    saved = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *args, **kw: saved.append(fig))
    reach_figure(geom, a, tmp_path / "reach.png", points=200)
    (fig,) = saved
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    (ax,) = [ax for ax in fig.axes if ax.get_title().startswith("pair spans")]
    legends = [c for c in ax.get_children() if isinstance(c, Legend)]
    assert len(legends) == 2
    titles = [legend.get_title().get_text() for legend in legends]
    assert sum(t.startswith("grasp features") for t in titles) == 1, titles
    boxes = [legend.get_window_extent(renderer) for legend in legends]
    assert not boxes[0].overlaps(boxes[1]), boxes
    page = fig.bbox
    for box in boxes:
        assert page.x0 <= box.x0 and box.x1 <= page.x1, (box, page)
        assert page.y0 <= box.y0 and box.y1 <= page.y1, (box, page)
    panel = ax.get_window_extent(renderer)
    assert all(box.x0 > panel.x1 for box in boxes)


def test_a_sparse_reach_verdict_says_a_grasp_can_be_missed(geom, small) -> None:
    """A new user's ``report reach --samples 2000`` said "pair L closes down to 20.0 mm
    ..., pair R closes down to 3.0 mm": the pairs are mirror images, and at the default
    sampling both close down to the same thinnest feature, so the difference was the
    sparse sampling, which nothing said. A verdict sampled under the default says so; at
    the default it does not, and the two mirrored pairs agree."""
    from payload.envelope import REACH_SAMPLES
    from payload.envelope.verdict import reach_verdict

    assert small.samples < REACH_SAMPLES
    line = reach_verdict(small)
    assert line.endswith(
        f"; sampled {small.samples:,} times (default {REACH_SAMPLES:,}): a grasp can be missed"
    ), line
    full = analyse_reach(geom, VEHICLE, seed=0)
    assert full.samples == REACH_SAMPLES
    thinnest = {p.name: min(g.feature.thickness for g in p.grasps if g.closes) for p in full.pairs}
    assert len(set(thinnest.values())) == 1, thinnest  # mirror images: the same grasp
    assert "sampled" not in reach_verdict(full) and "can be missed" not in reach_verdict(full)


def test_no_axis_label_of_reach_png_touches_the_figures_edge(reach_png) -> None:
    """reach.png's side view had its "z [mm]" label at the figure's very left edge (its
    first pixel column dark): every axis label and tick label now lies inside the figure
    with a margin."""
    fig, _ = reach_png
    renderer = fig.canvas.get_renderer()
    box = fig.bbox
    margin = 3.0  # [px] at the figure's dpi
    for ax in fig.axes:
        for text in (ax.xaxis.label, ax.yaxis.label, *ax.get_yticklabels()):
            if not text.get_text() or not text.get_visible():
                continue
            ext = text.get_window_extent(renderer)
            inside = (
                ext.x0 >= box.x0 + margin
                and ext.y0 >= box.y0 + margin
                and ext.x1 <= box.x1 - margin
                and ext.y1 <= box.y1 - margin
            )
            assert inside, (ax.get_title(), text.get_text(), ext, box)
