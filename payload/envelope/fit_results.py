"""Results of the stowed checks: part fits, link contacts, the sweep, the analysis."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from payload.envelope.vehicle import Vehicle

VOLUME_TOL = 1e-12
"""Volume (1e-3 mm^3) below which an overlap or an outside part counts as nil [m^3]."""
TIGHT_CLEARANCE = 0.5e-3
"""Clearance below which a stowed fit that passes is tight [m]: a part this close to a bay
wall, or two links this close to each other (ASSUMPTION: about the dimensional tolerance
of a printed part, so a tighter fit is worth a second look). The verdicts say it; the
design review and the envelope figure draw such parts amber."""


def clearance_text(metres: float) -> str:
    """A clearance as the reports print it: ``0.06 mm`` under 1 mm (two decimals: a tight
    fit's hundredths matter), ``1.0 mm`` from 1 mm on (one decimal), ``-0.30 mm`` for a
    negative one; the one formatting of a clearance in every verdict, report, figure and
    the design review."""
    mm = metres * 1e3
    text = f"{mm:.2f}"
    if abs(float(text)) >= 1.0:  # 0.996 mm reads 1.0 mm, not 1.00 mm
        text = f"{mm:.1f}"
    return f"{text} mm"


OUTSIDE_MEANING = "outside the bays"
"""What a drawing's red (hatched in envelope.png) means: a part beyond a bay wall."""
COLLIDES_MEANING = "collides with another link"
"""What a drawing's magenta means: a part in contact with another, not outside the bays."""


def tight_meaning(*, walls: bool, links: bool) -> str:
    """What a drawing's amber means, for its legend: ``tight: under 0.50 mm to a bay wall``
    (``walls``), ``... to another link`` (``links``) or ``... to a bay wall or another
    link`` (both); the one wording in the envelope figure and the design review."""
    near = [what for what, said in (("a bay wall", walls), ("another link", links)) if said]
    return f"tight: under {clearance_text(TIGHT_CLEARANCE)} to {' or '.join(near)}"


class PartFit(NamedTuple):
    """How one part (link) sits in the bay envelope.

    Attributes:
        name: Link name.
        inside: Wholly inside the envelope.
        clearance: Smallest distance to a wall when inside, minus the protrusion when not [m].
        protrusion: Largest distance of a part point beyond the walls (0 inside) [m].
        wall: The nearest wall (inside) or the wall crossed most (outside).
        outside_volume: Part volume outside the envelope [m^3].
        mounted: The part is the one bolted to the mount face (+z wall), whose contact
            with that face is its mounting and not a clearance.
        wall_clearance: python-fcl distance to each of the six walls, -x .. +z [m]
            (NaN for a mounted part's mount face; 0 when touching or crossing).
        wall_protrusion: How far the part reaches beyond each of the six walls, -x .. +z
            [m] (0 when it does not cross it): what tells a wall it crosses from one it
            touches, both 0 in ``wall_clearance``.
    """

    name: str
    inside: bool
    clearance: float
    protrusion: float
    wall: str
    outside_volume: float
    mounted: bool
    wall_clearance: tuple[float, ...]
    wall_protrusion: tuple[float, ...] = (0.0,) * 6


class PairContact(NamedTuple):
    """Two links' proximity.

    Attributes:
        a: First link.
        b: Second link.
        distance: Signed distance between their convex pieces [m] (negative = depth).
        overlap_volume: Exact volume the two solids share [m^3].
    """

    a: str
    b: str
    distance: float
    overlap_volume: float

    @property
    def colliding(self) -> bool:
        return bool(self.overlap_volume > VOLUME_TOL)


class SweepResult(NamedTuple):
    """The deployment sweep: the stage from stowed to deployed, fingers in one posture.

    Attributes:
        clear: No contact with the vehicle body or the fixed base along the path, and no
            self-collision among the parts the stage carries (they move as one body).
        vehicle_clear: No contact with the vehicle body or the base along the path.
        min_distance: Smallest signed distance to the vehicle or the base [m].
        at_stage: Stage travel where it occurs [m].
        between: The two things closest there.
        samples: Stage positions evaluated.
        certified: Every interval between samples was proved contact-free (the
            distance is 1-Lipschitz in the stage travel: ``d0 + d1 > step``) or holds a
            sample in contact.
        first_contact: Stage travel of the first contact (NaN when none) [m].
    """

    clear: bool
    vehicle_clear: bool
    min_distance: float
    at_stage: float
    between: tuple[str, str]
    samples: int
    certified: bool
    first_contact: float = float("nan")


class BodyHit(NamedTuple):
    """A link reaching into the vehicle body.

    Attributes:
        link: The link.
        body: The vehicle body's box it reaches into (``vehicle body (left of the bays)``).
        distance: Signed distance between them [m] (zero or negative: in contact).
    """

    link: str
    body: str
    distance: float


class UnfoldResult(NamedTuple):
    """The second half of a deployment: the fingers and the rail from the stowed posture to
    home, straight in joint space, with the stage deployed.

    Attributes:
        collisions: Link pairs that collide on the way and not stowed (those are the stowed
            check's), each at its deepest, deepest first.
        hits: Links that reach into the vehicle body on the way, each at its deepest,
            deepest first.
        samples: Postures checked (no joint moves more than
            :data:`~payload.envelope.deployment.UNFOLD_STEP_RAD` or
            :data:`~payload.envelope.deployment.UNFOLD_STEP_M` between two).
        certified: Every stretch of the line between the postures evaluated was proved
            contact-free (each distance changes no faster than the links' points move:
            ``d0 / r + d1 / r > step``, ``r`` the two things' bound of
            :func:`~payload.envelope.deployment.unfolding_rates`), or ends at a posture
            whose contact is reported.
        min_distance: Smallest signed distance among the pairs and links not reported,
            over every posture evaluated [m] (inf when nothing moves).
        between: The two things closest there.
        evaluated: Postures evaluated: the samples, the stowed end and the halving's.
    """

    collisions: list[PairContact]
    hits: list[BodyHit]
    samples: int
    certified: bool = True
    min_distance: float = float("inf")
    between: tuple[str, str] = ("", "")
    evaluated: int = 0

    @property
    def clear(self) -> bool:
        return not self.collisions and not self.hits and self.certified


class PostureSearch(NamedTuple):
    """The finger posture (shared by the four fingers) that maximises the minimum clearance.

    Attributes:
        finger: Joint values [mcp_flex, mcp_abd, pip, dip] [rad].
        clearance: The minimum over envelope clearances and self-collision distances [m].
        limited_by: What sets that minimum (a part and a wall, or two links).
        evaluations: Objective evaluations.
        seconds: Wall time [s].
    """

    finger: tuple[float, float, float, float]
    clearance: float
    limited_by: str
    evaluations: int
    seconds: float


@dataclass
class StowedCheck:
    """Every check of one stowed configuration.

    Attributes:
        q: Joint values (every joint of the tree) [rad, m].
        parts: Per-part fit.
        self_contacts: Every checked (non-adjacent) pair, closest first.
        sweep: The deployment sweep from this configuration (the stage down).
        unfolding: The fingers and the rail from this configuration to home, the stage
            down (the deployment's second half).
    """

    q: dict[str, float]
    parts: list[PartFit]
    self_contacts: list[PairContact]
    sweep: SweepResult
    unfolding: UnfoldResult

    @property
    def fits(self) -> bool:
        return all(p.inside for p in self.parts)

    @property
    def min_clearance(self) -> float:
        """Smallest part clearance (negative: largest protrusion) [m]."""
        return min(p.clearance for p in self.parts)

    @property
    def tightest(self) -> PartFit:
        return min(self.parts, key=lambda p: p.clearance)

    def nearest_to_wall(self, w: int) -> PartFit | None:
        """The part with the least clearance to wall ``w`` (0..5, -x .. +z) over every part
        that has one, inside the bays or not (a part touching or crossing it: 0; the
        mounted part's mount face: none); a tie: the first in the parts' order, as
        :attr:`tightest`. None when no part has one."""
        has = [p for p in self.parts if np.isfinite(p.wall_clearance[w])]
        return min(has, key=lambda p: p.wall_clearance[w], default=None)

    def beyond_wall(self, w: int) -> list[PartFit]:
        """The parts reaching beyond wall ``w`` (0..5, -x .. +z), farthest beyond it first
        (:attr:`PartFit.wall_protrusion`): every part crossing it, not only those crossing
        it most (:attr:`PartFit.wall`); empty when none does (its wall clearances, then,
        are clearances: :meth:`nearest_to_wall`)."""
        out = [p for p in self.parts if p.wall_protrusion[w] > 0.0]
        return sorted(out, key=lambda p: -p.wall_protrusion[w])

    @property
    def collisions(self) -> list[PairContact]:
        return [c for c in self.self_contacts if c.colliding]

    @property
    def self_collision(self) -> bool:
        return bool(self.collisions)

    @property
    def min_self_clearance(self) -> PairContact:
        return min(self.self_contacts, key=lambda c: c.distance)

    @property
    def passed(self) -> bool:
        return self.fits and not self.self_collision and self.deploy_clear

    @property
    def stows(self) -> bool:
        """The payload stows: inside the bays, no two links colliding, and the stage's way
        down clear (what a stowed posture decides; the fingers' unfolding is the home
        posture's as much)."""
        return self.fits and not self.self_collision and self.sweep.clear

    @property
    def deploy_clear(self) -> bool:
        """The whole deployment is clear: the stage down (:attr:`sweep`), then the fingers
        and the rail to home (:attr:`unfolding`)."""
        return self.sweep.clear and self.unfolding.clear

    @property
    def tight_parts(self) -> list[PartFit]:
        """Parts inside the bays with less than :data:`TIGHT_CLEARANCE` to a wall,
        tightest first."""
        tight = [p for p in self.parts if p.inside and p.clearance < TIGHT_CLEARANCE]
        return sorted(tight, key=lambda p: p.clearance)

    @property
    def tight_pairs(self) -> list[PairContact]:
        """Non-adjacent links that do not collide but are less than
        :data:`TIGHT_CLEARANCE` apart, closest first."""
        return [c for c in self.self_contacts if not c.colliding and c.distance < TIGHT_CLEARANCE]

    @property
    def tight_links(self) -> list[str]:
        """Every link that is tight: the :attr:`tight_parts` and both links of each of the
        :attr:`tight_pairs`, each once, in that order."""
        names = [p.name for p in self.tight_parts]
        names += [n for c in self.tight_pairs for n in (c.a, c.b)]
        return list(dict.fromkeys(names))

    def link_role(self, name: str) -> str | None:
        """What a link's colour says, failing first: ``"outside"`` (outside the bays),
        ``"hit"`` (hits the vehicle or the base as the stage deploys, or reaches into the
        vehicle as the fingers unfold), ``"colliding"`` (collides with another link,
        stowed or as the fingers unfold), ``"tight"`` (one of the :attr:`tight_links`), else
        None; the one order of the envelope figure and the design review (a failing link
        that is also tight is drawn failing, never amber)."""
        if any(p.name == name and not p.inside for p in self.parts):
            return "outside"
        if not self.sweep.vehicle_clear and name in self.sweep.between:
            if any(p.name == name for p in self.parts):
                return "hit"
        if any(h.link == name for h in self.unfolding.hits):
            return "hit"
        if any(name in (c.a, c.b) for c in [*self.collisions, *self.unfolding.collisions]):
            return "colliding"
        return "tight" if name in self.tight_links else None

    @property
    def tight(self) -> bool:
        """Whether a part is under :data:`TIGHT_CLEARANCE` from a wall or two links are
        under it apart (a fit that passes all the same, but said)."""
        return bool(self.tight_parts or self.tight_pairs)

    @property
    def fits_words(self) -> str:
        """``fits``, or ``fits, tight`` when :attr:`tight`: the one wording of a fit in
        every verdict."""
        return "fits, tight" if self.tight else "fits"

    @property
    def tight_tail(self) -> str:
        """``; <tight_phrase>`` when :attr:`tight`, else empty: what a verdict adds."""
        return f"; {self.tight_phrase()}" if self.tight else ""

    def tight_phrase(self) -> str:
        """What is tight, for a verdict: ``C_distal 0.06 mm to the +y (left) wall,
        stage / A_distal 0.06 mm apart: under 0.50 mm, about a printed part's tolerance``
        (the tightest part's wall clearance and the closest pair, each when under
        :data:`TIGHT_CLEARANCE`); empty when nothing is."""
        said = [
            f"{p.name} {clearance_text(p.clearance)} to the {p.wall} wall"
            for p in self.tight_parts[:1]
        ]
        said += [f"{c.a} / {c.b} {clearance_text(c.distance)} apart" for c in self.tight_pairs[:1]]
        if not said:
            return ""
        return (
            f"{', '.join(said)}: under {clearance_text(TIGHT_CLEARANCE)}, about a printed "
            "part's tolerance"
        )

    def failures(self) -> list[str]:
        """One phrase per failed check, naming parts and millimetres."""
        out = []
        for p in sorted(self.parts, key=lambda p: round(p.clearance, 8)):
            if not p.inside:
                out.append(
                    f"{p.name} protrudes {p.protrusion * 1e3:.1f} mm beyond the {p.wall} wall"
                )
        for c in self.collisions:
            out.append(
                f"{c.a} and {c.b} collide ({-c.distance * 1e3:.1f} mm deep, "
                f"{c.overlap_volume * 1e9:.0f} mm^3)"
            )
        if not self.sweep.vehicle_clear:
            a, b = self.sweep.between
            if np.isfinite(self.sweep.first_contact):
                out.append(
                    f"deployment: {a} hits {b} from stage {self.sweep.first_contact * 1e3:.1f} mm "
                    f"(deepest {-self.sweep.min_distance * 1e3:.1f} mm at "
                    f"{self.sweep.at_stage * 1e3:.1f} mm)"
                )
            else:
                out.append("deployment: the sweep could not prove the path contact-free")
        for c in self.unfolding.collisions:
            out.append(
                f"deployment: {c.a} and {c.b} collide as the fingers unfold "
                f"({-c.distance * 1e3:.1f} mm deep)"
            )
        for h in self.unfolding.hits:
            out.append(
                f"deployment: {h.link} hits the {h.body} as the fingers unfold "
                f"({-h.distance * 1e3:.1f} mm deep)"
            )
        if not self.unfolding.certified:
            out.append("deployment: the fingers' unfolding could not be proved contact-free")
        return out


@dataclass
class EnvelopeAnalysis:
    """The envelope report's content.

    Attributes:
        vehicle: The vehicle and bay envelope used.
        design_source: The design file.
        given: Checks of the design's stowed configuration.
        search: The stowed-posture search (run when the given posture does not stow, or on request).
        suggested: Checks of the searched posture (when a search ran).
        excluded_pairs: Adjacent link pairs left out of self-collision.
        approximate: Parts whose convex hull is larger than the part (name, excess).
        seconds: Wall time of the analysis [s].
    """

    vehicle: Vehicle
    design_source: str
    given: StowedCheck
    search: PostureSearch | None
    suggested: StowedCheck | None
    excluded_pairs: list[tuple[str, str]]
    approximate: list[tuple[str, float]]
    seconds: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        return self.given.passed

    def assumptions(self) -> list[str]:
        v = self.vehicle
        size = " x ".join(f"{s * 1e3:.0f}" for s in v.bay_size)
        body = " x ".join(f"{s * 1e3:.0f}" for s in v.body_size)
        return [
            f"ASSUMPTION (bay size): {v.assumption}",
            f"bay envelope {size} mm from {v.source}; vehicle body {body} mm with its "
            f"bottom face at z = {v.bottom_z * 1e3:.0f} mm (payload frame)",
            "the mounted part's contact with the mount face (+z wall) is its mounting, "
            "not a clearance",
            "self-collision ignores parent/child link pairs (they meet at their joint by "
            "construction)",
        ]


__all__ = [
    "TIGHT_CLEARANCE",
    "VOLUME_TOL",
    "BodyHit",
    "EnvelopeAnalysis",
    "PairContact",
    "PartFit",
    "PostureSearch",
    "StowedCheck",
    "SweepResult",
    "UnfoldResult",
    "clearance_text",
    "tight_meaning",
]
