"""Self-collision distances of one finger pair, as CasADi expressions and in numpy.

The solver's own geometry, derived once per pair:

* every link a finger's joints move is enclosed by one **capsule** (a segment swept by a
  sphere): the axis is the best of the link frame's axes and the principal axis of the
  link's collision geometry (its mesh vertices, or points on its box, cylinder and
  sphere primitives, from the URDF), the radius is the smallest circle enclosing the
  points projected across the axis, and the end caps are pulled in as far as every
  point stays inside, so the capsule contains the collision geometry;
* the **structure** (the links no pair joint moves: for our hand the base, the stage and
  the rail carriage) is a set of **boxes** fixed in the pair's base frame, posed at the
  model's neutral configuration: the design's collision boxes and guide columns when the
  hand names a design (``payload.design.solids``), else the URDF's primitives and, for a
  mesh, the oriented bounding box of each connected piece.

Checked pairs are those the python-fcl check (:mod:`payload.retarget.meshcheck`) checks:
a link of finger 1 against a link of finger 2 except the two **pad links** (the links
carrying the fingertip pads, :func:`pad_links`, from the design's ``retarget.pad_link``:
a pinch closes them on each other and on what they hold, docs/retargeting.md), exactly
(segment-to-segment distance less both radii), and a finger link against a structure
box, exactly too while apart (the smallest distance of the box along the capsule axis,
:func:`segment_box_distance_expr`, less the radius; an axis entering the box gets the
depth in the middle of its inside part), except a finger's first link against the link
it is mounted on (they touch by construction). Pairs that never come within
:data:`PRUNE_DISTANCE` of each other over :data:`PRUNE_SAMPLES` seeded postures of the
joint box are left out.

The clearance of a term is its distance less the hand's ``collision_margin``; a command
is collision-free in the solver's sense when every clearance is non-negative. The
distances' closed forms are :mod:`payload.retarget.collision_distance` (re-exported here).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path

import casadi as ca
import numpy as np
import pinocchio as pin

from payload.native import find_compiler
from payload.retarget import features as _features
from payload.retarget.collision_cache import CollisionShape, load_shape, shape_key, store_shape
from payload.retarget.collision_distance import (
    _segment_distance_ca,
    box_sdf,
    segment_box_distance,
    segment_box_distance_expr,
    segment_box_distances,
    segment_distance,
    segment_distances,
)
from payload.retarget.collision_geometry import (
    Box,
    Capsule,
    _points,
    enclosing_capsule,
    link_geometry,
    structure_boxes,
)
from payload.retarget.features import PairKinematics
from payload.retarget.symbolic import chain_point, frame_point_chain

PRUNE_DISTANCE = 0.010
"""Terms farther than this over every sampled posture are left out [m]."""

PRUNE_SAMPLES = 4000
"""Seeded postures of the joint box the pruning samples."""


@dataclass(frozen=True)
class Term:
    """One clearance term: a capsule of finger 1 or 2 against another capsule or a box.

    Attributes:
        capsule: Index into :attr:`PairCollision.capsules`.
        other: Index of the other capsule, or of the box (``box`` True).
        box: True for a capsule-box term (the exact segment-box distance).
    """

    capsule: int
    other: int
    box: bool


class PairCollision:
    """The solver's self-collision model of one pair (see the module docstring).

    Args:
        pk: The pair's kinematics.
        margin: Required distance [m] (``None``: the hand's ``collision_margin``).

    Attributes:
        margin: [m].
        capsules: Finger link capsules.
        finger_of: Per capsule, 0 or 1.
        boxes: Structure boxes in the base frame.
        pads: Per finger, its pad link (``None``: none found); the two pad links keep
            no margin between them, so they have no term.
        terms: The clearance terms kept after pruning.
    """

    def __init__(self, pk: PairKinematics, margin: float | None = None) -> None:
        self.pk = pk
        self.margin = float(pk.hand.collision_margin if margin is None else margin)
        key = shape_key(pk, self.margin)
        self.key: str | None = key
        """The disk cache's key of this geometry (None: not cached), which what is derived
        from it (the seed table's postures) is keyed by too."""
        shape = load_shape(key) if key is not None else None
        derived = shape is None
        if shape is None:
            shape = self._derive()
        self.capsules: tuple[Capsule, ...] = shape.capsules
        self.finger_of: tuple[int, ...] = shape.finger_of
        self.boxes: tuple[Box, ...] = shape.boxes
        self.pads: tuple[str | None, ...] = shape.pads
        self.all_terms: tuple[Term, ...] = tuple(Term(*t) for t in shape.all_terms)
        self.terms: tuple[Term, ...] = self.all_terms
        self._chains = [
            (frame_point_chain(pk, c.link, c.a), frame_point_chain(pk, c.link, c.b))
            for c in self.capsules
        ]
        model = pk.kin.model
        self._data = model.createData()
        self._batch: dict[tuple, tuple] = {}
        self._fids = [model.getFrameId(c.link, pin.FrameType.BODY) for c in self.capsules]
        if not derived:
            self.terms = tuple(t for t, k in zip(self.all_terms, shape.kept) if k)
            return
        if self.all_terms:
            self._prune()
        # kept only when derived from the bytes keyed (no file changed meanwhile) and, with
        # a compiler, pruned by the compiled distances (not CasADi's virtual machine)
        if key is not None and shape_key(pk, self.margin) == key and self.compiled_distances():
            kept = tuple(t in self.terms for t in self.all_terms)
            store_shape(key, replace(shape, kept=kept))
        else:
            self.key = None  # not stored: nothing derived from it is either

    def compiled_distances(self, terms: tuple[Term, ...] | None = None) -> bool:
        """Whether :meth:`distances_many` of ``terms`` (default: every candidate term, the
        pruning's) evaluated the compiled distances, or there is no C compiler to compile
        them (the virtual machine's are then every process's): what the disk cache keeps
        is only what every process with the same key computes."""
        made = self._batch.get(tuple(self.all_terms if terms is None else terms))
        return made is None or made[1] is not None or find_compiler() is None

    def _derive(self) -> CollisionShape:
        """The capsules, structure boxes, pad links and candidate terms, from the URDF's
        collision geometry and the design (every term kept: :meth:`_prune` follows)."""
        pk = self.pk
        kin, d = pk.kin, pk.desc
        model = kin.model
        geometry = link_geometry(Path(kin.urdf))
        all_pair_joints = {j for p in pk.hand.pairs.values() for j in p.joints}

        def ancestors(link: str) -> set[str]:
            j, out = model.frames[model.getFrameId(link, pin.FrameType.BODY)].parentJoint, set()
            while j > 0:
                out.add(model.names[j])
                j = model.parents[j]
            return out

        links = [n for n in geometry if model.existBodyName(n)]
        caps: list[Capsule] = []
        finger_of: list[int] = []
        for i, fj in enumerate(d.finger_joints):
            for n in sorted(x for x in links if ancestors(x) & set(fj)):
                pts = np.vstack([_points(k, g, o) for k, g, o in geometry[n]])
                caps.append(enclosing_capsule(n, pts))
                finger_of.append(i)
        structure = [n for n in links if not ancestors(n) & all_pair_joints]
        local = structure_boxes(pk.hand.design, geometry, structure)
        q0 = kin.neutral()
        base = kin.frame_placement(q0, d.base)
        boxes: list[Box] = []
        for n in sorted(structure):
            pl = base.inverse() * kin.frame_placement(q0, n)
            rot, tr = np.array(pl.rotation), np.array(pl.translation)
            for bx in local[n]:
                boxes.append(Box(n, rot @ bx.centre + tr, rot @ bx.rotation, bx.half))
        joint_parent = {j.get("name"): j.find("parent").get("link") for j in _joints(kin.urdf)}
        joint_child = {j.get("name"): j.find("child").get("link") for j in _joints(kin.urdf)}
        mounted = {(joint_parent[fj[0]], joint_child[fj[0]]) for fj in d.finger_joints if fj}
        pads = pad_links(pk, frozenset(links))
        pad_pair = set(pads) if None not in pads else set()
        terms: list[tuple[int, int, bool]] = []
        for i, ci in enumerate(caps):
            for j in range(i + 1, len(caps)):
                if finger_of[i] != finger_of[j] and {ci.link, caps[j].link} != pad_pair:
                    terms.append((i, j, False))
            for bi, bx in enumerate(boxes):
                if (bx.link, ci.link) not in mounted:
                    terms.append((i, bi, True))
        return CollisionShape(
            tuple(caps), tuple(finger_of), tuple(boxes), pads, tuple(terms),
            (True,) * len(terms),
        )  # fmt: skip

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_batch"] = {}  # compiled libraries are loaded again where needed
        return state

    @property
    def available(self) -> bool:
        """True when the pair has any clearance term."""
        return bool(self.terms)

    def _prune(self) -> None:
        pk = self.pk
        rng = np.random.default_rng(2024)
        qs = np.vstack([pk.rest, pk.lower + rng.random((PRUNE_SAMPLES, pk.n)) * pk.range])
        dist = self.distances_many(qs, self.all_terms)  # (terms, samples)
        keep = dist.min(axis=1) < PRUNE_DISTANCE + self.margin
        self.terms = tuple(t for t, k in zip(self.all_terms, keep) if k)

    def _term_expr(self, t: Term, ends: list) -> ca.SX:
        ci = self.capsules[t.capsule]
        a, b = ends[t.capsule]
        if t.box:
            bx = self.boxes[t.other]
            d = segment_box_distance_expr(
                a, b, ca.DM(bx.centre), ca.DM(bx.rotation), ca.DM(bx.half)
            )
            return d - ci.radius
        a2, b2 = ends[t.other]
        return _segment_distance_ca(a, b, a2, b2) - ci.radius - self.capsules[t.other].radius

    def distances_expr(
        self, q: ca.SX | ca.MX, terms: tuple[Term, ...] | None = None
    ) -> ca.SX | ca.MX:
        """The terms' distances [m] at symbolic q, shape (k, 1) (k may be 0).

        With an ``SX`` q, one expression (every term written out); with an ``MX`` q, a
        graph calling one shared function per kind of term with each term's geometry as
        constants, so generated C stays small and compiles in seconds."""
        terms = self.terms if terms is None else terms
        if isinstance(q, ca.MX):
            return self._distances_mx(q, terms)
        used = sorted({t.capsule for t in terms} | {t.other for t in terms if not t.box})
        ends: list = [None] * len(self.capsules)
        for i in used:
            ca_, cb_ = self._chains[i]
            ends[i] = (chain_point(ca_, q), chain_point(cb_, q))
        return ca.vertcat(*[self._term_expr(t, ends) for t in terms])

    def ends_function(self) -> ca.Function:
        """``q -> ends (6 per capsule)``: every capsule's axis ends in the base frame."""
        q = ca.SX.sym("q", self.pk.n)
        ends = [chain_point(c, q) for pair in self._chains for c in pair]
        return ca.Function("capsule_ends", [q], [ca.vertcat(*ends)], {"cse": True})

    def _distances_mx(self, q: ca.MX, terms: tuple[Term, ...]) -> ca.MX:
        if not terms:
            return ca.MX(0, 1)
        ends = self.ends_function()(q)
        e = [
            (ends[6 * i : 6 * i + 3], ends[6 * i + 3 : 6 * i + 6])
            for i in range(len(self.capsules))
        ]
        a, b, c, h = (ca.SX.sym(x, 3) for x in "abch")
        r, a2, b2 = ca.SX.sym("R", 3, 3), ca.SX.sym("a2", 3), ca.SX.sym("b2", 3)
        box_fn = ca.Function(
            "segment_box",
            [a, b, c, r, h],
            [segment_box_distance_expr(a, b, c, r, h)],
            {"cse": True},
        )
        pair_fn = ca.Function(
            "segment_segment", [a, b, a2, b2], [_segment_distance_ca(a, b, a2, b2)], {"cse": True}
        )
        out = []
        for t in terms:
            ci = self.capsules[t.capsule]
            if t.box:
                bx = self.boxes[t.other]
                d = box_fn(*e[t.capsule], ca.DM(bx.centre), ca.DM(bx.rotation), ca.DM(bx.half))
                out.append(d - ci.radius)
            else:
                d = pair_fn(*e[t.capsule], *e[t.other])
                out.append(d - ci.radius - self.capsules[t.other].radius)
        return ca.vertcat(*out)

    def clearance_expr(self, q: ca.SX | ca.MX) -> ca.SX | ca.MX:
        """Distances less the margin, shape (k, 1): non-negative when collision-free."""
        return self.distances_expr(q) - self.margin

    def distance_function(self, terms: tuple[Term, ...] | None = None) -> ca.Function:
        """CasADi ``q (n) -> distances (k)`` [m]."""
        q = ca.SX.sym("q", self.pk.n)
        return ca.Function("pair_distances", [q], [self.distances_expr(q, terms)], {"cse": True})

    def distances_many(self, qs: np.ndarray, terms: tuple[Term, ...] | None = None) -> np.ndarray:
        """The terms' distances [m] at many postures ``qs`` (m, n): shape (k, m). The
        CasADi expressions compiled to C once per set of terms (CasADi's virtual machine
        without a C compiler)."""
        from payload.retarget.compiled import _compiled_or_none

        terms = self.terms if terms is None else terms
        key = tuple(terms)
        if key not in self._batch:
            qm = ca.MX.sym("q", self.pk.n)
            fn = ca.Function("pair_distances", [qm], [self.distances_expr(qm, terms)])
            name = "payload_distances_" + "".join(c if c.isalnum() else "_" for c in self.pk.name)
            self._batch[key] = (fn, _compiled_or_none(ca.Function(name, [qm], [fn(qm)])))
        fn, compiled = self._batch[key]
        qs = np.atleast_2d(np.asarray(qs, dtype=float))
        if compiled is None:
            return np.array(fn.map(qs.shape[0])(qs.T)).reshape(len(terms), qs.shape[0])
        out = np.empty((len(terms), qs.shape[0]))
        for i, q in enumerate(qs):
            compiled.inputs[0][:] = q
            compiled()
            out[:, i] = compiled.outputs[0]
        return out

    def distances(self, q: np.ndarray) -> np.ndarray:
        """The terms' distances at q [m], shape (k,), in numpy with Pinocchio placements."""
        pk = self.pk
        model = pk.kin.model
        pin.framesForwardKinematics(model, self._data, pk.full_configuration(pk.check_q(q)))
        base = pk.kin.frame_placement(pk.kin.neutral(), pk.desc.base).inverse()
        ends = []
        for c, fid in zip(self.capsules, self._fids):
            m = base * self._data.oMf[fid]
            ends.append((m.act(c.a), m.act(c.b)))
        out = np.empty(len(self.terms))
        kb = [k for k, t in enumerate(self.terms) if t.box]
        if kb:
            tb = [self.terms[k] for k in kb]
            a = np.array([ends[t.capsule][0] for t in tb])
            b = np.array([ends[t.capsule][1] for t in tb])
            boxes = [self.boxes[t.other] for t in tb]
            d = segment_box_distances(
                a,
                b,
                np.array([x.centre for x in boxes]),
                np.array([x.rotation for x in boxes]),
                np.array([x.half for x in boxes]),
            )
            out[kb] = d - np.array([self.capsules[t.capsule].radius for t in tb])
        for k, t in enumerate(self.terms):
            if not t.box:
                a, b = ends[t.capsule]
                a2, b2 = ends[t.other]
                radii = self.capsules[t.capsule].radius + self.capsules[t.other].radius
                out[k] = segment_distance(a, b, a2, b2) - radii
        return out

    def clearance(self, q: np.ndarray) -> float:
        """Smallest distance less the margin at q [m] (``inf`` without terms)."""
        return float(self.distances(q).min() - self.margin) if self.terms else np.inf


def pad_links(pk: PairKinematics, links: set[str] | frozenset[str]) -> tuple[str | None, ...]:
    """Per finger of the pair, its pad link (the two keep no margin), or ``None``.

    With a hand ``pad_link`` (the design's ``retarget.pad_link``), the finger's link among
    ``links`` (the links with collision geometry) whose URDF name ends in ``_<pad_link>``;
    without one, the first link with collision geometry at or above the finger's tip
    frame (the link the fingertip is fixed to).
    """
    model = pk.kin.model
    out: list[str | None] = []
    for tip in pk.desc.tips:
        fid = model.getFrameId(tip)
        found: str | None = None
        while fid < len(model.frames):
            f = model.frames[fid]
            if f.type == pin.FrameType.BODY and f.name in links:
                found = f.name
                break
            if fid == 0 or f.parentFrame == fid:
                break
            fid = f.parentFrame
        if pk.hand.pad_link is not None:
            # the design names the pad link: the one of this finger's chain with that suffix
            found = next(
                (
                    n
                    for n in sorted(links)
                    if n.endswith("_" + pk.hand.pad_link) and _same_finger(model, n, tip)
                ),
                None,
            )
        out.append(found)
    return tuple(out)


def _same_finger(model: pin.Model, link: str, tip: str) -> bool:
    """True when ``link`` is ``tip``'s frame's body or one of its ancestors."""
    j_tip = model.frames[model.getFrameId(tip)].parentJoint
    j_link = model.frames[model.getFrameId(link, pin.FrameType.BODY)].parentJoint
    while j_tip > 0:
        if j_tip == j_link:
            return True
        j_tip = model.parents[j_tip]
    return False


def _joints(urdf: str | Path) -> list[ET.Element]:
    return ET.parse(urdf).getroot().findall("joint")


def register() -> None:
    """Name :class:`PairCollision` as the pairs' self-collision model
    (:attr:`PairKinematics.collision <payload.retarget.features.PairKinematics.collision>`).

    Called explicitly by what builds a model on a pair (the retargeters, the span range,
    the seed table, the optimum check); idempotent. Importing this module registers
    nothing.
    """
    _features.COLLISION_MODEL[:] = [PairCollision]


__all__ = [
    "PRUNE_DISTANCE",
    "PRUNE_SAMPLES",
    "PairCollision",
    "Term",
    "box_sdf",
    "pad_links",
    "register",
    "segment_box_distance",
    "segment_box_distance_expr",
    "segment_box_distances",
    "segment_distance",
    "segment_distances",
]
