"""The payload back into its bays: a bring-up that finds the fingers out folds them before
the stage goes up (or refuses a fold that would collide), ``recover()`` does not home the
stage with the fingers out, and ``stow`` reverses the deployment; on the emulated bus,
watched from the emulator's side (the physical positions, not the driver's reading)."""

from __future__ import annotations

import logging
import re
import threading
import time

import numpy as np
import pytest
from conftest import band_ticks

from firmware_interface.control_table import TICKS_PER_REV
from firmware_interface.deployment import move_to_home, stow
from firmware_interface.driver import DynamixelDriver
from firmware_interface.emulator import EmulatorProcess
from firmware_interface.errors import HardwareFault, HomingError
from firmware_interface.options import EMULATOR_LATENCY_MS as LAT  # [ms] reply allowance
from firmware_interface.servo_map import load_servo_map, posture_command, posture_ticks
from payload.design.params import load_design
from payload.schema import CONTROL_DT, PayloadCommand

TENTH_RAD_TICKS = 0.1 * TICKS_PER_REV / (2 * np.pi)  # a tenth of a radian of a shaft [ticks]


class Watch:
    """The emulator's physical positions, sampled on a thread every few ms while the
    driver works (the emulator answers its control channel beside the bus)."""

    def __init__(self, emu: EmulatorProcess) -> None:
        self.emu, self.rows, self._stop = emu, [], threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.rows.append({i: s["pos"] for i, s in self.emu.servos().items()})
            time.sleep(0.003)

    def __enter__(self) -> Watch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def of(self, dxl_id: int) -> np.ndarray:
        return np.array([r[dxl_id] for r in self.rows], dtype=float)


def test_a_payload_powered_up_deployed_folds_its_fingers_before_the_stage_goes_up(caplog):
    """A session ended with the payload deployed (a fault, the power lost, ``--stay-
    deployed``): at the next bring-up homing drove the rail and the stage to their
    stowed stops at once, the stage up into the bays with the fingers unfolded at home.
    Now the fingers fold first, their goals on the straight line to the stowed posture,
    paced at 50 Hz no faster than half the servos' no-load speed, while the stage and the
    rail hold; then the rail goes to its stop, and only then the stage goes up."""
    design, smap = load_design(), load_servo_map()
    stowed, home = posture_ticks(smap, design, "stowed"), posture_ticks(smap, design, "home")
    fingers, rail, stage = smap.servos[:16], smap.servos[16], smap.servos[17]
    sent = []
    with EmulatorProcess(positions=home) as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            goal_ticks = drv.goal_ticks
            drv.goal_ticks = lambda t: (sent.append((time.monotonic(), dict(t))), goal_ticks(t))
            with caplog.at_level(logging.WARNING, logger="firmware_interface"), Watch(emu) as w:
                drv.bring_up()
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and "out of its bays" in said[0], said
    st, ra = w.of(stage.id), w.of(rail.id)
    assert st[0] == home[stage.id] and ra[0] == home[rail.id]  # powered up deployed
    up = int(np.argmax(np.abs(st - st[0]) > band_ticks("stage")))  # the stage starts up
    retract = int(np.argmax(np.abs(ra - ra[0]) > band_ticks("rail")))  # the rail starts in
    assert 0 < retract < up, (retract, up)
    for s in fingers:  # folded before the rail moved, and held stowed from then on
        off = np.abs(w.of(s.id)[retract:] - stowed[s.id])
        assert off.max() <= TENTH_RAD_TICKS, (s.joint, off.max())
    assert np.all(np.abs(ra[up:] - rail.zero) <= band_ticks("rail") + 1)  # the rail stowed
    assert st[-1] == stage.zero and ra[-1] == rail.zero  # both at their stops, homed
    # the fold's goals: the 16 fingers only, on the line from where they were to stowed
    assert all(set(t) == {s.id for s in fingers} for _, t in sent)
    g = np.array([[t[s.id] for s in fingers] for _, t in sent], dtype=float)
    a = np.array([home[s.id] for s in fingers], dtype=float)
    b = np.array([stowed[s.id] for s in fingers], dtype=float)
    along = (g - a) @ (b - a) / ((b - a) @ (b - a))
    assert np.all(np.abs(g - (a + np.outer(along, b - a))) <= 1.0)  # (each goal rounded to a tick)
    assert np.all(np.diff(along) >= 0) and np.array_equal(g[-1], b)
    omega = design.servo.no_load_speed * TICKS_PER_REV / (2 * np.pi)  # [ticks/s of a shaft]
    steps = np.abs(np.diff(np.vstack([a, g]), axis=0))
    assert steps.max() <= 0.5 * omega * CONTROL_DT + 1.0, steps.max()  # (+ a tick's rounding)
    n = int(np.count_nonzero(along < 1.0))  # the ramp's goals before the last: at 50 Hz
    assert sent[n - 1][0] - sent[0][0] >= 0.9 * (n - 1) * CONTROL_DT, n


def _fold_contacts(design_dict, fingers: dict[str, float], rail: float, upto: float) -> set:
    """MuJoCo's link pairs in contact (its collision model of the convex pieces) along the
    fingers' straight fold from ``fingers`` toward stowed, stage down, the rail at
    ``rail``, sampled every 0.25 degree up to the share ``upto`` of the way (0: the start
    only)."""
    from test_envelope import VEHICLE, geometry_of

    from payload.design.tree import ALL_JOINTS
    from payload.envelope.collisions import CollisionModel

    geom = geometry_of(design_dict)
    stowed, down = geom.tree.posture("stowed"), geom.tree.posture("home")["stage"]
    start = {**stowed, **fingers, "rail": rail}
    n = int(np.ceil(max(abs(start[j] - stowed[j]) for j in fingers) / np.radians(0.25)))
    rows = [
        [down if j == "stage" else rail if j == "rail" else (1 - s) * start[j] + s * stowed[j]
         for j in ALL_JOINTS]
        for s in np.linspace(0.0, upto, max(1, round(n * upto)) + 1)
    ]  # fmt: skip
    counts = CollisionModel(geom, VEHICLE).check(np.array(rows)).pair_counts()
    return {frozenset(p) for p in counts}


@pytest.mark.parametrize("case", ["fold collides", "stage partway", "in the bays"])
def test_a_fold_that_is_not_checked_clear_is_refused_and_nothing_moves(design_dict, case):
    """Refused at power-up before anything moves, the fingers where they were and the
    stage where it was: fingers abducted -0.3 rad and straight with the stage down, whose
    straight fold puts B's and C's distal links through each other (MuJoCo's collision
    model finds the pair on the way, not at the start); fingers out with the stage partway
    (30 mm of 75: a reading that puts it at 30.0 or 67.7 mm, neither down); a finger 0.3
    rad off stowed with the stage up (0.0 or 37.7 mm: in the bays, where the fold is not
    checked; it was folded, or sent home at once, before)."""
    from payload.design.params import FINGER_JOINTS, FINGERS

    design, smap = load_design(), load_servo_map()
    stage = smap.servos[17]
    turn = TICKS_PER_REV * stage.units_per_tick  # [m] of the stage a turn of its servo

    def mm(*values: float) -> str:  # the positions as the refusal says them
        return " or ".join(re.escape(f"{v * 1e3:.1f}") for v in values)

    ticks = posture_ticks(smap, design, "stowed" if case == "in the bays" else "home")
    if case == "fold collides":
        splayed = dict(zip(FINGER_JOINTS, (0.0, -0.3, 0.0, 0.0)))
        q = {f"{f}_{j}": v for f in FINGERS for j, v in splayed.items()}
        ticks.update({s.id: s.to_ticks(q[s.joint]) for s in smap.servos if s.joint in q})
        pair = frozenset(("B_distal", "C_distal"))
        assert pair not in _fold_contacts(design_dict, q, design.home.rail, 0.0)
        assert pair in _fold_contacts(design_dict, q, design.home.rail, 1.0)
        says = f"B_distal and C_distal collide .*rail at {mm(design.home.rail)} mm"
    elif case == "stage partway":
        ticks[stage.id] = stage.to_ticks(0.03)
        down = mm(design.home.stage)
        says = rf"and the stage not down \(at {mm(0.03, 0.03 + turn)} mm, not {down}\)"
    else:
        a_pip = next(s for s in smap.servos if s.joint == "A_pip")
        ticks[a_pip.id] += round(0.3 / a_pip.units_per_tick)
        says = rf"with A_pip 0\.30 rad from stowed and the stage not down \(at {mm(0.0, turn)} mm"
    with EmulatorProcess(positions=ticks) as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            with pytest.raises(HomingError, match=says):
                drv.bring_up()
            after = {i: s["pos"] for i, s in emu.servos().items()}
    moved = {smap.joint_of(i): after[i] - ticks[i] for i in ticks if abs(after[i] - ticks[i]) > 1}
    assert moved == {}, moved


def test_recover_does_not_home_the_stage_with_the_fingers_out():
    """The bus's power lost and back mid-session, the payload deployed: ``recover()``
    homed the rail and the stage again at once, the stage driven up into the bays with
    the fingers out. It refuses, naming the stage and the finger farthest out, and the
    payload stays stopped, the stage where it was."""
    design, smap = load_design(), load_servo_map()
    stage = smap.servos[17]
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT, health_every=5) as drv,
    ):
        drv.bring_up()
        at_home = move_to_home(drv, cleared=True)
        down = emu.servos()[stage.id]["pos"]
        emu.power_cycle()
        hold = PayloadCommand(at_home.q, at_home.deploy, 0.0)
        for _ in range(drv.health_every):
            drv.send(hold)
            drv.read()
        assert isinstance(drv.fault, HardwareFault)
        with pytest.raises(HomingError, match=r"rail and stage lost their count with \w+ "):
            drv.recover()
        assert not drv.homed & {smap.servos[16].id, stage.id}  # unknown until homed again
        time.sleep(0.2)
        assert abs(emu.servos()[stage.id]["pos"] - down) <= 1
        assert drv.fault is not None  # still stopped
    assert abs(down - stage.to_ticks(design.home.stage)) <= band_ticks("stage")


def test_recover_does_not_home_the_stage_with_the_rail_out():
    """The stage alone rebooted with the fingers stowed and the rail out (the deployment
    half done): ``recover()`` checked only the fingers, and homing drove the stage up
    into the bays with the rail out, a path the envelope check never cleared (the stage
    moves only with the fingers and the rail stowed). It refuses, naming the rail and how
    far out it is, and the stage stays where it was."""
    from firmware_interface.deployment import RAIL, STAGE, settle, tolerance

    design, smap = load_design(), load_servo_map()
    rail, stage = smap.servos[RAIL], smap.servos[STAGE]
    fingers = posture_command(design, "stowed").q[:RAIL]
    with (
        EmulatorProcess() as emu,
        DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv,
    ):
        drv.bring_up()
        tol = tolerance(drv)
        down = PayloadCommand(np.append(fingers, design.stowed.rail), design.home.stage, 0.0)
        settle(drv, down, tol, 6.0, "stage down")
        out = PayloadCommand(np.append(fingers, design.home.rail), design.home.stage, 0.0)
        settle(drv, out, tol, 6.0, "rail out")
        before = {i: s["pos"] for i, s in emu.servos().items()}
        emu.fault(f"error:{stage.id}:overload")
        drv.read()
        assert isinstance(drv.fault, HardwareFault) and drv.fault.id == stage.id
        with pytest.raises(HomingError, match=r"stage lost its count with rail ") as err:
            drv.recover()
        time.sleep(0.2)
        after = {i: s["pos"] for i, s in emu.servos().items()}
        assert drv.fault is not None and stage.id not in drv.homed
    assert all(abs(after[sp.id] - before[sp.id]) <= 1 for sp in (rail, stage))
    # how far out, from the emulator's physical rail and the design's stowed rail by hand
    mm = abs(before[rail.id] - rail.to_ticks(design.stowed.rail)) * rail.units_per_tick * 1e3
    said = float(re.search(r"rail ([\d.]+) mm from stowed", str(err.value)).group(1))
    out_mm = abs(design.home.rail - design.stowed.rail) * 1e3  # where it was sent
    assert abs(mm - out_mm) <= (band_ticks("rail") + 1) * rail.units_per_tick * 1e3
    assert abs(said - mm) <= 0.1 + 1.5 * rail.units_per_tick * 1e3


def test_stow_reverses_the_deployment(caplog):
    """From home (a session's end, the fingers out), ``stow`` brings the payload back as
    it deployed, backwards: the fingers and the rail on the straight line from home to
    the stowed posture with the stage held down, and only then the stage up; it rests
    stowed, the rail and the stage at their stops, and the guard is back."""
    design, smap = load_design(), load_servo_map()
    stowed = posture_ticks(smap, design, "stowed")
    rail, stage = smap.servos[16], smap.servos[17]
    sent = []
    with EmulatorProcess() as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            drv.bring_up()
            home = move_to_home(drv, cleared=True)
            drv.set_watchdog(False)  # as a session's end disarms it (`hw run`)
            guard, send = drv.guard, drv.send
            drv.send = lambda c: (sent.append(c), send(c))[1]
            with caplog.at_level(logging.WARNING), Watch(emu) as w:
                end = stow(drv)
            restored = drv.guard
    assert not caplog.records, caplog.text
    assert restored is guard
    st = w.of(stage.id)
    up = int(np.argmax(np.abs(st - st[0]) > band_ticks("stage")))
    assert up > 0
    for s in smap.servos[:17]:  # the fingers and the rail stowed before the stage moved
        off = np.abs(w.of(s.id)[up:] - stowed[s.id])
        assert off.max() <= band_ticks(s.joint) + 2, (s.joint, off.max())
    assert st[-1] == stage.zero and w.of(rail.id)[-1] <= rail.zero + band_ticks("rail")
    at_home = posture_command(design, "home").q
    last = max(k for k, c in enumerate(sent) if np.array_equal(c.q, at_home))
    fold = np.array([c.q for c in sent[last + 1 :] if c.deploy == design.home.stage])
    b = np.array([*design.stowed.finger] * 4 + [design.stowed.rail])
    d = fold[0] - b  # the fold's goals: one straight line, walked once, ending stowed
    along = (fold - b) @ d / (d @ d)
    assert np.linalg.norm(d) > 1.0 and np.allclose(fold, b + np.outer(along, d), atol=1e-9)
    assert np.all(np.diff(along) <= 0) and along[-1] == 0.0
    assert np.all(np.abs(fold[0] - home.q) <= np.abs(b - home.q) / 20)  # it starts at home
    tol = np.array([s.units_per_tick * band_ticks(s.joint) for s in smap.servos])
    assert np.all(np.abs(np.append(end.q, end.deploy) - np.append(b, 0.0)) <= tol)
    # where the servos physically were, posed in the design's collision model: no pair
    # through each other and nothing in the vehicle (the goals stopped at the stowed
    # posture from speed: the fingers overshot it, B_distal 2 mm into the carriage)
    from payload.design import build_tree
    from payload.design.tree import ALL_JOINTS
    from payload.envelope.deployment import _obstacles
    from payload.envelope.geometry import PayloadGeometry
    from payload.envelope.vehicle import vehicle_from_dict

    geom = PayloadGeometry(build_tree(design))
    body = _obstacles(geom, vehicle_from_dict(design.vehicle or {}, source="test"))
    moving = [n for n in geom.links if n != geom.root]
    values = np.array([[sp.from_ticks(w.of(sp.id)[k]) for sp in smap.servos]
                       for k in range(0, up, 2)])  # fmt: skip
    least = min(
        geom.min_distance(geom.poses(dict(zip(ALL_JOINTS, q))), others=body, moving=moving)[0]
        for q in values
    )
    assert least > 0.0, least


def test_an_unhomed_rail_or_stage_is_placed_at_its_reading_plus_whole_turns():
    """A power-up keeps the last homing's Homing Offset and loses the turn count: the
    reading is the true position's tick plus or minus whole turns. Over the packaged rail's
    and stage's travels (each over a turn, under two) and any turn count, the true position
    is among the one or two positions the reading names, each a whole number of turns from
    the reading and inside the travel; a servo resting inside its dead band past an end
    (the stage a few ticks past deployed) is placed at that end, and the stage up does not
    read as down (two turns are 43 ticks more than its travel)."""
    from firmware_interface.deployment import linear_positions

    smap = load_servo_map()
    for spec in smap.servos[16:]:
        band = band_ticks(spec.joint)
        pad = band * spec.units_per_tick
        for v in np.linspace(spec.lower, spec.upper, 41):
            true = spec.to_ticks(v)
            for k in range(-3, 4):
                places = linear_positions(spec, true + k * TICKS_PER_REV, pad)
                assert 1 <= len(places) <= 2, (spec.joint, v, k, places)
                assert min(abs(p - v) for p in places) <= spec.units_per_tick, (spec.joint, v)
                for p in places:
                    turns = (spec.to_ticks(p) - true) / TICKS_PER_REV
                    assert abs(turns - round(turns)) * TICKS_PER_REV <= band  # (an end's clamp)
                    assert spec.lower <= p <= spec.upper
        for end in (spec.lower, spec.upper):  # a few ticks past an end: at the end
            past = spec.to_ticks(end) + spec.direction * (1 if end else -1) * int(band - 1)
            assert end in linear_positions(spec, past, pad), (spec.joint, end)
    stage = smap.servos[17]
    up = linear_positions(stage, stage.to_ticks(0.0), band_ticks("stage") * stage.units_per_tick)
    assert stage.upper not in up and 0.0 in up


def test_a_homing_cut_short_keeps_the_last_homings_offset():
    """Homing cleared the Homing Offset (EEPROM, kept over a power cycle) before it drove
    to the stop: one cut short (here a blocked rail, refused by the free-travel check)
    left 0, and the next power-up's reading, which places the rail before it is homed
    (the fold's check), was off by the last offset. It is written only once the stop is
    found, so the last homing's stays."""
    from conftest import reg

    smap = load_servo_map()
    rail = smap.servos[16]
    out = rail.to_ticks(0.03)  # past a turn from its stop: the homing's offset is a turn
    with EmulatorProcess(positions={rail.id: out}) as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            drv.bring_up()
            kept = reg(emu.table(rail.id), "homing_offset")
            assert kept == TICKS_PER_REV  # the count started a turn below the stop
            emu.fault(f"block:{rail.id}")
            with pytest.raises(HomingError, match="did not move off where it stalled"):
                drv.home([rail])
            assert reg(emu.table(rail.id), "homing_offset") == kept


@pytest.mark.parametrize("how", ["fault", "ctrl-c"])
def test_a_stow_after_a_fault_or_a_ctrl_c_leaves_the_payload_where_it_is(caplog, how):
    """A payload stopped by a hardware fault is not stowed (it stays where the fault left
    it); a Ctrl-C mid-stow stops the motion, the payload holding where it is, and is a
    warning, not an exception (the session is still scored)."""
    from firmware_interface.deployment import stow_after_session

    smap = load_servo_map()
    stage = smap.servos[17]
    with EmulatorProcess() as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            drv.bring_up()
            move_to_home(drv, cleared=True)
            if how == "fault":
                emu.fault("error:3:overload")
                drv.read()
                assert drv.fault is not None
            else:
                sends, send = [0], drv.send

                def interrupted(c):
                    sends[0] += 1
                    if sends[0] == 30:  # the fingers on their way
                        raise KeyboardInterrupt
                    send(c)

                drv.send = interrupted
            before = {i: s["pos"] for i, s in emu.servos().items()}
            with caplog.at_level(logging.WARNING, logger="firmware_interface"):
                assert stow_after_session(drv) is False
            time.sleep(0.3)
            held = {i: s["pos"] for i, s in emu.servos().items()}
            time.sleep(0.3)
            after = {i: s["pos"] for i, s in emu.servos().items()}
    said = [r.getMessage() for r in caplog.records if r.name == "firmware_interface.deployment"]
    assert len(said) == 1
    if how == "fault":
        assert said[0].startswith("the payload is not stowed: stopped by")
        assert all(abs(after[i] - before[i]) <= 1.0 for i in after)  # nothing moved
    else:
        assert said[0].startswith("stowing interrupted (Ctrl-C)")
        assert all(abs(after[i] - held[i]) <= band_ticks(smap.joint_of(i)) for i in after)
        assert abs(after[stage.id] - before[stage.id]) <= band_ticks("stage")  # still down


def test_a_posture_read_past_a_joints_limit_is_settled_at_the_limit():
    """A session can end with a servo past its joint's limit (overshooting a goal at the
    limit: C_mcp_flex read 0.045 rad past it under load); the stow held the posture it
    read, which the driver's send clips to the limit, and waited 6 s for the servo to
    reach the unclipped value ("did not reach its posture"). Settling waits for the limit."""
    from firmware_interface.deployment import settle, tolerance

    smap = load_servo_map()
    k = next(i for i, s in enumerate(smap.servos) if s.joint == "C_mcp_flex")
    lower = smap.servos[k].lower
    with EmulatorProcess() as emu:
        with DynamixelDriver(emu.port, smap, latency_timer_ms=LAT) as drv:
            drv.bring_up()
            home = move_to_home(drv, cleared=True)
            q = home.q.copy()
            q[k] = lower - 0.045
            state = settle(drv, PayloadCommand(q, home.deploy, 0.0), tolerance(drv), 6.0, "x")
            true = emu.servos()[smap.servos[k].id]["pos"]
    assert abs(state.q[k] - lower) <= band_ticks("C_mcp_flex") * smap.servos[k].units_per_tick
    assert abs(true - smap.servos[k].to_ticks(lower)) <= band_ticks("C_mcp_flex")
