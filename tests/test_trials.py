"""Trials: recorder (incl. a SIGKILLed writer), the paper's metrics (eq. 4, eq. 5) against
hand-computed values, figures, campaigns on Dask against a serial run, and the CLI."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from payload.schema import CONTROL_DT
from payload.trials.codec import STEP_GRIDS
from payload.trials.metrics import (
    CONFIRM_MAX_GAP_S,
    CONFIRM_MIN_S,
    MetricsError,
    compute_metrics,
    ctb_in_body_frame,
    first_contact_interval,
)
from payload.trials.recorder import (
    FIELD_SPECS,
    Recording,
    RecordingError,
    StepRecord,
    TrialRecorder,
    read_recording,
)

ROOT = Path(__file__).resolve().parents[1]
DT = 0.02  # 50 Hz


# -- helpers ---------------------------------------------------------------------------
def make_step(t: float, **kw: Any) -> StepRecord:
    """A valid step at time ``t``; keywords override fields."""
    fields: dict[str, Any] = {
        "t": t,
        "phase": "translation",
        "left_joints": np.zeros((25, 3)),
        "right_joints": np.zeros((25, 3)),
        "left_tracked": True,
        "right_tracked": True,
        "q_left": np.zeros(8),
        "q_right": np.zeros(8),
        "rail_cmd": 0.0,
        "twist_cmd": np.zeros(6),
        "q_cmd": np.zeros(17),
        "deploy_cmd": 0.075,
        "q_meas": np.zeros(17),
        "deploy_meas": 0.075,
        "astrobee_pos": np.zeros(3),
        "astrobee_quat": np.array([1.0, 0.0, 0.0, 0.0]),
        "astrobee_twist": np.zeros(6),
        "ctb_pos": np.array([0.0, 0.0, -0.3]),
        "ctb_quat": np.array([1.0, 0.0, 0.0, 0.0]),
        "contact": True,
        "ctb_module": "kibo",
    }
    fields.update(kw)
    return StepRecord(**fields)


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product, w x y z."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.array(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ]
    )


def vehicle_pose(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Translating and rotating (yaw 0.3 rad/s then pitch 0.1 rad/s) vehicle: (p, R, q)."""
    psi, theta = 0.3 * t + 0.2, 0.1 * t - 0.05
    p = np.array([0.2 * t + 1.0, 0.05 * t * t - 0.4, -0.1 * t + 0.3])
    R = rot_z(psi) @ rot_y(theta)
    qz = np.array([math.cos(psi / 2), 0.0, 0.0, math.sin(psi / 2)])
    qy = np.array([math.cos(theta / 2), 0.0, math.sin(theta / 2), 0.0])
    return p, R, quat_mul(qz, qy)


def recording_with_offsets(
    offsets_mm: list[tuple[float, float, float]],
    contact: list[bool],
    modules: list[str] | None = None,
    phases: list[str] | None = None,
    base: tuple[float, float, float] = (0.05, -0.02, -0.28),
) -> Recording:
    """CTB at body-frame position ``base + offset`` on a moving, rotating vehicle."""
    steps = []
    for k, (off, c) in enumerate(zip(offsets_mm, contact, strict=True)):
        t = k * DT
        p, R, q = vehicle_pose(t)
        b = np.asarray(base) + 1e-3 * np.asarray(off)
        steps.append(
            make_step(
                t,
                astrobee_pos=p,
                astrobee_quat=q,
                ctb_pos=p + R @ b,
                contact=c,
                ctb_module=modules[k] if modules else "node2",
                phase=phases[k] if phases else "translation",
            )
        )
    return Recording.from_steps(steps)


# -- eq. 4 -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("quat", "rel_world", "expected_body"),
    [
        ((1, 0, 0, 0), (0.1, 0.0, -0.3), (0.1, 0.0, -0.3)),
        # yaw +90 deg: body x points along world y
        ((math.sqrt(0.5), 0, 0, math.sqrt(0.5)), (0.0, 0.5, 0.0), (0.5, 0.0, 0.0)),
        # roll +90 deg: body y points along world z
        ((math.sqrt(0.5), math.sqrt(0.5), 0, 0), (0.0, 0.0, 0.2), (0.0, 0.2, 0.0)),
        # yaw 180 deg
        ((0, 0, 0, 1), (0.3, 0.1, 0.0), (-0.3, -0.1, 0.0)),
        # not normalised: same rotation as yaw +90
        ((2 * math.sqrt(0.5), 0, 0, 2 * math.sqrt(0.5)), (-0.2, 0.0, 0.1), (0.0, 0.2, 0.1)),
    ],
)
def test_eq4_hand_computed(quat, rel_world, expected_body) -> None:
    pb = np.array([[1.0, 2.0, 3.0]])
    out = ctb_in_body_frame(pb, np.array([quat], dtype=float), pb + np.array([rel_world]))
    np.testing.assert_allclose(out[0], expected_body, atol=1e-12)


def test_eq4_on_moving_vehicle_recovers_body_offsets() -> None:
    offs = [(0, 0, 0), (3, 4, 0), (0, 0, 12), (-6, 8, 0), (0, 5, 12)]
    rec = recording_with_offsets(offs, [True] * 5)
    bp = ctb_in_body_frame(rec.astrobee_pos, rec.astrobee_quat, rec.ctb_pos)
    expected = np.array([0.05, -0.02, -0.28]) + 1e-3 * np.array(offs)
    np.testing.assert_allclose(bp, expected, atol=1e-12)
    # the vehicle really rotates: world-frame offsets differ from body-frame ones
    assert np.max(np.abs((rec.ctb_pos - rec.astrobee_pos) - expected)) > 0.01


def test_eq5_hand_computed_on_rotating_translating_vehicle() -> None:
    # 3 samples before contact, 5 in the first interval, 2 after (contact lost).
    # Offsets relative to t0 inside the interval: norms 0, 5, 12, 10, 13 mm.
    big = (80.0, -60.0, 40.0)
    offs = [
        big,
        (10, 0, 0),
        big,
        (0, 0, 0),
        (3, 4, 0),
        (0, 0, 12),
        (-6, 8, 0),
        (0, 5, 12),
        big,
        big,
    ]
    contact = [False, False, False, True, True, True, True, True, False, False]
    m = compute_metrics(recording_with_offsets(offs, contact))
    # eq. 5 by hand: sqrt((0 + 25 + 144 + 100 + 169) / 5) = sqrt(87.6)
    assert m.rms_mm == pytest.approx(math.sqrt(87.6), abs=1e-9)
    assert m.peak_mm == pytest.approx(13.0, abs=1e-9)
    assert m.t0_s == pytest.approx(3 * DT)
    assert m.contact_s == pytest.approx(4 * DT)
    assert m.n_contact_samples == 5
    assert m.b_p_c_t0_m == pytest.approx((0.05, -0.02, -0.28), abs=1e-12)
    assert not m.contact_to_end


def test_eq5_reference_is_first_sample_not_mean() -> None:
    # the CTB drifts linearly 1 mm per sample along body x for 4 samples
    offs = [(float(k), 0.0, 0.0) for k in range(4)]
    m = compute_metrics(recording_with_offsets(offs, [True] * 4))
    assert m.rms_mm == pytest.approx(math.sqrt((0 + 1 + 4 + 9) / 4), abs=1e-9)
    assert m.peak_mm == pytest.approx(3.0, abs=1e-9)


# -- first interval --------------------------------------------------------------------
def test_first_interval_when_contact_flickers() -> None:
    c = [False, False, True, False, True, True, False] + [True] * 20 + [False] + [True] * 10
    t = np.arange(len(c)) * DT
    assert first_contact_interval(t, np.array(c)) == (2, 2)
    # skipping touches shorter than 30 ms leaves the 2-sample run out too
    assert first_contact_interval(t, np.array(c), min_interval_s=0.03) == (7, 26)
    assert first_contact_interval(t, np.zeros(5, bool)) is None
    assert first_contact_interval(t[:3], np.ones(3, bool)) == (0, 2)


def test_optional_dropout_bridging() -> None:
    c = np.array([0, 1, 1, 1, 0, 1, 1, 0, 0, 0, 1, 1, 1, 1, 1], dtype=bool)
    t = np.arange(len(c)) * DT
    assert first_contact_interval(t, c) == (1, 3)  # the paper's definition
    assert first_contact_interval(t, c, max_gap_s=0.04) == (1, 6)  # one missing sample
    assert first_contact_interval(t, c, max_gap_s=0.1) == (1, 14)
    assert first_contact_interval(t, c, min_interval_s=0.2) is None
    assert first_contact_interval(t, c, min_interval_s=0.1, max_gap_s=0.04) == (1, 6)
    # eq. 5 over a bridged interval counts the dropout sample too: norms 0, 5, 12, 13, 0, 10
    offs = [(99, 0, 0), (0, 0, 0), (3, 4, 0), (0, 0, 12), (0, 5, 12), (0, 0, 0), (6, 8, 0)]
    offs += [(99, 0, 0)] * 8
    m = compute_metrics(recording_with_offsets(offs, c.tolist()), max_gap_s=0.04)
    assert m.n_contact_samples == 6 and m.contact_s == pytest.approx(5 * DT)
    assert m.rms_mm == pytest.approx(math.sqrt((25 + 144 + 169 + 100) / 6), abs=1e-9)
    assert m.max_gap_s == 0.04 and m.as_dict()["max_gap_s"] == 0.04
    with pytest.raises(MetricsError, match="max_gap_s"):
        first_contact_interval(t, c, max_gap_s=-0.1)


def test_flicker_after_long_contact_ends_the_first_interval() -> None:
    # 20 samples of contact with small offsets, one dropout, then 10 with large offsets
    small = [(0, 0, 0), (0, 3, 4)] * 10  # norms 0 and 5 mm alternating
    large = [(50, 0, 0)] * 11
    offs = [(0, 0, 0)] * 3 + small + large
    contact = [False] * 3 + [True] * 20 + [False] + [True] * 10
    m = compute_metrics(recording_with_offsets(offs, contact))
    assert m.n_contact_samples == 20
    assert m.t0_s == pytest.approx(3 * DT)
    assert m.contact_s == pytest.approx(19 * DT)
    assert m.rms_mm == pytest.approx(math.sqrt(25 / 2), abs=1e-9)
    assert m.peak_mm == pytest.approx(5.0, abs=1e-9)
    assert m.contact_samples_total == 30


# -- success, duration, displacement ---------------------------------------------------
@pytest.mark.parametrize(
    ("contact", "modules", "success"),
    [
        ("1111111111", "kkkkkhhnnn", True),  # contact to the end, ends in node2
        ("1111111111", "kkkkkhhhhh", False),  # never arrives
        ("1111100011", "kkkkkhhnnn", False),  # contact lost before arrival
        ("1111111100", "kkkkkhhnnn", False),  # no arrival phase: must hold to the end
        ("1111111111", "kknnkhhnnn", True),  # re-entered node2, still in contact
        ("0000000011", "kkkkkhhnnn", False),  # first contact only after entry
        ("1100011111", "kkkkkhhnnn", False),  # the first interval ended early
        ("0000000000", "nnnnnnnnnn", False),  # never any contact
    ],
)
def test_success_criterion(contact: str, modules: str, success: bool) -> None:
    names = {"k": "kibo", "h": "hatch", "n": "node2"}
    rec = recording_with_offsets(
        [(0, 0, 0)] * 10, [c == "1" for c in contact], [names[c] for c in modules]
    )
    m = compute_metrics(rec)
    assert m.success is success
    assert m.final_module == names[modules[-1]]


@pytest.mark.parametrize(
    ("contact", "phases", "success", "arrival_index"),
    [
        ("111111111111", "tttttttttaaa", True, 9),  # held through the arrival phase
        ("111111110000", "tttttttttaaa", False, 9),  # carried into node2, lost in the turn
        ("111111111100", "tttttttttaaa", True, 9),  # released once arrived
        ("111111111110", "tttttttttttt", False, 11),  # never arrived: hold to the end
        ("111111100000", "ttaaaaaaaaaa", True, 6),  # arrival phase before entry: entry wins
        ("111111100000", "ttaattttttaa", False, 10),  # the last arrival block counts
    ],
)
def test_arrival_is_the_later_of_entry_and_arrival_phase(
    contact: str, phases: str, success: bool, arrival_index: int
) -> None:
    names = {"t": "turn", "a": "arrival"}
    modules = ["kibo"] * 4 + ["hatch"] * 2 + ["node2"] * 6  # entry at sample 6
    rec = recording_with_offsets(
        [(0, 0, 0)] * 12, [c == "1" for c in contact], modules, [names[p] for p in phases]
    )
    m = compute_metrics(rec)
    assert m.success is success
    assert m.arrival_s == pytest.approx(arrival_index * DT)
    assert m.entry_s == pytest.approx(6 * DT)


def test_duration_and_net_displacement() -> None:
    steps = []
    for k in range(30):
        phase = "calibration" if k < 10 else ("arrival" if k > 25 else "translation")
        steps.append(make_step(k * DT, phase=phase, ctb_pos=np.array([0.3 * k, 0.4 * k, -0.3])))
    m = compute_metrics(Recording.from_steps(steps))
    assert m.duration_s == pytest.approx(19 * DT)  # t = 0.20 .. 0.58 s
    assert m.net_displacement_m == pytest.approx(0.5 * 29)  # 3-4-5 triangle per step
    assert m.n_samples == 30


def test_metrics_errors() -> None:
    empty = Recording.from_dicts([])
    with pytest.raises(MetricsError, match="no steps"):
        compute_metrics(empty)
    rec = recording_with_offsets([(0, 0, 0)] * 3, [True] * 3)
    with pytest.raises(MetricsError, match="destination"):
        compute_metrics(rec, destination="columbus")
    with pytest.raises(MetricsError, match="min_interval_s"):
        first_contact_interval(rec.t, rec.contact, -1.0)


# -- recorder --------------------------------------------------------------------------
def test_recording_round_trip_and_schema(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    steps = []
    for k in range(120):
        lj = rng.normal(size=(25, 3))
        if k % 7 == 0:
            lj[:] = np.nan  # untracked
        steps.append(
            make_step(
                k * DT,
                left_joints=lj,
                left_tracked=k % 7 != 0,
                right_joints=rng.normal(size=(25, 3)),
                q_left=rng.normal(size=8),
                q_cmd=rng.normal(size=17),
                q_meas=rng.normal(size=17),
                astrobee_pos=rng.normal(size=3),
                astrobee_quat=rng.normal(size=4),
                ctb_pos=rng.normal(size=3),
                twist_cmd=rng.normal(size=6),
                contact=bool(k % 3),
                phase="calibration" if k < 20 else "acquisition",
                ctb_module="hatch" if k > 100 else "kibo",
            )
        )
    path = tmp_path / "log.mcap"
    with TrialRecorder(path) as rec:
        rec.write_meta({"seed": 7, "design_hash": "abc"})
        for s in steps:
            rec.write(s)
        rec.write_meta({"calibration": {"span_m": np.float64(0.08)}})
    back = read_recording(path)
    mem = Recording.from_steps(steps)
    assert back.complete and len(back) == 120
    assert back.meta == {"seed": 7, "design_hash": "abc", "calibration": {"span_m": 0.08}}
    grids = {name: grid for name, grid, _ in STEP_GRIDS}
    for name in FIELD_SPECS:
        a, b = getattr(back, name), getattr(mem, name)
        if name in grids:  # to the stated resolution: half a grid step (plus the last bit)
            assert np.all(np.abs(a - b) <= grids[name] / 2 + 4e-16 * np.abs(b)), name
        elif a.dtype.kind == "f":
            np.testing.assert_array_equal(a, b)  # exact: hand joints and pair channels
        else:
            assert (a == b).all(), name
    assert np.isnan(back.left_joints[0]).all() and not back.left_tracked[0]
    np.testing.assert_array_equal(back.seq, np.arange(120))
    ours, exact = compute_metrics(back), compute_metrics(mem)
    for key, value in vars(exact).items():
        got = getattr(ours, key)
        if isinstance(value, (bool, int, str)) or value is None:
            assert got == value, key
        else:  # figures of the numbers: within a micrometre (or its part)
            np.testing.assert_allclose(got, value, rtol=1e-9, atol=1e-6, err_msg=key)


def test_recording_is_standard_mcap_with_protobuf_steps(tmp_path: Path) -> None:
    """The mcap package's own reader and mcap_protobuf's decoder (not ours) read every step
    message from the schema stored in the file; the values are the ones written."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    rng = np.random.default_rng(5)
    path = tmp_path / "log.mcap"
    written = []
    with TrialRecorder(path) as rec:
        for k in range(120):
            q = rng.normal(size=17)
            written.append(q)
            rec.write(make_step(k * DT, q_cmd=q, contact=bool(k % 2), phase="turn"))

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        msgs = list(reader.iter_decoded_messages(topics=["/trial/step"]))
        assert reader.get_summary().statistics.message_count == 120
        assert reader.get_summary().chunk_indexes  # zstd chunks, indexed
    assert len(msgs) == 120
    schema, channel, _, _ = msgs[0]
    assert schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
    assert schema.name == "payload.trials.Step"
    # the grid numbers, summed here from the generic decoder's deltas (key after a flush)
    names = [name for name, _, n in STEP_GRIDS for _ in range(n)]
    at = [i for i, name in enumerate(names) if name == "q_cmd"]
    grid = dict((name, g) for name, g, _ in STEP_GRIDS)["q_cmd"]
    total = None
    for k, (_, _, raw, msg) in enumerate(msgs):
        assert raw.sequence == msg.seq == k
        delta = np.array(msg.grid, dtype=np.int64)
        total = delta if msg.grid_key or total is None else total + delta
        assert np.all(np.abs(total[at] * grid - written[k]) <= grid / 2 + 1e-15)
        assert msg.contact == bool(k % 2)
        phase = msg.DESCRIPTOR.fields_by_name["phase"].enum_type
        assert phase.values_by_number[msg.phase].name == "PHASE_TURN"


def test_step_record_validation() -> None:
    with pytest.raises(RecordingError, match=r"q_cmd.*shape"):
        make_step(0.0, q_cmd=np.zeros(16))
    with pytest.raises(RecordingError, match=r"q_meas.*non-finite"):
        make_step(0.0, q_meas=np.full(17, np.nan))
    with pytest.raises(RecordingError, match="phase"):
        make_step(0.0, phase="cruise")
    with pytest.raises(RecordingError, match="ctb_module"):
        make_step(0.0, ctb_module="columbus")
    with pytest.raises(RecordingError, match=r"astrobee_quat.*zero"):
        make_step(0.0, astrobee_quat=np.zeros(4))
    with pytest.raises(RecordingError, match=r"contact.*bool"):
        make_step(0.0, contact=1)
    with pytest.raises(RecordingError, match=r"left_joints.*non-finite"):
        make_step(0.0, left_joints=np.full((25, 3), np.inf))
    joints = np.full((25, 3), np.nan)  # untracked, but for one infinity
    joints[7, 2] = -np.inf
    with pytest.raises(RecordingError, match=r"right_joints.*non-finite.*\[7 2\]"):
        make_step(0.0, right_joints=joints)
    with pytest.raises(RecordingError, match=r"t: not finite"):
        make_step(np.inf)
    s = make_step(0.0)
    with pytest.raises(ValueError):
        s.q_cmd[0] = 1.0  # read-only
    # every array its own values: read-only, unchanged when the caller's arrays change
    given = {"q_cmd": np.arange(17.0), "left_joints": np.full((25, 3), np.nan)}
    s = make_step(0.0, **given)
    for name, value in given.items():
        kept = getattr(s, name)
        assert not kept.flags.writeable and kept.shape == value.shape
        before = kept.copy()
        value[0] = 5.0
        assert np.array_equal(kept, before, equal_nan=True)
    # finite values whose sum overflows are finite values
    big = np.zeros(17)
    big[:2] = 1e308
    with np.errstate(over="ignore"):  # the check's sum overflows, as it did before
        assert make_step(0.0, q_cmd=big).q_cmd[1] == 1e308


def test_recorder_errors(tmp_path: Path) -> None:
    path = tmp_path / "log.mcap"
    with TrialRecorder(path) as rec:
        rec.write(make_step(0.0))
        with pytest.raises(RecordingError, match="not after"):
            rec.write(make_step(0.0))
        with pytest.raises(RecordingError, match="StepRecord"):
            rec.write({"t": 1.0})  # type: ignore[arg-type]
        with pytest.raises(RecordingError, match="not a string"):
            rec.write_meta({1: 2})  # type: ignore[dict-item]
        with pytest.raises(RecordingError, match="not JSON"):
            rec.write_meta({"x": object()})
    with pytest.raises(RecordingError, match="already exists"):
        TrialRecorder(path)
    with pytest.raises(RecordingError, match="flush_period_s"):
        TrialRecorder(tmp_path / "b.mcap", flush_period_s=2.0)
    with pytest.raises(RecordingError, match="no such recording"):
        read_recording(tmp_path / "missing.mcap")
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        read_recording(tmp_path / "junk.mcap")


def test_a_recorder_never_truncates_a_file_made_after_it_was_set_up(tmp_path: Path) -> None:
    """Two recorders set up on one path before either opens it (two live servers on one
    ``--record`` folder, say): the second to open refuses, and the first's steps stay."""
    path = tmp_path / "log.mcap"
    first, second = TrialRecorder(path), TrialRecorder(path)
    with first:
        for k in range(3):
            first.write(make_step(0.02 * k))
        first.flush()
        with pytest.raises(RecordingError, match="already exists"):
            second.open()
    assert len(read_recording(path)) == 3


def test_truncated_file_reads_whole_records_only(tmp_path: Path) -> None:
    path = tmp_path / "log.mcap"
    with TrialRecorder(path) as rec:
        for k in range(50):
            rec.write(make_step(k * DT, rail_cmd=0.001 * k))
    data = path.read_bytes()
    full = read_recording(path)
    # cut inside the summary, then inside messages: every prefix reads, never a torn step
    for cut in (len(data) - 20, len(data) // 2, len(data) // 3 + 7, 200):
        p = tmp_path / f"cut{cut}.mcap"
        p.write_bytes(data[:cut])
        part = read_recording(p)
        assert not part.complete
        n = len(part)
        np.testing.assert_array_equal(part.rail_cmd, full.rail_cmd[:n])
    assert len(read_recording(tmp_path / f"cut{len(data) - 20}.mcap")) == 50


KILL_CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from payload.trials.recorder import StepRecord, TrialRecorder

    path, dt_rec, pace = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
    rec = TrialRecorder(path).open()
    rec.write_meta({"seed": 11})
    k = 0
    while True:
        t = k * dt_rec
        before = time.monotonic()  # the recorder's flush clock
        rec.write(StepRecord(
            t=t, phase="translation",
            left_joints=np.full((25, 3), float(k)), right_joints=np.zeros((25, 3)),
            left_tracked=True, right_tracked=True, q_left=np.zeros(8), q_right=np.zeros(8),
            rail_cmd=0.0, twist_cmd=np.zeros(6), q_cmd=np.full(17, 0.001 * k),
            deploy_cmd=0.075, q_meas=np.zeros(17), deploy_meas=0.075,
            astrobee_pos=[0.1 * t, 0, 0], astrobee_quat=[1, 0, 0, 0],
            astrobee_twist=np.zeros(6), ctb_pos=[0.1 * t, 0, -0.3], ctb_quat=[1, 0, 0, 0],
            contact=True, ctb_module="kibo"))
        print(k, before, time.monotonic(), flush=True)
        k += 1
        time.sleep(pace)
    """
)


@pytest.mark.parametrize(
    ("dt_rec", "pace"),
    [(0.02, 0.02), (1e-4, 0.01), (0.02, 0.002)],
    ids=["real-time-50Hz", "slow-recorded-time", "10x-faster-than-real-time"],
)
def test_sigkilled_recording_is_read_back(tmp_path: Path, dt_rec: float, pace: float) -> None:
    """A writer killed with SIGKILL mid-trial: the file reads, losing at most ~1 s.

    The second case advances recorded time so slowly that only the wall-clock flush
    deadline can save the data; the third runs 10x faster than real time, so only the
    recorded-time deadline bounds the loss in recorded seconds.
    """
    path = tmp_path / "log.mcap"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-c", KILL_CHILD, str(path), str(dt_rec), str(pace)],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert proc.stdout is not None
    returned: list[float] = []  # when each write returned, on the writer's clock
    last_k, last_before = -1, 0.0
    deadline = time.time() + 60
    try:
        for line in proc.stdout:
            k, before, after = line.split()
            last_k, last_before = int(k), float(before)
            returned.append(float(after))
            if last_before - returned[0] > 2.6 or time.time() > deadline:
                break
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert last_k > 50
    rec = read_recording(path)
    assert not rec.complete
    assert rec.meta == {"seed": 11}
    n = len(rec)
    assert n >= 1
    # lost at most the last second of wall-clock time: the writer flushes when a write
    # starts a second or more after the last flush ended, so every write that returned a
    # second before the last write started is on disk, however slowly the machine ran
    # (timed on the writer's own clock, not from this process); and at most the last
    # second of recorded time (+ one step)
    must_have = [j for j, r in enumerate(returned) if r <= last_before - 1.0]
    assert must_have and n > must_have[-1]
    assert rec.t[-1] >= last_k * dt_rec - 1.0 - dt_rec - 1e-9
    # what was read is exactly what was written, in order
    np.testing.assert_array_equal(rec.seq, np.arange(n))
    np.testing.assert_allclose(rec.q_cmd[:, 0], 0.001 * np.arange(n))
    np.testing.assert_array_equal(rec.left_joints[:, 0, 0], np.arange(n, dtype=float))
    np.testing.assert_allclose(rec.t, dt_rec * np.arange(n))
    assert compute_metrics(rec).n_samples == n


# -- test fixture: a seeded synthetic trial through the recorder ------------------------
def fixture_synthetic_trial(
    seed: int, out_dir: Path, contact: str = "held", **score: float
) -> dict[str, Any]:
    """Test fixture (not a product feature): synthesise a seeded 6 s trial recording
    through the recorder, then score it with ``finish_trial`` (``score``: its contact
    definition, ``min_interval_s`` and ``max_gap_s``). ``contact``: the opposing-contact
    indicator set from a seeded step to the end (``held``), at that step alone (``blip``),
    or never (``none``)."""
    from payload.trials.campaign import finish_trial

    rng = np.random.default_rng(seed)
    n = 300
    n_cal = 20
    start = int(rng.integers(30, 60))  # first confirmed contact
    drift = rng.normal(scale=0.002, size=(n, 3)).cumsum(axis=0)
    out_dir = Path(out_dir)
    path = out_dir / "log.mcap"
    with TrialRecorder(path, overwrite=True) as rec:
        rec.write_meta({"seed": seed, "operator": "fixture"})
        for k in range(n):
            t = k * DT
            yaw = 0.0 if t < 3.0 else -0.5 * (t - 3.0)  # right turn
            q = np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
            p = np.array([0.3 * t, 0.0, 0.0])
            body = np.array([0.0, 0.0, -0.28]) + (drift[k] - drift[start] if k >= start else 0)
            phase = (
                "calibration"
                if k < n_cal
                else "acquisition"
                if k < start
                else "translation"
                if t < 3.0
                else "turn"
                if t < 5.0
                else "arrival"
            )
            module = "kibo" if p[0] < 1.0 else ("hatch" if p[0] < 1.3 else "node2")
            rec.write(
                make_step(
                    t,
                    phase=phase,
                    astrobee_pos=p,
                    astrobee_quat=q,
                    ctb_pos=p + rot_z(yaw) @ body,
                    contact={"held": k >= start, "blip": k == start, "none": False}[contact],
                    ctb_module=module,
                )
            )
    modules = [("kibo", -1, -1, 1.0, 1), ("node2", 1.3, -2, 3, 2)]
    return finish_trial(out_dir, path, modules, **score)


def _metric_view(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    drop = {"out_dir", "wall_s", "recording", "traceback"}
    return [{k: v for k, v in r.items() if k not in drop} for r in results]


def test_finish_trial_writes_files(tmp_path: Path) -> None:
    from matplotlib.image import imread

    result = fixture_synthetic_trial(5, tmp_path / "t")
    d = tmp_path / "t"
    assert sorted(p.name for p in d.iterdir()) == sorted(
        ["log.mcap", "metrics.json", "fig_ctb_body_frame.png", "fig_route.png"]
    )
    on_disk = json.loads((d / "metrics.json").read_text())
    assert on_disk == json.loads(json.dumps(result))
    m = compute_metrics(read_recording(d / "log.mcap"))
    assert on_disk["rms_mm"] == pytest.approx(m.rms_mm) and on_disk["success"] is m.success
    assert on_disk["seed"] == 5 and m.success
    for name in ("fig_ctb_body_frame.png", "fig_route.png"):
        img = imread(d / name)
        assert img.shape[0] > 400 and img.shape[1] > 400
        assert img[..., :3].std() > 0.05  # not a blank canvas


def _zlib_level(png: Path) -> str:
    """The compression level a PNG's image data says it was written at: the FLEVEL bits of
    its first IDAT chunk's zlib header (RFC 1950)."""
    data, at = png.read_bytes(), 8  # after the PNG signature
    while True:
        length, kind = int.from_bytes(data[at : at + 4], "big"), data[at + 4 : at + 8]
        if kind == b"IDAT":
            flg = data[at + 9]
            return ("fastest", "fast", "default", "maximum")[flg >> 6]
        at += 12 + length


def test_the_trial_figures_keep_every_text_on_the_canvas(tmp_path: Path, monkeypatch) -> None:
    """The fixed margins (no layout engine) leave room for wide tick labels, every phase in
    the legend and two-line titles: each axes' drawn extent (tick labels, axis labels,
    titles) and each legend lie inside the figure, read from the drawn figure."""
    from matplotlib.image import imread
    from matplotlib.legend import Legend

    from payload.trials import figures

    drawn = []
    save = figures.save_figure

    def keep(fig, path, dpi, *rest):
        drawn.append((fig, path, dpi))
        return save(fig, path, dpi, *rest)

    monkeypatch.setattr(figures, "save_figure", keep)
    n = 600
    phases = list(figures.PHASE_COLORS)
    k = np.arange(n)
    # offsets of ten metres and more: tick labels such as "-12000" on every panel
    offsets = [(-12345.0 * (i % 7), 23456.0 * math.sin(i / 9), -34567.0) for i in range(n)]
    rec = recording_with_offsets(
        offsets,
        [bool(i > 100) for i in range(n)],
        phases=[phases[min(len(phases) - 1, int(i * len(phases) / n))] for i in k],
    )
    modules = [{"name": "kibo", "x_min": -2, "x_max": 2, "y_min": 3, "y_max": 10}]
    figures.plot_ctb_body_frame(rec, tmp_path / "ctb.png")
    figures.plot_route(rec, tmp_path / "route.png", modules)
    assert len(drawn) == 2
    # a module is labelled by its title, not the recorded identifier
    assert [t.get_text().strip() for t in drawn[1][0].axes[0].texts] == ["Kibo (JEM)"]
    for fig, path, dpi in drawn:
        # written at zlib's fastest level (not Pillow's default), to the same pixels
        default = save(fig, tmp_path / f"default-{path.name}", dpi)
        assert (_zlib_level(path), _zlib_level(default)) == ("fastest", "default")
        assert np.array_equal(imread(default), imread(path))
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        page = fig.bbox
        boxes = [ax.get_tightbbox(renderer) for ax in fig.axes]
        boxes += [a.get_window_extent(renderer) for a in fig.findobj(Legend)]
        if fig._suptitle is not None:
            boxes.append(fig._suptitle.get_window_extent(renderer))
        for box in boxes:
            assert box.x0 >= page.x0 - 0.5 and box.x1 <= page.x1 + 0.5, (box, page)
            assert box.y0 >= page.y0 - 0.5 and box.y1 <= page.y1 + 0.5, (box, page)


def test_fig3_without_metrics_scores_as_the_recording_was_made_to(
    tmp_path: Path, monkeypatch
) -> None:
    """Fig. 3 drawn without metrics states the contact time under the definition the
    recording stores (as its trial's metrics.json does), and the paper's without one: a
    contact from step 101 to the last (599) with a one-step dropout at step 300 is one
    interval of about 10 s bridged (a 0.1 s gap), about 4 s paper-literal."""
    import re

    from payload.trials import figures

    titles: list[str] = []
    save = figures.save_figure

    def keep(fig, path, dpi, *rest):
        titles.append(fig._suptitle.get_text())
        return save(fig, path, dpi, *rest)

    monkeypatch.setattr(figures, "save_figure", keep)
    n = 600
    rec = recording_with_offsets([(0.0, 0.0, 0.0)] * n, [100 < i != 300 for i in range(n)])
    figures.plot_ctb_body_frame(rec, tmp_path / "literal.png")
    rec.meta["contact_definition"] = {"min_interval_s": 0.5, "max_gap_s": 0.1}
    figures.plot_ctb_body_frame(rec, tmp_path / "recorded.png")
    contact = [float(re.search(r"contact ([0-9.]+) s of", t).group(1)) for t in titles]
    assert 3.9 <= contact[0] <= 4.1, titles[0]
    assert 9.8 <= contact[1] <= 10.1, titles[1]
    # each figure names the definition it scored, and the trial's seed once it has one
    assert "first contact (>= 0 s, gaps <= 0 s) (t0)" in titles[0], titles[0]
    assert "first confirmed contact (t0)" in titles[1] and "seed" not in titles[1], titles[1]
    rec.meta.update(seed=7, ended_by="max_time")
    drawn = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, *a: drawn.append(fig))
    figures.plot_ctb_body_frame(rec, tmp_path / "capped.png")
    assert "), seed 7 -- " in drawn[0]._suptitle.get_text()
    top = [t.get_text() for t in drawn[0].axes[0].texts]  # the title has no room for it
    assert "session stopped by the --max-time cap" in top, top
    figures.plot_route(rec, tmp_path / "route.png")
    assert drawn[1].axes[0].get_title().startswith("Route, top view, seed 7 (")


def test_figures_reject_bad_modules(tmp_path: Path) -> None:
    from payload.trials.figures import FigureError, plot_route

    rec = recording_with_offsets([(0, 0, 0)] * 3, [True] * 3)
    with pytest.raises(FigureError, match="kibo"):
        plot_route(rec, tmp_path / "r.png", [("kibo", 1, 0, 0, 1)])
    with pytest.raises(FigureError, match="x_max"):
        plot_route(rec, tmp_path / "r.png", [{"name": "kibo", "x_min": 0, "y_min": 0}])


# -- campaigns -------------------------------------------------------------------------
def test_campaign_on_dask_local_cluster_matches_serial(tmp_path: Path) -> None:
    from payload.trials.campaign import run_campaign, trial_dir, write_summary

    seeds = [3, 0, 1, 2]
    serial = run_campaign(fixture_synthetic_trial, seeds, tmp_path / "s", workers=0, progress=False)
    dask = run_campaign(fixture_synthetic_trial, seeds, tmp_path / "d", workers=2, progress=False)
    assert [r["seed"] for r in dask] == [0, 1, 2, 3]
    assert all(r["error"] is None for r in serial + dask), [r.get("error") for r in dask]
    assert _metric_view(dask) == _metric_view(serial)
    # the trials really differ from one another (seeded)
    assert len({r["rms_mm"] for r in serial}) == len(seeds)
    # workers ran in other processes, each trial in its own folder
    for s in seeds:
        files = {p.name for p in trial_dir(tmp_path / "d", s).iterdir()}
        assert {"log.mcap", "metrics.json", "fig_ctb_body_frame.png", "fig_route.png"} <= files
    summary = write_summary(dask, tmp_path / "d")
    rms = [r["rms_mm"] for r in serial]
    assert summary["n"] == 4 and summary["success"] == 4
    assert summary["rms_mm"]["median"] == pytest.approx(float(np.median(rms)))
    assert summary["rms_mm"]["min"] == pytest.approx(min(rms))
    on_disk = json.loads((tmp_path / "d" / "summary.json").read_text())
    for key in ("duration_s", "net_displacement_m", "rms_mm", "peak_mm", "contact_s"):
        assert set(on_disk[key]) >= {"median", "min", "max"}
    # the fixture's trials use the paper's definition: both columns agree
    assert "| task success | 4/4 | 4/4 | 10/10 |" in (tmp_path / "d" / "summary.md").read_text()


def _worker_profiler_enabled() -> bool:
    import dask
    import distributed  # noqa: F401  (its import registers the distributed.* defaults)

    return bool(dask.config.get("distributed.worker.profile.enabled"))


def test_the_local_clusters_workers_run_without_the_dask_profiler() -> None:
    # the profiler samples the task's stack every 10 ms under the GIL (docs/speed-log.md, item 9);
    # asked of each worker process itself, not of this one's configuration
    # distributed's defaults registered before the set below: else leaving the set removes
    # the whole "distributed" table it found missing, and a later Client in this process
    # fails on a KeyError
    import dask
    import distributed  # noqa: F401

    from payload.trials.cluster import dask_client

    # on here (Dask's default, set explicitly whatever the environment says), so the
    # workers would run it unless the cluster turns it off for them
    with dask.config.set({"distributed.worker.profile.enabled": True}):
        with dask_client(2, None, RuntimeError) as client:
            seen = client.run(_worker_profiler_enabled)
        assert _worker_profiler_enabled()  # the setting did not leak into this process
    assert len(seen) == 2 and not any(seen.values())


def test_a_local_cluster_beside_another_takes_a_free_port_without_a_warning() -> None:
    # a second campaign or sweep while one runs: Dask's default HTTP port (8787) is held
    import socket
    import warnings

    import distributed  # noqa: F401

    from payload.trials.cluster import dask_client

    holder = socket.socket()
    try:
        holder.bind(("", 8787))
        holder.listen()
    except OSError:
        pass  # something already holds it: the same situation
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with dask_client(1, None, RuntimeError) as client:
                assert client.submit(sum, [40, 2]).result() == 42
                port = client.scheduler_info()["services"].get("dashboard")
    finally:
        holder.close()
    assert not [w for w in caught if "already in use" in str(w.message)]
    assert port is not None and port != 8787


def _ignores_ctrl_c() -> bool:
    import signal

    return signal.getsignal(signal.SIGINT) is signal.SIG_IGN


def test_a_local_clusters_workers_leave_ctrl_c_to_the_command() -> None:
    """A Ctrl-C in the terminal reaches every process of the group: the local cluster's
    workers ignore it (each printed a KeyboardInterrupt traceback while the command
    stopped the campaign or sweep and closed them), and this process takes it again
    once the cluster is up."""
    import signal

    import distributed  # noqa: F401

    from payload.trials.cluster import dask_client

    before = signal.getsignal(signal.SIGINT)
    assert before is not signal.SIG_IGN
    with dask_client(1, None, RuntimeError) as client:
        seen = client.run(_ignores_ctrl_c)
        assert signal.getsignal(signal.SIGINT) is before
    assert len(seen) == 1 and all(seen.values())


def test_campaign_on_existing_scheduler_matches_serial(tmp_path: Path) -> None:
    from distributed import LocalCluster

    from payload.trials.campaign import run_campaign

    seeds = [0, 1]
    serial = run_campaign(fixture_synthetic_trial, seeds, tmp_path / "s", workers=1, progress=False)
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        remote = run_campaign(
            fixture_synthetic_trial,
            seeds,
            tmp_path / "r",
            scheduler=cluster.scheduler_address,
            progress=False,
        )
    assert _metric_view(remote) == _metric_view(serial)


def _broken_trial(seed: int, out_dir: Path) -> dict[str, Any]:
    if seed == 1:
        raise RuntimeError("simulator exploded")
    return {"success": True, "duration_s": 10.0 + seed, "rms_mm": None}


def test_campaign_records_a_crashed_trial_as_failure(tmp_path: Path) -> None:
    from payload.trials.campaign import CampaignError, run_campaign, summarize

    results = run_campaign(_broken_trial, [0, 1, 2], tmp_path, workers=0, progress=False)
    assert results[1]["error"] == "RuntimeError: simulator exploded"
    s = summarize(results)
    assert (s["n"], s["success"], s["errors"]) == (3, 2, 1)
    assert s["duration_s"] == {"median": 11.0, "min": 10.0, "max": 12.0, "count": 2}
    assert s["rms_mm"] == {"median": None, "min": None, "max": None, "count": 0}
    with pytest.raises(CampaignError, match="duplicate"):
        run_campaign(_broken_trial, [0, 0], tmp_path, workers=0, progress=False)
    with pytest.raises(CampaignError, match="no seeds"):
        run_campaign(_broken_trial, [], tmp_path, workers=0, progress=False)
    for seeds, problem in (([3, -1], "seeds must be >= 0, got -1"), ([1, 2**63], "at most")):
        with pytest.raises(CampaignError, match=re.escape(problem)):
            run_campaign(_broken_trial, seeds, tmp_path / "x", workers=0, progress=False)
    assert not (tmp_path / "x").exists()  # refused before anything is made


def test_summary_table_against_hand_values() -> None:
    from payload.trials.campaign import summarize, summary_markdown

    rows = [
        {"seed": s, "success": ok, "duration_s": d, "net_displacement_m": 9.0 + s,
         "rms_mm": r, "peak_mm": 2 * r, "contact_s": d - 1, "final_module": "node2"}
        for s, ok, d, r in [(0, True, 70.0, 30.0), (1, False, 90.0, 10.0), (2, True, 80.0, 50.0)]
    ]  # fmt: skip
    for r in rows:  # debounced figures; the paper-literal ones are shorter contacts
        r.update(acquired=True, min_interval_s=0.5, max_gap_s=0.1, ctb="rigid")
        r.update(propulsion="nozzles")
        r["literal"] = {**r, "success": False, "contact_s": 0.2, "rms_mm": 1.0}
        r["literal"].update(min_interval_s=0.0, max_gap_s=0.0)
    rows[1]["acquired"] = rows[1]["literal"]["acquired"] = False
    s = summarize(rows)
    assert s["success"] == 2 and s["n"] == 3
    assert s["duration_s"] == {"median": 80.0, "min": 70.0, "max": 90.0, "count": 3}
    assert s["peak_mm"]["median"] == 60.0
    assert s["acquisition_success"] == pytest.approx(2 / 3)
    assert s["ctb"] == "rigid" and s["propulsion"] == "nozzles"
    lit = s["literal"]
    assert s["physics_dt"] is None  # rows from before the option: no step recorded
    assert set(s) - {"literal", "ctb", "propulsion", "physics_dt", "station", "capped"} == set(lit)
    assert lit["success"] == 0 and lit["contact_s"]["median"] == 0.2
    assert lit["contact_definition"] == {"min_interval_s": 0.0, "max_gap_s": 0.0}
    assert s["contact_definition"] == {"min_interval_s": 0.5, "max_gap_s": 0.1}
    md = summary_markdown(s)
    assert "| task success | 2/3 | 0/3 | 10/10 |" in md
    assert "| acquisition success | 67 % | 67 % | n/a |" in md
    assert "80.0 (70.0 to 90.0) | 80.0 (70.0 to 90.0) | 77.5 (67.3 to 97.5) |" in md
    assert "30.0 (10.0 to 50.0) | 1.0 (1.0 to 1.0) | 35.6 (16.4 to 79.0) |" in md
    assert "| 1 | no | 90.0 | 10.00 | 10.0 | 20.0 | 89.0 | node2 | no | 1.0 | 0.2 |" in md
    assert "any single sample" in md and "0.50 s skipped" in md
    assert "CTB model `rigid`" in md


def test_a_campaign_without_contact_says_its_contact_interval_is_none(tmp_path, capsys) -> None:
    """A campaign none of whose trials held a contact (a new user's first, short runs)
    said "First confirmed-contact interval 0.0 (0.0 to 0.0)" beside an RMS of n/a: the
    0 s is the metric's value for no interval, which summary.json keeps, but summary.md,
    the command's output and the terminal summary say n/a, as for the RMS. A single
    contact sample is a paper-literal interval that lasted 0 s: said as 0.0."""
    from payload.cli import main
    from payload.trials.campaign import trial_dir
    from payload.trials.summary_fields import METRIC_LABELS
    from payload.trials.terminal import summary_terminal

    camp = tmp_path / "camp"
    confirmed = {"min_interval_s": CONFIRM_MIN_S, "max_gap_s": CONFIRM_MAX_GAP_S}
    for seed, contact in ((1, "none"), (2, "blip")):
        fixture_synthetic_trial(seed, trial_dir(camp, seed), contact, **confirmed)
    samples = {  # the recordings' own indicator, not the metrics
        s: int(read_recording(trial_dir(camp, s) / "log.mcap").contact.sum()) for s in (1, 2)
    }
    assert samples == {1: 0, 2: 1}
    assert main(["trials", "summarize", str(camp)]) == 0
    out = capsys.readouterr().out
    md = (camp / "summary.md").read_text()
    assert out.startswith(md), out  # the command prints what it wrote
    row = next(ln for ln in md.splitlines() if ln.startswith(f"| {METRIC_LABELS['contact_s']}"))
    rms = next(ln for ln in md.splitlines() if ln.startswith(f"| {METRIC_LABELS['rms_mm']}"))
    # confirmed: no trial has an interval; paper-literal: trial 2's one sample, 0 s long
    assert row.split(" | ")[1:3] == [
        "n/a (no confirmed contact) [0 of 2 trials]",
        "0.0 (0.0 to 0.0) [1 of 2 trials]",
    ], row
    assert rms.split(" | ")[1:3] == ["n/a [0 of 2 trials]", "0.0 (0.0 to 0.0) [1 of 2 trials]"]
    cells = {  # per trial: RMS [mm], contact [s], then the literal RMS and contact
        ln[2]: [ln.strip("| ").split(" | ")[i] for i in (4, 6, 9, 10)]
        for ln in md.splitlines()
        if ln.startswith(("| 1 |", "| 2 |"))
    }
    assert cells == {"1": ["n/a"] * 4, "2": ["n/a", "n/a", "0.0", "0.0"]}, cells
    # each trial's figure is as it was: 0 s for no interval (a contract); the statistics
    # are over the trials with an interval (none here), as the RMS's are
    summary = json.loads((camp / "summary.json").read_text())
    assert summary["contact_s"] == {"median": None, "min": None, "max": None, "count": 0}
    assert [t["contact_s"] for t in summary["trials"]] == [0.0, 0.0]
    assert summary["literal"]["contact_s"]["count"] == 1  # trial 2's 0 s literal interval
    terminal = summary_terminal(summary, summary.get("title"))
    line = next(ln for ln in terminal.splitlines() if METRIC_LABELS["contact_s"] in ln)
    assert "n/a (no confirmed contact)" in line and "0.0 (0.0" not in line, line


def test_a_campaign_some_of_whose_trials_held_no_contact_times_only_those_that_did(
    tmp_path, monkeypatch
) -> None:
    """The committed 1 s link-delay campaign, two of whose ten trials held the handle, said
    "First confirmed-contact interval 0.0 (0.0 to 124.0)": the eight trials without an
    interval, each "n/a" in the per-trial table, went into the median as 0 s, while the
    RMS beside it was over the two that had one ("[2 of 10 trials]"). The interval's
    median, range and count (summary.json, summary.md, the figure) are now over the trials
    that have one; each trial's own 0 s stays in its row."""
    import statistics

    from matplotlib.collections import PathCollection

    from payload.cli import main
    from payload.trials.campaign import trial_dir

    camp = tmp_path / "camp"
    confirmed = {"min_interval_s": CONFIRM_MIN_S, "max_gap_s": CONFIRM_MAX_GAP_S}
    kinds = {1: "none", 2: "held", 3: "held"}
    metrics = {
        s: fixture_synthetic_trial(s, trial_dir(camp, s), k, **confirmed) for s, k in kinds.items()
    }
    held = [float(metrics[s]["contact_s"]) for s in (2, 3)]
    assert min(held) > 0 and float(metrics[1]["contact_s"]) == 0.0
    drawn = _drawn_campaign_figures(monkeypatch)
    assert main(["trials", "summarize", str(camp)]) == 0
    summary = json.loads((camp / "summary.json").read_text())
    want = {"median": statistics.median(held), "min": min(held), "max": max(held), "count": 2}
    assert summary["contact_s"] == pytest.approx(want)
    assert [t["contact_s"] for t in summary["trials"]] == [0.0, *held]
    md = (camp / "summary.md").read_text()
    row = next(ln for ln in md.splitlines() if ln.startswith("| First confirmed-contact interval"))
    cell = f"{statistics.median(held):.1f} ({min(held):.1f} to {max(held):.1f}) [2 of 3 trials]"
    assert row.split(" | ")[1] == cell, row
    from payload.trials.terminal import summary_terminal

    terminal = summary_terminal(summary).splitlines()  # what `trials run` prints: the count
    line = next(ln for ln in terminal if ln.strip().startswith("First confirmed-contact"))
    assert cell in line, line
    (fig,) = drawn
    ax = fig.axes[[a.get_title() for a in fig.axes].index("First confirmed-contact interval [s]")]
    dots = next(c for c in ax.collections if isinstance(c, PathCollection))
    assert sorted(dots.get_offsets()[:, 1]) == pytest.approx(sorted(held))
    assert ax.get_xticklabels()[0].get_text() == "this run\n(n = 2)"


def _drawn_campaign_figures(monkeypatch) -> list[Any]:
    """The campaign figures a summary writes from now on, as drawn (and still written)."""
    from payload.trials import campaign_figure

    drawn: list[Any] = []
    save = campaign_figure.save_figure

    def keep(fig, *rest):
        drawn.append(fig)
        return save(fig, *rest)

    monkeypatch.setattr(campaign_figure, "save_figure", keep)
    return drawn


def test_a_campaign_without_contact_draws_no_contact_interval(tmp_path, monkeypatch) -> None:
    """A new user's capped first campaign, no trial of which held a contact: its summary.md
    said "First confirmed-contact interval n/a (no confirmed contact)" but its figure drew
    that panel as "this run (n = 2)", both dots and the median bar at 0 s (each trial's
    metric is 0 without an interval). The panel is now empty, n = 0, as the RMS panel
    beside it is, each saying why; and the paper-literal column, where no trial has a
    contact either, says so of the paper-literal contact, not of the confirmed one."""
    from matplotlib.collections import LineCollection, PathCollection

    from payload.cli import main
    from payload.trials.campaign import trial_dir

    camp = tmp_path / "camp"
    confirmed = {"min_interval_s": CONFIRM_MIN_S, "max_gap_s": CONFIRM_MAX_GAP_S}
    for seed in (1, 2):
        fixture_synthetic_trial(seed, trial_dir(camp, seed), "none", **confirmed)
    drawn = _drawn_campaign_figures(monkeypatch)
    assert main(["trials", "summarize", str(camp)]) == 0
    md = (camp / "summary.md").read_text()
    row = next(ln for ln in md.splitlines() if ln.startswith("| First confirmed-contact interval"))
    assert row.split(" | ")[1:3] == [
        "n/a (no confirmed contact) [0 of 2 trials]",
        "n/a (no paper-literal contact) [0 of 2 trials]",
    ]
    (fig,) = drawn
    titles = [ax.get_title() for ax in fig.axes]
    rms = "RMS deviation in the body frame, eq. 5 [mm]"
    for panel in ("First confirmed-contact interval [s]", rms):
        ax = fig.axes[titles.index(panel)]
        dots = next(c for c in ax.collections if isinstance(c, PathCollection))
        assert len(dots.get_offsets()) == 0, panel
        bars = [c for c in ax.collections if isinstance(c, LineCollection)]
        assert len(bars) == 1, panel  # the paper's alone
        assert ax.get_xticklabels()[0].get_text() == "this run\n(n = 0)", panel
        said = [t.get_text() for t in ax.texts]  # and says why, as Fig. 3 does (it did not)
        assert said == ["no confirmed contact"], (panel, said)
    # the duration is known for both trials: drawn
    ax = fig.axes[titles.index("Teleoperation duration after calibration [s]")]
    assert ax.get_xticklabels()[0].get_text() == "this run\n(n = 2)"


def test_a_rescored_summary_names_its_own_contact_everywhere(tmp_path, monkeypatch) -> None:
    """Rescoring a campaign with the paper's definition (``--min-contact-s 0 --max-gap-s
    0``) wrote a summary whose header named that definition but whose contact-interval row,
    success paragraph and per-trial note still said "confirmed", and a figure that did not
    say how it was scored. Each now names the rescoring's contact; the campaign's own
    summary and figure, under the recorded (confirmed) definition, read as before."""
    from payload.cli import main
    from payload.trials.campaign import trial_dir

    camp = tmp_path / "camp"
    confirmed = {"min_interval_s": CONFIRM_MIN_S, "max_gap_s": CONFIRM_MAX_GAP_S}
    for seed in (4, 6):
        fixture_synthetic_trial(seed, trial_dir(camp, seed), **confirmed)
    drawn = _drawn_campaign_figures(monkeypatch)
    assert main(["trials", "summarize", str(camp)]) == 0
    rescore = ["--recompute", "--min-contact-s", "0", "--max-gap-s", "0"]
    assert main(["trials", "summarize", str(camp), *rescore]) == 0
    numbers = "(>= 0 s, gaps <= 0 s)"
    md = (camp / "summary.contact-min0s-gap0s.md").read_text()
    assert "confirmed" not in md.lower()
    assert f"\n| First contact interval {numbers} [s] | " in md
    assert f"the first continuous contact interval {numbers} carries it there" in md
    assert f"Per trial, contact {numbers}, then the paper-literal success" in md
    recorded = (camp / "summary.md").read_text()
    assert "\n| First confirmed-contact interval [s] | " in recorded
    assert "the first continuous confirmed-contact interval carries it there" in recorded
    assert "Per trial, confirmed contact, then the paper-literal success" in recorded
    from payload.trials.terminal import summary_terminal  # the terminal's words, the same

    rescored = json.loads((camp / "summary.contact-min0s-gap0s.json").read_text())
    terminal = summary_terminal(rescored)
    assert "confirmed" not in terminal.lower() and f"First contact interval {numbers}" in terminal
    ours, rescored = drawn
    said = " ".join(rescored.get_suptitle().split())
    assert f"2/2 succeeded, scored with contact {numbers} (paper 10/10)" in said, said
    panels = " ".join(" ".join(ax.get_title().split()) for ax in rescored.axes)
    assert "confirmed" not in panels and f"First contact interval {numbers} [s]" in panels
    assert "2/2 succeeded (paper 10/10)" in " ".join(ours.get_suptitle().split())
    assert ours.axes[-1].get_title() == "First confirmed-contact interval [s]"


def test_the_committed_campaign_summaries_follow_their_summary_json() -> None:
    """Each ``analyses/campaign/*/summary.md`` is what the summary's Markdown makes of the
    ``summary.json`` beside it (``payload trials summarize`` writes both from one summary),
    line for line."""
    from payload.trials.summary_markdown import summary_markdown

    paths = sorted((ROOT / "analyses" / "campaign").glob("*/summary.json"))
    assert len(paths) >= 6
    for path in paths:
        summary = json.loads(path.read_text(encoding="utf-8"))
        made = summary_markdown(summary, summary.get("title")).splitlines()
        kept = (path.parent / "summary.md").read_text(encoding="utf-8").splitlines()
        assert len(made) == len(kept), path
        for a, b in zip(made, kept, strict=True):
            assert a == b, (path, a, b)


def test_summary_of_trials_scored_without_literal_figures() -> None:
    """Older metrics.json files (no "literal"): paper-definition trials count as literal."""
    from payload.trials.campaign import summarize

    rows = [{"seed": 0, "success": True, "duration_s": 1.0, "contact_s": 0.5, "acquired": True}]
    s = summarize(rows)
    assert s["literal"]["success"] == 1 and s["literal"]["contact_s"]["median"] == 0.5
    rows[0]["min_interval_s"] = 0.5
    s = summarize(rows)
    assert s["literal"]["success"] == 0 and s["literal"]["contact_s"]["count"] == 0


def test_summary_of_no_scored_trial_claims_no_contact_definition() -> None:
    """A campaign whose every trial raised or was cut short (a Ctrl-C) scored nothing: its
    summary names no definition for the confirmed contact, rather than the paper's."""
    from payload.trials.campaign import summarize, summary_markdown

    cut = "log.mcap: cut short (never closed: the run was killed or crashed); not scored"
    s = summarize([{"seed": 5, "error": cut}, {"seed": 6, "error": cut}])
    assert "contact_definition" not in s
    md = summary_markdown(s)
    assert "Confirmed contact (the recorded one): none (no trial was scored). " in md
    assert "Paper-literal: the paper's: any single sample" in md


def test_a_rescoring_with_no_scored_trial_is_named_so(tmp_path: Path) -> None:
    """Rescoring a campaign none of whose trials can be scored (here a recording cut in
    half) writes its summary as ``contact-unscored``, not as a mix of definitions."""
    from payload.cli import main
    from payload.trials.campaign import run_campaign

    run_campaign(fixture_synthetic_trial, [4], tmp_path, workers=0, progress=False)
    log = tmp_path / "trial-0004" / "log.mcap"
    log.write_bytes(log.read_bytes()[: log.stat().st_size // 2])
    (tmp_path / "trial-0004" / "metrics.json").unlink()
    assert main(["trials", "summarize", str(tmp_path), "--max-gap-s", "0.1", "--json"]) == 0
    names = sorted(p.name for p in tmp_path.iterdir() if p.is_file())
    assert names == [
        "fig_campaign.contact-unscored.png",
        "summary.contact-unscored.json",
        "summary.contact-unscored.md",
    ]


def test_a_rescoring_as_recorded_writes_only_what_differs(tmp_path: Path, capsys) -> None:
    """``--recompute`` with the definition each trial was recorded with gives a trial's own
    ``metrics.json`` again: no tagged copy of it, nor of a summary that would equal the
    campaign's (nothing written, and said). A trial whose ``metrics.json`` no longer says
    what its recording scores to (here its RMS edited, as an older scoring would leave it)
    gets its rescoring beside it, and the tagged summary; the other trial does not."""
    from payload.cli import main
    from payload.trials.campaign import run_campaign

    run_campaign(fixture_synthetic_trial, [4, 6], tmp_path, workers=0, progress=False)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert main(["trials", "summarize", str(tmp_path), "--recompute", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["rescored_as_recorded"] == [4, 6] and out["n"] == 2
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    assert main(["trials", "summarize", str(tmp_path), "--recompute"]) == 0
    said = capsys.readouterr().out
    assert "rescored 2 trial(s)" in said and "nothing written" in said

    older = tmp_path / "trial-0006" / "metrics.json"
    kept = json.loads(older.read_text())
    older.write_text(json.dumps({**kept, "rms_mm": kept["rms_mm"] + 1.0}))
    assert main(["trials", "summarize", str(tmp_path), "--recompute"]) == 0
    said = capsys.readouterr().out
    assert "wrote the rescored metrics and figures of trial-0006, beside theirs" in said
    assert "1 trial(s) scored as their metrics.json says" in said
    tag = "contact-min0s-gap0s"  # the fixture's recorded definition: the paper's
    new = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob(f"*.{tag}.*"))
    assert new == [
        f"fig_campaign.{tag}.png", f"summary.{tag}.json", f"summary.{tag}.md",
        f"trial-0006/fig_ctb_body_frame.{tag}.png", f"trial-0006/fig_route.{tag}.png",
        f"trial-0006/metrics.{tag}.json",
    ]  # fmt: skip
    assert json.loads((tmp_path / "trial-0006" / f"metrics.{tag}.json").read_text())[
        "rms_mm"
    ] == pytest.approx(kept["rms_mm"])
    # the same again writes nothing, and says so (it said it wrote each trial's rescoring)
    assert main(["trials", "summarize", str(tmp_path), "--recompute"]) == 0
    said = capsys.readouterr().out
    assert "wrote" not in said, said
    assert "the rescorings of 1 trial(s)" in said and "1 trial(s) scored as their" in said

    # a trial scored before whose recording is gone is news, not "nothing written": its
    # row says so in the tagged summary; trial 6's tagged copy, there now, is kept equal
    older.write_text(json.dumps(kept))
    (tmp_path / "trial-0004" / "log.mcap").unlink()
    again = ["trials", "summarize", str(tmp_path), "--recompute", "--json"]
    assert main(again) == 2  # the tagged summary would change: not without --force
    assert "exists with different content" in capsys.readouterr().err
    assert main([*again, "--force"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["rescored_as_recorded"] == [] and out["errors"] == 1
    rows = json.loads((tmp_path / f"summary.{tag}.json").read_text())["trials"]
    assert [r["error"] for r in rows] == ["no log.mcap to rescore", None]


def test_summarize_folder_rebuilds_and_rescores(tmp_path: Path) -> None:
    from payload.trials.campaign import load_trial_results, run_campaign

    ran = run_campaign(fixture_synthetic_trial, [4, 6], tmp_path, workers=0, progress=False)
    (tmp_path / "trial-0006" / "metrics.json").unlink()
    loaded = load_trial_results(tmp_path)
    assert _metric_view(loaded) == _metric_view(ran)
    assert (tmp_path / "trial-0006" / "metrics.json").exists()  # rescored from log.mcap


# -- CLI -------------------------------------------------------------------------------
def _fake_runner(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """Stand in for the teleoperation runner (issue 6) with the fixture trial."""
    calls: list[dict[str, Any]] = []
    budgets: list[str] = []
    modelled: list[bool] = []

    def run_trial(
        seed: int,
        operator: str,
        replay: Path | None,
        out_dir: Path,
        retarget_budget: str | None = None,
        retarget_collisions: bool | None = None,
        project: object = None,
        **setup: Any,
    ) -> dict:
        calls.append({"seed": seed, "operator": operator, "replay": replay, **setup})
        budgets.append(retarget_budget)
        modelled.append(retarget_collisions)
        return {  # what the real runner resolves a left-out setting to
            **fixture_synthetic_trial(seed, out_dir),
            "retarget_budget": retarget_budget or "paper",
            "retarget_collisions": bool(retarget_collisions),
            "controller": setup.get("controller") or "paper",
            "controller_overrides": [],
        }

    module = types.ModuleType("payload.trials.runner")
    module.run_trial = run_trial  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "payload.trials.runner", module)
    module.budgets = budgets  # type: ignore[attr-defined]
    module.modelled = modelled  # type: ignore[attr-defined]
    return calls


def test_a_cap_before_the_calibrations_end_is_warned_of(tmp_path: Path, monkeypatch, capsys):
    """``--max-time`` at or under the calibration's length (its prompts' holds added up)
    leaves a trial with no teleoperation at all: a new user's
    ``--max-time 10`` gave empty trials without a word. Now one warning line; half a
    second more runs without one."""
    from payload.cli import main
    from payload.teleop.calibration import DEFAULT_STEPS

    calibration = sum(step.hold for step in DEFAULT_STEPS)
    _fake_runner(monkeypatch)
    run = ["trials", "run", "--n", "1", "--workers", "0", "--out", str(tmp_path / "c")]
    for argv, cap in (
        (["trial", "--out", str(tmp_path / "a")], calibration),
        (["trial", "--out", str(tmp_path / "b")], calibration + 0.5),
        (run, calibration - 2.0),
    ):
        assert main([*argv, "--max-time", f"{cap:g}", "--json"]) == 0
        err = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
        want = [f"payload: warning: --max-time {cap:g} s ends each session before the "
                f"operator's calibration does ({calibration:g} s): no teleoperation is "
                "recorded"]  # fmt: skip
        assert err == ([] if cap > calibration else want), err


def test_cli_trial_and_campaign(tmp_path: Path, monkeypatch, capsys) -> None:
    from payload.cli import main

    calls = _fake_runner(monkeypatch)
    assert main(["trial", "--seed", "2", "--out", str(tmp_path / "one"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["seed"] == 2 and out["success"] is True
    assert (tmp_path / "one" / "fig_route.png").exists()
    replay = tmp_path / "hands.mcap"
    replay.write_bytes(b"x")
    assert main(["trial", "--replay", str(replay), "--out", str(tmp_path / "r")]) == 0
    # a replay's seed and setup are left to the runner, which takes the recording's
    runner = sys.modules["payload.trials.runner"]
    assert calls[-1] == {"seed": None, "operator": "replay", "replay": replay}
    assert runner.budgets[-1] is None and runner.modelled[-1] is None  # type: ignore[attr-defined]
    capsys.readouterr()
    again = ["trial", "--replay", str(replay), "--out", str(tmp_path / "r2")]
    assert main([*again, "--ctb", "rigid", "--retarget-collisions"]) == 0
    # only what is given overrides the recording's
    assert calls[-1] == {"seed": None, "operator": "replay", "replay": replay, "ctb": "rigid"}
    assert runner.budgets[-1] is None and runner.modelled[-1] is True  # type: ignore[attr-defined]
    assert (
        "retargeting budget paper, self-collision modelled "
        "(given: ctb, retarget_collisions; the rest the recording's)\n"
    ) in capsys.readouterr().out
    # the earlier spelling, kept for one release: the same run, and one warning line
    off = ["trial", "--operator", "replay", str(replay), "--out", str(tmp_path / "r3")]
    capsys.readouterr()
    assert main([*off, "--no-retarget-collisions", "--retarget-budget", "converged"]) == 0
    assert runner.modelled[-1] is False and runner.budgets[-1] == "converged"  # type: ignore[attr-defined]
    assert calls[-1]["operator"] == "replay" and calls[-1]["replay"] == replay
    warning = capsys.readouterr().err.strip().splitlines()
    assert len(warning) == 1 and "--operator is deprecated" in warning[0]
    assert "--replay FILE" in warning[0]
    # its synthetic use is advised to give no option (not a recording to replay)
    assert main(["trial", "--operator", "synthetic", "--out", str(tmp_path / "s0")]) == 0
    warning = capsys.readouterr().err.strip().splitlines()
    assert len(warning) == 1 and "for the synthetic operator, no option" in warning[0], warning
    # a synthetic trial gets the defaults, spelled out
    assert main(["trial", "--out", str(tmp_path / "s")]) == 0
    assert calls[-1]["ctb"] == "single" and calls[-1]["propulsion"] == "nozzles"
    assert runner.budgets[-1] == "paper" and runner.modelled[-1] is False  # type: ignore[attr-defined]
    capsys.readouterr()
    assert (
        main(["trial", "--ctb", "rigid", "--propulsion", "box", "--out", str(tmp_path / "b")]) == 0
    )
    assert calls[-1]["ctb"] == "rigid" and calls[-1]["propulsion"] == "box"
    capsys.readouterr()

    camp = tmp_path / "camp"
    args = ["trials", "run", "--n", "3", "--seed", "1", "--workers", "0", "--out", str(camp)]
    assert main([*args, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["n"] == 3 and summary["seeds"] == [1, 2, 3]
    run = summary["run"]
    assert run["workers"] == 0 and run["scheduler"] is None
    trial_wall = sum(t["wall_s"] for t in summary["trials"])
    assert run["trial_wall_s"] == pytest.approx(trial_wall) and run["wall_s"] >= trial_wall
    assert "Ran serially in" in (camp / "summary.md").read_text()
    for key in ("duration_s", "net_displacement_m", "rms_mm", "peak_mm", "contact_s"):
        assert set(summary[key]) >= {"median", "min", "max"}
    assert main(["trials", "summarize", str(camp), "--json"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert {k: again[k] for k in ("n", "success", "rms_mm")} == {
        k: summary[k] for k in ("n", "success", "rms_mm")
    }
    assert main(["trials", "summarize", str(camp)]) == 0
    text = capsys.readouterr().out
    assert "| task success | 3/3 | 3/3 | 10/10 |" in text and "NOT the paper" not in text
    # rescoring with a relaxed contact definition writes beside the originals, named by
    # the definition, and says so; the originals stay byte for byte
    originals = {p: p.read_bytes() for p in camp.rglob("*") if p.is_file()}
    assert main(["trials", "summarize", str(camp), "--max-gap-s", "0.1", "--json"]) == 0
    relaxed = json.loads(capsys.readouterr().out)
    assert relaxed["contact_definition"] == {"min_interval_s": 0.0, "max_gap_s": 0.1}
    assert relaxed["run"] == summary["run"]  # how the campaign ran is kept
    assert {p: p.read_bytes() for p in originals} == originals
    tag = "contact-min0s-gap0.1s"
    rescored = json.loads((camp / "trial-0002" / f"metrics.{tag}.json").read_text())
    assert rescored["max_gap_s"] == 0.1
    assert (camp / "trial-0002" / f"fig_route.{tag}.png").is_file()
    assert "NOT the paper's definition" in (camp / f"summary.{tag}.md").read_text()
    assert "NOT the paper" not in (camp / "summary.md").read_text()
    # the rescoring's column names its own definition, not "confirmed contact"
    text = (camp / f"summary.{tag}.md").read_text()
    assert "| this campaign, contact (>= 0 s, gaps <= 0.1 s) |" in text, text
    assert "confirmed contact |" not in text
    assert json.loads((camp / f"summary.{tag}.json").read_text())["contact_definition"] == {
        "min_interval_s": 0.0,
        "max_gap_s": 0.1,
    }
    # the same rescoring again changes nothing; a campaign is never run over another
    assert main(["trials", "summarize", str(camp), "--max-gap-s", "0.1", "--json"]) == 0
    capsys.readouterr()
    assert main([*args, "--json"]) == 2
    assert "already holds a campaign" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in originals} == originals
    # --force replaces the campaign: its rescorings (which described the old one) go too
    assert sorted(p.name for p in camp.glob(f"*.{tag}.*")) == [
        f"fig_campaign.{tag}.png", f"summary.{tag}.json", f"summary.{tag}.md"
    ]  # fmt: skip
    assert main([*args, "--force", "--json"]) == 0
    capsys.readouterr()
    assert list(camp.glob(f"*.{tag}.*")) == [] and (camp / "summary.json").is_file()
    # a --force run of other seeds keeps the earlier trials (recordings) and says so
    other = ["trials", "run", "--n", "1", "--seed", "7", "--workers", "0", "--out", str(camp)]
    assert main([*other, "--force", "--json"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "trial-0001, trial-0002, trial-0003 from an earlier" in err[0], err
    assert json.loads((camp / "summary.json").read_text())["seeds"] == [7]
    assert sorted(p.name for p in camp.glob("trial-*")) == [
        "trial-0001", "trial-0002", "trial-0003", "trial-0007"
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["trial", "--replay", "/nonexistent/hands.mcap"], "--replay: /nonexistent/hands.mcap: no"),
        (["trial", "--replay", "a.mcap", "--operator", "synthetic"], "give one"),
        (["trial", "--seed", "-1"], "--seed must be >= 0"),
        (["trial", "--seed", str(2**63)], f"--seed must be at most {2**63 - 1} (2^63"),
        (
            ["trials", "run", "--n", "2", "--seed", str(2**63 - 1), "--out", "x"],
            f"--seed must be at most {2**63 - 2} for 2 trials (their seeds run to {2**63}",
        ),
        (["bench", "trial", "--seed", str(2**64)], f"--seed must be at most {2**63 - 1}"),
        (["trial", "--ctb", "soft"], "--ctb: expected one of single, rigid"),
        (["trial", "--ctb", "singel"], "got 'singel' (did you mean 'single'?)"),
        (["trials", "run", "--n", "2", "--ctb", "double", "--out", "x"], "--ctb: expected"),
        (["trials", "run", "--n", "0", "--out", "x"], "--n must be >= 1"),
        (["trials", "summarize", "/nonexistent/campaign"], "no such campaign folder"),
        (["trial", "--physics-dt", "0.0015"], "--physics-dt: the physics step 0.0015 s does"),
        (["trials", "run", "--n", "1", "--out", "x", "--physics-dt", "0"], "--physics-dt:"),
        (["bench", "trial", "--physics-dt", "-0.002"], "--physics-dt: the physics step must"),
        (["bench", "trial", "--repeat", "0"], "--repeat must be >= 1, got 0"),
        (["bench", "trial", "--repeat", "2", "--out", "x"], "--out keeps one trial's folder"),
    ],
)
def test_cli_bad_input_exits_2(argv: list[str], message: str, capsys) -> None:
    from payload.cli import main

    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    err = [ln for ln in lines if not ln.startswith("payload: warning: --operator is deprecated")]
    assert len(err) == 1 and message in err[0]


def test_a_physics_step_outside_the_validated_two_says_what_it_costs(capsys) -> None:
    """A usable --physics-dt that is neither the paper's 1 ms nor the validated 2 ms runs,
    with one warning: 0.1 ms is ten times the steps (slower, nothing else); 5 ms was never
    validated. The two validated steps say nothing."""
    from payload.trials.setup_options import _check_physics_dt

    for dt in (None, 0.001, 0.002):
        _check_physics_dt(dt)
    assert capsys.readouterr().err == ""
    _check_physics_dt(0.0001)
    _check_physics_dt(0.005)
    _check_physics_dt(0.00125)  # between the two, dividing 20 ms (16 steps): not validated
    slower, unvalidated, between = capsys.readouterr().err.splitlines()
    assert slower.startswith("payload: warning: --physics-dt 0.0001: 10 times the paper's 1 kHz")
    assert unvalidated.startswith("payload: warning: --physics-dt 0.005: not validated")
    assert between.startswith("payload: warning: --physics-dt 0.00125: not validated")


def test_cli_bench_trial_accounts_for_its_time(tmp_path: Path, capsys, fresh_checks) -> None:
    """The stages add up to the measured total; sizes are the file's; with no check stamps
    (``fresh_checks``) the run names the full self-checks it ran."""
    from conftest import running_environment

    from payload.cli import main

    out = tmp_path / "bench"
    start = time.perf_counter()
    assert main(["bench", "trial", "--seconds", "3", "--out", str(out), "--json"]) == 0
    outside = time.perf_counter() - start
    r = json.loads(capsys.readouterr().out)
    assert r["warm"] is False  # the default: a cold process's only run
    assert r["steps"] == 151 and r["sim_seconds"] == pytest.approx(3.02)
    assert set(r["breakdown"]) >= {"physics", "pipeline", "operator", "recording", "startup"}
    assert sum(r["breakdown"].values()) == pytest.approx(r["wall_seconds"], rel=1e-6)
    assert sum(r["breakdown_cpu"].values()) == pytest.approx(r["cpu_seconds"], rel=1e-6)
    assert all(v >= 0 for v in r["breakdown"].values()) and r["breakdown"]["physics"] > 0
    # the bench's clock against this one: it cannot have run longer than the call did
    assert 0 < r["wall_seconds"] <= outside
    assert r["realtime_factor"] >= r["sim_seconds"] / outside
    size = (out / "log.mcap").stat().st_size
    assert r["log_bytes_per_sim_minute"] == pytest.approx(size / (r["sim_seconds"] / 60))
    # mj_step alone: inside the physics stage, a control period's steps of 1 ms each
    assert 0 < r["mj_step_seconds"] < r["breakdown"]["physics"]
    physics_steps = round(CONTROL_DT / r["physics_dt"]) * r["steps"]
    assert r["mj_step_seconds"] / (r["mj_step_us"] * 1e-6) == pytest.approx(physics_steps)
    assert r["physics_only_realtime_factor"] == pytest.approx(
        r["sim_seconds"] / r["mj_step_seconds"]
    )
    # the physics floor is the summed mj_step time; the default step is the paper's 1 ms
    assert r["physics_dt"] == 0.001
    assert r["physics_floor_s"] == r["mj_step_seconds"]
    assert r["overhead_ratio"] == pytest.approx(r["wall_seconds"] / r["mj_step_seconds"])
    assert r["overhead_ratio"] > 1.0
    assert r["overhead_ratio_cpu"] == pytest.approx(r["cpu_seconds"] / r["mj_step_cpu_seconds"])
    # the kernels built for this trial ran compiled (a C compiler and numpy's OpenBLAS
    # here); 3 s end before the calibration, so the pipeline's are not built
    per_trial = {"vehicle controller", "thrusts", "station bound", "frame poses"}
    assert per_trial <= set(r["kernels"]), r["kernels"]
    assert all(r["kernels"][k] == "compiled" for k in per_trial), r["kernels"]
    assert r["environment"] == running_environment()  # what the figures were measured on
    # no stamps: the kernels each driver makes ran their full self-checks in the run, and
    # each is a library in the cache; the stamps they left make the next run's checks short
    from payload.cache import cache_dir

    built = {p.name.rsplit("_", 1)[0] for p in cache_dir().glob("*.so")}
    assert {"period", "readout"} <= set(r["full_checks"]) <= built, r["full_checks"]
    assert {p.name.split("_")[0] for p in fresh_checks.iterdir()} >= {"period", "readout"}


def test_cli_bench_trial_warm_measures_the_trials_second_run(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    """``--warm``: the same trial runs once first in the same process, untimed (no stage
    timer and no ``mj_step`` clock around it), into a temporary folder that is gone
    afterwards; the measured run is the second, into ``--out``, and it is the same trial
    (every metric the first run scored, over 13 s: past the calibration, so the pipeline's
    retargeters, kept between trials, solved in both); the text output says it was warm,
    and ``--repeat`` takes it to each fresh process."""
    import mujoco

    from payload.cli import main
    from payload.teleop.pipeline import TeleopPipeline
    from payload.trials import runner
    from payload.trials.bench import run_trial_bench_repeated

    runs: list[tuple[Path, dict, bool, int]] = []
    real, real_step, real_pipeline = runner.run_trial, mujoco.mj_step, TeleopPipeline.step
    solves = [0]

    def pipeline_step(self, *args, **kwargs):
        solves[0] += 1
        return real_pipeline(self, *args, **kwargs)

    def counted(seed, **kwargs):
        timed = mujoco.mj_step is not real_step  # the bench's clock wraps it
        solves[0] = 0
        metrics = real(seed, **kwargs)
        runs.append((Path(kwargs["out_dir"]), metrics, timed, solves[0]))
        return metrics

    monkeypatch.setattr(runner, "run_trial", counted)
    monkeypatch.setattr(TeleopPipeline, "step", pipeline_step)
    out = tmp_path / "bench"
    assert main(["bench", "trial", "--warm", "--seconds", "13", "--out", str(out), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["warm"] is True
    assert [o for o, *_ in runs][1:] == [out] and runs[0][0] != out
    assert [timed for *_, timed, _ in runs] == [False, True]
    assert runs[0][3] > 0 and runs[0][3] == runs[1][3]  # the pipeline ran in both
    assert not runs[0][0].exists() and (out / "log.mcap").is_file()
    same = ("out_dir", "provenance")
    first, second = ({k: v for k, v in m.items() if k not in same} for _, m, *_ in runs)
    assert first == second
    assert json.loads((out / "metrics.json").read_text())["steps"] == r["steps"]
    # the text output says it measured a warm run
    runs.clear()
    assert main(["bench", "trial", "--warm", "--seconds", "0.5"]) == 0
    assert len(runs) == 2 and "warm: the trial's second run" in capsys.readouterr().out
    # each fresh process of --repeat warms up too (the run reported is a child's)
    assert run_trial_bench_repeated(0, 1, max_time=0.5, warm=True)["warm"] is True


def test_bench_trial_interrupted_while_warming_up_says_nothing_was_kept(
    tmp_path: Path, monkeypatch
) -> None:
    """Ctrl-C in ``--warm``'s untimed first run: the recorder's "recording kept" would
    name a file in the bench's temporary folder, gone with it; the bench says instead that
    nothing was kept and ``--out`` was not written."""
    from payload.sim.driver import SimDriver
    from payload.trials.bench import run_trial_bench

    real = SimDriver.step
    calls, stop_at = [0], 20  # control steps of the first run, then Ctrl-C

    def interrupted(self, *args, **kwargs):
        calls[0] += 1
        if calls[0] == stop_at:
            raise KeyboardInterrupt
        return real(self, *args, **kwargs)

    monkeypatch.setattr(SimDriver, "step", interrupted)
    out = tmp_path / "bench"
    with pytest.raises(KeyboardInterrupt) as caught:
        run_trial_bench(0, out_dir=out, warm=True, max_time=1.0)
    notes = getattr(caught.value, "__notes__", [])
    assert len(notes) == 1 and "untimed first run" in notes[0], notes
    assert "--out not written" in notes[0] and not out.exists()
    assert calls[0] == stop_at  # interrupted in the first run: the measured one never began


def test_cli_bench_trial_repeated_reports_the_median_run(capsys) -> None:
    """`--repeat 3`: three runs, each in a fresh process, said as they end; the result is
    the run of the middle ratio, with each run's figures and the ratios' median and range
    (worked out here from the runs); a run that fails says which and why."""
    import statistics

    from payload.cli import main
    from payload.trials.bench import run_trial_bench_repeated

    assert main(["bench", "trial", "--repeat", "3", "--seconds", "1", "--json"]) == 0
    captured = capsys.readouterr()
    r = json.loads(captured.out)
    said = [ln for ln in captured.err.splitlines() if ln.startswith("bench run ")]
    assert [ln.split(":")[0] for ln in said] == [f"bench run {i} of 3" for i in (1, 2, 3)]
    assert r["repeat"] == 3 and len(r["runs"]) == 3
    ratios = [run["wall_seconds"] / run["physics_floor_s"] for run in r["runs"]]
    for run, ratio, line in zip(r["runs"], ratios, said):
        assert run["overhead_ratio"] == pytest.approx(ratio)
        assert len(run["load_average"]) == 3
        # each run's core speed beside its ratio: its floor over its physics steps
        physics_steps = round(CONTROL_DT / r["physics_dt"]) * r["steps"]
        assert run["physics_floor_s"] / (run["mj_step_us"] * 1e-6) == pytest.approx(physics_steps)
        assert f"mj_step {run['mj_step_us']:.1f} us a step" in line
    middle = sorted(ratios)[1]
    assert r["overhead_ratio"] == pytest.approx(middle)
    assert r["overhead_ratio_median"] == pytest.approx(statistics.median(ratios))
    assert (r["overhead_ratio_min"], r["overhead_ratio_max"]) == pytest.approx(
        (min(ratios), max(ratios))
    )
    # the median run's own figures come with it (a whole result, not a mix of runs)
    mine = next(run for run in r["runs"] if run["overhead_ratio"] == r["overhead_ratio"])
    assert mine["wall_seconds"] == r["wall_seconds"] and r["steps"] == 51
    with pytest.raises(RuntimeError, match=r"bench run 1 of 2 failed \(exit 1\): .*0\.0015"):
        run_trial_bench_repeated(0, 2, max_time=1.0, physics_dt=0.0015)


def test_cli_bench_trial_says_which_full_checks_it_ran(fresh_checks, capsys):
    """The text output names the run's full self-checks (none once their stamps exist),
    and ``--repeat`` says of each run whether it had any, as its JSON does."""
    from payload.cli import main

    assert main(["bench", "trial", "--seconds", "1"]) == 0
    first = [x for x in capsys.readouterr().out.splitlines() if "full kernel self-checks" in x]
    assert len(first) == 1 and "period" in first[0] and "readout" in first[0], first
    assert main(["bench", "trial", "--seconds", "1"]) == 0  # stamped now: short checks
    assert "full kernel self-checks" not in capsys.readouterr().out
    assert main(["bench", "trial", "--repeat", "2", "--seconds", "1", "--json"]) == 0
    captured = capsys.readouterr()
    runs = json.loads(captured.out)["runs"]
    said = [ln for ln in captured.err.splitlines() if ln.startswith("bench run ")]
    assert len(said) == len(runs) == 2
    for line, run in zip(said, runs):
        assert ("full self-checks" in line) == bool(run["full_checks"]), (line, run)


def test_cli_bench_trial_says_which_kernels_ran_in_numpy(tmp_path: Path, monkeypatch, capsys):
    from payload.cli import main

    monkeypatch.setenv("PAYLOAD_NATIVE", "0")
    assert main(["bench", "trial", "--seconds", "1", "--out", str(tmp_path / "b")]) == 0
    text = capsys.readouterr().out
    line = next(x for x in text.splitlines() if "compiled kernels" in x)
    assert "vehicle controller" in line and "thrusts" in line and "station bound" in line
    assert "in numpy" in line and "(PAYLOAD_NATIVE=0)" in line
    # and what it ran on, for comparing figures between machines
    from conftest import running_environment

    env = running_environment()
    ran = next(x for x in text.splitlines() if "ran on" in x)
    assert f"numpy {env['numpy']} (OpenBLAS kernels {env['openblas_core']})" in ran


def test_cli_bench_recorder(capsys) -> None:
    from payload.cli import main

    assert main(["bench", "recorder", "--seconds", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["steps"] == 100 and out["recorded_s"] == 2.0
    # ~230 numbers per step as JSON: far more than 1 kB, far less than 100 kB per step
    assert 1e3 * 100 / 1e6 < out["file_mb_per_min"] * 2 / 60 < 1e5 * 100 / 1e6
    assert 0 < out["write_us_median"] <= out["write_us_p99"]


# -- every step validated --------------------------------------------------------------
def _bad(msg: dict[str, Any], field: str, value: Any) -> dict[str, Any]:
    out = dict(msg)
    if value is _MISSING:
        del out[field]
    else:
        out[field] = value
    return out


_MISSING = object()
BAD_STEPS = [
    ("q_cmd", _MISSING, "q_cmd: missing"),
    ("q_cmd", [0.0] * 16, "q_cmd: expected 17 numbers, got a list of 16"),
    ("q_cmd", [0.0] * 16 + ["x"], "q_cmd: [16]: expected a number, got str"),
    ("q_left", [0.0] * 7 + [True], "q_left: [7]: expected a number, got bool"),
    ("left_joints", [[0.0] * 3] * 24 + [[0.0] * 2], "left_joints: [24]: expected 3 numbers"),
    ("ctb_pos", [0.0, math.inf, 0.0], "ctb_pos: [1]: expected a finite number, got inf"),
    ("phase", "flying", "phase: expected one of ['calibration'"),
    ("contact", 1, "contact: expected true or false, got int 1"),
    ("t", None, "t: expected a number, got null"),
]


@pytest.mark.parametrize(("field", "value", "message"), BAD_STEPS)
def test_check_step_names_step_field_and_expectation(field: str, value: Any, message: str) -> None:
    from payload.trials.stepcheck import StepError, check_step

    good = {"seq": 0, "wall_time": 0.0, **make_step(0.0).to_json_dict()}
    check_step(good, FIELD_SPECS, 0)
    with pytest.raises(StepError) as info:
        check_step(_bad(good, field, value), FIELD_SPECS, 57, "runs/x/log.mcap")
    assert str(info.value).startswith(f"runs/x/log.mcap: step 57: {message}"), str(info.value)


def _recording_with_bad_step(path: Path, field: str, value: Any, at: int = 30) -> None:
    """A recording with JSON steps (schema version 1, still read) whose step ``at`` (of
    60) carries a bad field; typed (protobuf) steps cannot carry most of these."""
    from mcap.writer import Writer

    from payload.trials.recorder import STEP_SCHEMA, STEP_SCHEMA_NAME, STEP_TOPIC

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="payload-workbench")
        sid = w.register_schema(
            name=STEP_SCHEMA_NAME, encoding="jsonschema", data=json.dumps(STEP_SCHEMA).encode()
        )
        cid = w.register_channel(topic=STEP_TOPIC, message_encoding="json", schema_id=sid)
        for k in range(60):
            msg = {"seq": k, "wall_time": 0.0, **make_step(k * DT).to_json_dict()}
            if k == at:
                msg = _bad(msg, field, value)
            w.add_message(
                channel_id=cid,
                log_time=k,
                publish_time=round(k * DT * 1e9),
                data=json.dumps(msg).encode(),
                sequence=k,
            )
        w.finish()


@pytest.mark.parametrize(("field", "value", "message"), BAD_STEPS[:3] + BAD_STEPS[5:7])
def test_a_bad_step_in_the_middle_of_a_recording_gives_one_line_and_exit_2(
    tmp_path: Path, field: str, value: Any, message: str, capsys
) -> None:
    from payload.cli import main

    path = tmp_path / "log.mcap"
    _recording_with_bad_step(path, field, value)
    with pytest.raises(RecordingError, match=f"step 30: {field}"):
        read_recording(path)
    assert main(["export", "lerobot", str(path), "--out", str(tmp_path / "ds")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    # the file's old schema is said first, as a warning; the error is one line
    warned = [ln for ln in lines if ln.startswith("payload: warning: ")]
    assert len(warned) == 1 and "schema version 1 (JSON steps)" in warned[0], lines
    err = [ln for ln in lines if ln not in warned]
    assert len(err) == 1 and f"{path}: step 30: {message}" in err[0], err
    assert not (tmp_path / "ds").exists()


BAD_METRICS = [
    ("rms_mm", "abc", "rms_mm: expected a number or null, got str 'abc'"),
    ("success", "false", "success: expected true or false, got str 'false'"),
    ("seed", "one", "seed: expected an integer >= 0 or null, got 'one'"),
    ("min_interval_s", "x", "min_interval_s: expected a number or null, got str 'x'"),
    ("final_module", 3, "final_module: expected text or null, got 3"),
    ("literal", {"success": 1}, "literal: success: expected true or false, got int 1"),
    ("success", None, "success: missing"),
]


@pytest.mark.parametrize(("field", "value", "message"), BAD_METRICS)
def test_a_bad_field_in_a_trials_metrics_gives_one_line_and_exit_2(
    tmp_path: Path, field: str, value: Any, message: str, capsys
) -> None:
    """A campaign's ``metrics.json`` with a field of the wrong kind (edited by hand, written
    by another tool): summarize and compare name the file and the field, exit 2, and write
    nothing (before: a traceback, or a string "false" counted as a success)."""
    from payload.cli import main

    camp = tmp_path / "camp"
    for seed in (0, 1):
        trial = camp / f"trial-{seed:04d}"
        trial.mkdir(parents=True)
        good = {"seed": seed, "success": True, "rms_mm": 30.0, "final_module": "node2"}
        (trial / "metrics.json").write_text(json.dumps(good))
    bad = camp / "trial-0001" / "metrics.json"
    data = json.loads(bad.read_text())
    data.pop(field) if value is None else data.update({field: value})
    bad.write_text(json.dumps(data))
    before = sorted(p.name for p in camp.rglob("*"))
    for argv in (["trials", "summarize", str(camp)], ["trials", "compare", str(camp), str(camp)]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{bad}: {message}" in err[0], err
    assert sorted(p.name for p in camp.rglob("*")) == before


def test_finish_trial_scores_both_contact_definitions(tmp_path: Path) -> None:
    from payload.trials.campaign import finish_trial
    from payload.trials.metrics import compute_metrics
    from payload.trials.recorder import read_recording

    fixture_synthetic_trial(3, tmp_path)
    result = finish_trial(
        tmp_path, tmp_path / "log.mcap", min_interval_s=0.5, max_gap_s=0.1, force=True
    )
    rec = read_recording(tmp_path / "log.mcap")
    literal = compute_metrics(rec).as_dict()
    literal.pop("criterion")
    assert result["literal"] == json.loads(json.dumps(literal))
    assert result["min_interval_s"] == 0.5 and result["literal"]["min_interval_s"] == 0.0
    assert json.loads((tmp_path / "metrics.json").read_text())["literal"] == result["literal"]


def test_cli_controller_profile_reaches_the_runner_and_the_summary(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    """``--controller safe`` on a campaign: the self-collision model on in every trial,
    the profile named in the summary and its table; a bad profile is refused (exit 2)."""
    from payload.cli import main

    calls = _fake_runner(monkeypatch)
    runner = sys.modules["payload.trials.runner"]
    camp = tmp_path / "camp"
    args = ["trials", "run", "--n", "2", "--workers", "0", "--out", str(camp)]
    assert main([*args, "--controller", "safe", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert runner.modelled == [True, True]  # type: ignore[attr-defined]
    assert runner.budgets == ["paper", "paper"]  # type: ignore[attr-defined]
    assert [c["controller"] for c in calls] == ["safe", "safe"]
    assert summary["controller"] == "safe" and summary["controller_overrides"] == []
    assert "Controller profile: safe" in (camp / "summary.md").read_text()
    with pytest.raises(SystemExit) as info:
        main(["trial", "--controller", "careful"])
    assert info.value.code == 2
    assert "invalid choice: 'careful'" in capsys.readouterr().err


def test_trial_setup_resolves_the_profile_and_names_the_overrides() -> None:
    from payload.errors import PayloadError
    from payload.trials.sources import trial_setup

    paper = trial_setup()
    assert (paper["controller"], paper["retarget_collisions"]) == ("paper", False)
    safe = trial_setup(controller="safe")
    assert safe["retarget_collisions"] is True and safe["controller_overrides"] == []
    off = trial_setup(controller="safe", retarget_collisions=False, retarget_budget="paper")
    assert off["retarget_collisions"] is False
    assert off["controller_overrides"] == ["retarget_collisions"]  # paper is safe's own
    assert trial_setup(**{k: off[k] for k in ("retarget_budget", "retarget_collisions",
                                              "controller")}) == off  # fmt: skip
    with pytest.raises(PayloadError, match="--controller: expected one of paper, safe"):
        trial_setup(controller="careful")


def test_cli_retarget_settings_reach_the_runner_and_the_summary(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    """``--retarget-budget`` and ``--retarget-collisions``: defaults on a trial, both given
    to a campaign, each reaching the runner, the summary and its table."""
    from payload.cli import main

    _fake_runner(monkeypatch)
    runner = sys.modules["payload.trials.runner"]
    assert main(["trial", "--out", str(tmp_path / "one"), "--json"]) == 0
    one = json.loads(capsys.readouterr().out)
    assert one["retarget_budget"] == "paper"  # the defaults
    assert one["retarget_collisions"] is False
    camp = tmp_path / "camp"
    args = ["trials", "run", "--n", "2", "--workers", "0", "--out", str(camp)]
    given = ["--retarget-budget", "converged", "--retarget-collisions"]
    assert main([*args, *given, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert runner.budgets == ["paper", "converged", "converged"]  # type: ignore[attr-defined]
    assert runner.modelled == [False, True, True]  # type: ignore[attr-defined]
    assert summary["retarget_budget"] == "converged"
    assert summary["retarget_collisions"] is True
    md = (camp / "summary.md").read_text()
    assert "retargeting budget converged, self-collision modelled)" in md
    assert "Retargeting budget: converged" in md
    assert "Self-collision modelled in the pair solves: yes" in md
    with pytest.raises(SystemExit) as exc:
        main(["trial", "--retarget-budget", "fast"])
    assert exc.value.code == 2


@pytest.mark.parametrize(
    ("values", "expected", "line"),
    [
        ([True, True], True, "yes"),
        ([False, False], False, "no"),
        ([True, False], [False, True], "mixed"),
        ([True, "true"], [None, True], "mixed"),  # a non-bool value is not taken as one
        ([True, None], [None, True], "mixed"),  # a trial that does not say
        ([None, None], None, None),  # trials from before the setting: nothing said
    ],
)
def test_summary_says_whether_self_collision_was_modelled(tmp_path, values, expected, line):
    from payload.trials.campaign import write_summary

    results = []
    for seed, value in enumerate(values):
        r = fixture_synthetic_trial(seed, tmp_path / f"t{seed}")
        if value is not None:
            r["retarget_collisions"] = value
        results.append(r)
    summary = write_summary(results, tmp_path / "camp")
    assert summary.get("retarget_collisions") == expected
    md = (tmp_path / "camp" / "summary.md").read_text()
    said = [x for x in md.splitlines() if x.startswith("Self-collision modelled")]
    if line is None:
        assert said == []
    else:
        assert said and said[0].startswith(f"Self-collision modelled in the pair solves: {line} ")


def test_campaign_prints_a_line_per_trial_then_a_headline_off_a_terminal(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    """Not on a terminal (captured stdout), ``trials run`` prints one line per finished
    trial as it finishes, then the headline (successes and medians, from the trials'
    own metrics.json, beside the paper's), the metric table, and leaves the definitions
    and the per-trial table to summary.md. Without --out it makes runs/campaign-0001,
    then campaign-0002. --json prints only the JSON object."""
    from payload.cli import main
    from payload.trials.definition import contact_words
    from payload.trials.summary import PAPER_RESULTS

    _fake_runner(monkeypatch)
    project = tmp_path / "proj"
    (project / "cad").mkdir(parents=True)
    (project / "cad" / "design.toml").write_text((ROOT / "cad" / "design.toml").read_text())
    argv = ["--project", str(project), "trials", "run", "--n", "3", "--seed", "4"]
    assert main([*argv, "--workers", "0"]) == 0
    lines = capsys.readouterr().out.splitlines()
    camp = project / "runs" / "campaign-0001"
    metrics = [
        json.loads((camp / f"trial-{s:04d}" / "metrics.json").read_text()) for s in (4, 5, 6)
    ]
    assert lines[0] == f"project: {project.resolve()}"
    assert lines[1].startswith("models: rebuilt ")  # a new project's models, built first
    del lines[1]
    for k, m in enumerate(metrics):  # one line per trial, in order, before the summary
        assert lines[1 + k].startswith(f"[{k + 1}/3] seed {4 + k}: ")
        assert f"RMS {m['rms_mm']:.1f} mm" in lines[1 + k]
    ok = sum(bool(m["success"]) for m in metrics)
    rms = float(np.median([m["rms_mm"] for m in metrics]))
    head = lines[4]
    # the contact the trials were scored with, from their metrics.json (the fake runner's
    # trials: the paper's definition, so not "confirmed")
    (definition,) = {(m["min_interval_s"], m["max_gap_s"]) for m in metrics}
    assert head.startswith(f"{ok}/3 succeeded ({contact_words(*definition).contact}"), head
    assert f"paper {PAPER_RESULTS['success']}/{PAPER_RESULTS['n']}" in head
    assert f"RMS median {rms:.1f} mm (paper {PAPER_RESULTS['rms_mm']['median']:.1f})" in head
    text = "\n".join(lines)
    assert "Contact definitions" not in text and "## Trials" not in text
    assert "Contact definitions" in (camp / "summary.md").read_text()
    assert f"wrote {camp / 'summary.md'}" in text
    assert main([*argv, "--workers", "0", "--json"]) == 0
    out = capsys.readouterr().out
    assert json.loads(out)["out_dir"] == str(project / "runs" / "campaign-0002")
    assert len(out.strip().splitlines()) == 1


def test_a_campaigns_environment_is_its_trials_own() -> None:
    """The campaign summary's environment is what its trials' processes reported: one when
    they agree, each distinct one (in order) when they do not, None when none reported."""
    from payload.trials.summary import trials_environment

    here = {"numpy": "2.4.6", "openblas_core": "SkylakeX"}
    there = {"numpy": "2.4.6", "openblas_core": "Haswell"}
    ran = [{"provenance": {"environment": e}} for e in (here, here, there, here)]
    assert trials_environment(ran[:2]) == here
    assert trials_environment(ran) == [here, there]
    assert trials_environment([{"error": "x"}, {"provenance": {}}]) is None
    assert trials_environment([{"error": "x"}, *ran[:1]]) == here


def test_a_trial_and_a_campaign_never_share_a_folder(tmp_path: Path, capsys) -> None:
    """A trial's ``--out`` holding a campaign, or a campaign's holding a trial, is refused
    with one line, ``--force`` or not (it replaces its own kind only); nothing written."""
    from payload.cli import main

    camp, trial, live = tmp_path / "campaign", tmp_path / "trial", tmp_path / "live"
    report = tmp_path / "report"  # a campaign's Markdown summary alone
    for folder in (camp, trial, live, report):
        folder.mkdir()
    (report / "summary.md").write_text("# a campaign")
    (camp / "summary.json").write_text("{}")
    (trial / "log.mcap").write_bytes(b"recorded")
    (live / "hands.jsonl").write_text("{}\n")  # a live session's hands, its recording lost
    runs = [
        (["trial", "--out", str(camp)], "already holds summary.json"),
        (["trial", "--out", str(camp), "--force"], "already holds summary.json"),
        (["trials", "run", "--n", "1", "--out", str(trial)], "already holds log.mcap"),
        (["trials", "run", "--n", "1", "--out", str(trial), "--force"], "already holds log"),
        (["trials", "run", "--n", "1", "--out", str(live), "--force"], "already holds hands"),
        (["trial", "--out", str(report), "--force"], "already holds summary.md"),
    ]
    for argv, message in runs:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
    assert sorted(p.name for p in camp.iterdir()) == ["summary.json"]
    assert sorted(p.name for p in trial.iterdir()) == ["log.mcap"]
    assert (trial / "log.mcap").read_bytes() == b"recorded"
    assert sorted(p.name for p in live.iterdir()) == ["hands.jsonl"]
    assert sorted(p.name for p in report.iterdir()) == ["summary.md"]


def test_a_rescorings_files_are_tagged_before_their_suffix() -> None:
    """``folders.tagged``: the contact definition's tag goes between a file's stem and
    its suffix (the names ``trials summarize --max-gap-s`` writes, spelled out here); no
    tag leaves the name as it is."""
    from payload.folders import METRICS, SUMMARY_TEXT, tagged

    tag = "contact-min0s-gap0.1s"
    assert tagged(METRICS, tag) == "metrics.contact-min0s-gap0.1s.json"
    assert tagged(SUMMARY_TEXT, tag) == "summary.contact-min0s-gap0.1s.md"
    assert tagged("fig_route.png", tag) == "fig_route.contact-min0s-gap0.1s.png"
    assert tagged(METRICS, None) == tagged(METRICS, "") == "metrics.json"


def test_a_campaign_whose_worker_died_still_gets_its_summary(tmp_path: Path) -> None:
    """A trial lost with its worker (no result, no wall time: ``wall_s`` None) is a row of
    the summary, which is written (JSON refuses a NaN wall time)."""
    from payload.trials.summary import write_summary

    ok = json.loads(
        (Path(__file__).parents[1] / "analyses/campaign/single/summary.json").read_text()
    )["trials"][0]
    lost = {"seed": 1, "out_dir": str(tmp_path / "trial-0001"), "wall_s": None,
            "error": "KilledWorker: the worker died"}  # fmt: skip
    summary = write_summary([{**ok, "out_dir": str(tmp_path / "trial-0000")}, lost], tmp_path)
    written = json.loads((tmp_path / "summary.json").read_text())
    assert written["n"] == summary["n"] == 2
    assert [t["error"] for t in written["trials"]] == [None, lost["error"]]


def _dying_trial(seed: int, out_dir: Path) -> dict[str, Any]:
    """A trial whose worker process dies under it (seed 1): nothing the trial's own
    ``except`` can catch."""
    if seed == 1:
        os._exit(3)
    return {"success": True, "duration_s": 10.0 + seed, "rms_mm": None}


def test_a_campaign_whose_worker_process_dies_keeps_the_other_trial(tmp_path: Path) -> None:
    """A Dask worker process that dies during a trial (the scheduler allowed no retry
    here): that trial is a row with Dask's error and no wall time, the trial on the other
    worker stands with its own, and the campaign's summary is written (JSON has no NaN).
    Two trials on two workers: each worker gets one, so the dead worker held no other."""
    import dask
    import distributed  # noqa: F401  (its defaults loaded first: leaving the set keeps them)

    from payload.trials.campaign import run_campaign
    from payload.trials.summary import write_summary

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        results = run_campaign(_dying_trial, [0, 1], tmp_path, workers=2, progress=False)
    assert dask.config.get("distributed.comm.timeouts.connect") is not None
    kept, lost = results
    assert lost["seed"] == 1 and lost["wall_s"] is None, lost
    assert lost["error"].startswith("KilledWorker"), lost
    assert kept["error"] is None and kept["wall_s"] > 0 and kept["success"] is True
    write_summary(results, tmp_path)
    written = json.loads((tmp_path / "summary.json").read_text())
    assert (written["n"], written["success"], written["errors"]) == (2, 1, 1)
    assert [t["wall_s"] for t in written["trials"]][1] is None


def test_summarizing_trials_with_no_campaign_summary_keeps_their_provenance(
    tmp_path: Path, capsys
) -> None:
    """``trials summarize`` of trial folders that no campaign summarized before writes the
    provenance the trials themselves recorded (design, commit, environment), as every
    summary has one."""
    from payload.cli import main
    from payload.trials.runner import run_trial

    camp = tmp_path / "campaign"
    run_trial(0, out_dir=camp / "trial-0000", max_time=2.0)
    own = json.loads((camp / "trial-0000" / "metrics.json").read_text())["provenance"]
    assert main(["trials", "summarize", str(camp), "--json"]) == 0
    capsys.readouterr()
    prov = json.loads((camp / "summary.json").read_text())["provenance"]
    assert prov["design_sha256"] == own["design_sha256"]
    assert prov["environment"] == own["environment"]


@pytest.mark.parametrize("address", ["nonsense", "foo://127.0.0.1:1", "tcp://:notaport"])
def test_a_scheduler_that_is_not_an_address_is_one_line_and_leaves_no_folder(
    tmp_path: Path, address: str, capsys
) -> None:
    """``--scheduler`` that Dask cannot parse: one line naming it, exit 2 (was a ValueError
    traceback), for a campaign and a sweep; the campaign's folder it made for nothing is
    gone again, a folder the user made is kept."""
    from payload.cli import main

    for argv in (
        ["trials", "run", "--n", "1", "--out", str(tmp_path / "camp")],
        ["sweep", "--set", "rail.travel=0.04", "--out", str(tmp_path / "sweep")],
    ):
        assert main([*argv, "--scheduler", address]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"--scheduler {address}: not a Dask scheduler address" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    # nor a numbered default folder in the project (no --out)
    project = tmp_path / "project"
    assert main(["new", str(project)]) == 0
    for argv in (["trials", "run", "--n", "1"], ["sweep", "--set", "rail.travel=0.04"]):
        assert main([*argv, "--project", str(project), "--scheduler", address]) == 2
        capsys.readouterr()
    assert not (project / "runs").exists() or not any((project / "runs").iterdir())
    shutil.rmtree(project)
    (tmp_path / "mine").mkdir()
    assert main(["trials", "run", "--n", "1", "--out", str(tmp_path / "mine"), "--scheduler",
                 address]) == 2  # fmt: skip
    assert (tmp_path / "mine").is_dir()


def _drawn_zones(path: Path) -> list[tuple[float, ...]]:
    """The zone boxes a recording's /safety/keepin channel draws (centre and size, from the
    filter the run had), sorted: what the vehicle was kept in and out of."""
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
    from mcap.reader import make_reader

    from payload.trials.safety import KEEPIN_TOPIC

    with open(path, "rb") as f:
        first = next(iter(make_reader(f).iter_messages(topics=[KEEPIN_TOPIC])))
    cubes = SceneUpdate.FromString(first[2].data).entities[0].cubes
    return sorted(
        tuple(round(v, 6) for v in (c.pose.position.x, c.pose.position.y, c.pose.position.z,
                                    c.size.x, c.size.y, c.size.z))
        for c in cubes
    )  # fmt: skip


def _zones_trial(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A short ``safe`` trial run with a keep-out box across Kibo (``--zones keepout.json``):
    ``(its folder, keepout.json, other.json)`` (another keep-out box)."""
    from payload.sim.zones import StationZones, station_zones
    from payload.trials.runner import run_trial

    keepout, other = tmp_path / "keepout.json", tmp_path / "other.json"
    station_zones(keepout=[((1.2, 5.6, -0.9), (1.8, 5.9, 0.9))]).write(keepout)
    station_zones(keepout=[((1.0, 4.0, -0.5), (2.0, 4.5, 0.5))]).write(other)
    src = tmp_path / "src"
    run_trial(4, out_dir=src, max_time=0.5, controller="safe", zones=StationZones.read(keepout))
    return src, keepout, other


def test_a_trial_records_the_zones_it_ran(tmp_path):
    """``--zones`` was not recorded: neither the recording's metadata nor ``metrics.json``
    said a keep-out box had stopped the vehicle. Both hold the zones as data (the file's
    Astrobee zone objects) and the file's name."""
    from payload.trials.runner import run_trial
    from payload.trials.sources import load_replay

    src, keepout, _ = _zones_trial(tmp_path)
    for record in (
        load_replay(src / "log.mcap")[0]["meta"],
        json.loads((src / "metrics.json").read_text()),
    ):
        assert record["zones"] == json.loads(keepout.read_text()), record.get("zones")
        assert record["zones_file"] == str(keepout)
    station = tmp_path / "station"
    run_trial(4, out_dir=station, max_time=0.5, controller="safe")  # the station's: null
    metrics = json.loads((station / "metrics.json").read_text())
    assert (metrics["zones"], metrics["zones_file"]) == (None, None)


def test_a_replay_runs_its_recordings_zones_unless_given_others(tmp_path, capsys):
    """A replay ran the station's zones while saying it ran the recording's setup (a
    keep-out box across Kibo stopped the trial; its replay flew through it). Without
    ``--zones`` it runs the recording's (the filter's boxes, drawn on /safety/keepin, are
    the file's, even with the file gone), with ``--zones`` the given ones; the setup line
    names them."""
    from payload.cli import main
    from payload.sim.zones import StationZones
    from payload.trials.runner import run_trial

    src, keepout, other = _zones_trial(tmp_path)
    drawn = _drawn_zones(src / "log.mcap")
    assert len(drawn) == 4 and (1.5, 5.75, 0.0, 0.6, 0.3, 1.8) in drawn
    keepout.unlink()  # the recording's zones are its own: the file may go
    capsys.readouterr()
    same = tmp_path / "same"
    argv = ["trial", "--replay", str(src / "log.mcap"), "--max-time", "0.5", "--out", str(same)]
    assert main(argv) == 0
    assert _drawn_zones(same / "log.mcap") == drawn
    setup = [x for x in capsys.readouterr().out.splitlines() if "setup:" in x]
    assert f"zones {keepout} (3 keep-in, 1 keep-out boxes) (the recording's)" in setup[0], setup

    given = tmp_path / "given"
    run_trial(None, "replay", src / "log.mcap", given, max_time=0.5,
              zones=StationZones.read(other))  # fmt: skip
    assert (1.5, 4.25, 0.0, 1.0, 0.5, 1.0) in _drawn_zones(given / "log.mcap")
    assert len(_drawn_zones(given / "log.mcap")) == 4
    assert (1.5, 5.75, 0.0, 0.6, 0.3, 1.8) not in _drawn_zones(given / "log.mcap")


def test_hw_run_keeps_the_vehicle_in_its_source_trials_zones(tmp_path, capsys):
    """``payload hw run`` of a trial run with ``--zones`` (on the emulated bus): its base
    filter runs the recording's zones, drawn on /safety/keepin as the source's were, and
    records them (data and file name) in its metrics; its setup line names them."""
    from firmware_interface.options import EMULATOR_LATENCY_MS
    from payload.cli import main

    src, keepout, _ = _zones_trial(tmp_path)
    out = tmp_path / "hw"
    argv = ["hw", "run", "--emulator", "--replay", str(src / "log.mcap"), "--out", str(out),
            "--no-pace", "--latency-ms", f"{EMULATOR_LATENCY_MS:g}"]  # fmt: skip
    assert main(argv) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["base_filter"] is True  # hw run's default profile, safe
    assert metrics["zones"] == json.loads(keepout.read_text())
    assert metrics["zones_file"] == str(keepout)
    assert _drawn_zones(out / "log.mcap") == _drawn_zones(src / "log.mcap")
    setup = [x for x in capsys.readouterr().out.splitlines() if "setup:" in x]
    assert f"zones {keepout} (3 keep-in, 1 keep-out boxes)" in setup[0], setup


def test_a_link_delay_on_some_trials_only_is_said_to_differ() -> None:
    """Trials with a delayed link and trials without were summarised as if the campaign
    had the delay (a recorded null was taken as "not recorded"); the summary says they
    differ, and a campaign without any delay says none."""
    from payload.trials.campaign import summarize, summary_markdown

    base = {"success": True, "acquired": True, "station_contacts": 0, "base_filter": True}
    rows = [{**base, "seed": 0, "link_delay": [1.0, 0.1]}, {**base, "seed": 1, "link_delay": None}]
    s = summarize(rows)
    assert s["station"]["link_delay"] == {"mixed": ["None", "[1.0, 0.1]"]}
    assert "link delay (delay, jitter) differs between the trials: none, [1.0, 0.1] s" in (
        summary_markdown(s)
    )
    same = summarize([{**r, "link_delay": None} for r in rows])
    assert same["station"]["link_delay"] is None
    assert "link delay" not in summary_markdown(same)
    delayed = summarize([{**r, "link_delay": [1.0, 0.1]} for r in rows])
    assert "link delay (delay, jitter) [1.0, 0.1] s." in summary_markdown(delayed)


def test_a_campaign_summary_names_the_zones_its_trials_ran() -> None:
    """The summary's station part names the zones the filtered trials ran (the station's, or
    a zones file's with its box counts, counted here from the boxes given), says when they
    differ, and says nothing for trials without the filter or recorded before the zones."""
    from payload.trials.campaign import summarize
    from payload.trials.summary_markdown import summary_markdown

    def row(seed: int, **extra: Any) -> dict[str, Any]:
        return {"seed": seed, "success": True, "station_contacts": 0, **extra}

    box = {"position": [0, 0, 0], "orientation": [1, 0, 0, 0], "size": [1, 1, 1]}
    mine = [{"safe": True, "sequence": [box, box]}, {"safe": False, "sequence": [box]}]
    station = [row(0, base_filter=True, zones=None), row(1, base_filter=True, zones=None)]
    s = summarize(station)
    assert s["station"]["zones"] == "the station's"
    assert "base filter on (zones: the station's)" in summary_markdown(s)
    both = summarize([*station, row(2, base_filter=True, zones=mine, zones_file="lab.json")])
    assert both["station"]["zones"] == {
        "mixed": ["lab.json (2 keep-in, 1 keep-out boxes)", "the station's"]
    }
    assert "zones differ between the trials: lab.json (2 keep-in" in summary_markdown(both)
    for rows in ([row(0, base_filter=False, zones=None)], [row(0, base_filter=True)]):
        assert "zones" not in summarize(rows)["station"]
