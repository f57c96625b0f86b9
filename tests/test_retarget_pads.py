"""The contact-aware self-collision rule (issue 36): the two pads of a pair may close on
each other, every other link pair and the structure keep the design's margin, checked
with python-fcl on the generated meshes (an independent library)."""

from __future__ import annotations

from pathlib import Path

import fcl
import numpy as np
import pytest

from payload.retarget import PairKinematics, load_hand
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
