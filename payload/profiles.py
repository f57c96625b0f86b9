"""Controller profiles: what sits between the operator and the robot (docs/safety-filter.md).

``paper`` is the paper's controller (the 20-evaluation pair solve, no self-collision
model, no base safety filter): the default of ``payload trial`` and ``trials run`` so the
reproduction is the paper's. ``safe`` adds every safety layer (the contact-aware
self-collision model, the base safety filter): the default wherever a person or real
servos are in the loop (``teleop serve``, ``hw run``). Finer flags override a profile;
trials and summaries record the profile and every override.

This module imports nothing heavy: the command line reads it to build its options.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from payload.errors import PayloadError


@dataclass(frozen=True)
class ControllerProfile:
    """One controller profile.

    Attributes:
        name: ``paper`` or ``safe``.
        retarget_budget: Pair-solve budget (``paper``: at most 20 residual evaluations;
            ``converged``).
        retarget_collisions: The self-collision model in the pair solves.
        base_filter: The base safety filter between the base channel and the vehicle
            controller.
    """

    name: str
    retarget_budget: str
    retarget_collisions: bool
    base_filter: bool

    def override(
        self,
        retarget_budget: str | None = None,
        retarget_collisions: bool | None = None,
        base_filter: bool | None = None,
    ) -> ControllerProfile:
        """This profile with each setting given (not ``None``) replacing its own."""
        changes = {
            k: v
            for k, v in (
                ("retarget_budget", retarget_budget),
                ("retarget_collisions", retarget_collisions),
                ("base_filter", base_filter),
            )
            if v is not None
        }
        return replace(self, **changes)

    def as_dict(self) -> dict[str, object]:
        """The profile as recorded in a trial and a summary."""
        return {
            "controller": self.name,
            "retarget_budget": self.retarget_budget,
            "retarget_collisions": self.retarget_collisions,
            "base_filter": self.base_filter,
        }


PROFILE_SETTINGS = ("retarget_budget", "retarget_collisions", "base_filter")
"""The settings a controller profile sets (:class:`ControllerProfile`'s but its name): a
replay given ``--controller`` takes them from that profile, not from its recording."""


PROFILES: dict[str, ControllerProfile] = {
    "paper": ControllerProfile("paper", "paper", False, False),
    "safe": ControllerProfile("safe", "paper", True, True),
}
"""The profiles by name."""

PAPER = "paper"
"""The profile of ``payload trial`` and ``trials run``."""
SAFE = "safe"
"""The profile wherever a person or real servos are in the loop."""


def profile(name: str) -> ControllerProfile:
    """The profile called ``name``.

    Raises:
        PayloadError: No such profile.
    """
    try:
        return PROFILES[name]
    except KeyError:
        raise PayloadError(
            f"--controller: expected one of {', '.join(PROFILES)}, got {name!r}"
        ) from None


def resolve(name: str | None, default: str, **given: object) -> tuple[ControllerProfile, list[str]]:
    """The profile called ``name`` (``None``: ``default``) with the settings given (not
    ``None``) replacing its own, and the names of those that differ from the profile's
    (the overrides a trial and a summary record; a flag equal to the profile's own setting
    is none, so the same setup resolved twice reads the same).

    Raises:
        PayloadError: No such profile.
    """
    prof = profile(default if name is None else name)
    overrides = sorted(k for k, v in given.items() if v is not None and getattr(prof, k) != v)
    return prof.override(**given), overrides  # type: ignore[arg-type]


def resolve_args(args: Any, default: str) -> tuple[ControllerProfile, list[str]]:
    """:func:`resolve` of a command's ``--controller`` and the finer flags that override a
    profile (``--retarget-budget``, ``--[no-]retarget-collisions``, ``--[no-]base-filter``:
    ``None`` when not given), ``default`` where no ``--controller`` is given."""
    return resolve(
        args.controller,
        default,
        retarget_budget=args.retarget_budget,
        retarget_collisions=args.retarget_collisions,
        base_filter=args.base_filter,
    )
