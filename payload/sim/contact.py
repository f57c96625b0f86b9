"""The opposing-contact indicator: the CTB touches fingertips from both sides of the array.

The paper's confirmed contact: the CTB touches fingertips of side 1 {A, B} and of side 2
{C, D} at the same time. A fingertip is the pad sphere at the end of the distal link
(``payload/<finger>_distal_pad``); ``links="distal"`` widens it to every collision geom of
the distal link, for postures whose link edge rather than pad meets the cargo.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, NamedTuple

import mujoco
import numpy as np

from payload.design import FINGERS, SIDE_OF
from payload.sim.world import SimError, World

SIDES: dict[int, tuple[str, ...]] = {
    side: tuple(f for f in FINGERS if SIDE_OF[f] == side) for side in (1, 2)
}
"""Fingers of each side of the array: {1: (A, B), 2: (C, D)}."""


_EVERY_SIDE = sum(1 << side for side in SIDES)
"""A bit per side of the array (:meth:`ContactMonitor.opposing`)."""


_FINGER_SETS = tuple(
    frozenset(f for k, f in enumerate(FINGERS) if bits >> k & 1)
    for bits in range(1 << len(FINGERS))
)
"""The set of fingers of each bit pattern (bit k: ``FINGERS[k]``)."""

_OPPOSING: dict[frozenset[str], bool] = {}
""":func:`opposing` of each set of :data:`_FINGER_SETS` (filled below it: every set the
contact monitor returns), looked up instead of worked out at every control step."""


def opposing(fingers: Iterable[str]) -> bool:
    """True when ``fingers`` (those touching the cargo) include both sides of the array."""
    known = _OPPOSING.get(fingers) if isinstance(fingers, frozenset) else None
    if known is not None:
        return known
    sides = {SIDE_OF[f] for f in fingers}
    return sides >= {1, 2}


_OPPOSING.update((fingers, opposing(fingers)) for fingers in _FINGER_SETS)


class Contact(NamedTuple):
    """One active contact.

    Attributes:
        geom1: Name of the first geom.
        geom2: Name of the second geom.
        pos: Contact point, world frame, shape (3,) [m].
        normal_force: Normal force magnitude [N].
        dist: Signed distance (negative = penetration) [m].
    """

    geom1: str
    geom2: str
    pos: np.ndarray
    normal_force: float
    dist: float


class ContactMonitor:
    """Which fingertips touch the CTB, and the opposing-contact indicator.

    Args:
        world: The compiled world (needs a CTB for the indicator to ever be true).
        links: ``"pad"`` (fingertip pads only, the default) or ``"distal"`` (every
            collision geom of the distal links).
    """

    def __init__(self, world: World, links: str = "pad") -> None:
        if links not in ("pad", "distal"):
            raise SimError(f"ContactMonitor.links: {links!r} is not 'pad' or 'distal'")
        self.world = world
        model = world.model
        self._finger_of = np.full(model.ngeom, -1, dtype=np.int64)
        for k, f in enumerate(FINGERS):
            geoms = (world.pad_geoms[f],) if links == "pad" else world.distal_geoms[f]
            self._finger_of[list(geoms)] = k
        self._is_ctb = np.zeros(model.ngeom, dtype=bool)
        self._is_ctb[list(world.ctb_geoms)] = True
        # geom pair -> the finger whose fingertip geom touches a CTB geom in it (-1: none)
        pair = np.full((model.ngeom, model.ngeom), -1, dtype=np.int64)
        tips, ctb = np.flatnonzero(self._finger_of >= 0), np.flatnonzero(self._is_ctb)
        for g in tips:
            pair[g, ctb] = pair[ctb, g] = self._finger_of[g]
        self._pair_finger = pair
        # ... and the bit of that finger's side (0: none), for the indicator in one pass
        side_bit = np.array([1 << SIDE_OF[f] for f in FINGERS], dtype=np.int64)
        self._pair_side = np.where(pair >= 0, side_bit[pair], 0)
        self._force = np.zeros(6)
        self._touching: tuple[Any] | None = None  # (the compiled reader or None) once tried

    def touching(self, data: mujoco.MjData) -> frozenset[str]:
        """Fingers whose fingertip geoms are in contact with any CTB geom."""
        if data.ncon == 0:
            return frozenset()
        kernel = self._touching_kernel(data)
        if kernel is not None:
            return _FINGER_SETS[kernel(data)]
        return _FINGER_SETS[self._touching_bits(data)]

    def _touching_bits(self, data: mujoco.MjData) -> int:
        """The touching fingers in numpy, as bits (bit k: ``FINGERS[k]``)."""
        n = data.ncon
        contact = data.contact
        pairs = contact.geom[:n][contact.dist[:n] <= 0.0]
        hits = set(self._pair_finger[pairs[:, 0], pairs[:, 1]].tolist())
        return sum(1 << k for k in hits if k >= 0)

    def _touching_kernel(self, data: mujoco.MjData) -> Any:
        """:meth:`_touching_bits` compiled (:mod:`payload.sim.contacts_c`, checked on the
        first data with contacts it is asked about), or None."""
        if self._touching is None:
            from payload.sim.contacts_c import compiled_touching

            self._touching = (compiled_touching(data, self._pair_finger, self._touching_bits),)
        return self._touching[0]

    def opposing(self, data: mujoco.MjData) -> bool:
        """The opposing-contact indicator for the current state: :func:`opposing` of
        :meth:`touching`, from the sides of the touching pairs in one pass (it runs every
        control step in the base safety filter)."""
        n = data.ncon
        if n == 0:
            return False
        contact = data.contact
        pairs = contact.geom[:n][contact.dist[:n] <= 0.0]
        bits = np.bitwise_or.reduce(self._pair_side[pairs[:, 0], pairs[:, 1]], initial=0)
        return int(bits) & _EVERY_SIDE == _EVERY_SIDE

    def ctb_touched(self, data: mujoco.MjData) -> bool:
        """True when anything at all touches the CTB."""
        n = data.ncon
        if n == 0:
            return False
        pairs = data.contact.geom[:n]
        return bool(np.any(self._is_ctb[pairs[:, 0]] | self._is_ctb[pairs[:, 1]]))

    def contacts(self, data: mujoco.MjData) -> tuple[Contact, ...]:
        """Every active contact with names, point and normal force."""
        out = []
        model = self.world.model
        for i in range(data.ncon):
            c = data.contact[i]
            mujoco.mj_contactForce(model, data, i, self._force)
            out.append(
                Contact(
                    self.world.name(mujoco.mjtObj.mjOBJ_GEOM, int(c.geom[0])),
                    self.world.name(mujoco.mjtObj.mjOBJ_GEOM, int(c.geom[1])),
                    np.array(c.pos),
                    float(abs(self._force[0])),
                    float(c.dist),
                )
            )
        return tuple(out)


__all__ = ["SIDES", "Contact", "ContactMonitor", "opposing"]
