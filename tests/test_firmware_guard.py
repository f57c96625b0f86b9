"""The driver's collision guard (firmware_interface.guard): checked against python-fcl on
the generated meshes, and end to end through the emulated servo bus."""

from __future__ import annotations

import logging

import fcl
import numpy as np
import pytest

from firmware_interface.control_table import ADDR
from firmware_interface.driver import DynamixelDriver
from firmware_interface.emulator import EmulatorProcess
from firmware_interface.guard import JOINTS, default_guard
from firmware_interface.options import EMULATOR_LATENCY_MS as LAT  # [ms] reply allowance
from firmware_interface.servo_map import load_servo_map
from payload.retarget.features import PairKinematics
from payload.retarget.meshcheck import PairMeshCheck
from payload.schema import PayloadCommand

DEPLOYED = {"rail": 0.025, "stage": 0.075}


@pytest.fixture(scope="module")
def guard():
    return default_guard()


@pytest.fixture(scope="module")
def mesh_l():
    return PairMeshCheck(PairKinematics(pair="L"))


def _values(pair_q: dict[str, float] | None = None) -> np.ndarray:
    v = np.zeros(len(JOINTS))
    for name, x in {**DEPLOYED, **(pair_q or {})}.items():
        v[JOINTS.index(name)] = x
    return v


def _crossed_middles(mesh: PairMeshCheck, guard, seed: int = 0) -> np.ndarray:
    """A pair-L posture whose A_middle and C_middle meshes intersect (python-fcl) and that
    comes near nothing but pair L's own links (so only pair L should be held)."""
    pk = mesh.pk
    rng = np.random.default_rng(seed)
    req = fcl.CollisionRequest()
    own = [set(guard._names(t)) <= set(mesh.fingers[0] + mesh.fingers[1])
           for t in range(guard.terms)]  # fmt: skip
    for _ in range(5000):
        q = pk.lower + rng.random(pk.n) * pk.range
        mesh._pose(q)
        a, c = mesh._objects["A_middle"][0][0], mesh._objects["C_middle"][0][0]
        if fcl.collide(a, c, req, fcl.CollisionResult()) == 0:
            continue
        clear = guard.clearances(_values(dict(zip(pk.joints, q))))
        if all(own[t] for t in np.flatnonzero(clear < 0)):
            return q
    raise AssertionError("no crossed posture found")


def test_capsule_distances_bound_the_mesh_distances(guard, mesh_l):
    """Every guard term of pair L is at most python-fcl's distance between the meshes
    (the capsules and boxes enclose them), so a guard-clear command is mesh-clear."""
    pk = mesh_l.pk
    rng = np.random.default_rng(4)
    names = [guard._names(t) for t in range(guard.terms)]
    compared = 0
    for _ in range(12):
        q = pk.lower + rng.random(pk.n) * pk.range
        v = _values(dict(zip(pk.joints, q)))
        clear = guard.clearances(v) + guard.margin
        least: dict[tuple[str, str], float] = {}  # a structure link has several boxes
        for t, key in enumerate(names):
            least[key] = min(least.get(key, np.inf), float(clear[t]))
        mesh_l._pose(q)
        for (a, b), c in least.items():
            if a not in mesh_l._objects or b not in mesh_l._objects:
                continue  # the other pair's links
            if b in ("carriage", "base"):
                continue  # posed at the rail's and stage's neutral by the pair check
            d = min(
                fcl.distance(oa, ob, fcl.DistanceRequest(), fcl.DistanceResult())
                for oa, _ in mesh_l._objects[a]
                for ob, _ in mesh_l._objects[b]
            )
            if d > 0.03:
                continue  # far apart: the bound holds trivially
            assert c <= max(d, 0.0) + 1e-6, (a, b, c, d)
            compared += 1
    assert compared > 20


def test_pad_pair_is_not_checked_and_every_other_pair_is(guard):
    pairs = {frozenset(guard._names(t)) for t in range(guard.terms)}
    assert frozenset(("A_distal", "C_distal")) not in pairs
    assert frozenset(("B_distal", "D_distal")) not in pairs
    assert frozenset(("A_distal", "B_distal")) in pairs  # across the pairs
    assert frozenset(("A_middle", "C_middle")) in pairs


def test_a_pinch_on_nothing_passes_and_going_deeper_from_stowed_does_not(guard, design):
    g = default_guard()
    # the pinch pre-shape closed until the pads meet: no non-pad margin is violated
    pinch = dict(zip(("mcp_flex", "mcp_abd", "pip", "dip"), design.pinch.finger))
    v = _values({f"{f}_{j}": x for f in "ABCD" for j, x in pinch.items()})
    assert g.filter(v) is not None and g.refusals == 0
    # stowed: packed closer than the margin; the guard lets it move out, not further in
    stowed = dict(zip(("mcp_flex", "mcp_abd", "pip", "dip"), design.stowed.finger))
    s = _values({f"{f}_{j}": x for f in "ABCD" for j, x in stowed.items()})
    s[JOINTS.index("rail")], s[JOINTS.index("stage")] = design.stowed.rail, design.stowed.stage
    g.reset(s)
    before = g.clearances(s)
    assert before.min() < 0
    assert np.array_equal(g.filter(s), s) and g.refusals == 0  # holding there is allowed
    k = JOINTS.index("A_pip")
    for step in (0.05, -0.05):
        out = s.copy()
        out[k] += step
        deeper = g.clearances(out) < np.minimum(before, 0.0) - 1e-4
        sent = g.filter(out)
        g.reset(s)
        # refused (A's pair held) exactly when a pair already inside goes deeper
        assert np.array_equal(sent, s if deeper.any() else out), step
    assert g.refusals >= 1


def test_crossed_middle_links_never_reach_the_servos(guard, mesh_l, caplog):
    crossed = dict(zip(mesh_l.pk.joints, _crossed_middles(mesh_l, guard)))
    smap = load_servo_map()
    with EmulatorProcess() as emu, DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
        drv.bring_up()
        safe = _values()
        drv.send(PayloadCommand(safe[:17], float(safe[17]), 0.0))
        bad = _values({**crossed, "B_mcp_flex": 0.2})  # and a harmless move of pair R
        with caplog.at_level(logging.WARNING, logger="firmware_interface.guard"):
            for _ in range(3):
                drv.send(PayloadCommand(bad[:17], float(bad[17]), 0.0))
                drv.read()
        tables = emu.tables()
        a = ADDR["goal_position"]

        def goal(joint: str) -> int:
            spec = next(s for s in smap.servos if s.joint == joint)
            return int.from_bytes(tables[spec.id][a : a + 4], "little", signed=True)

        def ticks(joint: str, x: float) -> int:
            spec = next(s for s in smap.servos if s.joint == joint)
            return int(np.rint(spec.zero + spec.direction * x / spec.units_per_tick))

        for joint in crossed:  # pair L held at the safe command
            assert goal(joint) == ticks(joint, 0.0), joint
        assert goal("B_mcp_flex") == ticks("B_mcp_flex", 0.2)  # pair R went through
        assert drv.guard.refusals == 3
        assert "L" in drv.guard.last.held and "R" not in drv.guard.last.held
        assert any(("A_middle", "C_middle") == p[:2] for p in drv.guard.last.pairs)
        assert sum("command refused" in r.getMessage() for r in caplog.records) == 3
