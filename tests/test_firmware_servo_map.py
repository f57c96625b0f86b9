"""The servo map: validation against the design, and the joint <-> tick conversions."""

from __future__ import annotations

import copy
import math
import sys

import numpy as np
import pytest

from firmware_interface.servo_map import ServoMapError, load_servo_map, servo_map_from_dict
from payload.design.tree import ALL_JOINTS

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


@pytest.fixture(scope="module")
def map_dict():
    from firmware_interface.servo_map import default_map_text

    return tomllib.loads(default_map_text())


def test_default_map_covers_every_joint_once(design):
    smap = load_servo_map(design=design)
    assert [s.joint for s in smap.servos] == list(ALL_JOINTS)
    assert len(set(smap.ids)) == 18
    assert smap.current_limit_ma == round(design.servo.current_limit * 1000) == 350


def test_rail_and_stage_follow_the_design_rack_and_pinion(design):
    """x = r * theta: one servo turn (4096 ticks) moves the carriage 2 pi r."""
    smap = load_servo_map(design=design)
    rail, stage = smap.servos[-2], smap.servos[-1]
    for spec, r in ((rail, design.rail.drive_radius), (stage, design.stage.drive_radius)):
        x = 0.0314
        ticks = spec.to_ticks(x)
        assert ticks - spec.zero == spec.direction * round(x / (2 * math.pi * r) * 4096)
        assert spec.from_ticks(spec.zero + spec.direction * 4096) == pytest.approx(2 * math.pi * r)


def test_gear_scales_the_linear_conversion(map_dict, design):
    d = copy.deepcopy(map_dict)
    d["servo"][16]["gear"] = 3.0
    geared = servo_map_from_dict(d, design).servos[-2]
    plain = servo_map_from_dict(map_dict, design).servos[-2]
    assert geared.units_per_tick == pytest.approx(plain.units_per_tick / 3.0)


def test_round_trip_within_one_tick_with_directions_and_offsets(design):
    smap = load_servo_map(design=design)
    rng = np.random.default_rng(0)
    for spec in smap.servos:
        for v in rng.uniform(spec.lower, spec.upper, 50):
            back = spec.from_ticks(spec.to_ticks(v))
            assert abs(back - v) <= 0.5 * spec.units_per_tick + 1e-12
        # direction: increasing joint value moves the ticks by the direction's sign
        a, b = spec.to_ticks(spec.lower), spec.to_ticks(spec.upper)
        assert np.sign(b - a) == spec.direction


def test_commands_are_clamped_to_the_limits_before_conversion(design):
    smap = load_servo_map(design=design)
    s = smap.servos[0]
    assert s.to_ticks(s.upper + 1.0) == s.to_ticks(s.upper)
    assert s.to_ticks(s.lower - 1.0) == s.to_ticks(s.lower)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["servo"].pop(3), "not mapped: A_dip"),
        (lambda d: d["servo"][3].update(joint="A_pip"), "A_pip is mapped twice"),
        (lambda d: d["servo"][3].update(id=1), "ID 1 is used by A_mcp_flex and A_dip"),
        (lambda d: d["servo"][0].update(joint="E_pip"), "'E_pip' is not a joint"),
        # counted from 1, and the joint a misspelling is closest to named
        (
            lambda d: d["servo"][2].update(joint="A_pipp"),
            r"m.toml: \[\[servo\]\] table 3.joint: 'A_pipp' is not a joint of the design "
            r"\(did you mean 'A_pip'\?\)",
        ),
        (lambda d: d["servo"][0].update(upper=3.0), "not inside the design's"),
        (lambda d: d["servo"][16].update(upper=0.2), "not inside the design's"),
        (lambda d: d["servo"][0].update(direction=2), "direction: expected 1 or -1"),
        (lambda d: d["servo"][0].update(gear=2.0), "only the rail and the stage"),
        (lambda d: d.update(watchdog_ms=30), "multiple of 20"),
        (lambda d: d.update(on_fault="explode"), "on_fault"),
    ],
)
def test_bad_maps_name_the_entry(map_dict, design, edit, message):
    d = copy.deepcopy(map_dict)
    edit(d)
    with pytest.raises(ServoMapError, match=message):
        servo_map_from_dict(d, design, "m.toml")
