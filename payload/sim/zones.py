"""The station's free space in one place: keep-in and keep-out boxes.

Astrobee's flight software describes where the robot may fly as axis-aligned boxes,
``KEEPIN`` (free space) and ``KEEPOUT`` (obstacles), in a JSON form its mapper reads::

    {"sequence": [[xmin, ymin, zmin, xmax, ymax, zmax], ...], "safe": true}

(``safe`` true: keep-in, false: keep-out; docs/sources.md, "ISS and cargo": keep-in /
keep-out zones). :func:`station_zones` derives the keep-in boxes from the ISS layout the
simulator builds (:mod:`payload.sim.iss`): Kibo, the hatch vestibule and Node 2, each
shrunk off its handrailed faces by the handrail layer (standoff plus half a section), the
vestibule lengthened through that layer so it still joins Node 2. A zone file holds one
such object or a list of them (keep-in and keep-out).

The base safety filter works with the obstacles, the complement of the keep-in union
near it: :meth:`StationZones.obstacles` cuts, for every face of every keep-in box, a slab
beyond the face and removes from it what the other keep-in boxes cover (the hatch
openings), then adds the keep-out boxes. Everything here is in the world frame, metres.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from payload.errors import not_text
from payload.sim.errors import SimError
from payload.sim.iss import IssLayout
from payload.sim.zone_form import SAFE, SEQUENCE

Box = tuple[tuple[float, float, float], tuple[float, float, float]]
"""An axis-aligned box: (lo (3,), hi (3,)) [m]."""

SLAB = 0.5
"""Thickness of the obstacle slab cut beyond each keep-in face [m]: more than any
activation distance of the filter, so nothing is ever judged to be beyond a slab."""


class ZoneError(SimError):
    """A zone file or zone list is malformed."""


def _box(values: Sequence[float], where: str) -> Box:
    if len(values) != 6:
        raise ZoneError(f"{where}: a zone needs 6 numbers [xmin, ymin, zmin, xmax, ymax, zmax]")
    try:
        v = [float(x) for x in values]
    except (TypeError, ValueError):
        raise ZoneError(f"{where}: zone values must be numbers, got {list(values)!r}") from None
    if not all(math.isfinite(x) for x in v):
        raise ZoneError(f"{where}: zone values must be finite")
    if not all(v[i] < v[i + 3] for i in range(3)):
        raise ZoneError(f"{where}: zone min corner must be below its max corner: {v}")
    return (v[0], v[1], v[2]), (v[3], v[4], v[5])


@dataclass(frozen=True)
class StationZones:
    """Keep-in boxes (free space, their union) and keep-out boxes (obstacles in it).

    Attributes:
        keepin: Keep-in boxes, each (lo, hi) [m].
        keepout: Keep-out boxes, each (lo, hi) [m].
        names: A name per keep-in box (``kibo``, ``vestibule``, ``node2`` for the
            station's; ``keepin<i>`` for a loaded file's).
        source: The file the zones were read from (``None``: not read from a file); a
            label, not part of the zones (equal zones from two files compare equal).
    """

    keepin: tuple[Box, ...]
    keepout: tuple[Box, ...] = ()
    names: tuple[str, ...] = ()
    source: str | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if not self.keepin:
            raise ZoneError("zones: at least one keep-in box is needed")
        if self.names and len(self.names) != len(self.keepin):
            raise ZoneError("zones: one name per keep-in box")
        if not self.names:
            object.__setattr__(self, "names", tuple(f"keepin{i}" for i in range(len(self.keepin))))

    # -- JSON -----------------------------------------------------------------------------
    def as_json(self) -> list[dict[str, Any]]:
        """The zones as Astrobee zone objects: the keep-in one, then the keep-out one if any."""
        out = [{SEQUENCE: [[*lo, *hi] for lo, hi in self.keepin], SAFE: True}]
        if self.keepout:
            out.append({SEQUENCE: [[*lo, *hi] for lo, hi in self.keepout], SAFE: False})
        return out

    def write(self, path: str | Path) -> None:
        """Write the zones as a JSON list of Astrobee zone objects."""
        Path(path).write_text(json.dumps(self.as_json(), indent=2) + "\n")

    @classmethod
    def from_json(cls, data: Any, where: str = "zones") -> StationZones:
        """Zones from one Astrobee zone object or a list of them.

        Raises:
            ZoneError: Not that form (one line naming what is wrong).
        """
        objects = data if isinstance(data, list) else [data]
        keepin: list[Box] = []
        keepout: list[Box] = []
        for i, obj in enumerate(objects):
            at = f"{where}[{i}]" if isinstance(data, list) else where
            named = at or "the zone object"
            if not isinstance(obj, dict) or SEQUENCE not in obj or SAFE not in obj:
                form = f'{{"{SEQUENCE}": [[6 numbers], ...], "{SAFE}": bool}}'
                raise ZoneError(f"{named}: expected {form}")
            if not isinstance(obj[SAFE], bool):
                raise ZoneError(f"{named}: '{SAFE}' must be true (keep-in) or false (keep-out)")
            if not isinstance(obj[SEQUENCE], list):
                raise ZoneError(f"{named}: '{SEQUENCE}' must be a list of zones")
            target = keepin if obj[SAFE] else keepout
            for j, values in enumerate(obj[SEQUENCE]):
                zone = f"{at}.{SEQUENCE}[{j}]" if at else f"{SEQUENCE}[{j}]"
                if not isinstance(values, list):
                    raise ZoneError(f"{zone}: a zone is a list of 6 numbers")
                target.append(_box(values, zone))
        if not keepin:
            where = where or "the file"
            raise ZoneError(f'{where}: no keep-in zone (an object with "{SAFE}": true)')
        return cls(tuple(keepin), tuple(keepout))

    @classmethod
    def read(cls, path: str | Path) -> StationZones:
        """Zones from a JSON file (:meth:`from_json`).

        Raises:
            ZoneError: Unreadable, not JSON, or not the zone form.
        """
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
        except OSError as exc:
            raise ZoneError(f"{path}: cannot read the zone file: {exc.strerror}") from None
        except UnicodeDecodeError as exc:
            raise ZoneError(f"{path}: {not_text(exc, 'JSON')}") from None
        except json.JSONDecodeError as exc:
            raise ZoneError(f"{path}: not JSON ({exc.msg}, line {exc.lineno})") from None
        try:  # the file, then where in it: "zones.json: sequence[0]: ..."
            return replace(cls.from_json(data, ""), source=str(path))
        except ZoneError as exc:
            raise ZoneError(f"{path}: {exc}") from None

    # -- a trial's record -----------------------------------------------------------------
    def record(self) -> dict[str, Any]:
        """The zones as a trial records them (:func:`zones_record`)."""
        return {"zones": self.as_json(), "zones_file": self.source}

    @classmethod
    def recorded(cls, meta: dict[str, Any]) -> StationZones | None:
        """The zones a trial's metadata records (:func:`zones_record`); ``None``: the
        station's (recorded as null, or by a recording older than the record).

        Raises:
            ZoneError: The recorded zones are not the zone form.
        """
        data = meta.get("zones")
        if data is None:
            return None
        source = meta.get("zones_file")
        return replace(cls.from_json(data), source=source if isinstance(source, str) else None)

    # -- geometry -------------------------------------------------------------------------
    def contains(self, point: Sequence[float]) -> bool:
        """Whether ``point`` (3,) [m] lies in the keep-in union and in no keep-out box."""
        p = [float(x) for x in point]

        def inside(box: Box) -> bool:
            return all(box[0][i] <= p[i] <= box[1][i] for i in range(3))

        return any(inside(b) for b in self.keepin) and not any(inside(b) for b in self.keepout)

    def obstacles(self, slab: float = SLAB) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """The obstacles next to the free space as axis-aligned boxes.

        Returns:
            (lo (M, 3), hi (M, 3), a name per box: ``<keep-in box> <axis><+|->`` for a face
            slab, ``keepout<i>`` for a keep-out box).
        """
        los, his, names = [], [], []
        for k, (lo, hi) in enumerate(self.keepin):
            for axis in range(3):
                for side, sign in ((0, "-"), (1, "+")):
                    s_lo = np.array(lo, float) - slab
                    s_hi = np.array(hi, float) + slab
                    if side == 0:
                        s_lo[axis], s_hi[axis] = lo[axis] - slab, lo[axis]
                    else:
                        s_lo[axis], s_hi[axis] = hi[axis], hi[axis] + slab
                    pieces = [(s_lo, s_hi)]
                    for m, other in enumerate(self.keepin):
                        if m != k:
                            pieces = [q for p in pieces for q in _subtract(p, other)]
                    for p_lo, p_hi in pieces:
                        los.append(p_lo)
                        his.append(p_hi)
                        names.append(f"{self.names[k]} {'xyz'[axis]}{sign}")
        for i, (lo, hi) in enumerate(self.keepout):
            los.append(np.array(lo, float))
            his.append(np.array(hi, float))
            names.append(f"keepout{i}")
        return np.array(los), np.array(his), names


def _subtract(box: tuple[np.ndarray, np.ndarray], cut: Box) -> list[tuple[np.ndarray, np.ndarray]]:
    """``box`` minus ``cut`` as at most six disjoint boxes (empty pieces dropped)."""
    lo, hi = box
    c_lo, c_hi = np.array(cut[0], float), np.array(cut[1], float)
    if np.any(c_hi <= lo) or np.any(c_lo >= hi):
        return [box]
    out = []
    cur_lo, cur_hi = lo.copy(), hi.copy()
    for axis in range(3):
        if c_lo[axis] > cur_lo[axis]:
            p_lo, p_hi = cur_lo.copy(), cur_hi.copy()
            p_hi[axis] = c_lo[axis]
            out.append((p_lo, p_hi))
            cur_lo[axis] = c_lo[axis]
        if c_hi[axis] < cur_hi[axis]:
            p_lo, p_hi = cur_lo.copy(), cur_hi.copy()
            p_lo[axis] = c_hi[axis]
            out.append((p_lo, p_hi))
            cur_hi[axis] = c_hi[axis]
    return [(a, b) for a, b in out if np.all(b - a > 1e-9)]


def handrail_depth(layout: IssLayout) -> float:
    """How far a handrail reaches from its rack face into the module [m]."""
    return layout.handrail_standoff + layout.handrail_section / 2.0


def station_zones(layout: IssLayout | None = None, keepout: Iterable[Box] = ()) -> StationZones:
    """The keep-in boxes of the route's three volumes (Kibo, vestibule, Node 2).

    Kibo's handrails line its x and z faces, Node 2's its y and z faces
    (:mod:`payload.sim.iss`); each box stops at the handrail layer there. The vestibule
    (no handrails) is lengthened into Node 2 through that layer so the union stays
    connected; Kibo's forward face has no handrails, so the vestibule ends on it.

    Args:
        layout: The ISS layout (default: the simulator's default layout).
        keepout: Optional keep-out boxes, each (lo, hi) [m].
    """
    layout = layout or IssLayout()
    r = handrail_depth(layout)
    kibo, vest, node2 = layout.zones()

    def shrink(zone: Any, axes: tuple[int, ...]) -> Box:
        lo, hi = list(zone.lo), list(zone.hi)
        for a in axes:
            lo[a] += r
            hi[a] -= r
        return (lo[0], lo[1], lo[2]), (hi[0], hi[1], hi[2])

    v_lo = list(vest.lo)
    v_lo[1] -= r
    boxes = (
        shrink(kibo, (0, 2)),
        ((v_lo[0], v_lo[1], v_lo[2]), tuple(vest.hi)),
        shrink(node2, (1, 2)),
    )
    return StationZones(
        boxes,  # type: ignore[arg-type]
        tuple(_box([*lo, *hi], "keepout") for lo, hi in keepout),
        ("kibo", "vestibule", "node2"),
    )


def zones_record(zones: StationZones | None) -> dict[str, Any]:
    """What a trial's metadata and ``metrics.json`` say of its base filter's zones:
    ``zones``, their Astrobee zone objects (:meth:`StationZones.as_json`: the data, so a
    replay runs them wherever the file went), and ``zones_file``, the file they were read
    from; both null for the station's (``zones`` None)."""
    return {"zones": None, "zones_file": None} if zones is None else zones.record()


__all__ = [
    "SLAB",
    "Box",
    "StationZones",
    "ZoneError",
    "handrail_depth",
    "station_zones",
    "zones_record",
]
