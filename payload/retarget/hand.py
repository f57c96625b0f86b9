"""Hand description files: which URDF frames and joints each finger pair drives.

A hand description is a small TOML file::

    name = "payload"
    urdf = "{project}/urdf/payload.urdf"  # in the design project, relative to the TOML
                                          # file, or absolute
    design = "{project}/cad/design.toml"  # optional: the design the URDF was built from
                                          # (pad radius, collision margin, structure)
    collision_margin = 0.002              # optional, [m], only without a design

    [pairs.L]
    base = "stage"                        # frame the pair features are expressed in
    tips = ["A_tip", "C_tip"]             # p_1, p_2 of eq. 2
    distals = ["A_distal", "C_distal"]    # a_1, a_2 of eq. 2
    joints = [["A_mcp_flex", ...], ["C_mcp_flex", ...]]   # per finger, base -> tip
    tip_radius = 0.011                    # optional, [m]: pads touch at span 2 * tip_radius
                                          # (default: the design's finger.pad.radius, else 0)
    rest = [0.0, ...]                     # optional, [rad or m] per joint: the rest posture
                                          # (default: the design's pinch pre-shape
                                          # pinch.finger, matched by joint-name suffix;
                                          # without a design, zeros clipped to limits)

Ours ships as package data, ``payload/retarget/hands/payload.toml``
(:data:`DEFAULT_HAND`); its URDF path starts with ``{project}/``, which stands for the
root of the design project the hand is loaded for (:func:`load_hand`'s ``project``,
default the current project), so it always drives that project's generated model. The
retargeter runs on any hand URDF by writing one of these. A hand that names its
``design`` takes the fingertip pad radius (``finger.pad.radius``), the self-collision
margin (``retarget.collision_margin``) and the rest posture (the grasp pre-shape
``pinch.finger``) from it, so they have one source; a hand without
one may give ``collision_margin`` (default :data:`DEFAULT_COLLISION_MARGIN`).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from payload.errors import not_text
from payload.kinematics import Kinematics, KinematicsError
from payload.project import Project, current_project
from payload.retarget.errors import RetargetError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

DEFAULT_HAND: Path = Path(
    str(resources.files("payload.retarget").joinpath("hands", "payload.toml"))
)
"""Our payload's hand description (pairs L = (A, C) and R = (B, D)), shipped as package data."""

DEFAULT_COLLISION_MARGIN = 0.002
"""Self-collision margin [m] of a hand that names no design (ours: ``cad/design.toml``)."""

PROJECT_PLACEHOLDER = "{project}/"
"""A hand's ``urdf`` starting with this is relative to the design project's root."""


@dataclass(frozen=True)
class PairDescription:
    """One finger pair of a hand description.

    Attributes:
        name: Pair name (``L`` or ``R`` for ours).
        base: Frame the pair features are expressed in (an ancestor of both chains).
        tips: Fingertip frames (p_1, p_2).
        distals: Distal-joint frames (a_1, a_2).
        finger_joints: Joint names per finger, from the base outward.
        tip_radius: Fingertip pad radius [m]; the pads touch at span ``2 * tip_radius``.
        rest: Rest posture, shape (n,) [rad or m], or ``None`` for zeros clipped to limits.
    """

    name: str
    base: str
    tips: tuple[str, str]
    distals: tuple[str, str]
    finger_joints: tuple[tuple[str, ...], tuple[str, ...]]
    tip_radius: float = 0.0
    rest: tuple[float, ...] | None = None

    @property
    def joints(self) -> tuple[str, ...]:
        """All pair joints: finger 1's, then finger 2's (the optimisation variables)."""
        return self.finger_joints[0] + self.finger_joints[1]


@dataclass(frozen=True)
class HandDescription:
    """A hand description: a URDF and its finger pairs.

    Attributes:
        name: Hand name.
        urdf: Absolute path of the URDF.
        pairs: Pair name -> description, in file order.
        source: The TOML file it was loaded from (``None`` if built in code).
        design: The design file the URDF was built from, or ``None``.
        collision_margin: Least distance a command keeps between links of different
            fingers and between a finger and the structure [m].
        pad_link: The finger link carrying the fingertip pad, as the suffix of its URDF
            name (the design's ``retarget.pad_link``), or ``None``: the link each tip
            frame is fixed to. The two pad links of one pair keep no margin.
    """

    name: str
    urdf: Path
    pairs: dict[str, PairDescription]
    source: Path | None = None
    design: Path | None = None
    collision_margin: float = DEFAULT_COLLISION_MARGIN
    pad_link: str | None = None

    def pair(self, name: str) -> PairDescription:
        """The pair called ``name``.

        Raises:
            RetargetError: No such pair.
        """
        if name not in self.pairs:
            raise RetargetError(
                f"hand {self.name!r} has no pair {name!r} (pairs: {', '.join(self.pairs)})"
            )
        return self.pairs[name]

    def kinematics(self) -> Kinematics:
        """A fresh Pinocchio model of the hand's URDF."""
        return Kinematics(self.urdf)


def _str_list(where: str, value: Any, n: int) -> tuple[str, ...]:
    if (
        not isinstance(value, list)
        or len(value) != n
        or not all(isinstance(v, str) and v for v in value)
    ):
        raise RetargetError(f"{where}: expected a list of {n} frame or joint names, got {value!r}")
    return tuple(value)


def design_rest(where: str, joints: tuple[str, ...], preshape: dict[str, float]) -> tuple:
    """The rest posture from the design's pinch pre-shape, matching joints by name suffix."""
    rest = []
    for j in joints:
        match = [v for suffix, v in preshape.items() if j.endswith(f"_{suffix}")]
        if len(match) != 1:
            raise RetargetError(
                f"{where}.rest: joint {j!r} is not one of the design's finger joints "
                f"({', '.join(preshape)}); give the rest posture here"
            )
        rest.append(match[0])
    return tuple(rest)


def _pair_from_dict(
    where: str,
    name: str,
    raw: Any,
    pad_radius: float | None = None,
    preshape: dict[str, float] | None = None,
) -> PairDescription:
    if not isinstance(raw, dict):
        raise RetargetError(f"{where}: expected a table")
    allowed = {"base", "tips", "distals", "joints", "tip_radius", "rest"}
    unknown = sorted(set(raw) - allowed)
    if unknown:
        raise RetargetError(f"{where}.{unknown[0]}: unknown key (allowed: {sorted(allowed)})")
    for key in ("base", "tips", "distals", "joints"):
        if key not in raw:
            raise RetargetError(f"{where}.{key}: missing")
    if not isinstance(raw["base"], str) or not raw["base"]:
        raise RetargetError(f"{where}.base: expected a frame name, got {raw['base']!r}")
    tips = _str_list(f"{where}.tips", raw["tips"], 2)
    distals = _str_list(f"{where}.distals", raw["distals"], 2)
    joints = raw["joints"]
    if not isinstance(joints, list) or len(joints) != 2:
        raise RetargetError(f"{where}.joints: expected two lists of joint names (one per finger)")
    fj = tuple(
        _str_list(f"{where}.joints[{i}]", j, max(1, len(j)) if isinstance(j, list) else 1)
        for i, j in enumerate(joints)
    )
    flat = fj[0] + fj[1]
    if len(set(flat)) != len(flat):
        raise RetargetError(f"{where}.joints: a joint is listed twice")
    radius = raw.get("tip_radius", 0.0 if pad_radius is None else pad_radius)
    if not isinstance(radius, (int, float)) or isinstance(radius, bool) or radius < 0:
        raise RetargetError(f"{where}.tip_radius: expected a non-negative number [m]")
    rest = raw.get("rest")
    if rest is not None:
        if (
            not isinstance(rest, list)
            or len(rest) != len(flat)
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in rest)
        ):
            raise RetargetError(f"{where}.rest: expected {len(flat)} numbers (one per joint)")
        rest = tuple(float(v) for v in rest)
    elif preshape is not None:
        rest = design_rest(where, flat, preshape)
    return PairDescription(
        name=name,
        base=raw["base"],
        tips=(tips[0], tips[1]),
        distals=(distals[0], distals[1]),
        finger_joints=(fj[0], fj[1]),
        tip_radius=float(radius),
        rest=rest,
    )


def hand_from_dict(
    raw: dict[str, Any],
    base_dir: Path,
    source: Path | None = None,
    project: Project | None = None,
) -> HandDescription:
    """Build and validate a hand description from parsed TOML.

    Args:
        raw: The parsed TOML document.
        base_dir: Directory a relative ``urdf`` path is resolved against.
        source: File the data came from, for messages.
        project: The design project a ``{project}/...`` URDF path refers to (default:
            the current project).

    Raises:
        RetargetError: A missing or unknown key, a bad value, a frame or joint that is
            not in the URDF, or joints that are not exactly the chain from base to tip.
    """
    where = str(source) if source else "hand"
    allowed = ("name", "urdf", "design", "collision_margin", "pairs")
    unknown = sorted(set(raw) - set(allowed))
    if unknown:
        raise RetargetError(f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(allowed)})")
    if not isinstance(raw.get("urdf"), str):
        raise RetargetError(f"{where}: urdf: missing (path of the hand's URDF)")
    urdf = _path(raw["urdf"], base_dir, project)
    if not urdf.is_file():
        raise RetargetError(f"{where}: urdf: file not found: {urdf}")
    design, pad_radius, margin, preshape = None, None, DEFAULT_COLLISION_MARGIN, None
    pad_link = None
    if "design" in raw:
        if "collision_margin" in raw:
            raise RetargetError(
                f"{where}: collision_margin: the design's retarget.collision_margin applies "
                "(give one or the other)"
            )
        if not isinstance(raw["design"], str):
            raise RetargetError(f"{where}: design: expected a path")
        design = _path(raw["design"], base_dir, project)
        from payload.design.params import load_design
        from payload.errors import DesignError

        try:
            d = load_design(design)
        except DesignError as exc:
            raise RetargetError(f"{where}: design: {exc}") from exc
        pad_radius, margin = d.finger.pad.radius, d.retarget.collision_margin
        pad_link = d.retarget.pad_link
        from payload.design import FINGER_JOINTS

        preshape = dict(zip(FINGER_JOINTS, d.pinch.finger))
    elif "collision_margin" in raw:
        margin = raw["collision_margin"]
        if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not margin > 0:
            raise RetargetError(f"{where}: collision_margin: expected a positive number [m]")
    pairs_raw = raw.get("pairs")
    if not isinstance(pairs_raw, dict) or not pairs_raw:
        raise RetargetError(f"{where}: pairs: expected at least one [pairs.NAME] table")
    pairs = {
        name: _pair_from_dict(f"{where}: pairs.{name}", name, value, pad_radius, preshape)
        for name, value in pairs_raw.items()
    }
    hand = HandDescription(
        name=str(raw.get("name", urdf.stem)),
        urdf=urdf,
        pairs=pairs,
        source=source,
        design=design,
        collision_margin=float(margin),
        pad_link=pad_link,
    )
    validate_hand(hand)
    return hand


def _path(value: str, base_dir: Path, project: Project | None) -> Path:
    if value.startswith(PROJECT_PLACEHOLDER):
        p = (project or current_project()).root / value[len(PROJECT_PLACEHOLDER) :]
    else:
        p = Path(value)
    return p if p.is_absolute() else (base_dir / p).resolve()


def validate_hand(hand: HandDescription, kin: Kinematics | None = None) -> None:
    """Check every pair's frames and joints against the URDF.

    Raises:
        RetargetError: A frame or joint is missing, a finger's joints are not exactly the
            moving joints between the base and its tip, a distal frame is not on its
            finger's chain, or a joint has no finite range.
    """
    kin = kin or hand.kinematics()
    for pair in hand.pairs.values():
        where = f"pairs.{pair.name}"
        try:
            for i in range(2):
                chain = [kin.model.names[j] for j in kin.chain(pair.base, pair.tips[i])]
                listed = pair.finger_joints[i]
                if sorted(chain) != sorted(listed):
                    raise RetargetError(
                        f"{where}.joints[{i}]: the joints between {pair.base!r} and "
                        f"{pair.tips[i]!r} are {chain}, not {list(listed)}"
                    )
                dchain = [kin.model.names[j] for j in kin.chain(pair.base, pair.distals[i])]
                if not set(dchain) <= set(chain):
                    raise RetargetError(
                        f"{where}.distals[{i}]: {pair.distals[i]!r} is not on the chain of "
                        f"{pair.tips[i]!r}"
                    )
                for j in listed:
                    kin.joint_motion(kin.joint_id(j))
            idx = kin.q_indices(pair.joints)
        except KinematicsError as exc:
            raise RetargetError(f"{where}: {exc}") from exc
        lo, hi = kin.lower[idx], kin.upper[idx]
        bad = [
            j
            for j, a, b in zip(pair.joints, lo, hi)
            if not (np.isfinite(a) and np.isfinite(b) and b > a)
        ]
        if bad:
            raise RetargetError(f"{where}.joints: {bad[0]!r} has no finite range in the URDF")
        if pair.rest is not None:
            rest = np.asarray(pair.rest)
            out = [j for j, v, a, b in zip(pair.joints, rest, lo, hi) if not a <= v <= b]
            if out:
                raise RetargetError(f"{where}.rest: the value for {out[0]!r} is outside its limits")


def load_hand(path: str | Path | None = None, project: Project | None = None) -> HandDescription:
    """Load a hand description TOML (``None``: ours, :data:`DEFAULT_HAND`).

    Args:
        path: The TOML file.
        project: The design project whose models a ``{project}/...`` URDF path names
            (default: the current project, :func:`payload.project.current_project`).

    Raises:
        RetargetError: The file is missing, not TOML, or invalid (message names the key).
        ProjectError: The hand names ``{project}/...`` and there is no current project.
    """
    p = Path(path) if path is not None else DEFAULT_HAND
    if not p.is_file():
        raise RetargetError(f"hand description not found: {p}")
    try:
        raw = tomllib.loads(p.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise RetargetError(f"{p}: {not_text(exc, 'TOML')}") from None
    except tomllib.TOMLDecodeError as exc:
        raise RetargetError(f"{p}: not valid TOML: {exc}") from exc
    return hand_from_dict(raw, p.resolve().parent, source=p, project=project)
