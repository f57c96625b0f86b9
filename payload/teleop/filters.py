"""Keypoint filtering: the One Euro filter (Casiez, Roussel and Vogel, CHI 2012)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from payload.vecmath import all_reduce


@dataclass(frozen=True)
class OneEuroConfig:
    """One Euro filter settings.

    The defaults (0.3 Hz at rest, beta 1 s/m) were tuned in the ISS trials: with 1 mm of
    per-joint tracking noise, a 1 Hz cutoff let the retargeted finger commands jitter by
    about 0.03 rad, enough to walk the pads off the CTB handle under vehicle acceleration.

    Attributes:
        min_cutoff: Cutoff frequency at rest [Hz]; lower removes more jitter.
        beta: Speed coefficient [s/m]: the cutoff rises by ``beta * |speed|`` Hz, so fast
            motion lags less.
        d_cutoff: Cutoff of the speed estimate [Hz].
    """

    min_cutoff: float = 0.3
    beta: float = 1.0
    d_cutoff: float = 1.0


def _alpha(cutoff: np.ndarray | float, dt: float) -> np.ndarray | float:
    if isinstance(cutoff, float):  # a scalar: the same arithmetic on a float, sooner
        return 1.0 / (1.0 + (1.0 / (2.0 * math.pi * cutoff)) / dt)
    tau = 1.0 / (2.0 * math.pi * np.asarray(cutoff))
    return 1.0 / (1.0 + tau / dt)


class OneEuroFilter:
    """One Euro filter over an array of any shape, each element filtered independently.

    The speed driving the adaptive cutoff is the per-row norm for (N, 3) point arrays
    (so each keypoint adapts to its own 3-D speed), else the element's own magnitude.

    The pipeline's compiled intake (:mod:`payload.teleop.intake_c`) runs the compiled step
    from its own C on the estimates (``_x``, ``_dx``, bound in ``_bound``) and sets the
    clock (``_t``) as :meth:`__call__` does.
    """

    def __init__(self, config: OneEuroConfig | None = None) -> None:
        self.config = config or OneEuroConfig()
        self._x: np.ndarray | None = None
        self._dx: np.ndarray | None = None
        self._t: float | None = None
        self._bound: tuple[Any, Any, Any, Any] | None = None

    def reset(self) -> None:
        """Forget the history: the next sample passes through unfiltered."""
        self._x = self._dx = self._t = None

    def estimate(self) -> np.ndarray:
        """The current estimate (what the last call returned), a copy.

        Raises:
            ValueError: No sample taken since the start or a reset.
        """
        if self._x is None:
            raise ValueError("One Euro filter: no sample yet")
        return self._x.copy()

    def __call__(self, x: np.ndarray, t: float) -> np.ndarray:
        """Filter sample ``x`` taken at time ``t`` [s]; returns the filtered sample."""
        x = np.asarray(x, dtype=np.float64)
        if not all_reduce(np.isfinite(x), axis=None):  # ndarray.all's, sooner
            raise ValueError("One Euro filter: non-finite sample")
        if self._x is None or self._t is None:
            self._x, self._dx, self._t = x.copy(), np.zeros_like(x), t
            return x.copy()
        if t <= self._t:  # a repeated (or older) stamp: nothing new to filter
            return self._x.copy()
        c = self.config
        dt = t - self._t
        a_d = _alpha(c.d_cutoff, dt)
        step = None
        if isinstance(a_d, float) and x.shape == self._x.shape:
            step = self._stepper(x)
        if step is not None:  # the compiled step: the estimates updated in place
            step(x, dt, a_d)
            self._t = t
            return self._x.copy()
        x_hat, dx_hat = _step_numpy(x, self._x, self._dx, dt, a_d, c.min_cutoff, c.beta)
        self._x, self._dx, self._t = x_hat, dx_hat, t
        return x_hat.copy()

    def _stepper(self, x: np.ndarray) -> Any:
        """The compiled step (:mod:`payload.teleop.filter_c`) bound to this filter's
        estimate arrays for samples like ``x``, or None to run :func:`_step_numpy`."""
        bound = self._bound
        if (
            bound is not None
            and bound[0] is self._x
            and bound[1] is self._dx
            and bound[3] is self.config  # a frozen config: another object, other settings
        ):
            return bound[2]
        step = None
        if x.ndim == 2 and x.shape[1] == 3 and x.shape == self._x.shape == self._dx.shape:
            from payload.teleop.filter_c import compiled_one_euro

            kernel = compiled_one_euro(_step_numpy)
            if kernel is not None:
                # estimates of the filter's own that the kernel may update in place
                self._x = np.ascontiguousarray(self._x, dtype=float).copy()
                self._dx = np.ascontiguousarray(self._dx, dtype=float).copy()
                c = self.config
                step = kernel.stepper(self._x, self._dx, float(c.min_cutoff), float(c.beta))
        self._bound = (self._x, self._dx, step, self.config)
        return step


def _step_numpy(
    x: np.ndarray,
    prev_x: np.ndarray,
    prev_dx: np.ndarray,
    dt: float,
    a_d: float | np.ndarray,
    min_cutoff: float,
    beta: float,
) -> tuple[np.ndarray, np.ndarray]:
    """One filter step after the first sample: (estimate, speed estimate) of ``x``."""
    dx = (x - prev_x) / dt
    dx_hat = a_d * dx + (1 - a_d) * prev_dx
    if x.ndim == 2 and x.shape[1] == 3:
        # np.linalg.norm(dx_hat, axis=1, keepdims=True)'s formula, without its overhead
        speed = np.sqrt(np.add.reduce(dx_hat * dx_hat, axis=1, keepdims=True))
    else:
        speed = np.abs(dx_hat)
    a = _alpha(min_cutoff + beta * speed, dt)
    return a * x + (1 - a) * prev_x, dx_hat
