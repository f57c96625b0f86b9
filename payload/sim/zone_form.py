"""The form of Astrobee's zone objects, ``{"sequence": [[6 numbers], ...], "safe": bool}``
(:mod:`payload.sim.zones`), in a module without numpy: what a terminal summary reads of a
trial's recorded zones needs the form, not the zones' geometry."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

SEQUENCE = "sequence"
"""A zone object's list of boxes, each ``[xmin, ymin, zmin, xmax, ymax, zmax]`` [m]."""
SAFE = "safe"
"""A zone object's kind: true for keep-in (free space), false for keep-out (obstacles)."""


def box_counts(objects: Sequence[Mapping[str, Any]]) -> tuple[int, int]:
    """The keep-in and keep-out box counts of zone objects already checked
    (:meth:`payload.sim.zones.StationZones.as_json`'s, as a trial records them)."""
    keep_in = keep_out = 0
    for obj in objects:
        boxes = len(obj.get(SEQUENCE) or [])
        if obj.get(SAFE):
            keep_in += boxes
        else:
            keep_out += boxes
    return keep_in, keep_out


__all__ = ["SAFE", "SEQUENCE", "box_counts"]
