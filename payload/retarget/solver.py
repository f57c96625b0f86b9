"""What every pair retargeter shares: input checks, the held command, the cost.

A retargeter solves eq. 3 for one finger pair per call. It keeps the last command
it produced (:attr:`Retargeter.command`): the warm start and temporal-term reference
of the next call when the caller passes no ``q_prev``. An invalid input (a NaN or
infinite target, a malformed vector) raises :class:`RetargetError` before anything
changes, so the previous command stays in place.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import NamedTuple

import numpy as np

from payload.retarget.collision import register as register_collision_model
from payload.retarget.errors import RetargetError
from payload.retarget.features import PairFeatures, PairKinematics, as_feature_vector
from payload.retarget.hand import HandDescription
from payload.retarget.objective import (
    Objective,
    RetargetConfig,
    collision_residual,
    cost_of_residuals,
)
from payload.vecmath import clip


class SolveInfo(NamedTuple):
    """What one pair solve did.

    Attributes:
        cost: Eq. 3's value at the returned command.
        iterations: Iterations (production, all starts) or function evaluations
            (reference) used.
        converged: True if a convergence test stopped the solver before its cap.
        evaluations: Residual evaluations used (each computes the residual vector once,
            with or without its Jacobian; what scipy counts as ``nfev``).
        clearance: Smallest self-collision distance less the margin at the command, in
            the solver's own geometry [m] (``inf`` when collisions are not modelled).
    """

    cost: float
    iterations: int
    converged: bool
    evaluations: int = 0
    clearance: float = float("inf")


class Retargeter(ABC):
    """Base of the pair retargeters: ``solve(targets, q_prev, q_ref) -> (q, info)``.

    Args:
        hand: Hand description (``None``: ours).
        pair: Pair name (``L`` or ``R`` for ours); ``None``: the pair of ``kinematics``,
            else the hand's first pair.
        config: Eq. 3 settings (``None``: the paper's constants).
        kinematics: An existing :class:`PairKinematics` for this hand and pair to share.
    """

    def __init__(
        self,
        hand: HandDescription | None = None,
        pair: str | None = None,
        config: RetargetConfig | None = None,
        kinematics: PairKinematics | None = None,
    ) -> None:
        if kinematics is not None:
            if hand is not None and kinematics.hand is not hand:
                raise RetargetError("kinematics was built for another hand")
            if pair is not None and kinematics.name != pair:
                raise RetargetError(f"kinematics is for pair {kinematics.name!r}, not {pair!r}")
        else:
            kinematics = PairKinematics(hand, pair)
        register_collision_model()  # kinematics.collision, when the config models it
        self.kinematics: PairKinematics = kinematics
        self.config: RetargetConfig = config or RetargetConfig()
        self.objective: Objective = Objective(self.lower, self.upper, self.config)
        self._command = self.kinematics.rest.copy()

    # ------------------------------------------------------------ properties
    @property
    def pair(self) -> str:
        """The pair's name."""
        return self.kinematics.name

    @property
    def n(self) -> int:
        """Number of pair joints."""
        return self.kinematics.n

    @property
    def joints(self) -> tuple[str, ...]:
        """Joint names in the order of q."""
        return self.kinematics.joints

    @property
    def lower(self) -> np.ndarray:
        """Lower joint limits, shape (n,)."""
        return self.kinematics.lower

    @property
    def upper(self) -> np.ndarray:
        """Upper joint limits, shape (n,)."""
        return self.kinematics.upper

    @property
    def command(self) -> np.ndarray:
        """The last command (the rest posture before the first solve), shape (n,) (a copy)."""
        return self._command.copy()

    def reset(self, q: np.ndarray | None = None) -> None:
        """Set the held command (``None``: the rest posture), clipped to the limits."""
        q = self.kinematics.rest if q is None else self.kinematics.check_q(q, "reset q")
        self._command = np.clip(q, self.lower, self.upper)

    def hold(self, q: np.ndarray) -> None:
        """Set the held command (the next solve's warm start) to ``q``, clipped to the
        limits, keeping what the solver carries from its earlier solves (for the compiled
        solver, the collision groups' clearance bounds: they stay valid at the posture
        they were computed at, so the next answer is the same as after :meth:`reset`,
        sooner). The teleoperation pipeline holds what it actually commanded."""
        self._command = clip(self.kinematics.check_q(q, "hold q"), self.lower, self.upper)

    # ---------------------------------------------------------------- maths
    def features(self, q: np.ndarray) -> PairFeatures:
        """Eq. 2 features at q (shape (n,)), with Pinocchio."""
        return self.kinematics.features(q)

    def cost(
        self,
        q: np.ndarray,
        targets: PairFeatures | np.ndarray,
        q_ref: np.ndarray | None = None,
        q_prev: np.ndarray | None = None,
    ) -> float:
        """Eq. 3's value at q, evaluated with Pinocchio and numpy (independent of the solver).

        ``q_ref`` defaults to the rest posture and ``q_prev`` to the held command.
        """
        t = as_feature_vector(targets)
        q = self.kinematics.check_q(q)
        qr = self.kinematics.rest if q_ref is None else self.kinematics.check_q(q_ref, "q_ref")
        qp = self._command if q_prev is None else self.kinematics.check_q(q_prev, "q_prev")
        f, _ = self.kinematics.features_jacobian(q)
        r = self.objective.residuals(f, q, t, qr, qp)
        if self.collisions:
            col = self.kinematics.collision
            r = np.append(r, collision_residual(col.distances(q) - col.margin, self.config))
        return cost_of_residuals(r)

    @property
    def collisions(self) -> bool:
        """True when this solver keeps the hand's self-collision margin."""
        return bool(self.config.collisions) and self.kinematics.collision.available

    def clearance(self, q: np.ndarray) -> float:
        """Smallest self-collision distance less the margin at q, solver geometry [m]."""
        return self.kinematics.collision.clearance(q) if self.collisions else float("inf")

    def solve(
        self,
        targets: PairFeatures | np.ndarray,
        q_prev: np.ndarray | None = None,
        q_ref: np.ndarray | None = None,
    ) -> tuple[np.ndarray, SolveInfo]:
        """Solve eq. 3 for one pair.

        Args:
            targets: Mapped robot targets ``(l_bar, d_bar, c_bar, u_bar)`` as
                :class:`PairFeatures` or a stacked vector of shape (13,).
            q_prev: Previous command, shape (n,) (warm start and temporal term);
                ``None``: the held command. Clipped to the limits.
            q_ref: Posture reference, shape (n,); ``None``: the rest posture.

        Returns:
            ``(q, info)``: the command within the limits, shape (n,), and :class:`SolveInfo`.
            The command is also held as :attr:`command`.

        Raises:
            RetargetError: A NaN or infinite or malformed input; the held command is
                left unchanged.
        """
        t = as_feature_vector(targets)
        qp = self._command if q_prev is None else self.kinematics.check_q(q_prev, "q_prev")
        qr = self.kinematics.rest if q_ref is None else self.kinematics.check_q(q_ref, "q_ref")
        q, info = self._solve(t, np.clip(qp, self.lower, self.upper), qr)
        self._command = q
        return q.copy(), info

    @abstractmethod
    def _solve(
        self, targets: np.ndarray, q_prev: np.ndarray, q_ref: np.ndarray
    ) -> tuple[np.ndarray, SolveInfo]:
        """Solve with checked inputs: targets (13,), q_prev (n,) within limits, q_ref (n,)."""
