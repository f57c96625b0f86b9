"""The paper's trial metrics, computed from a recording (simulated, replayed or hardware).

Definitions (paper, Sec. III-C and IV):

* **eq. 4** -- CTB position in the instantaneous Astrobee body frame,
  ``b_p_c(t) = R_b^W(t)^T (p_c^W(t) - p_b^W(t))``, with ``R_b^W`` mapping body vectors into
  the world (the recorded ``astrobee_quat``, w x y z, body -> world).
* **first continuous confirmed-contact interval** -- the first maximal run of consecutive
  samples whose opposing-contact indicator is true; ``t0`` is its first sample and
  ``{t_k}, k = 1..N`` are all its samples (``t_1 = t0``). Two optional relaxations, both
  off by default (the paper's definition): ``max_gap_s`` > 0 first merges runs whose last
  and first contact samples are at most that far apart (bridging indicator dropouts; the
  bridged samples belong to the interval), then ``min_interval_s`` > 0 skips runs shorter
  than that (brief touches while the fingers close).
* **eq. 5** -- ``e_RMS = sqrt(1/N sum_k ||b_p_c(t_k) - b_p_c(t0)||^2)`` over that interval;
  **peak deviation** is the largest of those norms.
* **contact-interval length** -- ``t_N - t0`` [s].
* **duration after calibration** -- from the first sample not in phase ``calibration`` to
  the last sample [s].
* **CTB net world-frame displacement** -- ``||p_c^W(end) - p_c^W(start)||`` with start the
  first sample of the recording (the start of teleoperation) [m].
* **acquisition** -- succeeded when the recording has a first confirmed-contact interval.
* **success** -- the CTB is in the destination module at the last sample, *and* the first
  confirmed-contact interval carries it there and holds it until arrival: the interval
  starts no later than the CTB's entry into the destination (first sample of its final,
  uninterrupted stay there) and lasts at least until the arrival sample (in particular,
  an interval lasting to the end of the recording qualifies). The arrival sample is the
  later of that entry and the operator's arrival (first sample of the last block of phase
  ``arrival``; a recording that never reaches that phase, e.g. one stopped at its time
  limit, needs the interval to last to its last sample). So the CTB must be held through
  the whole maneuver, turn included, not merely carried across the hatch.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from payload.errors import PayloadError
from payload.rotations import rotate_by_quats
from payload.trials.definition import CONFIRM_MAX_GAP_S, CONFIRM_MIN_S, contact_words
from payload.trials.reading import aborted_note
from payload.trials.recorder import MODULES, Recording
from payload.trials.records import CALIBRATION


def confirmed_definition() -> dict[str, float]:
    """The confirmed-contact definition as a recording's metadata stores it (its
    ``contact_definition``, what its scoring reads; a recording without one is scored
    paper-literal, as recordings were before it was stored)."""
    return {"min_interval_s": CONFIRM_MIN_S, "max_gap_s": CONFIRM_MAX_GAP_S}


def recorded_definition(recording: Recording) -> tuple[float, float]:
    """The contact definition a recording was made to be scored with, ``(min_interval_s,
    max_gap_s)`` from its ``contact_definition`` metadata (:func:`confirmed_definition`);
    ``(0, 0)``, the paper's, for a recording without one."""
    recorded = recording.meta.get("contact_definition") or {}
    return float(recorded.get("min_interval_s", 0.0)), float(recorded.get("max_gap_s", 0.0))


SUCCESS_CRITERION = (
    "the recording was not aborted AND "
    "CTB in the destination module at the end of the recording AND the first continuous "
    "confirmed-contact interval starts no later than the CTB's final entry into the "
    "destination and lasts at least until arrival (or to the end); arrival = the later of "
    "that entry and the start of the last 'arrival' phase (without such a phase: the last "
    "sample)"
)


class MetricsError(PayloadError):
    """Metrics cannot be computed from this recording."""


@dataclass(frozen=True)
class TrialMetrics:
    """The paper's per-trial figures (units in the names: s, m, mm).

    Attributes:
        success: Task success (:data:`SUCCESS_CRITERION`).
        duration_s: Teleoperation duration after calibration [s].
        net_displacement_m: CTB net world-frame displacement [m].
        rms_mm: eq. 5 over the first confirmed-contact interval [mm]; NaN without contact.
        peak_mm: Peak deviation over that interval [mm]; NaN without contact.
        contact_s: Length of that interval [s]; 0 without contact.
        t0_s: Time of the interval's first sample [s]; NaN without contact.
        contact_end_s: Time of the interval's last sample [s]; NaN without contact.
        arrival_s: Time of arrival (success criterion) [s]; NaN if the CTB is not in the
            destination at the end.
        entry_s: Time the CTB entered the destination for good [s]; NaN if it did not.
        arrival_phase_s: Start of the last ``arrival`` phase [s]; NaN if none.
        final_module: Where the CTB is at the last sample.
        destination: The destination module scored against.
        n_samples: Samples in the recording.
        n_contact_samples: Samples N in the interval (bridged dropouts included).
        contact_samples_total: Samples with the opposing-contact indicator set, anywhere
            in the recording (raw samples: the same under every contact definition;
            bridged dropouts not counted).
        contact_to_end: The interval lasts to the last sample.
        b_p_c_t0_m: eq. 4 at ``t0`` (the reference CTB position in the body frame),
            shape (3,) [m]; NaN without contact.
        complete: The recording was closed properly (not cut short).
        min_interval_s: The interval definition used (0 = the paper's).
        max_gap_s: The interval definition used (0 = the paper's).
        acquired: The acquisition succeeded: the recording has a first confirmed-contact
            interval under this definition (the pinch closed on the handle from both
            sides).
    """

    success: bool
    duration_s: float
    net_displacement_m: float
    rms_mm: float
    peak_mm: float
    contact_s: float
    t0_s: float
    contact_end_s: float
    arrival_s: float
    entry_s: float
    arrival_phase_s: float
    final_module: str
    destination: str
    n_samples: int
    n_contact_samples: int
    contact_samples_total: int
    contact_to_end: bool
    b_p_c_t0_m: tuple[float, float, float]
    complete: bool
    min_interval_s: float = 0.0
    max_gap_s: float = 0.0
    acquired: bool = False

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict (NaN -> ``None``) with the criterion text under ``criterion``."""
        out = {k: _json_value(v) for k, v in asdict(self).items()}
        out["criterion"] = SUCCESS_CRITERION
        return out


def _json_value(v: Any) -> Any:
    if isinstance(v, float):
        return None if not math.isfinite(v) else v
    if isinstance(v, (tuple, list)):
        return [_json_value(x) for x in v]
    if isinstance(v, np.generic):
        return _json_value(v.item())
    return v


def ctb_in_body_frame(
    astrobee_pos: np.ndarray, astrobee_quat: np.ndarray, ctb_pos: np.ndarray
) -> np.ndarray:
    """eq. 4: CTB position in the instantaneous Astrobee body frame.

    Args:
        astrobee_pos: Astrobee position in the world, shape (N, 3) [m].
        astrobee_quat: Astrobee orientation, w x y z, body -> world, shape (N, 4)
            (normalised here).
        ctb_pos: CTB centre of mass in the world, shape (N, 3) [m].

    Returns:
        ``R_b^W(t)^T (p_c^W(t) - p_b^W(t))``, shape (N, 3) [m].

    Raises:
        MetricsError: Shapes disagree or a quaternion is zero or not finite.
    """
    pb = np.asarray(astrobee_pos, dtype=np.float64).reshape(-1, 3)
    pc = np.asarray(ctb_pos, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(astrobee_quat, dtype=np.float64).reshape(-1, 4)
    if not (pb.shape[0] == pc.shape[0] == q.shape[0]):
        raise MetricsError(
            f"eq. 4: {pb.shape[0]} Astrobee positions, {q.shape[0]} quaternions, "
            f"{pc.shape[0]} CTB positions"
        )
    if pb.shape[0] == 0:
        return np.zeros((0, 3))
    norms = np.linalg.norm(q, axis=1)
    if not np.all(np.isfinite(norms)) or np.any(norms < 1e-9):
        bad = int(np.flatnonzero(~np.isfinite(norms) | (norms < 1e-9))[0])
        raise MetricsError(f"eq. 4: Astrobee quaternion at sample {bad} is zero or not finite")
    return rotate_by_quats(q / norms[:, None], pc - pb, inverse=True)


def contact_runs(contact: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs of true samples.

    Args:
        contact: Confirmed-contact flags, shape (N,).

    Returns:
        ``(first, last)`` sample indices (inclusive) of every run, in time order.
    """
    c = np.asarray(contact, dtype=bool).reshape(-1)
    if c.size == 0:
        return []
    edges = np.diff(np.concatenate(([0], c.astype(np.int8), [0])))
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1) - 1
    return [(int(a), int(b)) for a, b in zip(starts, ends)]


def first_contact_interval(
    t: np.ndarray, contact: np.ndarray, min_interval_s: float = 0.0, max_gap_s: float = 0.0
) -> tuple[int, int] | None:
    """The first continuous confirmed-contact interval.

    Args:
        t: Sample times, shape (N,) [s].
        contact: Confirmed-contact flags, shape (N,).
        min_interval_s: Skip runs shorter than this [s] (0 = the paper's definition).
        max_gap_s: Merge runs whose last and first contact samples are at most this far
            apart [s] before applying ``min_interval_s`` (0 = the paper's definition).

    Returns:
        ``(first, last)`` sample indices (inclusive), or ``None`` if there is none.
    """
    for name, value in (("min_interval_s", min_interval_s), ("max_gap_s", max_gap_s)):
        if not math.isfinite(value) or value < 0:
            raise MetricsError(f"{name} must be >= 0, got {value}")
    tt = np.asarray(t, dtype=np.float64).reshape(-1)
    runs: list[tuple[int, int]] = []
    for a, b in contact_runs(contact):
        if runs and max_gap_s > 0 and tt[a] - tt[runs[-1][1]] <= max_gap_s + 1e-9:
            runs[-1] = (runs[-1][0], b)
        else:
            runs.append((a, b))
    for a, b in runs:
        if tt[b] - tt[a] >= min_interval_s - 1e-9:
            return a, b
    return None


def rms_deviation(b_p_c: np.ndarray) -> tuple[float, float]:
    """eq. 5 and the peak deviation over an interval whose first sample is ``t0``.

    Args:
        b_p_c: eq. 4 over the interval's samples, shape (N, 3) [m], row 0 at ``t0``.

    Returns:
        ``(rms, peak)`` of ``||b_p_c(t_k) - b_p_c(t0)||`` [m].
    """
    p = np.asarray(b_p_c, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] == 0:
        raise MetricsError("eq. 5: empty interval")
    d = np.linalg.norm(p - p[0], axis=1)
    return float(np.sqrt(np.mean(d**2))), float(np.max(d))


def _last_block_start(flags: np.ndarray) -> int | None:
    """First index of the last run of true values (``None`` if there is none)."""
    idx = np.flatnonzero(flags)
    if idx.size == 0:
        return None
    before = np.flatnonzero(~flags[: idx[-1]])
    return int(before[-1] + 1) if before.size else 0


def _entry_index(module: np.ndarray, destination: str) -> int | None:
    inside = np.asarray(module) == destination
    if inside.size == 0 or not inside[-1]:
        return None
    return _last_block_start(inside)


def compute_metrics(
    recording: Recording,
    destination: str = "node2",
    min_interval_s: float = 0.0,
    max_gap_s: float = 0.0,
) -> TrialMetrics:
    """Score one trial from its recording (module docstring for every definition).

    Args:
        recording: The recording (from :func:`~payload.trials.recorder.read_recording`).
        destination: Destination module, one of
            :data:`~payload.trials.recorder.MODULES`.
        min_interval_s: Shortest contact run that counts as the first interval [s]
            (0 = the paper's definition).
        max_gap_s: Longest indicator dropout bridged inside an interval [s] (0 = the
            paper's definition).

    Returns:
        The trial's metrics.

    Raises:
        MetricsError: Empty recording, unknown destination, or times not increasing.
    """
    if destination not in MODULES:
        raise MetricsError(f"destination {destination!r} is not one of {list(MODULES)}")
    n = len(recording)
    if n == 0:
        where = f" {recording.path}" if recording.path else ""
        raise MetricsError(f"recording{where} has no steps")
    t = recording.t
    if n > 1 and np.any(np.diff(t) <= 0):
        i = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise MetricsError(f"step times do not increase at sample {i + 1} (t = {t[i + 1]} s)")

    after_cal = np.flatnonzero(recording.phase != CALIBRATION)
    duration = float(t[-1] - t[after_cal[0]]) if after_cal.size else 0.0
    net = float(np.linalg.norm(recording.ctb_pos[-1] - recording.ctb_pos[0]))

    interval = first_contact_interval(t, recording.contact, min_interval_s, max_gap_s)
    entry = _entry_index(recording.ctb_module, destination)
    arrival_phase = _last_block_start(np.asarray(recording.phase) == "arrival")
    operator_arrival = arrival_phase if arrival_phase is not None else n - 1
    arrival = None if entry is None else max(entry, operator_arrival)
    if interval is None:
        rms = peak = t0 = t_end = math.nan
        contact_s = 0.0
        n_contact = 0
        ref = (math.nan, math.nan, math.nan)
        to_end = False
    else:
        a, b = interval
        bp = ctb_in_body_frame(
            recording.astrobee_pos[a : b + 1],
            recording.astrobee_quat[a : b + 1],
            recording.ctb_pos[a : b + 1],
        )
        rms_m, peak_m = rms_deviation(bp)
        rms, peak = 1e3 * rms_m, 1e3 * peak_m
        t0, t_end = float(t[a]), float(t[b])
        contact_s = t_end - t0
        n_contact = b - a + 1
        ref = (float(bp[0, 0]), float(bp[0, 1]), float(bp[0, 2]))
        to_end = b == n - 1
    success = bool(
        aborted_note(recording.meta) is None
        and entry is not None
        and arrival is not None
        and interval is not None
        and interval[0] <= entry
        and interval[1] >= arrival
    )
    return TrialMetrics(
        success=success,
        duration_s=duration,
        net_displacement_m=net,
        rms_mm=rms,
        peak_mm=peak,
        contact_s=contact_s,
        t0_s=t0,
        contact_end_s=t_end,
        arrival_s=float(t[arrival]) if arrival is not None else math.nan,
        entry_s=float(t[entry]) if entry is not None else math.nan,
        arrival_phase_s=float(t[arrival_phase]) if arrival_phase is not None else math.nan,
        final_module=str(recording.ctb_module[-1]),
        destination=destination,
        n_samples=n,
        n_contact_samples=n_contact,
        contact_samples_total=int(np.count_nonzero(recording.contact)),
        contact_to_end=to_end,
        b_p_c_t0_m=ref,
        complete=recording.complete,
        min_interval_s=float(min_interval_s),
        max_gap_s=float(max_gap_s),
        acquired=interval is not None,
    )


__all__ = [
    "CONFIRM_MAX_GAP_S",
    "CONFIRM_MIN_S",
    "SUCCESS_CRITERION",
    "MetricsError",
    "TrialMetrics",
    "compute_metrics",
    "confirmed_definition",
    "contact_runs",
    "contact_words",
    "ctb_in_body_frame",
    "first_contact_interval",
    "recorded_definition",
    "rms_deviation",
]
