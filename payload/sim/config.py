"""What to put in the simulated world (:class:`WorldConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from payload.project import Project, current_project, project_of
from payload.schema import CONTROL_DT, PHYSICS_DT
from payload.sim.cargo import CTB_SIZES, CtbSize, Handle
from payload.sim.errors import SimError
from payload.sim.iss import IssLayout


def check_physics_dt(dt: float) -> str | None:
    """What is wrong with a physics step [s] (``None`` if it is usable): it must be
    positive and divide the 50 Hz control period into a whole number of steps."""
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0.0):
        return f"the physics step must be a positive number of seconds, got {dt!r}"
    n = CONTROL_DT / dt
    if abs(n - round(n)) > 1e-9 * n or round(n) < 1:
        return (
            f"the physics step {dt:g} s does not divide the control period {CONTROL_DT:g} s "
            "into whole steps (e.g. 0.001 or 0.002)"
        )
    return None


@dataclass(frozen=True)
class WorldConfig:
    """What to put in the world.

    Attributes:
        ctb: CTB size name (``half``, ``single``, ``double``) or None for no CTB.
        ctb_mass: Override of the CTB mass [kg]; None keeps the size's loaded mass.
        handle: CTB handle geometry.
        layout: ISS volumes and route.
        payload_mjcf: The payload MJCF to attach (its meshdir is relative to the file).
            ``None``: the ``urdf/payload.xml`` of the project holding ``design``, or of
            the current project.
        design: The design file the payload was generated from. ``None``: the design of
            the project holding ``payload_mjcf``, or of the current project. Both are
            concrete paths once the config is made; :meth:`for_project` sets both.
        cone: Friction cone, ``elliptic`` or ``pyramidal``.
        impratio: Ratio of frictional to normal impedance (elliptic cones).
        pads: ``silicone`` (default: the pad contact's solref/solimp derived from the
            design's pad material, :mod:`payload.sim.pads`) or ``mujoco`` (MuJoCo's
            default contact parameters, the earlier model, for comparison).
        physics_dt: Physics time step [s] (default :data:`PHYSICS_DT`, 1 kHz); it must
            divide the control period. The pad contact's time constant is derived from
            it (:func:`payload.sim.pads.pad_contact`).
    """

    ctb: str | None = "single"
    ctb_mass: float | None = None
    handle: Handle = field(default_factory=Handle)
    layout: IssLayout = field(default_factory=IssLayout)
    payload_mjcf: Path | None = None
    design: Path | None = None
    cone: str = "elliptic"
    impratio: float = 10.0
    pads: str = "silicone"
    physics_dt: float = PHYSICS_DT

    @classmethod
    def for_project(cls, project: Project, **kwargs: Any) -> WorldConfig:
        """The world of ``project``: its generated MJCF and its design file."""
        return cls(payload_mjcf=project.mjcf, design=project.design_path, **kwargs)

    def __post_init__(self) -> None:
        if self.payload_mjcf is None or self.design is None:
            known = self.design if self.design is not None else self.payload_mjcf
            project = (project_of(known) if known is not None else None) or current_project()
            if self.payload_mjcf is None:
                object.__setattr__(self, "payload_mjcf", project.mjcf)
            if self.design is None:
                object.__setattr__(self, "design", project.design_path)
        if self.pads not in ("silicone", "mujoco"):
            raise SimError(f"WorldConfig.pads: {self.pads!r} is not 'silicone' or 'mujoco'")
        if self.ctb is not None and self.ctb not in CTB_SIZES:
            raise SimError(
                f"WorldConfig.ctb: unknown CTB size {self.ctb!r} "
                f"(expected one of {', '.join(CTB_SIZES)} or None)"
            )
        if self.ctb_mass is not None and not (math.isfinite(self.ctb_mass) and self.ctb_mass > 0.0):
            raise SimError(f"WorldConfig.ctb_mass: must be a positive mass, got {self.ctb_mass}")
        if self.cone not in ("elliptic", "pyramidal"):
            raise SimError(f"WorldConfig.cone: {self.cone!r} is not 'elliptic' or 'pyramidal'")
        if not (math.isfinite(self.impratio) and self.impratio >= 1.0):
            raise SimError(f"WorldConfig.impratio: must be >= 1, got {self.impratio}")
        problem = check_physics_dt(self.physics_dt)
        if problem is not None:
            raise SimError(f"WorldConfig.physics_dt: {problem}")

    @property
    def substeps(self) -> int:
        """Physics steps per control step (20 at 1 kHz)."""
        return round(CONTROL_DT / self.physics_dt)

    @property
    def ctb_size(self) -> CtbSize | None:
        """The CTB size with the mass override applied, or None."""
        if self.ctb is None:
            return None
        size = CTB_SIZES[self.ctb]
        if self.ctb_mass is None:
            return size
        return CtbSize(size.name, size.length, size.width, size.height, float(self.ctb_mass))
