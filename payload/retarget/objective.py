"""The retargeting objective of the paper's eq. 3 and its settings.

For one pair with joints q (shape (n,)), targets ``(l_bar, d_bar, c_bar, u_bar)``,
posture reference q_ref and previous command q_prev, the residual vector (shape
(13 + 2n,), 29 for n = 8) is::

    r = [ (l - l_bar) / sigma_l,
          w_d (d_hat - d_bar) / sigma_d,      (3)
          (c - c_bar) / sigma_c,              (3)
          w_f (u - u_bar) / sigma_f,          (6)
          w_p (q - q_ref) / range,            (n)
          w_t (q - q_prev) / range ]          (n)

and the cost is ``1/2 sum_k rho(r_k^2)`` with the soft-L1 ``rho(z) = 2 (sqrt(1 + z) - 1)``,
minimised over ``lower <= q <= upper``. This is exactly what
``scipy.optimize.least_squares(loss="soft_l1", f_scale=1)`` minimises.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from payload.errors import not_text
from payload.retarget.errors import RetargetError
from payload.retarget.features import N_FEATURES

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


BUDGETS = ("paper", "converged")
"""Evaluation budgets of a production pair solve (:attr:`RetargetConfig.budget`)."""


@dataclass(frozen=True)
class RetargetConfig:
    """Settings of eq. 3 and of both solvers; defaults are the paper's constants.

    Attributes:
        sigma_l: Span scale [m] (paper: 1.5 mm).
        sigma_c: Centre scale [m] (paper: 25 mm).
        sigma_d: Direction chordal scale [-] (paper: 0.15).
        sigma_f: Distal-direction chordal scale [-] (paper: 0.15).
        w_d: Direction weight (paper: 0.35).
        w_f: Distal-direction weight (paper: 0.10).
        w_p: Posture weight on range-normalised joints (paper: 3.0).
        w_t: Temporal weight on range-normalised joints (paper: 0.03).
        collisions: Keep the hand's self-collision margin (:mod:`payload.retarget.collision`)
            (off by default until a solve with it meets the 100 us budget, issue 14):
            no returned command comes closer than the margin (the iterates may cross it;
            each start keeps the best collision-free point it met), and a penalty residual
            ``w_c sum((band - clearance)_+^2) / band^2`` pushes away within ``collision_band``.
        w_c: Weight of the collision penalty residual.
        collision_band: Clearance below which the penalty acts [m].
        budget: ``paper``: at most ``max_nfev`` residual evaluations per pair solve for
            the production solver too (every evaluation counted); ``converged``: each
            start runs to its convergence tests or ``max_iterations``.
        max_nfev: Residual evaluations per pair solve: the scipy reference's
            ``max_nfev`` and the production solver's whole ``paper`` budget (paper: 20).
        warm_evaluations: Of the ``paper`` budget without self-collision, the
            evaluations the warm start may use; what it leaves goes to a second start from
            the posture reference (with self-collision modelled the starts are
            :data:`payload.retarget.budget.PAPER_COLLISION_PLAN`).
        max_iterations: Hard cap on iterations of each start of the production solver
            (``converged`` budget); each iteration evaluates the residuals and their
            Jacobian once.
        gtol: Production stops when the projected gradient's largest component is below.
        ftol: Production stops when an accepted step lowers the cost by less than this
            fraction.
    """

    sigma_l: float = 1.5e-3
    sigma_c: float = 25e-3
    sigma_d: float = 0.15
    sigma_f: float = 0.15
    w_d: float = 0.35
    w_f: float = 0.10
    w_p: float = 3.0
    w_t: float = 0.03
    collisions: bool = False
    w_c: float = 3.0
    collision_band: float = 3e-3
    budget: str = "paper"
    max_nfev: int = 20
    warm_evaluations: int = 20
    max_iterations: int = 150
    gtol: float = 1e-8
    ftol: float = 1e-7

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "collisions":
                if not isinstance(v, bool):
                    raise RetargetError("retarget config: collisions: expected true or false")
                continue
            if f.name == "budget":
                if v not in BUDGETS:
                    raise RetargetError(
                        f"retarget config: budget: expected one of {', '.join(BUDGETS)}, got {v!r}"
                    )
                continue
            if f.type == "int":
                if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                    raise RetargetError(f"retarget config: {f.name}: expected an integer >= 1")
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise RetargetError(f"retarget config: {f.name}: expected a finite number")
            if f.name.startswith("sigma") or f.name in ("gtol", "ftol", "collision_band"):
                if v <= 0:
                    raise RetargetError(f"retarget config: {f.name}: must be positive (got {v})")
            elif v < 0:
                raise RetargetError(f"retarget config: {f.name}: must not be negative (got {v})")
            object.__setattr__(self, f.name, float(v))

    def feature_scales(self) -> np.ndarray:
        """Per-component factors of the 13 geometric residuals, shape (13,)."""
        s = np.empty(N_FEATURES)
        s[0] = 1.0 / self.sigma_l
        s[1:4] = self.w_d / self.sigma_d
        s[4:7] = 1.0 / self.sigma_c
        s[7:13] = self.w_f / self.sigma_f
        return s

    def replace(self, **changes: Any) -> RetargetConfig:
        """A copy with some settings changed (validated)."""
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise RetargetError(f"retarget config: unknown setting {unknown[0]!r}")
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_mapping(cls, raw: dict[str, Any], where: str = "retarget config") -> RetargetConfig:
        """Defaults overridden by ``raw`` (a flat table of settings).

        Raises:
            RetargetError: An unknown setting or a bad value, named.
        """
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(raw) - names)
        if unknown:
            raise RetargetError(f"{where}: unknown setting {unknown[0]!r} (known: {sorted(names)})")
        try:
            return cls(**raw)
        except TypeError as exc:  # pragma: no cover - names checked above
            raise RetargetError(f"{where}: {exc}") from exc

    @classmethod
    def from_toml(cls, path: str | Path) -> RetargetConfig:
        """Defaults overridden by a TOML file (top-level keys or a ``[retarget]`` table).

        Raises:
            RetargetError: The file is missing or invalid.
        """
        p = Path(path)
        if not p.is_file():
            raise RetargetError(f"retarget config not found: {p}")
        try:
            raw = tomllib.loads(p.read_text(encoding="utf-8"))
        except UnicodeDecodeError as exc:
            raise RetargetError(f"{p}: {not_text(exc, 'TOML')}") from None
        except tomllib.TOMLDecodeError as exc:
            raise RetargetError(f"{p}: not valid TOML: {exc}") from exc
        if "retarget" in raw:
            if set(raw) != {"retarget"} or not isinstance(raw["retarget"], dict):
                raise RetargetError(f"{p}: put every setting inside the [retarget] table")
            raw = raw["retarget"]
        return cls.from_mapping(raw, where=str(p))


def collision_residual(clearance: np.ndarray, config: RetargetConfig) -> float:
    """The collision penalty residual ``w_c sum((band - clearance)_+^2) / band^2`` (numpy)."""
    over = np.maximum(config.collision_band - np.asarray(clearance, dtype=float), 0.0)
    return float(config.w_c * (over @ over) / config.collision_band**2)


def soft_l1(z: np.ndarray) -> np.ndarray:
    """The soft-L1 loss ``rho(z) = 2 (sqrt(1 + z) - 1)`` of squared residuals z."""
    return 2.0 * (np.sqrt(1.0 + z) - 1.0)


def cost_of_residuals(r: np.ndarray) -> float:
    """Eq. 3's value ``1/2 sum rho(r_k^2)`` for residuals r."""
    return 0.5 * float(np.sum(soft_l1(np.square(r))))


class Objective:
    """Residuals and Jacobian of eq. 3 for one pair (numpy, the reference path).

    Args:
        lower: Lower joint limits, shape (n,).
        upper: Upper joint limits, shape (n,).
        config: Weights and scales.
    """

    def __init__(self, lower: np.ndarray, upper: np.ndarray, config: RetargetConfig) -> None:
        self.lower = np.asarray(lower, dtype=float)
        self.upper = np.asarray(upper, dtype=float)
        self.config = config
        self.n = self.lower.size
        self.scales = config.feature_scales()
        inv_range = 1.0 / (self.upper - self.lower)
        self.posture_diag = config.w_p * inv_range
        self.temporal_diag = config.w_t * inv_range

    @property
    def m(self) -> int:
        """Number of residuals, 13 + 2n."""
        return N_FEATURES + 2 * self.n

    def residuals(
        self,
        features: np.ndarray,
        q: np.ndarray,
        targets: np.ndarray,
        q_ref: np.ndarray,
        q_prev: np.ndarray,
    ) -> np.ndarray:
        """Residuals, shape (13 + 2n,), from the stacked features (13,) at q (n,)."""
        r = np.empty(self.m)
        r[:N_FEATURES] = self.scales * (features - targets)
        r[N_FEATURES : N_FEATURES + self.n] = self.posture_diag * (q - q_ref)
        r[N_FEATURES + self.n :] = self.temporal_diag * (q - q_prev)
        return r

    def jacobian(self, features_jac: np.ndarray) -> np.ndarray:
        """Residual Jacobian, shape (13 + 2n, n), from the feature Jacobian (13, n)."""
        jac = np.zeros((self.m, self.n))
        jac[:N_FEATURES] = self.scales[:, None] * features_jac
        idx = np.arange(self.n)
        jac[N_FEATURES + idx, idx] = self.posture_diag
        jac[N_FEATURES + self.n + idx, idx] = self.temporal_diag
        return jac
