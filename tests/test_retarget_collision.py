"""Self-collision-aware retargeting (issue 14): the margin comes from the design, the
solver's geometry encloses the collision meshes, its distances and gradients are right,
and no command comes closer than the margin, by the solver's distance and by python-fcl
on the generated meshes (an independent library).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest
from conftest import hand_file, replace_once
from scipy.spatial.transform import Rotation

from payload.design.params import load_design
from payload.errors import DesignError
from payload.project import current_project
from payload.retarget import (
    PairKinematics,
    PairRetargeter,
    RetargetConfig,
    calibrate,
    features_from_points,
    load_hand,
    pair_range,
)
from payload.retarget.bench import human_pinch_and_open, synthetic_hand
from payload.retarget.budget import RESUME, budget_plan, evaluation_cap
from payload.retarget.collision import (
    Box,
    box_sdf,
    link_geometry,
    register,
    segment_box_distance,
    segment_box_distance_expr,
)
from payload.retarget.collision_eval import CollisionGroups
from payload.retarget.compiled import _CompiledSolve
from payload.retarget.errors import RetargetError
from payload.retarget.lm_graph import _step_functions
from payload.retarget.meshcheck import PairMeshCheck
from payload.retarget.objective import collision_residual
from payload.retarget.symbolic import objective_function

HANDS_DIR = Path(__file__).resolve().parents[1] / "payload" / "retarget" / "hands"
PAIRS = ("L", "R")
FCL_TOLERANCE = 0.5e-3
"""How much nearer python-fcl may find the meshes than the solver's capsules (issue 14) [m]."""
N_HUMAN = int(os.environ.get("PAYLOAD_HUMAN_PINCHES", "10000"))
"""Random human pinch inputs of the acceptance test (split over the two pairs). The suite
runs 10,000 (under a minute); issue 14 asks for 100,000 (``PAYLOAD_HUMAN_PINCHES=100000``,
6.5 minutes at load 1; passed with the exact capsule-box distance, after a run with the
earlier sampled box terms had found a command 1.29 mm from the structure by python-fcl)."""


@pytest.fixture(scope="module")
def hand():
    return load_hand()


@pytest.fixture(scope="module")
def pks(hand):
    register()  # the pairs' .collision below, before any retargeter registers it
    return {p: PairKinematics(hand, p) for p in PAIRS}


def test_the_collision_model_is_registered_by_a_call_not_by_an_import() -> None:
    """Importing the package and the collision module registers nothing; a pair's model
    without the call says what to call; a retargeter makes the call itself."""
    code = (
        "import payload.retarget, payload.retarget.collision as c\n"
        "from payload.retarget.features import COLLISION_MODEL, PairKinematics\n"
        "from payload.retarget.errors import RetargetError\n"
        "assert COLLISION_MODEL == [], COLLISION_MODEL\n"
        "pk = PairKinematics(None, 'L')\n"
        "try:\n"
        "    pk.collision\n"
        "    raise SystemExit('no error')\n"
        "except RetargetError as exc:\n"
        "    assert 'register()' in str(exc), exc\n"
        "from payload.retarget import ReferenceRetargeter, RetargetConfig\n"
        "ReferenceRetargeter(None, 'L', RetargetConfig(collisions=True), pk)\n"
        "assert COLLISION_MODEL == [c.PairCollision]\n"
        "assert pk.collision.margin > 0\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


@pytest.fixture(scope="module")
def solvers(hand, pks):
    return {p: PairRetargeter(hand, p, RetargetConfig(collisions=True), pks[p]) for p in PAIRS}


@pytest.fixture(scope="module")
def checks(pks):
    return {p: PairMeshCheck(pks[p]) for p in PAIRS}


def _free_postures(pk, k, seed):
    rng = np.random.default_rng(seed)
    qs = pk.lower + rng.random((40 * k, pk.n)) * pk.range
    dist = pk.collision.distances_many(qs)
    return qs[dist.min(axis=0) >= pk.collision.margin][:k]


# ------------------------------------------------------------- the shape kept on disk
def test_the_shape_kept_on_disk_gives_the_derived_model(pks, tmp_path, monkeypatch):
    """A pair's model built from the disk cache has the capsules, boxes, pad links and
    terms of the one derived from the URDF, and the same distances to the bit; a model
    built from the cache reads no collision geometry and fits no capsule."""
    from payload.retarget import collision, collision_cache

    monkeypatch.setattr(collision_cache, "cache_dir", lambda: tmp_path)
    for pair in PAIRS:
        derived = collision.PairCollision(pks[pair])
        assert len(list(tmp_path.glob("pair_collision_*.npz"))) == PAIRS.index(pair) + 1
        with monkeypatch.context() as m:
            for name in ("link_geometry", "enclosing_capsule", "structure_boxes"):
                m.setattr(collision, name, lambda *a, **k: pytest.fail("derived, not loaded"))
            m.setattr(collision.PairCollision, "_prune", lambda self: pytest.fail("pruned"))
            loaded = collision.PairCollision(pks[pair])
        assert loaded.terms and len(loaded.terms) < len(loaded.all_terms)  # pruned
        assert (loaded.all_terms, loaded.terms) == (derived.all_terms, derived.terms)
        assert (loaded.finger_of, loaded.pads) == (derived.finger_of, derived.pads)
        for a, b in zip(loaded.capsules, derived.capsules, strict=True):
            assert (a.link, a.radius) == (b.link, b.radius)
            assert a.a.tobytes() == b.a.tobytes() and a.b.tobytes() == b.b.tobytes()
        for a, b in zip(loaded.boxes, derived.boxes, strict=True):
            assert a.link == b.link
            for x, y in ((a.centre, b.centre), (a.rotation, b.rotation), (a.half, b.half)):
                assert x.tobytes() == y.tobytes()
        pk = pks[pair]
        qs = pk.lower + np.random.default_rng(3).random((50, pk.n)) * pk.range
        assert loaded.distances_many(qs).tobytes() == derived.distances_many(qs).tobytes()
        assert [loaded.clearance(q) for q in qs] == [derived.clearance(q) for q in qs]


@pytest.mark.parametrize("damage", ["torn", "short"])
def test_a_damaged_shape_on_disk_is_derived_again(pks, tmp_path, monkeypatch, damage):
    """A cache file cut short (a torn write) or whose verdicts do not match its terms is
    not read: the model is derived again, equal to the first, and the file rewritten."""
    from payload.retarget import collision, collision_cache

    monkeypatch.setattr(collision_cache, "cache_dir", lambda: tmp_path)
    first = collision.PairCollision(pks["L"])
    (path,) = tmp_path.glob("pair_collision_*.npz")
    if damage == "torn":
        path.write_bytes(path.read_bytes()[:200])
    else:
        with np.load(path) as z:
            parts = {k: z[k] for k in z.files}
        parts["kept"] = parts["kept"][:-1]
        np.savez(path, **parts)
    derived = []
    real = collision.link_geometry
    monkeypatch.setattr(collision, "link_geometry", lambda u: derived.append(u) or real(u))
    again = collision.PairCollision(pks["L"])
    assert len(derived) == 1
    assert (again.all_terms, again.terms) == (first.all_terms, first.terms)
    assert collision_cache.load_shape(path.stem.removeprefix("pair_collision_")) is not None


def test_the_shape_is_keyed_by_the_meshes_the_design_and_the_margin(tmp_path):
    """The cache key changes with a byte of a collision mesh the URDF names, of the URDF,
    of the design, and with the margin, and not with a file the URDF does not name; with
    a named mesh missing there is no key (the model is derived, and says why)."""
    from payload.retarget.collision_cache import shape_key

    project = current_project().root
    shutil.copytree(project / "cad", tmp_path / "cad")
    shutil.copytree(project / "urdf", tmp_path / "urdf")
    hand = hand_file(tmp_path, "urdf/payload.urdf", "cad/design.toml")

    def key(scale: float = 1.0) -> str:
        pk = PairKinematics(load_hand(hand), "L")
        got = shape_key(pk, scale * pk.hand.collision_margin)
        assert got is not None
        return got

    first = key()
    assert key() == first and key(1.5) != first
    (tmp_path / "cad" / "meshes" / "unused.stl").write_bytes(b"not named")
    assert key() == first
    mesh = tmp_path / "cad" / "meshes" / "stage.stl"
    mesh.write_bytes(mesh.read_bytes() + b"\0")
    assert key() != first
    mesh.write_bytes(mesh.read_bytes()[:-1])
    assert key() == first
    urdf = tmp_path / "urdf" / "payload.urdf"
    text = urdf.read_text()
    urdf.write_text(text + "<!-- a comment -->\n")
    assert key() != first
    urdf.write_text(text)
    assert key() == first
    design = tmp_path / "cad" / "design.toml"
    design.write_text(design.read_text() + "\n# a comment\n")
    second = key()
    assert second != first
    mesh.rename(mesh.with_suffix(".gone"))  # a named mesh missing: no key, no cache
    pk = PairKinematics(load_hand(hand), "L")
    assert shape_key(pk, pk.hand.collision_margin) is None


# ------------------------------------------------------------- one source
def test_margin_and_pad_radius_come_from_the_design(tmp_path, hand):
    design = load_design(current_project().design_path)
    assert hand.collision_margin == design.retarget.collision_margin == 0.002
    assert all(p.tip_radius == design.finger.pad.radius for p in hand.pairs.values())
    # A hand naming another design follows it: edit both keys in a copy.
    text = current_project().design_path.read_text()
    text = replace_once(text, "collision_margin = 0.002", "collision_margin = 0.0035")
    text = replace_once(text, "radius = 0.011 ", "radius = 0.0125 ")
    (tmp_path / "design.toml").write_text(text)
    shutil.copy(hand.urdf, tmp_path / "payload.urdf")
    other = load_hand(hand_file(tmp_path, "payload.urdf", "design.toml"))
    assert other.collision_margin == 0.0035
    assert all(p.tip_radius == 0.0125 for p in other.pairs.values())


def test_a_bad_margin_in_the_design_is_named(tmp_path):
    text = current_project().design_path.read_text()
    (tmp_path / "d.toml").write_text(
        replace_once(text, "collision_margin = 0.002", "collision_margin = -1")
    )
    with pytest.raises(DesignError, match=r"retarget\.collision_margin"):
        load_design(tmp_path / "d.toml")


# ------------------------------------------------------------ the geometry
@pytest.mark.parametrize("pair", PAIRS)
def test_capsules_contain_every_collision_mesh_vertex(pks, pair):
    pk = pks[pair]
    geo = link_geometry(Path(pk.kin.urdf))
    col = pk.collision
    assert len(col.capsules) == 8 and col.available
    for cap in col.capsules:
        (kind, mesh, pose), *_ = geo[cap.link]
        assert kind == "mesh"
        v = np.asarray(mesh.vertices) @ pose[:3, :3].T + pose[:3, 3]
        # point-to-segment distance, written out here
        ab = cap.b - cap.a
        t = np.clip((v - cap.a) @ ab / (ab @ ab), 0.0, 1.0)
        d = np.linalg.norm(v - (cap.a + t[:, None] * ab), axis=1)
        assert d.max() <= cap.radius


@pytest.mark.parametrize("pair", PAIRS)
def test_casadi_distances_equal_numpy_and_gradients_match_finite_differences(pks, pair):
    pk = pks[pair]
    col = pk.collision
    q = ca.SX.sym("q", pk.n)
    c = col.clearance_expr(q)
    fn = ca.Function("c", [q], [c, ca.jacobian(c, q)])
    h = 1e-7
    for q0 in _free_postures(pk, 5, 1):
        val, jac = (np.array(v) for v in fn(q0))
        np.testing.assert_allclose(val.ravel(), col.distances(q0) - col.margin, atol=1e-12)
        fd = np.column_stack(
            [
                (col.distances(q0 + h * e) - col.distances(q0 - h * e)) / (2 * h)
                for e in np.eye(pk.n)
            ]
        )
        np.testing.assert_allclose(jac, fd, atol=1e-5)


def test_the_segment_box_distance_is_the_smallest_along_the_segment():
    """The closed form (numpy and CasADi) against the box's signed distance at 20,001
    points along the segment: outside the box the smallest, through it a depth no deeper
    than the deepest; rotated and axis-aligned boxes."""
    a_, b_, c_, h_ = (ca.SX.sym(n, 3) for n in "abch")
    r_ = ca.SX.sym("R", 3, 3)
    fn = ca.Function("d", [a_, b_, c_, r_, h_], [segment_box_distance_expr(a_, b_, c_, r_, h_)])
    rng = np.random.default_rng(12)
    ts = np.linspace(0.0, 1.0, 20001)
    inside = 0
    for k in range(400):
        a = rng.uniform(-0.1, 0.1, 3)
        b = a + rng.uniform(-0.06, 0.06, 3)
        if k % 5 == 0:  # parallel to an axis
            b = a.copy()
            b[k % 3] += 0.03
        rot = (
            Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
            if k % 2
            else np.eye(3)
        )
        box = Box("x", rng.uniform(-0.02, 0.02, 3), rot, rng.uniform(0.005, 0.05, 3))
        local = (a + ts[:, None] * (b - a) - box.centre) @ box.rotation
        qv = np.abs(local) - box.half
        out = np.maximum(qv, 0)
        dense = float(np.min(np.sqrt(np.sum(out * out, axis=1) + 1e-18) + np.minimum(qv.max(1), 0)))
        assert box_sdf(a, box) == pytest.approx(
            np.sqrt(out[0] @ out[0] + 1e-18) + min(qv[0].max(), 0)
        )
        step = np.linalg.norm(b - a) / 20000
        d = segment_box_distance(a, b, box)
        assert float(fn(a, b, box.centre, box.rotation, box.half)) == pytest.approx(d, abs=1e-15)
        if dense > 0:  # outside: the smallest distance, which the samples bracket
            assert dense - step <= d <= dense + 1e-12
        else:  # entering: a depth inside the box, no deeper than the deepest sample
            assert dense - step <= d <= 1e-9
            inside += 1
    assert 0 < inside < 400


@pytest.mark.parametrize("pair", PAIRS)
def test_the_solvers_distance_never_exceeds_fcls_by_more_than_half_a_millimetre(pks, checks, pair):
    pk, mc = pks[pair], checks[pair]
    for q in _free_postures(pk, 150, 2):
        solver = pk.collision.distances(q).min()
        assert mc.min_distance(q)[0] >= min(solver, 0.02) - FCL_TOLERANCE


@pytest.mark.parametrize("pair", PAIRS)
def test_the_penalty_row_and_the_cost_agree_with_numpy(pks, solvers, pair):
    pk, r = pks[pair], solvers[pair]
    fun = objective_function(pk, r.config)
    rng = np.random.default_rng(8)
    qs = pk.lower + rng.random((30, pk.n)) * pk.range
    for q in qs:
        t = pk.features(qs[0]).as_vector()
        cost, res, _ = (np.array(v) for v in fun(q, t, pk.rest, pk.rest))
        want = collision_residual(pk.collision.distances(q) - pk.collision.margin, r.config)
        assert res.ravel()[-1] == pytest.approx(want, rel=1e-9, abs=1e-12)
        assert cost.item() == pytest.approx(r.cost(q, t, pk.rest, pk.rest), rel=1e-9)


def _group_minima(pk: PairKinematics, groups: CollisionGroups, q: np.ndarray) -> np.ndarray:
    c = pk.collision.distances(q) - pk.collision.margin
    return np.array([c[list(t)].min() for t in groups.terms])


def _ends(pk: PairKinematics, q: np.ndarray) -> np.ndarray:
    """Every capsule's axis ends in the pair's base frame, by Pinocchio (6 per capsule)."""
    col, model = pk.collision, pk.kin.model
    data = model.createData()
    pin.framesForwardKinematics(model, data, pk.full_configuration(q))
    base = pk.kin.frame_placement(pk.kin.neutral(), pk.desc.base).inverse()
    out = []
    for c in col.capsules:
        m = base * data.oMf[model.getFrameId(c.link, pin.FrameType.BODY)]
        out += [m.act(c.a), m.act(c.b)]
    return np.concatenate(out)


def _midpoint_bounds(pk: PairKinematics, groups: CollisionGroups, q: np.ndarray) -> np.ndarray:
    ends = _ends(pk, q)
    return np.array([groups.midpoint_bound(g, ends) for g in range(len(groups))])


@pytest.mark.parametrize("pair", PAIRS)
def test_the_midpoint_bounds_are_lower_bounds_of_each_group(pks, pair):
    """At random postures, every group's midpoint bound is below its smallest clearance
    (numpy distances); the capsule ends by Pinocchio equal the solver's CasADi ends."""
    pk = pks[pair]
    groups = CollisionGroups(pk)
    ends_fn = groups.ends_function()
    rng = np.random.default_rng(31)
    gaps = []
    for q in pk.lower + rng.random((200, pk.n)) * pk.range:
        ends = _ends(pk, q)
        np.testing.assert_allclose(np.array(ends_fn(q)).ravel(), ends, rtol=0, atol=1e-12)
        bound, exact = _midpoint_bounds(pk, groups, q), _group_minima(pk, groups, q)
        assert np.all(bound <= exact + 1e-12)
        gaps.append(exact - bound)
    gaps = np.concatenate(gaps)
    assert np.median(gaps) < 0.03  # not vacuous: typically within a few centimetres


@pytest.mark.parametrize("pair", PAIRS)
def test_the_groups_clearance_bounds_hold_for_every_move(pks, pair):
    """``min_g(q) >= min_g(q_a) - L_g . |q - q_a|``, by numpy distances at both postures."""
    pk = pks[pair]
    groups = CollisionGroups(pk)
    assert sorted(k for t in groups.terms for k in t) == list(range(len(pk.collision.terms)))
    rng = np.random.default_rng(21)
    tight = []
    for scale in (0.002, 0.02, 0.2, 1.0):
        for _ in range(40):
            qa = pk.lower + rng.random(pk.n) * pk.range
            q = np.clip(qa + scale * pk.range * rng.uniform(-1, 1, pk.n), pk.lower, pk.upper)
            drop = groups.lipschitz @ np.abs(q - qa)
            real = _group_minima(pk, groups, qa) - _group_minima(pk, groups, q)
            assert np.all(real <= drop + 1e-12)
            tight.append(np.max(real / np.maximum(drop, 1e-12)))
    assert max(tight) > 0.2  # not vacuous: some moves use a good part of the bound


@pytest.mark.parametrize("pair", PAIRS)
def test_the_grouped_evaluation_equals_the_dense_penalty(pks, solvers, pair):
    """Cost, gradient and curvature of the solver's evaluation against the dense CasADi
    objective (every term, no bounds) in numpy; bounds out are lower bounds, exact where
    the group was evaluated."""
    pk, r = pks[pair], solvers[pair]
    config = r.config
    fun = objective_function(pk, config)
    evaluate, _ = _step_functions(pk, config)
    groups = CollisionGroups(pk)
    rng = np.random.default_rng(5)
    band = config.collision_band
    seen = np.zeros(2, dtype=int)  # groups evaluated exactly, groups the midpoint skipped
    seen_band = 0  # postures with terms in the band
    qsym = ca.SX.sym("q", pk.n)
    dense = pk.collision.distance_function()(qsym)
    dense_jac = ca.Function("dense_jac", [qsym], [ca.jacobian(dense, qsym)])
    for k in range(24):
        q = pk.lower + rng.random(pk.n) * pk.range
        qa = (
            q
            if k % 3 == 0
            else np.clip(q + 0.05 * pk.range * rng.uniform(-1, 1, pk.n), pk.lower, pk.upper)
        )
        bounds = _group_minima(pk, groups, qa) if k % 4 else np.full(len(groups), -np.inf)
        t = pk.features(pk.lower + rng.random(pk.n) * pk.range).as_vector()
        par = np.concatenate([t, pk.rest, qa])
        cost, g, h, clear, out = (np.array(v).ravel() for v in evaluate(q, par, qa, bounds))
        c0, res, jac = (np.array(v) for v in fun(q, t, pk.rest, qa))
        res = res.ravel()
        w = 1.0 / np.sqrt(1.0 + res**2)
        np.testing.assert_allclose(cost, c0.ravel(), rtol=1e-12)
        np.testing.assert_allclose(g, jac.T @ (w * res), rtol=1e-9, atol=1e-12)
        # The penalty row's own curvature: 2 scale rho'(r_c) r_c sum(grad c grad c^T) over
        # the terms in the band, by the dense distances' Jacobian (every term).
        scale = config.w_c / band**2
        c_all = pk.collision.distances(q) - pk.collision.margin
        grad_c = np.array(dense_jac(q))[c_all < band]
        extra = 2 * scale * res[-1] * w[-1] * grad_c.T @ grad_c
        np.testing.assert_allclose(
            h, (jac.T @ (w[:, None] * jac) + extra).ravel(order="F"), rtol=1e-9, atol=1e-12
        )
        seen_band += grad_c.shape[0] > 0
        exact = _group_minima(pk, groups, q)
        assert np.all(out <= exact + 1e-12)
        pre = bounds - groups.lipschitz @ np.abs(q - qa)
        mid = _midpoint_bounds(pk, groups, q)
        evaluated = (pre < band) & (mid < band)
        np.testing.assert_allclose(out[evaluated], exact[evaluated], rtol=0, atol=1e-12)
        skipped = (pre < band) & ~evaluated  # kept the better of the two bounds
        np.testing.assert_allclose(out[skipped], np.maximum(pre, mid)[skipped], atol=1e-12)
        seen += evaluated.sum(), skipped.sum()
        _assert_reported_clearance(float(clear[0]), float(exact.min()), band)
    assert seen.min() > 0 and seen_band > 0  # both paths taken; the curvature tested


# ------------------------------------------------------------- calibration
@pytest.mark.parametrize("pair", PAIRS)
def test_the_calibrated_range_and_postures_keep_the_non_pad_margin(pks, checks, pair):
    pk, mc = pks[pair], checks[pair]
    rg, free = pair_range(pk, collisions=True), pair_range(pk)
    # the pads may close on each other (issue 36): the model keeps the pinch end, the
    # pads touching, where the kinematics put it; it narrows only the opening
    assert rg.span_min == pytest.approx(free.span_min, abs=1e-9)
    assert rg.span_min == pytest.approx(2 * pk.desc.tip_radius, abs=1e-6)
    assert rg.span_max <= free.span_max + 1e-9
    for q in np.vstack(
        [rg.postures, [rg.posture(s) for s in np.linspace(rg.span_min, rg.span_max, 97)]]
    ):
        assert pk.collision.clearance(q) >= 0
        assert mc.min_distance(q)[0] >= pk.collision.margin - FCL_TOLERANCE


# ------------------------------------------------------------------ solves
@pytest.mark.parametrize("pair", PAIRS)
def test_a_solve_from_inside_the_margin_still_returns_a_free_command(pks, solvers, pair):
    pk, r = pks[pair], solvers[pair]
    rng = np.random.default_rng(3)
    qs = pk.lower + rng.random((400, pk.n)) * pk.range
    bad = [q for q in qs if pk.collision.clearance(q) < -5e-3][:6]
    assert len(bad) == 6
    for q in bad:
        t = pk.features(q).as_vector()
        out, info = r.solve(t, q, q)  # the previous command and the reference collide
        assert info.evaluations <= 20
        assert r.clearance(out) >= 0 and info.clearance >= 0
        _assert_reported_clearance(info.clearance, r.clearance(out), r.config.collision_band)


def test_the_vm_agrees_with_the_compiled_solver_with_collisions_on(pks, solvers):
    """The virtual machine's graph (the conditional CasADi collision part) and the
    generated C (with the C group loop): the same commands, evaluations and clearances over
    a sequence that carries the groups' bounds."""
    pk, r = pks["L"], solvers["L"]
    assert r.backend == "compiled", r.backend_reason
    assert r.native is not None
    vm = PairRetargeter(kinematics=pk, config=r.config, backend="vm")
    r.reset()
    rng = np.random.default_rng(17)
    near = 0
    for q_true in _free_postures(pk, 6, 41):
        t = pk.features(np.clip(q_true + 0.05 * rng.standard_normal(pk.n), pk.lower, pk.upper))
        qc, ic = r.solve(t.as_vector(), None, pk.rest)
        qv, iv = vm.solve(t.as_vector(), None, pk.rest)
        np.testing.assert_allclose(qv, qc, rtol=0, atol=1e-9)
        assert iv.evaluations == ic.evaluations and iv.iterations == ic.iterations
        assert iv.clearance == pytest.approx(ic.clearance, abs=1e-9)
        near += ic.clearance < r.config.collision_band
    assert near > 0  # some answers end in the band, where the collision terms act


def test_a_solver_with_collisions_the_cache_names_loads_without_its_loop_or_graph(
    hand, pks, solvers, monkeypatch
):
    """With self-collision, a retargeter whose solver the cache names builds neither the
    collision loop's C nor the graph, and answers to the bit as the one that built them,
    over a sequence that carries the groups' bounds; its loop is built when asked for."""
    import payload.retarget.casadi_solver as cs

    built: list[str] = []
    for name in ("NativeCollision", "solve_parts"):
        real = getattr(cs, name)
        monkeypatch.setattr(
            cs, name, lambda *a, _n=name, _f=real, **k: built.append(_n) or _f(*a, **k)
        )
    pk, first = pks["L"], solvers["L"]
    assert first.backend == "compiled", first.backend_reason
    again = PairRetargeter(hand, "L", first.config, pk)
    assert built == [] and again.library == first.library, again.backend_reason
    first.reset(), again.reset()
    for q_true in _free_postures(pk, 6, 43):
        t = pk.features(q_true).as_vector()
        want, got = first.solve(t, None, pk.rest), again.solve(t, None, pk.rest)
        assert got[0].tobytes() == want[0].tobytes() and got[1] == want[1]
    assert again.native is not None and built == ["NativeCollision"]
    assert again.native.source == first.native.source  # the C the library was built with


def test_a_solver_is_named_in_the_cache_only_when_built_from_what_the_cache_keeps(
    hand, pks, solvers, monkeypatch
):
    """A compiled solver with self-collision is named in the cache only when its collision
    geometry is one the cache keeps (its key, the compiled distances) and it holds the
    collision loop's C; and only under the key it was built under."""
    import payload.retarget.casadi_solver as cs
    from payload.retarget import compiled

    named: list[str] = []
    monkeypatch.setattr(cs, "store_solver", lambda key, *rest: named.append(key))
    r, compiler = solvers["L"], compiled._compiler()
    assert r.backend == "compiled", r.backend_reason
    assert r.native is not None  # built now, if the solver came from the cache
    key = r._solver_key(compiler)
    assert key is not None
    r._store_solver(key, compiler)
    assert named == [key]
    r._store_solver("0" * 24, compiler)  # not the key it was built under
    col = pks["L"].collision
    for obj, attr, value in [
        (col, "key", None),  # a geometry the cache did not keep
        (type(col), "compiled_distances", lambda self, terms=None: False),
        (r, "_native", None),  # compiled without its collision loop
    ]:
        with monkeypatch.context() as m:
            m.setattr(obj, attr, value)
            r._store_solver(key, compiler)
    assert named == [key]


@pytest.mark.parametrize(
    ("collisions", "budget"), [(True, "converged"), (True, "paper"), (False, "paper")]
)
def test_the_c_driver_gives_the_graphs_generated_code_bit_for_bit(hand, pks, collisions, budget):
    """The compiled solver's C loop over the starts and iterations (payload.retarget.lm_c,
    with its own init, finish and proposal) and CasADi's own generated code of the
    nested-conditional graph, compiled beside it: the same bytes on a carried sequence.
    With collision groups, through all the starts of the converged budget (short
    iteration caps: the starts stop at their caps and the later ones still run) and the
    paper budget's starts with the model (probes, then the start from the best point met);
    without (no groups), the paper budget, with targets past the joint limits so that
    steps stop on bounds."""
    pk = pks["R"]
    if collisions and budget == "converged":
        config = RetargetConfig(collisions=True, budget="converged", max_iterations=4)
    elif collisions:
        config = RetargetConfig(collisions=True, budget="paper")
    else:
        config = RetargetConfig(collisions=False, budget="paper")
    r = PairRetargeter(hand, "R", config, pk, backend="compiled")
    extra = {f"{r.native.name}.c": r.native.source} if r.native is not None else None
    graph = _CompiledSolve(r.function, shutil.which("cc") or "gcc", extra)
    assert graph.path != r.library and (r.native is not None) == collisions
    rng = np.random.default_rng(5)
    used = set()
    postures = list(_free_postures(pk, 12, 8))
    if not collisions:  # past the limits: clipped targets, answers on the bounds
        postures += list(pk.lower - 0.2 * pk.range + rng.random((12, pk.n)) * 1.4 * pk.range)
    on_bound = 0
    for q_true in postures:
        t = pk.features(np.clip(q_true + 0.1 * rng.standard_normal(pk.n), pk.lower, pk.upper))
        anchor = (r._compiled.inputs[3].copy(), r._compiled.inputs[4].copy())
        q_prev = r.command.copy()
        q, info = r.solve(t.as_vector(), None, pk.rest)
        for buf, v in zip(graph.inputs, (q_prev, t.as_vector(), pk.rest, *anchor)):
            buf[:] = v
        graph()
        assert graph.outputs[0].tobytes() == q.tobytes()
        assert graph.outputs[1].tobytes() == r._compiled.outputs[1].tobytes()
        assert graph.outputs[2].tobytes() == r._compiled.outputs[2].tobytes()
        used.add(info.evaluations)
        on_bound += int(np.any((q == pk.lower) | (q == pk.upper)))
    if collisions:
        assert max(used) == evaluation_cap(config)  # every start ran, the last to its cap
        if budget == "paper":
            assert budget_plan(config)[-1][0] == RESUME
    else:
        assert used == {r.config.max_nfev} and on_bound > 0


@pytest.mark.parametrize("pair", PAIRS)
def test_the_c_group_loop_equals_the_conditional_casadi_form(pks, solvers, pair):
    """The compiled solver's C loop over the groups and the conditional CasADi form give
    the same penalty, gradient, group minima and curvature, with bounds that skip some
    groups, let the midpoint bound skip others and leave the rest to the exact terms."""
    pk, r = pks[pair], solvers[pair]
    groups = CollisionGroups(pk)
    native = r.native.penalty_function()
    form = groups.penalty_function(r.config)
    rng = np.random.default_rng(13)
    band = r.config.collision_band
    paths = np.zeros(3, dtype=int)  # bound-skipped, midpoint-skipped, exact
    free = _free_postures(pk, 60, 100)  # near the margin's edge, where groups are exact
    for k in range(120):
        q = free[k // 2 % len(free)] if k % 2 else pk.lower + rng.random(pk.n) * pk.range
        exact = _group_minima(pk, groups, q)
        pre = np.where(
            rng.random(len(groups)) < 0.5, -np.inf, exact - rng.random(len(groups)) * 0.02
        )
        a = [np.array(v).ravel() for v in native(q, pre)]
        b = [np.array(v).ravel() for v in form(q, pre)]
        for x, y in zip(a, b):
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-15)
        mid = _midpoint_bounds(pk, groups, q)
        evaluated = (pre < band) & (mid < band)
        paths += [(pre >= band).sum(), ((pre < band) & (mid >= band)).sum(), evaluated.sum()]
        np.testing.assert_allclose(a[2][evaluated], exact[evaluated], rtol=0, atol=1e-12)
    assert paths.min() > 0 and a[0].size == 1


def test_without_a_working_compiler_collisions_run_in_the_conditional_form(
    pks, solvers, failing_compiler
):
    """A compiler that fails: the collision loop and the solver are not compiled, both
    are said in one line each, and the virtual machine's conditional form gives the
    compiled solver's command."""
    pk, r = pks["R"], solvers["R"]
    with pytest.warns(RuntimeWarning) as caught:
        vm = PairRetargeter(kinematics=pk, config=r.config)
    messages = [str(w.message) for w in caught]
    assert any(
        "collision loop not compiled (compiling the collision loop failed" in m for m in messages
    )
    assert any("virtual machine" in m for m in messages)
    assert all("\n" not in m for m in messages)
    assert vm.backend == "vm" and vm.native is None
    t = pk.features(_free_postures(pk, 1, 5)[0]).as_vector()
    r.reset()
    qc, ic = r.solve(t, None, pk.rest)
    qv, iv = vm.solve(t, None, pk.rest)
    np.testing.assert_allclose(qv, qc, rtol=0, atol=1e-9)
    assert iv.evaluations == ic.evaluations and iv.clearance >= 0


def _assert_reported_clearance(reported: float, exact: float, band: float) -> None:
    """The solver's clearance: exact below the band, else a lower bound of at least it."""
    if exact < band:
        assert reported == pytest.approx(exact, abs=1e-9)
    else:
        assert band <= reported <= exact + 1e-12


@pytest.mark.slow
def test_random_human_pinches_over_the_full_opening_never_command_a_collision(pks, solvers, checks):
    pinch, open_ = human_pinch_and_open()
    rng = np.random.default_rng(14)
    worst_solver, worst_fcl, collided = np.inf, np.inf, 0
    for i, pair in enumerate(PAIRS):
        pk, r, mc = pks[pair], solvers[pair], checks[pair]
        cal = calibrate(pinch, open_, pair_range(pk, collisions=True))
        margin = pk.collision.margin
        r.reset()
        for _ in range(N_HUMAN // len(PAIRS)):
            opening = rng.uniform(-0.1, 1.1)  # beyond both calibrated ends too
            roll = rng.uniform(-0.8, 0.8)
            drift = rng.uniform(-0.02, 0.02, 3)
            pts = synthetic_hand(opening, roll, drift) + rng.normal(0.0, 1e-3, (4, 3))
            targets, q_ref = cal.command(features_from_points(*pts))
            q, info = r.solve(targets, None, q_ref)
            assert info.evaluations <= 20
            worst_solver = min(worst_solver, info.clearance)
            near = mc.near_pairs(q, margin)
            if near:
                d = mc.min_distance_near(q, margin)
                worst_fcl = min(worst_fcl, d)
                collided += int(d <= 0.0)
        del i
    assert collided == 0
    assert worst_solver >= 0.0  # the margin, in the solver's own distance
    assert worst_fcl >= margin - FCL_TOLERANCE  # and within 0.5 mm of it by python-fcl


# --------------------------------------------------------------- other hands
def test_hands_with_and_without_collision_geometry(tmp_path):
    register()  # the pair's .collision below, before any retargeter registers it
    offset = load_hand(HANDS_DIR / "offset_distal.toml")
    pk = PairKinematics(offset)
    assert pk.collision.available and offset.collision_margin == 0.002
    thumb = load_hand(HANDS_DIR / "thumb_abduction_first.toml")
    pk2 = PairKinematics(thumb)
    assert not pk2.collision.available
    r = PairRetargeter(thumb, config=RetargetConfig(collisions=True), kinematics=pk2)
    _, info = r.solve(pk2.features(pk2.rest), pk2.rest, pk2.rest)
    assert info.clearance == np.inf  # no collision geometry: nothing measured
    off = PairRetargeter(load_hand(), config=RetargetConfig())  # collisions off by default
    _, info = off.solve(off.kinematics.features(off.kinematics.rest), None, None)
    assert not off.collisions and info.clearance == np.inf


def test_hold_keeps_the_carried_bounds_and_answers_as_reset_does(hand, pks):
    """``hold`` (what the teleoperation pipeline calls between steps) keeps the collision
    groups' carried bounds, ``reset`` forgets them; both then give the same answers bit
    for bit, with the same evaluation counts, on a stream whose held command is not the
    last answer (a blend toward it, as after a tracking recovery)."""
    pk = pks["L"]
    held = PairRetargeter(hand, "L", RetargetConfig(collisions=True), pk)
    fresh = PairRetargeter(hand, "L", RetargetConfig(collisions=True), pk)
    rng = np.random.default_rng(21)
    kept = 0
    for q_true in _free_postures(pk, 40, 22):
        t = pk.features(np.clip(q_true + 0.05 * rng.standard_normal(pk.n), pk.lower, pk.upper))
        before = held.command
        q_a, info_a = held.solve(t.as_vector(), None, pk.rest)
        q_b, info_b = fresh.solve(t.as_vector(), None, pk.rest)
        np.testing.assert_array_equal(q_a, q_b)
        assert info_a.evaluations == info_b.evaluations
        blend = q_a + 0.3 * rng.random() * (before - q_a)  # partway back to the last hold
        held.hold(blend)
        fresh.reset(blend)
        np.testing.assert_array_equal(held.command, fresh.command)
        kept += int(np.isfinite(held._compiled.inputs[4]).any())
        assert not np.isfinite(fresh._compiled.inputs[4]).any()
    assert kept == 40  # every hold kept bounds to carry


def test_a_hand_without_its_meshes_retargets_without_the_model_and_names_the_file_with_it(
    tmp_path,
):
    # our URDF copied alone: every collision mesh it names is missing
    shutil.copy(current_project().root / "urdf" / "payload.urdf", tmp_path / "payload.urdf")
    bare = load_hand(hand_file(tmp_path, "payload.urdf", current_project().design_path))
    pk = PairKinematics(bare, "L")
    off = PairRetargeter(bare, "L", RetargetConfig(collisions=False), pk)
    cal = calibrate(*human_pinch_and_open(), pair_range(pk, collisions=False))
    targets, q_ref = cal.command(features_from_points(*synthetic_hand(0.5, 0.0, np.zeros(3))))
    q, info = off.solve(targets, None, q_ref)
    assert np.all(np.isfinite(q)) and info.evaluations <= 20
    with pytest.raises(RetargetError, match=r"^collision mesh not found: .*meshes/\w+\.stl \("):
        PairRetargeter(bare, "L", RetargetConfig(collisions=True), PairKinematics(bare, "L"))
    with pytest.raises(RetargetError, match=r"^collision mesh not found: .*\.stl"):
        PairMeshCheck(pk)
