"""The scripts in examples/ run as they are, print what an independent computation gives,
and the README's snippets are the scripts' own lines."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT

from payload.design import FINGER_JOINTS, build_tree
from payload.design.vehicle import DEFAULT_FLIGHT_MODE, FLIGHT_MODES
from payload.rotations import quat_to_matrix

EXAMPLES = ROOT / "examples"


def run_example(name: str) -> dict:
    res = subprocess.run(
        [sys.executable, str(EXAMPLES / name)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout)


def code_lines(text: str) -> list[str]:
    return [line.rstrip() for line in text.splitlines() if line.strip()]


PAGES = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").glob("*.md") if p.name != "cli.md")]


def _docs_text() -> str:
    return "\n".join(p.read_text() for p in PAGES)


def readme_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", _docs_text(), flags=re.S)


@pytest.mark.parametrize("name", ["retarget_pair.py", "simulate_ctb.py", "read_recording.py"])
def test_readme_snippet_is_a_run_of_the_examples_lines(name):
    script = code_lines((EXAMPLES / name).read_text())
    cited = [b for b in readme_blocks() if f"examples/{name}" in _after(b)]
    assert len(cited) == 1, f"the README shows no snippet of examples/{name}"
    block = code_lines(cited[0])
    starts = [i for i, line in enumerate(script) if line == block[0]]
    assert any(script[i : i + len(block)] == block for i in starts), name


def _after(block: str) -> str:
    """The docs' text just after a snippet (where it names its example)."""
    text = _docs_text()
    end = text.index(block) + len(block)
    return text[end : end + 300]


def test_every_readme_python_snippet_has_an_example():
    for block in readme_blocks():
        assert re.search(r"examples/\w+\.py", _after(block)), block[:60]


def test_retarget_example_against_the_calibration_formula_and_the_trees_kinematics(design):
    out = run_example("retarget_pair.py")
    # opening alpha = (l_h - l_pinch) / (l_open - l_pinch) of the script's 15, 90 and 50 mm
    alpha = (0.050 - 0.015) / (0.090 - 0.015)
    assert out["opening"] == pytest.approx(alpha, abs=1e-12)
    # the pair's range: pads touching, and the committed reach report's maximum
    reach = json.loads((ROOT / "analyses" / "reach.json").read_text())
    assert out["span_min_m"] == pytest.approx(2 * design.finger.pad.radius, abs=1e-12)
    assert out["span_max_m"] * 1e3 == pytest.approx(reach["pairs"]["L"]["span_max_mm"], abs=0.005)
    lo, hi = out["span_min_m"], out["span_max_m"]
    assert out["target_span_m"] == pytest.approx(lo + alpha * (hi - lo), abs=1e-12)
    # the solved joints: inside the limits, and their span by the tree's own kinematics
    tree = build_tree(design)
    q = dict(zip(out["joints"], out["q"]))
    assert set(q) == {f"{f}_{j}" for f in "AC" for j in FINGER_JOINTS}
    for name, v in q.items():
        joint = tree.joint_map[name]
        assert joint.lower - 1e-12 <= v <= joint.upper + 1e-12
    tips = tree.frame_positions(q)
    span = float(np.linalg.norm(tips["C_tip"] - tips["A_tip"]))
    assert out["span_m"] == pytest.approx(span, abs=1e-9)
    assert abs(span - out["target_span_m"]) < 1e-3


def test_simulate_example_velocities_against_finite_differences_and_the_flight_mode():
    out = run_example("simulate_ctb.py")
    s = out["samples"]
    t = np.array([x["time"] for x in s])
    p = np.array([x["position"] for x in s])
    v = np.array([x["body_velocity"] for x in s])
    assert np.allclose(np.diff(t), 0.5, atol=1e-9) and len(s) == 13
    # world velocity: central differences of the positions against the rotated body velocity
    for k in range(1, len(s) - 1):
        fd = (p[k + 1] - p[k - 1]) / (t[k + 1] - t[k - 1])
        world = quat_to_matrix(np.array(s[k]["quaternion"])) @ v[k]
        assert np.abs(fd - world).max() < 2e-4, t[k]
    # forward, never beyond the request, accelerating within the nominal flight mode
    speed = v[:, 0]
    assert np.all(np.diff(speed) > 0) and speed.max() <= out["commanded_speed"] + 1e-6
    accel = np.diff(np.concatenate([[0.0], speed])) / 0.5
    assert accel.max() <= FLIGHT_MODES[DEFAULT_FLIGHT_MODE].accel + 1e-6


def test_read_recording_example_against_the_files_own_messages(tmp_path):
    """examples/read_recording.py on a 1 s trial: its step count is the step channel's
    message count (read with mcap, record by record), every 10 Hz Foxglove joint state is
    a step's measured joints by name (within half the viewer's grid, on which that channel
    keeps them, and the step channel's 10 nm grid), and the safety channel has a record a
    step."""
    from mcap.stream_reader import StreamReader

    from payload.design import MANIPULATION_JOINTS
    from payload.trials.foxglove import VIEW_RESOLUTION
    from payload.trials.runner import run_trial

    log = tmp_path / "t" / "log.mcap"
    run_trial(0, out_dir=log.parent, force=True, max_time=1.0)
    res = subprocess.run(
        [sys.executable, str(EXAMPLES / "read_recording.py"), str(log)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    channels, steps = {}, 0
    for record in StreamReader(str(log)).records:
        if type(record).__name__ == "Channel":
            channels[record.id] = record.topic
        elif type(record).__name__ == "Message":
            steps += channels[record.channel_id] == "/trial/step"
    assert out["steps"] == steps > 40 and out["seed"] == 0 and out["complete"] is True
    q = np.array(out["q_meas"])
    assert q.shape == (steps, len(MANIPULATION_JOINTS))
    assert len(out["measured"]) >= steps // 5 - 1
    for state in out["measured"]:
        row = np.array([state[name] for name in MANIPULATION_JOINTS])
        off = np.abs(q - row).max(axis=1).min()
        assert off <= VIEW_RESOLUTION / 2 + 1e-8, f"a joint state no step has ({off})"
    assert len(out["safety"]) == steps and all("station_clearance_m" in r for r in out["safety"])
