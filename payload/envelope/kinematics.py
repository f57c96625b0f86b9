"""The shared kinematics of a design, for the reach report.

The reach report uses the models the retargeter uses: Pinocchio
(:class:`payload.kinematics.Kinematics`) on the URDF the design generates
(:func:`payload.design.urdf.to_urdf`, so a ``--design`` other than the project's is
honoured), and the retargeter's pairs (:class:`payload.retarget.PairKinematics`, our
hand description with the design's pad radius), whose span range is
:func:`payload.retarget.pair_range`'s.
"""

from __future__ import annotations

import dataclasses
import shutil
import sys
import tempfile
import weakref
from pathlib import Path
from typing import NamedTuple

from payload.design.params import FINGER_JOINTS
from payload.design.tree import KinematicTree
from payload.design.urdf import to_urdf
from payload.envelope.pairs import PAIRS
from payload.kinematics import Kinematics
from payload.retarget.features import PairKinematics
from payload.retarget.hand import DEFAULT_HAND, design_rest, hand_from_dict

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


class DesignKinematics(NamedTuple):
    """Pinocchio models of one design.

    Attributes:
        kin: The whole payload (every joint of the URDF).
        pairs: Pair name -> the retargeter's model of that pair (its base frame, its 8
            joints, the design's pad radius).
    """

    kin: Kinematics
    pairs: dict[str, PairKinematics]


def design_kinematics(tree: KinematicTree) -> DesignKinematics:
    """The shared kinematics of the design behind ``tree``.

    The URDF is generated from ``tree`` into a temporary folder, loaded there
    (Pinocchio reads no meshes) and removed with the model; the pairs are our hand description
    (:data:`payload.retarget.hand.DEFAULT_HAND`) on that model, with
    ``tip_radius`` taken from the design's ``finger.pad.radius``.
    """
    raw = tomllib.loads(DEFAULT_HAND.read_text())
    for pair in raw["pairs"].values():  # the pads touch at twice the given design's radius
        pair["tip_radius"] = float(tree.design.finger.pad.radius)
    # the margin and structure of the given design, not the current project's
    source = Path(tree.design.source)
    if source.is_file():
        raw["design"] = str(source.resolve())
    else:  # a design built in memory: what the hand would read from a design file
        raw.pop("design", None)
        raw["collision_margin"] = float(tree.design.retarget.collision_margin)
        preshape = dict(zip(FINGER_JOINTS, tree.design.pinch.finger))
        for name, pair in raw["pairs"].items():  # the rest posture: the pinch pre-shape
            joints = (*pair["joints"][0], *pair["joints"][1])
            pair["rest"] = list(design_rest(f"pairs.{name}", joints, preshape))
    # the URDF lives as long as the model: the span range's disk cache
    # (:mod:`payload.retarget.range_cache`) keys on its text, so a report run again on
    # the same design reads the range instead of solving it again
    tmp = tempfile.mkdtemp(prefix="payload-reach-")
    path = Path(tmp) / "payload.urdf"
    path.write_text(to_urdf(tree))
    kin = Kinematics(path)
    weakref.finalize(kin, shutil.rmtree, tmp, ignore_errors=True)
    raw["urdf"] = str(path)
    hand = hand_from_dict(raw, DEFAULT_HAND.parent, source=DEFAULT_HAND)
    if hand.design is None:  # the pad link, too, is the given design's
        hand = dataclasses.replace(hand, pad_link=tree.design.retarget.pad_link)
    pairs = {name: PairKinematics(hand, name, kin) for name in PAIRS}
    return DesignKinematics(kin, pairs)


__all__ = ["DesignKinematics", "design_kinematics"]
