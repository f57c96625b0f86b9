"""The contact-aware self-collision rule (issue 36): the two pads of a pair may close on
each other, every other link pair and the structure keep the design's margin, checked
with python-fcl on the generated meshes (an independent library)."""

from __future__ import annotations

from pathlib import Path

import fcl
import numpy as np
import pytest

from payload.retarget import PairKinematics, load_hand
from payload.retarget.collision import register
from payload.retarget.meshcheck import PairMeshCheck

DATA = Path(__file__).resolve().parent / "data"
POSTURES = DATA / "safe_trial_seed0_postures.npz"
"""Every 25th commanded pair posture (``q_left``, ``q_right``, 295 each, and the time
``t``) of ``payload trial --controller safe --seed 0`` (135 s, success), from its
``log.mcap`` (``payload.trials.reading.read_recording``: ``q_left``, ``q_right``)."""
FCL_TOLERANCE = 0.5e-3
"""How much nearer than the margin python-fcl may find the meshes (issue 36) [m]."""


@pytest.fixture(scope="module")
def hand():
    register()  # pk.collision (the retargeters call it; a test alone might not build one)
    return load_hand()


@pytest.mark.parametrize("pair", ("L", "R"))
def test_the_pad_links_are_the_only_pair_left_out(hand, pair):
    pk = PairKinematics(hand, pair)
    check = PairMeshCheck(pk)
    f1, f2 = check.fingers
    pads = {f"{f}_{hand.pad_link}" for f in pk.desc.tips[0][0] + pk.desc.tips[1][0]}
    assert set(check.pads) == pads
    finger_pairs = {frozenset(p) for p in check.pairs if p[1] in f2}
    assert finger_pairs == {frozenset((a, b)) for a in f1 for b in f2} - {frozenset(pads)}
    col = pk.collision
    left_out = {
        frozenset((col.capsules[t.capsule].link, col.capsules[t.other].link))
        for t in col.all_terms
        if not t.box
    }
    assert frozenset(pads) not in left_out
    assert frozenset((f"{pk.desc.tips[0][0]}_middle", f"{pk.desc.tips[1][0]}_middle")) in left_out


def test_every_commanded_posture_of_a_safe_trial_keeps_the_non_pad_margin(hand):
    data = np.load(POSTURES)
    margin = hand.collision_margin
    pads_least = np.inf
    for pair, key in (("L", "q_left"), ("R", "q_right")):
        check = PairMeshCheck(PairKinematics(hand, pair))
        qs = np.unique(data[key], axis=0)
        assert len(qs) > 100
        collided = sum(check.in_collision(q) for q in qs)
        least = min(check.min_distance_near(q, margin) for q in qs)
        assert collided == 0, pair
        assert least >= margin - FCL_TOLERANCE, (pair, least)
        a, b = check.pads
        for q in qs:
            check._pose(q)
            for oa, _ in check._objects[a]:
                for ob, _ in check._objects[b]:
                    d = fcl.distance(oa, ob, fcl.DistanceRequest(), fcl.DistanceResult())
                    pads_least = min(pads_least, d)
    # and the pinch did close the pads inside the margin the old rule kept between them
    assert pads_least < margin


N_PINCHES = 100_000
"""Random pinches and openings of the acceptance test (issue 36), split over the pairs."""


@pytest.mark.slow
def test_random_pinches_and_openings_give_no_non_pad_collision(hand):
    """100,000 solves of the safe controller (the paper budget with the model) on random
    human pinches and openings (beyond both calibrated ends, rolled, drifting, noisy).

    Every answer's capsule distances are computed for every non-pad link pair and the
    structure (the unpruned terms, in the generated C); the capsules and boxes enclose
    the meshes (``test_capsules_contain_every_collision_mesh_vertex``), so an answer whose
    capsules keep the margin has meshes at least that far apart. python-fcl then runs on
    every answer whose capsules come within the margin (none should), on the 200 nearest
    and on 300 drawn at random: an independent check of the bound where it is tightest.
    """
    from payload.retarget import (
        PairRetargeter,
        RetargetConfig,
        calibrate,
        features_from_points,
        pair_range,
    )
    from payload.retarget.bench import human_pinch_and_open, synthetic_hand

    pinch, open_ = human_pinch_and_open()
    rng = np.random.default_rng(36)
    margin = hand.collision_margin
    for pair in ("L", "R"):
        pk = PairKinematics(hand, pair)
        r = PairRetargeter(hand, pair, RetargetConfig(collisions=True), pk)
        cal = calibrate(pinch, open_, pair_range(pk, collisions=True))
        n = N_PINCHES // 2
        qs = np.empty((n, pk.n))
        for k in range(n):
            opening = rng.uniform(-0.1, 1.1)
            roll = rng.uniform(-0.8, 0.8)
            drift = rng.uniform(-0.02, 0.02, 3)
            pts = synthetic_hand(opening, roll, drift) + rng.normal(0.0, 1e-3, (4, 3))
            targets, q_ref = cal.command(features_from_points(*pts))
            qs[k], info = r.solve(targets, None, q_ref)
            assert info.evaluations <= 20
        col = pk.collision
        least = col.distances_many(qs, col.all_terms).min(axis=0)  # (n,)
        check = PairMeshCheck(pk)
        pick = set(np.flatnonzero(least < margin)) | set(np.argsort(least)[:200])
        pick |= set(rng.choice(n, 300, replace=False))
        for k in sorted(pick):
            assert not check.in_collision(qs[k]), (pair, k)
            d = check.min_distance_near(qs[k], margin)
            assert d >= min(least[k], margin) - FCL_TOLERANCE, (pair, k, d, least[k])
        assert least.min() >= margin - 1e-9, pair  # the solver's own distance keeps it
