"""The real trial runner (simulator + teleop pipeline + recorder): reproducibility.

Short trials (20 s of simulated time: calibration and the start of the acquisition) keep
these tests quick while exercising every part a full trial uses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from payload.trials.campaign import run_campaign, trial_dir
from payload.trials.recorder import read_recording
from payload.trials.runner import run_trial

SHORT = 20.0

FIELDS = (
    "q_cmd",
    "twist_cmd",
    "q_meas",
    "astrobee_pos",
    "ctb_pos",
    "contact",
    "left_joints",
    "right_joints",
)


def _short_trial(seed: int, out_dir: Path) -> dict:
    return run_trial(seed, out_dir=out_dir, max_time=SHORT)


def test_a_replayed_trial_reproduces_the_recorded_trial_bit_for_bit(tmp_path):
    first = tmp_path / "synthetic"
    run_trial(5, out_dir=first, max_time=SHORT)
    again = tmp_path / "replay"
    run_trial(5, operator="replay", replay=first / "log.mcap", out_dir=again)
    a, b = read_recording(first / "log.mcap"), read_recording(again / "log.mcap")
    # compact: the recording (steps, hand frames, Foxglove channels) under 2 MB a minute
    size = (first / "log.mcap").stat().st_size
    assert size / (len(a) * 0.02 / 60) < 2e6
    assert len(a.t) == len(b.t) > 0.9 * SHORT / 0.02
    for name in FIELDS:  # untracked hand joints are NaN: equal to NaN
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name


def test_a_dask_campaign_of_real_trials_matches_the_serial_run(tmp_path):
    seeds = [1, 2]
    serial = run_campaign(_short_trial, seeds, tmp_path / "serial", workers=0, progress=False)
    dask = run_campaign(_short_trial, seeds, tmp_path / "dask", workers=2, progress=False)
    assert [r["error"] for r in serial + dask] == [None] * 4
    for seed in seeds:
        a = read_recording(trial_dir(tmp_path / "serial", seed) / "log.mcap")
        b = read_recording(trial_dir(tmp_path / "dask", seed) / "log.mcap")
        for name in FIELDS:
            assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name
