"""The same replayed hand session through the same 50 Hz loop on SimDriver and on the
emulated hardware (DynamixelDriver), and ``payload hw run`` recording it as a trial."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import band_ticks

from firmware_interface.control_table import BY_NAME, decode
from firmware_interface.deployment import move_to_home
from firmware_interface.driver import DynamixelDriver
from firmware_interface.emulator import EmulatorProcess
from firmware_interface.options import EMULATOR_LATENCY_MS as LAT  # [ms] reply allowance
from firmware_interface.run import HardwareInTheLoop, replay_session
from firmware_interface.servo_map import load_servo_map
from payload.design.params import load_design
from payload.schema import CONTROL_DT
from payload.sim.driver import SimDriver
from payload.teleop.calibration import CalibrationProcedure
from payload.teleop.loop import ARM_AFTER_STEPS
from payload.teleop.operator import OperatorPlan, OperatorTraits, SyntheticOperator, WorldView
from payload.teleop.replay import HandRecordingWriter, read_hand_recording

EXTRA_S = 1.0  # teleoperation after the calibration prompts [s]


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A recorded hand session: the calibration prompts, then a second of teleoperation."""
    path = tmp_path_factory.mktemp("hands") / "hands.jsonl"
    proc = CalibrationProcedure()
    plan = OperatorPlan(route=np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]]))
    traits = OperatorTraits(tremor_amp=0.0, noise=0.0, dropout_rate=0.0, reaction=0.2)
    op = SyntheticOperator(plan, 5, proc, traits)
    t, end = 0.0, None
    with HandRecordingWriter(path) as out:
        while end is None or t < end:
            world = WorldView(t, np.zeros(3), np.eye(3), np.zeros(3), np.zeros(3), False)
            fr = op.act(world)
            out.write(fr)
            proc.step(fr)
            if proc.done and end is None:
                end = t + EXTRA_S
            t += CONTROL_DT
    return path


def test_the_payload_deploys_as_the_envelope_check_does(monkeypatch, caplog):
    """``move_to_home`` sent the home posture at once: every servo at its own pace, the
    fingers unfolding while the stage went down through the bays, a motion the envelope
    check never looked at. From the stowed posture the payload powers up in (the
    emulator's too: it powered up at home) it lowers the stage with the fingers and the
    rail held (their goals, and within their dead bands their measured positions), then
    steps their goals at 50 Hz along the straight line in joint space to home (the
    check's unfolding), no joint's step faster than half its no-load speed (the packaged
    map's rail pinion sits on the horn), paced, and rests at home; the command guard,
    whose capsule margins flag the stowed posture, refuses none of it."""
    import logging
    import time

    from payload.envelope.stowed_fit import stowed_fit_failures

    design, smap = load_design(), load_servo_map()
    # what `hw run` asks first: the design's deployment clear (kept: move_to_home asks again)
    assert stowed_fit_failures(design.source) == []
    sent, seen = [], []
    with EmulatorProcess() as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            drv.bring_up()
            start = drv.read()
            guard = drv.guard
            send, read = drv.send, drv.read
            monkeypatch.setattr(
                drv, "send", lambda c: (sent.append((time.monotonic(), c)), send(c))[1]
            )
            monkeypatch.setattr(drv, "read", lambda: seen.append(read()) or seen[-1])
            with caplog.at_level(logging.WARNING):
                end = move_to_home(drv, cleared=True)  # asked above, before the bring-up
            restored, last_safe = drv.guard, guard._safe
    assert not caplog.records, caplog.text
    tol = np.array([s.units_per_tick * band_ticks(s.joint) for s in smap.servos])
    # the guard, bypassed on the checked path, is back, its last safe command home
    assert restored is guard and np.all(np.abs(last_safe - np.append(end.q, end.deploy)) <= 1e-9)
    stowed = [*design.stowed.finger] * 4 + [design.stowed.rail]
    half_tick = np.array([s.units_per_tick for s in smap.servos[:-1]]) / 2
    assert np.all(np.abs(start.q - stowed) <= half_tick)  # powered up stowed, curled
    home = np.append(end.q, end.deploy)
    held = [k for k, (_, c) in enumerate(sent) if np.array_equal(c.q, start.q)]
    assert held and held == list(range(len(held))) and len(held) < len(sent)  # 1, then 2
    for state in seen[1 : len(held) + 1]:  # (seen[0]: its first look) the stage goes down
        assert np.all(np.abs(state.q - start.q) <= tol[:-1]), np.abs(state.q - start.q)
    assert abs(seen[len(held)].deploy - design.home.stage) <= tol[-1]
    down = seen[len(held)].q
    ramp = np.array([c.q for _, c in sent[len(held) :]])
    goal = ramp[-1]
    assert np.abs(goal - down)[:16].max() > 1.0  # the fingers unfold
    s = (ramp - down) @ (goal - down) / ((goal - down) @ (goal - down))
    assert np.allclose(ramp, down + np.outer(s, goal - down), atol=1e-12)  # on the line
    assert np.all(np.diff(s) >= 0) and s[-1] == 1.0
    omega = design.servo.no_load_speed  # [rad/s] the [servo] table's
    speed = np.full(17, omega)
    speed[16] = omega * design.rail.drive_radius  # the rail, through its pinion
    steps = np.abs(np.diff(np.vstack([down, ramp]), axis=0))
    assert np.all(steps <= 0.5 * speed * CONTROL_DT + 1e-12), (steps / speed).max()
    assert np.all(np.abs(home[:-1] - goal) <= tol[:-1])
    stamps = [t for t, c in sent[len(held) :] if not np.array_equal(c.q, goal)]
    n = int(np.count_nonzero(s < 1.0))  # the ramp's goals before the last: paced at 50 Hz
    assert stamps[-1] - stamps[0] >= 0.9 * (n - 1) * CONTROL_DT, (stamps[-1] - stamps[0], n)


def test_a_design_whose_deployment_is_not_clear_stays_stowed(tmp_path):
    """A home posture whose straight unfolding puts two fingers through each other (the
    envelope check fails it) is refused before any servo moves: the stage stays up."""
    import tomli_w
    import tomllib

    from firmware_interface.errors import DynamixelError
    from payload.design.params import load_design as load
    from payload.project import default_design_text

    data = tomllib.loads(default_design_text())
    data["home"]["finger"] = [0.0, -0.3, 0.0, 0.0]
    path = tmp_path / "design.toml"
    path.write_text(tomli_w.dumps(data))
    smap = load_servo_map()
    with EmulatorProcess() as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, design=load(path)) as drv:
            drv.bring_up()
            before = drv.read()
            with pytest.raises(
                DynamixelError, match=r"deployment is not clear .*as the fingers unfold"
            ):
                move_to_home(drv)
            after = drv.read()
    tol = np.array([s.units_per_tick * band_ticks(s.joint) for s in smap.servos])
    moved = np.abs(np.append(after.q, after.deploy) - np.append(before.q, before.deploy))
    assert np.all(moved <= tol), moved


def test_sim_and_hardware_get_the_same_commands_from_the_same_session(session):
    _, frames = read_hand_recording(session)
    with SimDriver() as sim:
        on_sim = replay_session(sim, frames)
    smap = load_servo_map()
    with EmulatorProcess() as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            drv.bring_up()
            move_to_home(drv)  # homing stowed the rail and the stage; the sim starts at home
            with SimDriver() as world:
                on_hw = replay_session(HardwareInTheLoop(drv, world), frames)
            tables = emu.tables()
    assert len(on_sim) == len(on_hw) == len(frames)
    tol = np.array([s.units_per_tick * band_ticks(s.joint) for s in smap.servos])
    sim_v = np.array([np.append(c.q, c.deploy) for c in on_sim])
    hw_v = np.array([np.append(c.q, c.deploy) for c in on_hw])
    # the hardware starts from its measured posture, where its servos came to rest: inside
    # each one's friction dead band around home, plus a tick of rounding (the rail, 2 ticks
    # from home after homing, is held there by its friction); within that throughout
    assert np.all(np.abs(sim_v - hw_v) <= tol), np.abs(sim_v - hw_v).max(axis=0) / tol
    moved = np.ptp(sim_v[:, :16], axis=0)
    assert moved.max() > 0.1  # the fingers really were driven
    # and the last command is what the servos hold as their goals
    goal = BY_NAME["goal_position"]
    got = [decode(goal, tables[s.id][goal.address : goal.address + 4]) for s in smap.servos]
    assert got == smap.command_ticks(on_hw[-1])


def test_hw_run_records_the_trial_like_the_simulator(session, tmp_path, capsys):
    from payload.cli import main
    from payload.trials.recorder import read_recording

    out = tmp_path / "trial"
    with EmulatorProcess() as emu:
        argv = ["hw", "run", "--stay-deployed", "--device", emu.port, "--replay", str(session),
                "--out", str(out), "--no-pace", "--latency-ms", str(LAT), "--json"]  # fmt: skip
        assert main(argv) == 0
        assert not any(s["torque"] for s in emu.servos().values())  # left safe
    # the seconds of set-up before the session are said, on stderr (stdout: the JSON)
    said = capsys.readouterr()
    json.loads(said.out)
    assert (
        f"bringing up the servos on {emu.port} and homing the rail and the stage ...\n"
        "moving to the design's home posture ...\n" in said.err
    )
    rec = read_recording(out / "log.mcap")
    _, frames = read_hand_recording(session)
    assert len(rec) == len(frames)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["steps"] == len(frames) and metrics["driver"] == "hardware"
    assert metrics["loop_overruns"] is None  # unpaced (--no-pace): no period due, none late
    # a bare hands.jsonl stores no contact definition: scored as a trial is (confirmed
    # contact, docs/trials.md), with what it ran on
    assert (metrics["min_interval_s"], metrics["max_gap_s"]) == (0.5, 0.1)
    assert "environment" in metrics["provenance"]
    _, replayed = read_hand_recording(out / "hands.jsonl")
    assert all(np.array_equal(a.left.joints, b.left.joints, equal_nan=True)
               for a, b in zip(frames, replayed))  # fmt: skip
    # its log.mcap carries the hands as a trial's does, so it replays in turn
    from payload.trials.recorder import read_hand_frames

    _, in_log = read_hand_frames(out / "log.mcap")
    assert len(in_log) == len(frames)
    assert all(np.array_equal(a.right.joints, b.right.joints, equal_nan=True)
               for a, b in zip(frames, in_log))  # fmt: skip
    # the safety channel a trial records, one record per step, and the station figures
    from payload.schema import CONTROL_DT
    from payload.trials.safety import FILTER_TOPIC

    safety = [json.loads(m.data) for m in _messages(out / "log.mcap", FILTER_TOPIC)]
    assert len(safety) == len(frames)
    assert all(r["station_clearance_m"] > 0 and "active" in r for r in safety)
    assert metrics["station_contacts"] == sum(r["station_contact"] for r in safety) == 0
    least = min(r["station_clearance_m"] for r in safety)
    assert metrics["min_station_clearance_mm"] == round(least * 1e3, 1)
    assert metrics["filter_active_s"] == round(sum(r["active"] for r in safety) * CONTROL_DT, 2)
    # refuses to overwrite the recording (asked in the earlier spellings, kept for a release)
    with EmulatorProcess() as emu:
        argv = ["hw", "run", "--port", emu.port, "--source", "replay", str(session),
                "--out", str(out)]  # fmt: skip
        assert main(argv) == 2


def test_hw_run_shows_its_progress_on_a_terminal(session, tmp_path, monkeypatch):
    """A paced ``hw run`` takes the replay's length in real time (minutes for a trial's):
    on a terminal it shows a progress bar over the session's recorded time, as
    ``payload trial`` does."""
    import sys

    import rich.progress

    from payload.cli import main

    seen: list[tuple[str, float | None]] = []

    class Bar:
        def __init__(self, **kw):
            pass

        def add_task(self, name, total):
            seen.append(("add", total))
            return 0

        def start(self):
            seen.append(("start", None))

        def update(self, task, completed):
            seen.append(("update", completed))

        def stop(self):
            seen.append(("stop", None))

    monkeypatch.setattr(rich.progress, "Progress", Bar)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    out = tmp_path / "trial"
    with EmulatorProcess() as emu:
        argv = ["hw", "run", "--stay-deployed", "--device", emu.port, "--replay", str(session),
                "--out", str(out), "--no-pace", "--latency-ms", str(LAT)]  # fmt: skip
        assert main(argv) == 0
    _, frames = read_hand_recording(session)
    assert seen[0] == ("add", pytest.approx(frames[-1].stamp - frames[0].stamp))
    assert seen[1] == ("start", None) and seen[-1] == ("stop", None)
    done = [v for k, v in seen if k == "update"]
    assert len(done) == len(frames) and done == sorted(done)


def test_hw_run_refuses_a_file_for_out_and_keeps_no_folder_it_made_for_nothing(
    session, tmp_path, capsys
):
    """``--out`` a regular file, or a folder holding a trial's or a campaign's files, is one
    line and exit 2 (nothing touched); a bus where nobody answers ends in one line too, as
    a failed start of the hardware (exit 1, as `hw check` says it: it was exit 2, bad
    input, and named eighteen servos), and the folder made for the run is not left
    behind, empty."""
    import os

    from payload.cli import main

    afile = tmp_path / "afile"
    afile.write_text("mine")
    argv = ["hw", "run", "--replay", str(session), "--no-pace", "--max-time", "1"]
    assert main([*argv, "--device", "/dev/null", "--out", str(afile)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a folder" in err[0] and afile.read_text() == "mine"
    for name in ("hands.jsonl", "metrics.json", "summary.json"):  # a trial's or a campaign's
        held = tmp_path / f"held-{name}"
        held.mkdir()
        (held / name).write_text("mine")
        assert main([*argv, "--device", "/dev/null", "--out", str(held)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"already holds {name}" in err[0], err
        assert [p.name for p in held.iterdir()] == [name] and (held / name).read_text() == "mine"
    master, slave = os.openpty()  # a serial line nobody answers on
    device = os.ttyname(slave)
    try:
        fresh = tmp_path / "fresh"
        code = main([*argv, "--device", device, "--out", str(fresh)])
    finally:
        os.close(master)
        os.close(slave)
    err = capsys.readouterr().err.strip().splitlines()
    # the stage it had begun (said before its seconds of bring-up), then one error line
    assert err[:-1] == [f"bringing up the servos on {device} and homing the rail and the stage ..."]
    assert code == 1, err
    assert (
        err[-1] == f"payload: aborted: no servo answered on {device} (power, wiring, baud "
        "rate, IDs?)"
    ), err
    assert not fresh.exists()


def test_hw_run_of_a_synthetic_trial_says_what_it_ran_on_and_places_the_ctb_as_its_source(
    tmp_path, capsys
):
    from payload.cli import main
    from payload.trials.recorder import read_recording
    from payload.trials.runner import run_trial

    src = tmp_path / "src"
    run_trial(3, "synthetic", out_dir=src, max_time=2.0)  # a short synthetic trial
    source = json.loads((src / "metrics.json").read_text())
    out = tmp_path / "hw"
    argv = ["hw", "run", "--stay-deployed", "--emulator", "--replay", str(src / "log.mcap"),
            "--out", str(out), "--no-pace", "--latency-ms", str(LAT)]  # fmt: skip
    assert main(argv) == 0
    printed = capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["driver"] == "hardware" and metrics["emulator"] is True
    assert metrics["device"].startswith("/dev/pts/")
    assert metrics["replay"] == str((src / "log.mcap").resolve())  # what it replayed
    assert metrics["provenance"]["design_sha256"] == source["provenance"]["design_sha256"]
    for key in ("ctb", "propulsion", "retarget_budget", "ctb_offset_m", "ctb_yaw_deg"):
        assert metrics[key] == source[key], key
    assert metrics["watchdog"]["trips"] == 0  # a healthy session never trips it
    assert metrics["torque_off_unconfirmed"] == []  # close read every torque off back
    a, b = read_recording(src / "log.mcap"), read_recording(out / "log.mcap")
    # the CTB where the source trial had it (both from rest: the first recorded step)
    assert np.linalg.norm(a.ctb_pos[0] - b.ctb_pos[0]) < 1e-4
    # what it replayed, as a trial's replay records it: a capped source marks it cut short
    # (the exports leave it out; it was taken for a whole run)
    from payload.trials.reading import cut_reason

    assert b.meta["replay"]["file"] == str(src / "log.mcap")
    assert "replay of an unfinished run" in (cut_reason(b.meta, b.complete) or ""), b.meta
    assert "success:" in printed and "emulator" in printed  # the trial's summary, its far end
    assert metrics["ended_by"] == "source" and "--max-time cap after" not in printed
    assert "session-length cap" not in printed
    # how it ended, said (it was not): the source trial was capped at 2 s, so is its replay
    ended = "  ended: the replayed recording's end, 2.0 s in; every servo's torque turned off"
    assert ended in printed.splitlines(), printed
    # capped before the recording's end: said as `payload trial` says it
    capped = tmp_path / "capped"
    argv[argv.index(str(out))] = str(capped)
    assert main([*argv, "--max-time", "1"]) == 0
    printed = capsys.readouterr().out
    assert json.loads((capped / "metrics.json").read_text())["ended_by"] == "max_time"
    assert "stopped by the --max-time cap after 1.0 s" in printed, printed
    assert (
        "  ended: the session-length cap (--max-time), 1.0 s in; every servo's torque turned off"
        in printed.splitlines()
    )


def test_hw_run_says_when_its_paced_loop_fell_behind_50_hz(tmp_path, capsys):
    """Every reply 25 ms late (the emulator's latency fault, longer than the 20 ms period
    by itself): each paced step ends after its period. `hw run` said nothing of it (the
    loop counted its overruns, and nothing read them): `metrics.json` has
    `loop_overruns` (every step here) and the summary a line saying it fell behind (an
    unpaced run has none due, null: test_hw_run_records_the_trial_like_the_simulator)."""
    from payload.cli import main
    from payload.trials.runner import run_trial

    src = tmp_path / "src"
    run_trial(3, "synthetic", out_dir=src, max_time=1.0)
    with EmulatorProcess(faults=["latency:25ms"]) as emu:
        argv = ["hw", "run", "--stay-deployed", "--device", emu.port, "--replay",
                str(src / "log.mcap"), "--max-time", "0.5", "--latency-ms", "30"]  # fmt: skip
        assert main([*argv, "--out", str(tmp_path / "paced")]) == 0
        printed = capsys.readouterr().out
    paced = json.loads((tmp_path / "paced" / "metrics.json").read_text())
    assert paced["loop_overruns"] == paced["steps"] > 0
    said = f"  fell behind 50 Hz: {paced['steps']} of {paced['steps']} steps ended after"
    assert any(line.startswith(said) for line in printed.splitlines()), printed


def test_a_ctrl_c_while_hw_run_scores_names_the_recording_kept(
    session, tmp_path, capsys, monkeypatch
):
    """Ctrl-C after the session ended, while it is scored: `hw run` said only "payload:
    interrupted"; it now names the recording it kept whole (its metrics not written)."""
    import payload.trials.scoring
    from payload.cli import main
    from payload.trials.recorder import read_recording

    def scoring(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(payload.trials.scoring, "finish_trial", scoring)
    out = tmp_path / "run"
    with EmulatorProcess() as emu:
        argv = ["hw", "run", "--stay-deployed", "--device", emu.port, "--replay", str(session),
                "--out", str(out), "--no-pace", "--latency-ms", str(LAT)]  # fmt: skip
        assert main(argv) == 130
    last = capsys.readouterr().err.strip().splitlines()[-1]
    recording = out / "log.mcap"
    assert last == (
        f"payload: interrupted; the session's recording is kept whole, not scored: {recording}"
    ), last
    _, frames = read_hand_recording(session)
    assert len(read_recording(recording)) == len(frames)  # every step, readable
    assert not (out / "metrics.json").exists()


def test_hw_run_without_a_terminal_says_how_far_the_session_is(
    session, tmp_path, capsys, monkeypatch
):
    """No progress bar without a terminal (a log, a pipe): a paced replay of a whole trial
    ran minutes without a word. A line now goes to stderr every PROGRESS_LINE_S of the
    session (shortened here), counting up to the recording's length."""
    import firmware_interface.run
    from payload.cli import main

    monkeypatch.setattr(firmware_interface.run, "PROGRESS_LINE_S", 1.0)
    _, frames = read_hand_recording(session)
    length = float(frames[-1].stamp) - float(frames[0].stamp)
    with EmulatorProcess() as emu:
        argv = ["hw", "run", "--stay-deployed", "--device", emu.port, "--replay", str(session),
                "--out", str(tmp_path / "run"), "--no-pace", "--latency-ms", str(LAT)]  # fmt: skip
        assert main(argv) == 0
    said = [x for x in capsys.readouterr().err.splitlines() if x.startswith("hw run: ")]
    assert len(said) == int(length // 1.0), said
    for k, line in enumerate(said, 1):
        assert line == f"hw run: {k} of {length:.0f} s of the session run ...", line


def _messages(path, topic):
    """The messages of one topic of an MCAP file, read with the mcap library itself."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [m for _, _, m in make_reader(f).iter_messages(topics=[topic])]


def test_a_hardware_fault_mid_run_aborts_it_exit_1_naming_the_recording_kept(
    session, tmp_path, capsys
):
    """A servo fault in the middle of ``hw run`` (overheating latched on servo 7 half a
    second into the recorded session) is a failed run, not bad input: exit 1 (was 2, as
    "error"), the last line says the run was aborted, by what, and where its recording
    is; the recording keeps the steps up to the fault, marked aborted; nothing is scored;
    the servos are left torque off."""
    import threading
    import time

    from payload.cli import main
    from payload.trials.recorder import read_recording

    out = tmp_path / "trial"
    with EmulatorProcess() as emu:

        def inject():
            deadline = time.monotonic() + 120
            while not (out / "log.mcap").exists() and time.monotonic() < deadline:
                time.sleep(0.01)
            time.sleep(0.5)  # the session is running: about 25 steps in
            emu.fault("error:7:overheating")

        fault = threading.Thread(target=inject, daemon=True)
        fault.start()
        argv = ["hw", "run", "--stay-deployed", "--device", emu.port, "--replay", str(session),
                "--out", str(out), "--latency-ms", str(LAT)]  # fmt: skip
        code = main(argv)
        fault.join()
        assert not any(s["torque"] for s in emu.servos().values())
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1, err
    last = err[-1]
    assert last.startswith("payload: aborted: hw run aborted at t = ")
    assert "servo 7 (B_pip): hardware error overheating" in last
    assert str(out / "log.mcap") in last
    rec = read_recording(out / "log.mcap")
    assert rec.complete and 0 < len(rec) < len(read_hand_recording(session)[1])
    assert "overheating" in rec.meta["aborted_by"] and "aborted" in rec.meta
    assert rec.meta["aborted_at_s"] == pytest.approx(rec.t[-1])
    assert not (out / "metrics.json").exists()


def test_the_grasps_load_on_a_servo_uses_the_designs_torque_constant():
    """``hw identify --write`` puts a measured ``kt`` into the design; the emulated servo
    and the driver then use it, and so must the grasp's load fed to the emulator: a
    contact torque just under the design's blocked torque (Goal Current x kt,
    ``joint_servo(...).torque_cap``) is a holding current under the servo's Goal Current,
    just over it one over (with the datasheet's stall ratio, 0.517 N m/A, a torque up to
    1.36x the blocked torque of a kt = 0.38 servo was taken as held)."""
    import dataclasses

    from payload.design.servo import joint_servo

    base = load_design()
    design = dataclasses.replace(base, servo=dataclasses.replace(base.servo, kt=0.38))
    blocked = joint_servo(design, "finger").torque_cap  # [N m]
    smap = load_servo_map()
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, design=design, latency_timer_ms=LAT, guard=False) as drv,
        SimDriver() as sim,
    ):
        hil = HardwareInTheLoop(drv, sim)
        dofs = hil._dofs
        cap = BY_NAME["goal_current"]
        drv.bring_up()  # Goal Current = the design's cap
        cap_ma = decode(cap, emu.table(1)[cap.address : cap.address + cap.size])
        for scale, held in ((0.97, True), (1.03, False)):
            sim.data.qfrc_constraint[dofs] = scale * blocked
            loads = hil.finger_loads()
            assert len(loads) == 16
            assert all((abs(ma) < cap_ma) == held for ma in loads.values()), (scale, loads)


def _hw_run_of(session: Path, out: Path, *extra: str, where: dict | None = None) -> Path:
    """``payload hw run`` of a recorded hand session on a fresh emulator, unpaced, into
    ``out`` (its exit checked), with ``extra`` options; returns ``out``. ``where``: filled
    with the servos' physical positions at the end (ID -> ticks)."""
    from payload.cli import main

    with EmulatorProcess() as emu:
        argv = ["hw", "run", "--device", emu.port, "--replay", str(session), "--out", str(out),
                "--no-pace", "--latency-ms", str(LAT), "--json", *extra]  # fmt: skip
        assert main(argv) == 0
        if where is not None:
            where.update({i: s["pos"] for i, s in emu.servos().items()})
    return out


def _stowed_at_the_end(out: Path, where: dict, stay: bool = False) -> None:
    """``hw run`` left the payload deployed (the stage down, the fingers where the session
    left them) with its torque off; the next bring-up then drove the stage up into the
    bays with the fingers out. It now stows it (``"stowed": true``): the servos rest at the
    stowed posture, the stage and the rail at their stowed stops (``where``: the emulator's
    physical positions after the run). With ``--stay-deployed`` (``stay``) the payload
    stays out (``"stowed": null``), the stage down."""
    from firmware_interface.servo_map import posture_ticks

    metrics = json.loads((out / "metrics.json").read_text())
    smap, design = load_servo_map(), load_design()
    target = posture_ticks(smap, design, "home" if stay else "stowed")
    stage = smap.servos[17]
    if stay:
        assert metrics["stowed"] is None
        assert abs(where[stage.id] - target[stage.id]) <= band_ticks("stage")  # still down
    else:
        assert metrics["stowed"] is True
        off = {s.joint: abs(where[s.id] - target[s.id]) for s in smap.servos}
        assert all(off[j] <= band_ticks(j) for j in off), off
        assert where[stage.id] == stage.zero  # at the stop


def test_hw_run_told_to_stay_deployed_leaves_the_payload_out(session, tmp_path):
    """``--stay-deployed``: the payload is not stowed (the stowing itself: the watchdog
    test below, whose run ends stowed)."""
    where: dict[int, float] = {}
    out = _hw_run_of(session, tmp_path / "trial", "--stay-deployed", where=where)
    _stowed_at_the_end(out, where, stay=True)


def test_a_bus_watchdog_trip_is_recorded_at_its_session_time(session, tmp_path, monkeypatch):
    """A host stall of 0.6 s mid-session (a pipeline step, well after the watchdog was
    armed) trips the servos' 100 ms Bus Watchdog once; ``metrics.json`` says when, in the
    session's time (the stalled step, whose command re-armed them) and on the wall clock
    (inside the stall), not only on the host's monotonic clock. (0.6 s: a loaded 2-core
    machine stalls a session by over 0.25 s of its own now and then.)"""
    import time

    from payload.teleop.pipeline import TeleopPipeline
    from payload.trials.recorder import read_recording

    calls, step = [0], TeleopPipeline.step
    stalled = ARM_AFTER_STEPS + 15  # the pipeline's step 15 steps after the watchdog is armed
    stall = 0.6  # [s]
    assert stall > load_servo_map().watchdog_ms / 1e3  # a stall that trips it

    def stall_once(self, *args, **kwargs):
        calls[0] += 1
        if calls[0] == stalled:
            time.sleep(stall)
        return step(self, *args, **kwargs)

    monkeypatch.setattr(TeleopPipeline, "step", stall_once)
    out = _hw_run_of(session, tmp_path / "trial")
    assert calls[0] > stalled
    trips = json.loads((out / "metrics.json").read_text())["watchdog"]
    # the stall's trip (a loaded machine may add short ones of its own: not this test's)
    stalls = [e for e in trips.get("events", []) if e["silence_s"] >= stall]
    assert len(stalls) == 1, trips
    trip = stalls[0]
    rec = read_recording(out / "log.mcap")
    wall = np.asarray(rec.wall_time)
    first = next(i for i, p in enumerate(rec.phase) if str(p) != "calibration")
    k = first + stalled - 1  # the stalled step: its record came the stall late
    assert wall[k] - wall[k - 1] >= stall
    assert trip["session_t"] == round(float(rec.t[k]), 3)
    assert wall[k - 1] <= trip["unix_s"] <= wall[k] + 1e-3


def test_the_first_teleoperation_step_does_not_trip_the_bus_watchdog(
    session, tmp_path, monkeypatch
):
    """The pipeline's first step, once the calibration ends, builds what it uses once (its
    compiled kernels' self-checks: 85 to 290 ms measured in a fresh ``hw run`` on a 2-core
    machine at load 2), longer than the watchdog's 100 ms. With the watchdog armed 25
    steps into the session (mid-calibration) every healthy ``hw run`` of a whole trial
    tripped it there; it is now disarmed while the pipeline is built and armed again
    once the pipeline has run its first steps. The one-off cost is made 0.2 s here, so
    the check does not hang on whether this process has built those kernels already."""
    import time

    from payload.teleop.pipeline import TeleopPipeline

    first, step = [True], TeleopPipeline.step
    assert 0.2 > load_servo_map().watchdog_ms / 1e3  # the slow step would trip it, armed

    def slow_first_step(self, *args, **kwargs):
        if first[0]:
            first[0] = False
            time.sleep(0.2)
        return step(self, *args, **kwargs)

    monkeypatch.setattr(TeleopPipeline, "step", slow_first_step)
    armed, arm = [], DynamixelDriver.set_watchdog

    def set_watchdog(self, on):
        armed.append(on)
        return arm(self, on)

    monkeypatch.setattr(DynamixelDriver, "set_watchdog", set_watchdog)
    where: dict[int, float] = {}
    out = _hw_run_of(session, tmp_path / "trial", where=where)
    _stowed_at_the_end(out, where)  # and the payload stowed after it
    assert not first[0]  # the session reached teleoperation
    # the watchdog guarded it to its end, and was disarmed once the 50 Hz traffic ended
    # (by the run, then by the stowing itself)
    assert armed[-3:] == [True, False, False], armed
    watchdog = json.loads((out / "metrics.json").read_text())["watchdog"]
    # no trip from the slow first step (a loaded machine may add short ones of its own)
    assert [e for e in watchdog.get("events", []) if e["silence_s"] >= 0.2] == [], watchdog


def test_a_servo_faulted_at_bring_up_aborts_the_run_as_a_failed_start(session, tmp_path, capsys):
    """A servo in overload when `hw run` brings the bus up: one line naming it, exit 1 (a
    failed start of the hardware, as `hw check` fails it), not exit 2 (bad input), and no
    folder left for the run."""
    from firmware_interface.emulator import EmulatorProcess
    from firmware_interface.servo_map import load_servo_map
    from payload.cli import main

    out = tmp_path / "run"
    with EmulatorProcess(faults=["error:12:overload"]) as emu:
        argv = ["hw", "run", "--device", emu.port, "--replay", str(session), "--no-pace",
                "--max-time", "1", "--out", str(out), "--latency-ms", str(LAT)]  # fmt: skip
        code = main(argv)
    joint = load_servo_map().joint_of(12)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1, err
    # and what to do: the error is latched until the servo restarts (it said no more)
    assert err[-1] == (
        f"payload: aborted: bring-up on {emu.port} failed: servo 12 ({joint}): hardware error "
        "overload (a hardware error stays latched until the servo restarts: remove its cause "
        "(a blocked joint for overload, the supply for input_voltage, time to cool for "
        "overheating), then power-cycle the servos; `payload hw check` shows every servo's "
        "state)"
    ), err
    assert not out.exists()


def test_hw_run_says_the_torque_off_is_unconfirmed_when_close_could_not_read_it_back(
    session, tmp_path, capsys, monkeypatch
):
    """Every reply lost once the session ended (the emulator's drop fault): close sends
    the torque-off but cannot read it back. `hw run` still said "every servo's torque
    turned off"; now it names the servos left unconfirmed, and `metrics.json` lists them."""
    import firmware_interface.run
    from payload.cli import main

    trial = firmware_interface.run.run_hardware_trial
    with EmulatorProcess() as emu:

        def then_silent(*args, **kwargs):
            result = trial(*args, **kwargs)
            emu.fault("drop:1.0")  # before the driver's close
            return result

        monkeypatch.setattr(firmware_interface.run, "run_hardware_trial", then_silent)
        out = tmp_path / "run"
        argv = ["hw", "run", "--stay-deployed", "--device", emu.port, "--replay", str(session),
                "--out", str(out), "--no-pace", "--max-time", "0.5",
                "--latency-ms", str(LAT)]  # fmt: skip
        assert main(argv) == 0
        torque = {i: s["torque"] for i, s in emu.servos().items()}
    printed = capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    unconfirmed = metrics["torque_off_unconfirmed"]
    assert unconfirmed == sorted(torque), unconfirmed  # every reply lost: none confirmed
    ended = [line for line in printed.splitlines() if line.startswith("  ended: ")]
    assert len(ended) == 1 and "every servo's torque turned off" not in ended[0], ended
    assert ended[0].endswith(f"not confirmed on servos {', '.join(map(str, unconfirmed))}: "
                             "check them before handling the hand")  # fmt: skip
    assert not any(torque.values())  # the torque-off itself reached every servo


def test_ctrl_c_at_a_terminal_stops_hw_run_emulator_with_the_torque_turned_off(tmp_path):
    """A terminal's Ctrl-C reaches the whole process group: the emulator that ``hw run
    --emulator`` starts took it too and ended first, so every such stop warned "close:
    could not turn the torque off". The emulator has a session of its own: the run stops
    as Ctrl-C stops it (exit 130, the recording kept), the torque off confirmed."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from payload.trials.runner import run_trial

    src = tmp_path / "src"
    run_trial(3, "synthetic", out_dir=src, max_time=4.0)
    out = tmp_path / "hw"
    code = "import sys; from payload.cli import main; sys.exit(main(sys.argv[1:]))"
    argv = [sys.executable, "-c", code, "hw", "run", "--stay-deployed", "--emulator", "--replay",
            str(src / "log.mcap"), "--out", str(out), "--latency-ms", str(LAT)]  # fmt: skip
    proc = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (out / "log.mcap").exists():
        time.sleep(0.05)
    time.sleep(0.5)  # the paced session under way
    assert proc.poll() is None, proc.communicate()
    os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole group
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "could not turn the torque off" not in err, err
    assert "could not confirm the torque off" not in err, err  # each servo read back off
    assert "payload: interrupted" in err.strip().splitlines()[-1], err
