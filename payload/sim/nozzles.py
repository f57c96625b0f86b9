"""Astrobee's 12 nozzles: the propulsion model's geometry.

Geometry from NASA's propulsion code (``docs/sources.md``: gnc/pmc/src/shared.cc):
nozzle positions, nozzle axes, widths and test-fitted discharge coefficients. The PMC
simulator (gnc/pmc/src/pmc_sim.cc) maps a nozzle's thrust ``t >= 0`` to the body wrench
``F = -a t`` and ``tau = r x (-a t)`` with ``a`` the nozzle axis and ``r`` its position:
the thrust on the robot points against the nozzle axis (the exhaust leaves along it).
"""

from __future__ import annotations

import numpy as np

INCH = 0.0254
"""[m]"""

NOZZLE_POSITIONS_IN = np.array(
    [
        # PM1 (+y side)
        (6.00, 4.01, -1.56),
        (-6.00, 4.01, 1.56),
        (2.83, 6.00, 2.83),
        (-2.83, 6.00, -2.83),
        (-2.66, 4.01, 6.00),
        (2.66, 4.01, -6.00),
        # PM2 (-y side)
        (-6.00, -4.01, -1.56),
        (6.00, -4.01, 1.56),
        (-2.83, -6.00, 2.83),
        (2.83, -6.00, -2.83),
        (2.66, -4.01, 6.00),
        (-2.66, -4.01, -6.00),
    ]
)
"""Nozzle positions in the body frame [inch] (docs/sources.md, shared.cc)."""

NOZZLE_AXES = np.array(
    [
        (1, 0, 0),
        (-1, 0, 0),
        (0, 1, 0),
        (0, 1, 0),
        (0, 0, 1),
        (0, 0, -1),
        (-1, 0, 0),
        (1, 0, 0),
        (0, -1, 0),
        (0, -1, 0),
        (0, 0, 1),
        (0, 0, -1),
    ],
    dtype=float,
)
"""Nozzle axes (``nozzle_orientations``); the thrust on the robot is ``-axis * t``."""

NOZZLE_WIDTHS_IN = np.array([5.0, 5.0, 2.8, 2.8, 2.8, 2.8] * 2)
"""Nozzle widths [inch], same order in both modules."""

DISCHARGE_COEFFS = np.array(
    [0.915, 0.756, 0.941, 0.792, 0.924, 0.930, 0.947, 0.764, 1.000, 0.905, 0.937, 0.894]
)
"""Test-fitted discharge coefficients, PM1 then PM2."""

N_NOZZLES = 12


__all__ = [
    "DISCHARGE_COEFFS",
    "INCH",
    "NOZZLE_AXES",
    "NOZZLE_POSITIONS_IN",
    "NOZZLE_WIDTHS_IN",
    "N_NOZZLES",
]
