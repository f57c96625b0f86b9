"""The driver's last line: every command checked against the self-collision margins.

Whatever produced a command (the retargeter with or without its collision model, a
replay, a script, a future policy), :class:`CommandGuard` checks it before it reaches the
servos, with the retargeter's own geometry (:mod:`payload.retarget.collision`): one
capsule per finger link, posed by Pinocchio's forward kinematics of the whole payload
(the 17 manipulation coordinates and the stage), and the structure's boxes (base, stage,
carriage). Every link pair keeps the design's ``retarget.collision_margin`` (two links of
different fingers, of one pair or across the pairs, and a finger link against the
structure, except a finger's first link against the link it is mounted on) but the two
pad links of one pair (``retarget.pad_link``): a pinch closes the pads on each other and
on what they hold, and that is the one contact the payload is built for.

A command that would violate a margin is not sent as it is: the joints involved hold the
last safe command (the groups: a pair's eight finger joints, the rail, the stage; a pair
term holds its pair, a term across the pairs or against the structure holds its pairs,
the rail and the stage), checked again until what is sent is safe (at worst the whole
last safe command). Each refusal is counted and logged. Its cost is measured by
``payload bench hw`` (``guard_us``).
"""

from __future__ import annotations

import functools
import logging
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import pinocchio as pin

from payload.design.tree import MANIPULATION_JOINTS
from payload.retarget.collision import (
    _points,
    enclosing_capsule,
    link_geometry,
    pad_links,
    structure_boxes,
)
from payload.retarget.collision_distance import (
    _segment_distance_ca,
    segment_box_distance_expr,
    segment_box_distances,
    segment_distances,
)
from payload.retarget.features import PairKinematics
from payload.retarget.hand import HandDescription, load_hand

log = logging.getLogger(__name__)

JOINTS: tuple[str, ...] = (*MANIPULATION_JOINTS, "stage")
"""The order of the values the guard checks: the 17 manipulation coordinates, the stage."""


DEEPER = 1e-4
"""A pair already inside its margin at the last safe command violates only by coming
closer than this more [m] (well under the servos' resolution at a link's end: 0.088 deg
a tick on a 45 mm link is 0.07 mm)."""


@dataclass
class Refusal:
    """One refused command.

    Attributes:
        held: The joint groups held at the last safe command.
        pairs: The link pairs (or link and structure link) that would have violated the
            margin, with their clearance [m] (negative: inside the margin).
    """

    held: tuple[str, ...]
    pairs: tuple[tuple[str, str, float], ...]


class CommandGuard:
    """Checks payload commands against the non-pad self-collision margins.

    Args:
        hand: The hand (default: ours, on the current project's URDF and design).
        margin: Least distance [m] (default: the hand's ``collision_margin``).

    Attributes:
        margin: [m].
        refusals: Commands refused so far.
        last: The last refusal, or ``None``.
    """

    def __init__(self, hand: HandDescription | None = None, margin: float | None = None) -> None:
        hand = hand if hand is not None else load_hand()
        self.margin = float(hand.collision_margin if margin is None else margin)
        kin = hand.kinematics()
        self._model = kin.model
        self._data = kin.model.createData()
        self._q = kin.neutral()
        self._qidx = kin.q_indices(JOINTS)
        model = kin.model
        geometry = link_geometry(Path(kin.urdf))
        links = [n for n in geometry if model.existBodyName(n)]

        def moved_by(link: str) -> set[str]:
            j, out = model.frames[model.getFrameId(link, pin.FrameType.BODY)].parentJoint, set()
            while j > 0:
                out.add(model.names[j])
                j = model.parents[j]
            return out

        joint_links = {
            j.get("name"): (j.find("parent").get("link"), j.find("child").get("link"))
            for j in ET.parse(kin.urdf).getroot().findall("joint")
        }
        group_of = {"rail": "rail", "stage": "stage"}
        caps, cap_group, cap_finger = [], [], []
        pads: set[frozenset[str]] = set()
        mounted: set[tuple[str, str]] = set()
        for name, desc in hand.pairs.items():
            pk = PairKinematics(hand, name, kin)
            found = pad_links(pk, frozenset(links))
            if None not in found:
                pads.add(frozenset(found))
            for i, fj in enumerate(desc.finger_joints):
                group_of.update({j: name for j in fj})
                for n in sorted(x for x in links if moved_by(x) & set(fj)):
                    pts = np.vstack([_points(k, g, o) for k, g, o in geometry[n]])
                    caps.append(enclosing_capsule(n, pts))
                    cap_group.append(name)
                    cap_finger.append((name, i))
                if fj:
                    mounted.add((joint_links[fj[0]][0], joint_links[fj[0]][1]))
        pair_joints = set(group_of) - {"rail", "stage"}
        structure = sorted(n for n in links if not moved_by(n) & pair_joints)
        local = structure_boxes(hand.design, geometry, structure)
        self.capsules = tuple(caps)
        self.boxes = tuple(b for n in structure for b in local[n])
        self._groups = np.array([group_of.get(j, "stage") for j in JOINTS])
        cc, cc_groups = [], []
        for i in range(len(caps)):
            for j in range(i + 1, len(caps)):
                if cap_finger[i] == cap_finger[j]:
                    continue
                if frozenset((caps[i].link, caps[j].link)) in pads:
                    continue
                cc.append((i, j))
                same = cap_group[i] == cap_group[j]
                cc_groups.append((cap_group[i],) if same else (cap_group[i], cap_group[j], "rail"))
        cb, cb_groups = [], []
        for i, c in enumerate(caps):
            for k, b in enumerate(self.boxes):
                if (b.link, c.link) not in mounted:
                    cb.append((i, k))
                    cb_groups.append((cap_group[i], "rail", "stage"))
        self._cc = np.array(cc, dtype=int).reshape(-1, 2)
        self._cb = np.array(cb, dtype=int).reshape(-1, 2)
        self._term_groups = cc_groups + cb_groups
        self._radius = np.array([c.radius for c in caps])
        self._radii = np.concatenate(
            [
                self._radius[self._cc[:, 0]] + self._radius[self._cc[:, 1]],
                self._radius[self._cb[:, 0]],
            ]
        )
        # the geometry in its link's joint frame (a body frame is fixed to its joint)
        frames = [model.frames[model.getFrameId(c.link, pin.FrameType.BODY)] for c in caps]
        box_frames = [
            model.frames[model.getFrameId(b.link, pin.FrameType.BODY)] for b in self.boxes
        ]
        self._joints = sorted({f.parentJoint for f in frames + box_frames})
        self._cap_joint = np.array([self._joints.index(f.parentJoint) for f in frames])
        self._box_joint = np.array([self._joints.index(f.parentJoint) for f in box_frames])
        self._cap_ends = np.array(
            [[f.placement.act(c.a), f.placement.act(c.b)] for c, f in zip(caps, frames)]
        )
        self._box_local = (
            np.array([f.placement.act(b.centre) for b, f in zip(self.boxes, box_frames)]),
            np.array([f.placement.rotation @ b.rotation for b, f in zip(self.boxes, box_frames)]),
            np.array([b.half for b in self.boxes]),
        )
        self._distances = _distance_program(self._cc, self._cb, len(caps), len(self.boxes))
        self.refusals = 0
        self.last: Refusal | None = None
        self._safe: np.ndarray | None = None
        self._safe_clear: np.ndarray | None = None

    @property
    def terms(self) -> int:
        """Number of link pairs checked."""
        return len(self._term_groups)

    def clearances(self, values: np.ndarray) -> np.ndarray:
        """Every checked pair's distance less the margin at ``values`` [m], shape (terms,):
        capsule pairs first, then capsule-box pairs.

        Args:
            values: The 17 manipulation coordinates and the stage, shape (18,) [rad, m].
        """
        q = self._q.copy()
        q[self._qidx] = values
        pin.forwardKinematics(self._model, self._data, q)
        omi = self._data.oMi
        pose = np.array([omi[j].homogeneous for j in self._joints])  # (frames, 4, 4)
        cap = pose[self._cap_joint]  # capsule ends: link frame -> joint frame -> world
        ends = np.einsum("kij,kej->kei", cap[:, :3, :3], self._cap_ends) + cap[:, None, :3, 3]
        box = pose[self._box_joint]
        c, r, h = self._box_local
        centres = np.einsum("kij,kj->ki", box[:, :3, :3], c) + box[:, :3, 3]
        rots = box[:, :3, :3] @ r
        compiled = self._distances
        if compiled is not None:
            compiled.inputs[0][:] = ends.ravel()
            compiled.inputs[1][:] = centres.ravel()
            compiled.inputs[2][:] = rots.transpose(0, 2, 1).ravel()  # column-major 3x3
            compiled.inputs[3][:] = h.ravel()
            compiled()
            d = compiled.outputs[0]
        else:  # no C compiler: the same closed forms in numpy
            i, j = self._cc[:, 0], self._cc[:, 1]
            d_cc = segment_distances(ends[i, 0], ends[i, 1], ends[j, 0], ends[j, 1])
            i, k = self._cb[:, 0], self._cb[:, 1]
            d_cb = segment_box_distances(ends[i, 0], ends[i, 1], centres[k], rots[k], h[k])
            d = np.concatenate([d_cc, d_cb])
        return d - self._radii - self.margin

    def _names(self, term: int) -> tuple[str, str]:
        n = len(self._cc)
        if term < n:
            i, j = self._cc[term]
            return self.capsules[i].link, self.capsules[j].link
        i, k = self._cb[term - n]
        return self.capsules[i].link, self.boxes[k].link

    def reset(self, values: np.ndarray | None) -> None:
        """Take ``values`` (shape (18,), e.g. the measured posture at bring-up) as the last
        safe command, or forget it (``None``)."""
        if values is None:
            self._safe, self._safe_clear = None, None
        else:
            self._safe = np.asarray(values, dtype=float).copy()
            self._safe_clear = self.clearances(self._safe)

    def _violations(self, clear: np.ndarray) -> np.ndarray:
        """Terms inside the margin and deeper than at the last safe command."""
        bad = clear < 0.0
        if self._safe_clear is not None:
            bad &= clear < self._safe_clear - DEEPER
        return np.flatnonzero(bad)

    def filter(self, values: np.ndarray) -> np.ndarray | None:
        """The command to send for ``values`` (shape (18,)).

        ``values`` when no checked pair violates its margin, else the joints of the
        violating pairs held at the last safe command (at worst the whole last safe
        command): checked again until none violates. A pair already inside its margin at
        the last safe command (the stowed posture packs the fingers closer than the margin)
        violates only by going deeper (by more than :data:`DEEPER`), so a command may
        always move out. Each refusal is counted and logged.

        Returns:
            The values to send, shape (18,), or ``None`` (a violating command with no last
            safe command: nothing is sent, the servos keep their goals).
        """
        values = np.asarray(values, dtype=float)
        clear = self.clearances(values)
        bad = self._violations(clear)
        if bad.size == 0:
            self._safe, self._safe_clear = values.copy(), clear
            return values
        pairs = tuple((*self._names(t), float(clear[t])) for t in bad)
        held: set[str] = set()
        out: np.ndarray | None = None
        if self._safe is not None:
            while True:
                held |= {g for t in bad for g in self._term_groups[t]}
                mask = np.isin(self._groups, sorted(held))
                out = np.where(mask, self._safe, values)
                clear = self.clearances(out)
                bad = self._violations(clear)
                if bad.size == 0 or mask.all():
                    break
            self._safe, self._safe_clear = out.copy(), clear
        self.refusals += 1
        self.last = Refusal(tuple(sorted(held)) if out is not None else ("all",), pairs)
        log.warning(
            "command refused (%d so far): %s; holding %s at the last safe command",
            self.refusals,
            ", ".join(f"{a}-{b} {c * 1e3:+.1f} mm" for a, b, c in pairs[:4])
            + (f" and {len(pairs) - 4} more" if len(pairs) > 4 else ""),
            ", ".join(self.last.held),
        )
        return out

    def cost_us(self, values: np.ndarray, n: int = 200) -> tuple[float, float]:
        """Mean wall-clock and CPU time of one check at ``values`` [us] (what
        :meth:`filter` adds to a cycle; on a loaded machine the wall clock mostly waits
        for the scheduler)."""
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(n):
            self.clearances(values)
        return (time.perf_counter() - t0) / n * 1e6, (time.process_time() - c0) / n * 1e6


def _distance_program(cc: np.ndarray, cb: np.ndarray, ncap: int, nbox: int) -> Any:
    """The segment-segment and segment-box distances of the checked pairs as generated C
    (:mod:`payload.retarget.compiled`; ``None`` without a C compiler): inputs the capsule
    axis ends (ncap, 2, 3), the box centres (nbox, 3), rotations (nbox, 3, 3, column-major)
    and half sizes (nbox, 3); output the distances, capsule pairs first."""
    from payload.retarget.compiled import _compiled_or_none

    a, b, c, h = (ca.SX.sym(x, 3) for x in "abch")
    r, a2, b2 = ca.SX.sym("R", 3, 3), ca.SX.sym("a2", 3), ca.SX.sym("b2", 3)
    box_fn = ca.Function(
        "segment_box", [a, b, c, r, h], [segment_box_distance_expr(a, b, c, r, h)], {"cse": True}
    )
    pair_fn = ca.Function(
        "segment_segment", [a, b, a2, b2], [_segment_distance_ca(a, b, a2, b2)], {"cse": True}
    )
    ends, centres = ca.MX.sym("ends", 6 * ncap), ca.MX.sym("centres", 3 * nbox)
    rots, halves = ca.MX.sym("rotations", 9 * nbox), ca.MX.sym("halves", 3 * nbox)

    def end(i: int, k: int) -> ca.MX:
        return ends[6 * i + 3 * k : 6 * i + 3 * k + 3]

    out = [pair_fn(end(i, 0), end(i, 1), end(j, 0), end(j, 1)) for i, j in cc]
    out += [
        box_fn(
            end(i, 0),
            end(i, 1),
            centres[3 * k : 3 * k + 3],
            ca.reshape(rots[9 * k : 9 * k + 9], 3, 3),
            halves[3 * k : 3 * k + 3],
        )
        for i, k in cb
    ]
    fn = ca.Function("payload_guard_distances", [ends, centres, rots, halves], [ca.vertcat(*out)])
    return _compiled_or_none(fn)


@functools.lru_cache(maxsize=4)
def _cached(urdf: Path, stamp: float, design_stamp: float) -> CommandGuard:
    return CommandGuard(load_hand())


def default_guard() -> CommandGuard:
    """A fresh guard for our hand on the current project; the geometry is built once per
    process and URDF/design version (the counters are the new guard's own)."""
    hand = load_hand()
    design = hand.design.stat().st_mtime if hand.design is not None else 0.0
    base = _cached(hand.urdf, hand.urdf.stat().st_mtime, design)
    guard = object.__new__(CommandGuard)
    guard.__dict__.update(base.__dict__)
    guard._data = base._model.createData()
    guard.refusals, guard.last, guard._safe, guard._safe_clear = 0, None, None, None
    return guard
