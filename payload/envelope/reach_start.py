"""The reach check's first step, light to import: sample the deployed joint space and
start the collision check in forked workers.

It needs MuJoCo, Numba (which loads SciPy's top-level package, not its optimize or
spatial modules) and the design only, so ``payload report reach`` starts the
workers before it imports what the rest of the analysis uses (Pinocchio, CasADi,
SciPy), and those load while the workers check (:func:`payload.envelope.reach.analyse_reach`
finishes the analysis).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from payload.envelope import MIN_SAMPLES
from payload.envelope.collisions import CollisionModel, Contacts
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.pairs import ReachError
from payload.envelope.progress import Progress, quiet
from payload.envelope.sampling import sample_configurations
from payload.envelope.vehicle import Vehicle


class StartedCheck(NamedTuple):
    """A reach analysis whose collision check is running.

    Attributes:
        samples: The sampled configurations, shape (n, 18).
        rng: The random generator after sampling (the grasp check draws from it next).
        model: The collision model.
        contacts: Waits for the check's result (call once, with a progress callback).
        t_start: ``time.perf_counter()`` when the analysis started.
        t_model: ... when the collision model's construction started.
    """

    samples: np.ndarray
    rng: np.random.Generator
    model: CollisionModel
    contacts: Callable[[Progress], Contacts]
    t_start: float
    t_model: float


def check_samples(samples: object) -> None:
    """Raise :class:`ReachError` unless ``samples`` is an integer of at least
    :data:`~payload.envelope.MIN_SAMPLES`."""
    if (
        isinstance(samples, bool)
        or not isinstance(samples, (int, np.integer))
        or samples < MIN_SAMPLES
    ):
        raise ReachError(f"samples must be an integer of at least {MIN_SAMPLES} (got {samples!r})")


def start_check(
    geom: PayloadGeometry,
    vehicle: Vehicle,
    samples: int,
    seed: int = 0,
    workers: int | None = None,
    progress: Progress = quiet,
) -> StartedCheck:
    """Sample the deployed joint space and start its collision check.

    Args:
        geom: Collision geometry of the design.
        vehicle: The vehicle.
        samples: Number of configurations (at least :data:`~payload.envelope.MIN_SAMPLES`).
        seed: Random seed.
        workers: Processes for the check (default: up to 2, the CPUs there are).
        progress: Progress callback.

    Raises:
        ReachError: Too few samples.
    """
    check_samples(samples)
    t_start = time.perf_counter()
    rng = np.random.default_rng(seed)
    progress("sampling", 0.0)
    q = sample_configurations(geom.tree, int(samples), rng)
    t_model = time.perf_counter()
    model = CollisionModel(geom, vehicle)
    if workers is None:
        workers = min(2, os.cpu_count() or 1)
    contacts = model.start(q, workers=workers)  # forked workers check from here on
    return StartedCheck(q, rng, model, contacts, t_start, t_model)


__all__ = ["StartedCheck", "check_samples", "start_check"]
