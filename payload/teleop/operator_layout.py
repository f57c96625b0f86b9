"""The synthetic operator's flight constants and the layout of its compiled flight step.

Each fact once: the flight's constants (the stop margin, the arrival distance, the turn
threshold, the rest speed and time, the pinch's lag, the dropout's length, ...) are read
by the Python operator (:class:`payload.teleop.operator.SyntheticOperator`) and passed to
the C (:mod:`payload.teleop.operator_c`) alike; the tuples name the places in the C's
arrays, which :func:`_layout` writes out as the C's enumerations and
:class:`~payload.teleop.operator_stepper.CompiledAct` fills.
"""

from __future__ import annotations

import itertools
import math

from payload.teleop.hands import JOINTS_SHAPE

FLIGHT_PHASES: tuple[str, ...] = ("translation", "turn", "arrival", "braking")
"""The operator's phases the kernel steps (its phase codes, in order)."""

STOP_SHORT_M = 0.3
"""The operator brakes to stop this far short of the route's end [m]."""
ARRIVAL_M = 0.45
"""Within this of the route's end (along it) the operator has arrived [m]."""
TURN_ABOVE_RAD = math.radians(12)
"""A heading error above this and the operator turns rather than translates [rad]."""
AIMLESS_M = 1e-6
"""A waypoint nearer than this gives the operator no direction to push [m]."""
REACH_MARGIN_M = 0.01
"""How far beyond the base channel's sphere the operator's wrist reaches at rest [m]."""
REST_SPEED = 0.005
"""The vehicle counts as at rest below this speed [m/s]."""
REST_S = 2.0
"""At rest this long at the end, the operator is done [s]."""
PINCH_LAG_S = 0.15
"""The time constant of the operator's pinch following its intent [s]."""
DROPOUT_S: tuple[float, float] = (0.03, 0.08)
"""How long a hand the tracker loses stays lost: uniform between these [s]."""

CONFIG: tuple[str, ...] = (
    "waypoint_radius",
    "brake_accel",
    "max_speed",
    "speed_pref",
    "corner_speed_squared",
    "sphere_radius",
    "full_speed_offset",
    "wrist_lag",
    "turn_above",
    "stop_short",
    "arrival",
    "aimless",
    "reach_margin",
    "rest_speed",
    "rest_time",
    "pinch_lag",
    "dropout_low",
    "dropout_range",
)
"""The kernel's constants (``cfg`` of :data:`~payload.teleop.operator_c.SOURCE`, in this
order): the plan's, the base channel's, the traits' and this module's (numpy's ``uniform``
of :data:`DROPOUT_S` as its low end and range, ``high - low``)."""

STATE: tuple[str, ...] = (
    "phase",
    "waypoint",
    "stopped_since",
    "finished",
    "aperture",
    "grip_aperture",
    "dropout_left",
    "dropout_right",
)
"""The operator's state the kernel reads and writes (``state`` of
:data:`~payload.teleop.operator_c.SOURCE`): the phase's code, the waypoint,
``stopped_since`` and ``grip_aperture`` (NaN: None), whether it finished at this step, the
aperture, and until when each hand is lost."""

HANDS: tuple[str, ...] = (
    "t",
    "dt",
    "hand_size",
    "tremor_amp",
    "tremor_freq",
    "noise",
    "dropout_rate",
    "curl",
    "grid",
)
"""The step's scalars (``s`` of :data:`~payload.teleop.operator_c.SOURCE`, in this order): its
time and period, the traits the hands are drawn with, the hand model's curl and the grid the
headset reports the joints on (0: none)."""

INPUT: tuple[tuple[str, int], ...] = (
    ("pos", 3),
    ("rot", 9),
    ("vel", 3),
    ("wrist_left", 3),
    ("wrist_right", 3),
    ("phases_left", 3),
    ("phases_right", 3),
)
"""The step's arrays (``in`` of :data:`~payload.teleop.operator_c.SOURCE`, in this order, with
their sizes): what the operator sees (position, rotation row-major, velocity), its wrists
and its tremor's phases."""

OUTPUT: tuple[tuple[str, int], ...] = (
    ("wrist_left", 3),
    ("wrist_right", 3),
    ("hands", 2 * math.prod(JOINTS_SHAPE)),
)
"""What the step writes (``out`` of :data:`~payload.teleop.operator_c.SOURCE`, in this order,
with their sizes): the wrists after the lag and both hands' joints (left then right)."""

ARGS: tuple[str, ...] = (
    "cfg",
    "route",
    "left",
    "n",
    "yaw",
    "centre",
    "half",
    "in",
    "state",
    "tables",
    "bitgen",
    "out",
)
"""The step's pointers, and the route's length ``n`` (``a`` of
:data:`~payload.teleop.operator_c.SOURCE`, in this order)."""


def _offsets(parts: tuple[tuple[str, int], ...]) -> dict[str, int]:
    """Each part's place in its array (the parts one after the other)."""
    return dict(zip((name for name, _ in parts), itertools.accumulate(
        (size for _, size in parts), initial=0)))  # fmt: skip


def _layout() -> str:
    """The C's names for the places in its arrays, from the tuples above (each fact once):
    ``PH_*`` the phase codes, ``CFG_*``, ``ST_*``, ``H_*`` and ``ARG_*`` the indices of
    :data:`CONFIG`, :data:`STATE`, :data:`HANDS` and :data:`ARGS`, ``IN_*`` and ``OUT_*``
    the offsets of :data:`INPUT` and :data:`OUTPUT`."""
    names = [
        *(f"PH_{name.upper()} = {i}" for i, name in enumerate(FLIGHT_PHASES)),
        *(f"CFG_{name.upper()} = {i}" for i, name in enumerate(CONFIG)),
        *(f"ST_{name.upper()} = {i}" for i, name in enumerate(STATE)),
        *(f"H_{name.upper()} = {i}" for i, name in enumerate(HANDS)),
        *(f"ARG_{name.upper()} = {i}" for i, name in enumerate(ARGS)),
        *(f"IN_{name.upper()} = {i}" for name, i in _offsets(INPUT).items()),
        *(f"OUT_{name.upper()} = {i}" for name, i in _offsets(OUTPUT).items()),
    ]
    return "enum {\n" + "".join(f"    {n},\n" for n in names) + "};\n"


__all__ = [
    "AIMLESS_M",
    "ARGS",
    "ARRIVAL_M",
    "CONFIG",
    "DROPOUT_S",
    "FLIGHT_PHASES",
    "HANDS",
    "INPUT",
    "OUTPUT",
    "PINCH_LAG_S",
    "REACH_MARGIN_M",
    "REST_S",
    "REST_SPEED",
    "STATE",
    "STOP_SHORT_M",
    "TURN_ABOVE_RAD",
]
