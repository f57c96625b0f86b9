"""Pads that land like silicone: contact parameters from the pad material, checked in MuJoCo."""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np
import pytest
from conftest import MJCF

from payload.design import load_design
from payload.design.params import DesignError
from payload.schema import PayloadCommand
from payload.sim import SimDriver, WorldConfig, build_world
from payload.sim.pads import pad_contact, pad_stiffness
from payload.sim.world import PHYSICS_DT
from payload.teleop.operator import OperatorTraits


@pytest.fixture(scope="module")
def design():
    return load_design()


def _penetration(solref, solimp, mass: float, force: float) -> float:
    """Steady penetration of a free sphere of ``mass`` pushed onto a plane with ``force``."""
    xml = f"""<mujoco><option timestep="{PHYSICS_DT}" gravity="0 0 0"/><worldbody>
      <geom type="plane" size="1 1 .1"/>
      <body pos="0 0 0.011"><freejoint/>
        <geom type="sphere" size="0.011" mass="{mass}" priority="1"
              solref="{solref[0]} {solref[1]}" solimp="{" ".join(str(v) for v in solimp)}"/>
      </body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    for _ in range(4000):
        d.xfrc_applied[1, 2] = -force
        mujoco.mj_step(m, d)
    assert abs(d.qvel[2]) < 1e-6  # settled
    return 0.011 - float(d.qpos[2])


def test_thin_layer_stiffness_closed_form(design):
    p = design.finger.pad
    k, delta0 = pad_stiffness(design)
    # F = 2 pi E R delta^2 / h at the design load, and k is its slope there
    assert 2 * math.pi * p.modulus * p.radius * delta0**2 / p.thickness == pytest.approx(p.load)
    f = lambda x: 2 * math.pi * p.modulus * p.radius * x**2 / p.thickness  # noqa: E731
    h = 1e-9
    assert k == pytest.approx((f(delta0 + h) - f(delta0 - h)) / (2 * h), rel=1e-5)


def test_mujoco_contact_has_the_derived_stiffness_and_is_critically_damped(design):
    c = pad_contact(design, str(MJCF), design.pinch.finger, 15.4, PHYSICS_DT)
    assert not c.clamped and c.dampratio >= 1.0
    # MuJoCo, not our formula: the indentation at the design load is the pad's
    pen = _penetration(c.solref, c.solimp, c.effective_mass, design.finger.pad.load)
    assert pen == pytest.approx(c.indentation, rel=0.1)
    # a quarter of the load: the thin layer's F ~ delta^2 gives half the indentation
    quarter = _penetration(c.solref, c.solimp, c.effective_mass, 0.25 * design.finger.pad.load)
    assert quarter == pytest.approx(0.5 * c.indentation, rel=0.1)
    # critically damped: a pad dropped onto the plane does not rebound
    xml_mass = c.effective_mass
    xml = f"""<mujoco><option timestep="{PHYSICS_DT}" gravity="0 0 0"/><worldbody>
      <geom type="plane" size="1 1 .1"/>
      <body pos="0 0 0.0115"><freejoint/>
        <geom type="sphere" size="0.011" mass="{xml_mass}" priority="1"
              solref="{c.solref[0]} {c.solref[1]}" solimp="{" ".join(str(v) for v in c.solimp)}"/>
      </body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qvel[2] = -0.02  # landing at 2 cm/s
    z = []
    for _ in range(300):
        mujoco.mj_step(m, d)
        z.append(d.qvel[2])
    # overdamped: MuJoCo's soft contact rebounds about 14 % at dampratio 1, 5 % at 2
    assert max(z) < 0.06 * 0.02


def test_pad_design_is_validated(design):
    pad = dataclasses.replace(design.finger.pad, damping_ratio=0.5)
    bad = dataclasses.replace(design, finger=dataclasses.replace(design.finger, pad=pad))
    with pytest.raises(DesignError, match="damping_ratio"):
        bad.validate()


def test_world_pads_carry_the_derived_contact(design):
    w = build_world(WorldConfig(ctb="single"))
    c = pad_contact(design, str(MJCF), design.pinch.finger, 15.4, PHYSICS_DT)
    for g in w.pad_geoms.values():
        np.testing.assert_allclose(w.model.geom_solref[g], c.solref)
        np.testing.assert_allclose(w.model.geom_solimp[g], c.solimp)
        assert w.model.geom_priority[g] > 0  # the pad's parameters rule its contacts


def test_scripted_closing_at_the_operators_rate_gives_one_continuous_contact():
    """Close the pinch from its pre-shape at the synthetic operator's mean closing rate
    (the aperture of a half-open hand, 0.5, closed at the traits' mean rate, in seconds)
    onto the handle: from the first opposing contact on, it never drops."""
    lo, hi = 0.18, 0.32  # OperatorTraits.sample's close_rate range [1/s]
    rate = 0.5 * (lo + hi)
    assert OperatorTraits().close_rate == pytest.approx(rate)
    duration = 0.5 / rate
    w = build_world(WorldConfig(ctb="single"))
    sim = SimDriver(w)
    p = w.pinch
    q_open, q_closed = p.command_q(False), p.command_q(True)
    sim.send(PayloadCommand(q_open, p.stage, 0.0))
    for _ in range(50):
        sim.step()
    flags = []
    for k in range(int((duration + 2.0) / 0.02)):
        s = min(1.0, k * 0.02 / duration)
        sim.send(PayloadCommand(q_open + s * (q_closed - q_open), p.stage, sim.time))
        flags.append(sim.step().opposing_contact)
    f = np.array(flags)
    assert f.any()
    first = int(np.argmax(f))
    assert f[first:].all(), f"contact dropped {int((~f[first:]).sum())} times after first touch"
    assert sim.warnings() == {}
