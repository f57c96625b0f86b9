"""The loop's two clocks, numpy-free so that a command's options can quote them at start.

:mod:`payload.schema` re-exports both; every module imports them from one place or the
other.
"""

from __future__ import annotations

CONTROL_DT = 0.02
"""Period of the teleoperation loop and of every command stream [s] (the paper's 50 Hz)."""

PHYSICS_DT = 0.001
"""Physics time step [s] (1 kHz, the paper's): the default of every command and the
generated MJCF's ``timestep``."""

__all__ = ["CONTROL_DT", "PHYSICS_DT"]
