"""Whether a design's stowed payload fits the bays, for commands that only need the answer.

A trial or a campaign runs whatever design the project holds; one whose stowed payload
does not fit the two lower bays (a part beyond a wall, links that collide, a deployment
path that hits the vehicle) still simulates, but it could not fly. Those commands warn
with :func:`stowed_fit_failures`: the design's own stowed posture checked as ``payload
report envelope`` checks it (no posture search: that is the report's), about 0.3 s, kept
in the cache (:func:`payload.cache.cache_dir`) under a hash of the design file and the
code, so that an unchanged design costs a file read.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from payload.cache import cache_dir, code_key
from payload.errors import first_of

_VERSION = "stowed-fit-1"
_LIBRARIES = ("numpy", "trimesh", "manifold3d", "python-fcl")
"""The libraries whose versions can move the answer (the solids and the distances)."""


def _key(design_path: Path, text: bytes) -> str:
    return code_key(_VERSION, _LIBRARIES, str(design_path).encode(), text)


def design_failures(design: Any, vehicle: Any = None) -> list[str]:
    """What the envelope check fails of ``design`` (a :class:`~payload.design.params.Design`)
    in ``vehicle``'s bays (default: its ``[vehicle]`` table's), computed (no cache:
    :func:`stowed_fit_failures` keeps a design file's)."""
    from payload.design import build_tree
    from payload.envelope.fit import check_stowed
    from payload.envelope.geometry import PayloadGeometry
    from payload.envelope.vehicle import vehicle_from_dict

    if vehicle is None:
        vehicle = vehicle_from_dict(design.vehicle or {}, source=str(design.source))
    geom = PayloadGeometry(build_tree(design))
    return check_stowed(geom, vehicle, geom.tree.posture("stowed")).failures()


def _check(design_path: Path) -> list[str]:
    from payload.envelope.vehicle import load_design_and_vehicle

    return design_failures(*load_design_and_vehicle(design_path))


def stowed_fit_failures(design_path: str | Path) -> list[str]:
    """What fails when the design's stowed payload is checked against the bays: one phrase
    per failed check (:meth:`~payload.envelope.fit_results.StowedCheck.failures`), empty
    when it fits.

    Args:
        design_path: The project's ``cad/design.toml``.

    Returns:
        The failures, worst first; ``[]`` for a design that fits.

    Raises:
        DesignError: The design file is invalid.
    """
    path = Path(design_path).resolve()
    text = path.read_bytes()
    cached = cache_dir() / f"stowed_{_key(path, text)}.json"
    try:
        failures = json.loads(cached.read_text(encoding="utf-8"))
        if isinstance(failures, list) and all(isinstance(f, str) for f in failures):
            return failures
    except (OSError, ValueError):
        pass
    failures = _check(path)
    try:  # best effort: a read-only cache costs the next check
        from payload.safeio import replace_file

        cached.parent.mkdir(parents=True, exist_ok=True)
        replace_file(cached, json.dumps(failures) + "\n")
    except OSError:
        pass
    return failures


def stowed_fit_warning(design_path: str | Path, ran: str) -> str | None:
    """The warning for a command that ``ran`` (``"the trial ran"``) a design whose stowed
    payload does not fit the bays or cannot deploy, naming what fails; ``None`` when it
    passes the envelope check."""
    failures = stowed_fit_failures(design_path)
    if not failures:
        return None
    deploying = all(f.startswith("deployment: ") for f in failures)
    what = "cannot deploy from the bays" if deploying else "does not fit the bays"
    return (
        f"{design_path}: the stowed payload {what}, so it could not be flown "
        f"({first_of(failures, 2, 'payload report envelope')}); {ran} all the same"
    )


__all__ = ["design_failures", "stowed_fit_failures", "stowed_fit_warning"]
