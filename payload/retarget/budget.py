"""How a production pair solve spends its residual evaluations (``RetargetConfig.budget``).

A solve runs its starts in turn (:func:`budget_plan`); every residual evaluation (the
residual vector with its Jacobian, at a start point or at an iteration's candidate)
counts one. ``paper``: at most ``max_nfev`` (20) in all (with self-collision modelled, a
start from the seed table among them). ``converged``: each start runs
to its convergence tests or ``max_iterations``, and :data:`TABLE_STARTS` starts come from
a fixed seed table (:func:`seed_table`), picked on the table's stored features
(:func:`table_seeds`).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from payload.retarget.collision import register as register_collision_model
from payload.retarget.collision_cache import load_postures, postures_key, store_postures
from payload.retarget.features import PairKinematics
from payload.retarget.objective import RetargetConfig


def budget_plan(config: RetargetConfig) -> tuple[tuple[str, int], ...]:
    """The starts of one pair solve and the evaluation count each may run up to.

    Returns ``(start, cumulative cap)`` pairs. Each start costs one evaluation at its
    start point and one per iteration; a start stops at its convergence tests, its
    iteration cap, or when the solve's evaluations reach its cumulative cap. The last cap
    is the solve's whole budget: ``config.max_nfev`` for ``paper``, ``1 + max_iterations``
    per start for ``converged``.

    * ``paper`` without self-collision: ``prev`` (the warm start, the previous command)
      with ``config.warm_evaluations``, then ``ref`` (the posture reference) with the rest.
    * ``paper`` with self-collision modelled: :data:`PAPER_COLLISION_PLAN`.
    * ``converged``: ``prev``, the table starts ``seed0`` to ``seed11`` (:func:`table_seeds`),
      then ``ref``.
    """
    if config.budget == "paper":
        total = config.max_nfev
        if not config.collisions:
            first = min(total, config.warm_evaluations)
            return (("prev", first), ("ref", total))
        out, used = [], 0
        for tag, evaluations in PAPER_COLLISION_PLAN:
            used = min(total, used + evaluations) if evaluations else total
            out.append((tag, used))
        return tuple(out)
    per = 1 + config.max_iterations
    tags = ("prev", *(f"seed{k}" for k in range(TABLE_STARTS)), "ref")
    return tuple((tag, (k + 1) * per) for k, tag in enumerate(tags))


RESUME = "best"
"""The tag of a start that begins at the best point the solve has met so far (evaluated
again there: one evaluation, as any start)."""

PAPER_COLLISION_PLAN: tuple[tuple[str, int], ...] = (
    ("prev", 8),
    ("ref", 1),
    ("seed0", 1),
    (RESUME, 0),
)
"""The ``paper`` budget's starts with self-collision modelled, each with the evaluations it
may use (0: what is left of ``max_nfev``): the warm start descends for 8; the posture
reference and the seed table's best posture for the targets (:func:`table_seeds`) are
each evaluated once (probes, no iteration); the rest descends from the best of the three.

Why: the collision penalty is soft, so on a jump the warm start's iterates cross the
other finger's margin and the only collision-free points they meet in 20 evaluations are
their first few (an answer inside the margin is never returned); a probe on the far side
of the crossing, where the table's margin-keeping postures and the posture reference lie,
gives the descent a collision-free start. On ours (``payload bench retarget --steps 300``,
600 pair solves with the model) the share not worse than scipy's went from 97.3 % to
99.5 %; without the model, where nothing blocks the warm start, the probes gave no gain
(99.3 % and 99.2 %) and the plan stays ``prev`` then ``ref``."""

TABLE_STARTS = 12
"""Starts of a ``converged`` solve taken from the seed table, besides the previous command
and the posture reference."""

SEEDS = 4096
"""Postures in the seed table of the ``converged`` budget (seeded, uniform in the box; with
self-collision modelled, the first that keep the margin)."""

PAPER_SEEDS = 256
"""The first postures of the seed table that the ``paper`` budget's table start picks from.
The pick costs each solve every table posture's eq. 3 terms: with 512 the paper solve's
median went from 65 us (no table start) to 238 us; with 256, 133 us, and the share of
answers not worse than scipy's on the bench stream (``--steps 300``, the model on) was the
same (99.67 %; 99.5 % with 128). Indicative times, load average about 2.5 on 2 cores."""


def seed_table(
    pk: PairKinematics, collisions: bool, size: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The first ``size`` (default :data:`SEEDS`) seed postures, shape (k, n), and their
    features, shape (k, 13); with ``collisions`` (the solve keeps the margin), only those
    that keep it."""
    qs = seed_candidates(pk)
    count = SEEDS if size is None else size
    if collisions:  # collision-free seeds only (the solver's own geometry)
        register_collision_model()
        qs = _margin_keeping(pk, qs, count)
    qs = qs[:count]
    return qs, pk.features_batch(qs)


def _margin_keeping(pk: PairKinematics, qs: np.ndarray, count: int) -> np.ndarray:
    """The first ``count`` postures of the candidates ``qs`` that keep the margin
    (:func:`_clear_first`), kept in the disk cache under the pair's collision geometry's
    key (:mod:`payload.retarget.collision_cache`: the candidates, the geometry and the
    code that picks them are all in it), when the geometry is cached and the distances
    were the compiled ones."""
    col = pk.collision
    key = postures_key(col.key, "seed-table", count) if col.key is not None else None
    kept = load_postures(key) if key is not None else None
    if kept is not None and kept.shape[1] == qs.shape[1]:
        return kept
    kept = _clear_first(pk, qs, count)[:count]
    if key is not None and col.compiled_distances(col.terms):
        store_postures(key, kept)
    return kept


def seed_candidates(pk: PairKinematics) -> np.ndarray:
    """The candidates of :func:`seed_table`, in order: the rest posture, then four times
    :data:`SEEDS` postures uniform in the joint box (seeded), shape (4 SEEDS + 1, n)."""
    rng = np.random.default_rng(12345)
    return np.vstack([pk.rest, pk.lower + rng.random((4 * SEEDS, pk.n)) * pk.range])


SEED_CHUNK = 512
"""Candidate postures whose clearances :func:`seed_table` computes at a time."""


def _clear_first(pk: PairKinematics, qs: np.ndarray, count: int) -> np.ndarray:
    """The postures of ``qs`` (in order) that keep the collision margin, at least the first
    ``count`` of them: their distances computed :data:`SEED_CHUNK` postures at a time,
    stopping once ``count`` are found (the ``paper`` budget's 256 need a quarter to a
    third of the candidates for our pairs; a posture's distances do not depend on the
    others')."""
    col = pk.collision
    kept: list[np.ndarray] = []
    found = 0
    for start in range(0, qs.shape[0], SEED_CHUNK):
        part = qs[start : start + SEED_CHUNK]
        part = part[col.distances_many(part).min(axis=0) >= col.margin]
        kept.append(part)
        found += part.shape[0]
        if found >= count:
            break
    return np.concatenate(kept)


def table_seeds(
    pk: PairKinematics,
    config: RetargetConfig,
    targets: ca.MX,
    q_ref: ca.MX,
    q0: ca.MX,
    count: int,
) -> list[ca.MX]:
    """``count`` table postures, picked in turn by their eq. 3 cost and by their geometric
    residuals alone (from the tabulated features), each pick another posture.

    The geometric picks ignore the posture and temporal terms, which pull every full-cost
    pick toward the posture reference and the previous command (starts of their own): on a
    target far from both (a jump), they reach the basins those terms hide.
    """
    size = PAPER_SEEDS if config.budget == "paper" else SEEDS
    qs, fs = seed_table(pk, bool(config.collisions) and pk.collision.available, size)
    k = qs.shape[0]
    scales = ca.DM(np.repeat(config.feature_scales()[:, None], k, axis=1))
    geo = scales * (ca.DM(fs.T) - ca.repmat(targets, 1, k))
    inv = ca.DM(np.repeat((1.0 / pk.range)[:, None], k, axis=1))
    post = config.w_p * inv * (ca.DM(qs.T) - ca.repmat(q_ref, 1, k))
    temp = config.w_t * inv * (ca.DM(qs.T) - ca.repmat(q0, 1, k))
    geo_cost = ca.sum1(ca.sqrt(1.0 + geo**2) - 1.0)  # (1, k)
    costs = [geo_cost + ca.sum1(ca.sqrt(1.0 + ca.vertcat(post, temp) ** 2) - 1.0), geo_cost]
    out = []
    for j in range(count):
        cost = costs[j % 2]
        pick = cost <= ca.mmin(cost)
        out.append(ca.mtimes(ca.DM(qs.T), pick.T) / ca.sum2(pick))
        costs = [c + 1e30 * pick for c in costs]  # the next picks are other postures
    return out


def evaluation_cap(config: RetargetConfig) -> int:
    """Most residual evaluations one pair solve may use under ``config.budget``."""
    return budget_plan(config)[-1][1]
