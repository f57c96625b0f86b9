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
from payload.sim.cargo import CTB_SIZES
from payload.sim.pads import pad_contact, pad_stiffness, patch_radius
from payload.sim.world import PHYSICS_DT
from payload.teleop.operator import OperatorTraits

SINGLE_CTB_KG = CTB_SIZES["single"].mass
"""The single CTB's loaded mass [kg], the load the pads are sized for."""


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


def test_hertz_stiffness_against_the_integrated_pressure(design):
    """Hertz's pressure p(r) = p0 sqrt(1 - r^2 / a^2), p0 = 2 E* a / (pi R), a^2 = R delta
    (Johnson 1985, eq. 4.21-4.24), integrated over the patch numerically, carries the design
    load at the derived indentation; k is the slope of that integral there; the contact
    radius is under the skin thickness (the half-space premise)."""
    p = design.finger.pad
    e_star = p.modulus / (1 - 0.5**2)

    def force(delta: float) -> float:
        a = math.sqrt(p.radius * delta)
        p0 = 2 * e_star * a / (math.pi * p.radius)
        r = np.linspace(0.0, a, 20001)
        return float(
            np.trapezoid(p0 * np.sqrt(np.clip(1 - (r / a) ** 2, 0, None)) * 2 * np.pi * r, r)
        )

    k, delta0 = pad_stiffness(design)
    assert force(delta0) == pytest.approx(p.load, rel=1e-4)
    h = 1e-7
    assert k == pytest.approx((force(delta0 + h) - force(delta0 - h)) / (2 * h), rel=1e-3)
    assert patch_radius(design) == pytest.approx(math.sqrt(p.radius * delta0))
    assert patch_radius(design) < p.thickness


def test_mujoco_contact_has_the_derived_stiffness_and_is_critically_damped(design):
    c = pad_contact(design, str(MJCF), design.pinch.finger, SINGLE_CTB_KG, PHYSICS_DT)
    assert not c.clamped and c.dampratio >= 1.0
    # MuJoCo, not our formula: the indentation at the design load is the pad's
    pen = _penetration(c.solref, c.solimp, c.effective_mass, design.finger.pad.load)
    assert pen == pytest.approx(c.indentation, rel=0.1)
    # a quarter of the load: Hertz's F ~ delta^(3/2) gives 0.25^(2/3) of the indentation
    quarter = _penetration(c.solref, c.solimp, c.effective_mass, 0.25 * design.finger.pad.load)
    assert quarter == pytest.approx(0.25 ** (2 / 3) * c.indentation, rel=0.1)
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
    c = pad_contact(design, str(MJCF), design.pinch.finger, SINGLE_CTB_KG, PHYSICS_DT)
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


def test_pad_contact_lands_on_hertz_at_the_design_load_and_half_way(design):
    """MuJoCo's resting secant is ``F / r = m d^2 / ((1 - d) dmax^2 timeconst^2
    dampratio^2)`` (the documentation's resting penetration ``a (1 - d) timeconst^2
    dampratio^2`` at ``d = dmax``; docs/sources.md, "Pad contact"), so the
    derived solref puts the design load at Hertz's indentation delta0 exactly, and
    Hertz's force at delta0 / 2 (``0.5^1.5 F0``, the sigmoid's midpoint) at delta0 / 2.
    The earlier law ``m d / (1 - d)`` left the pad 1 / dmax (5 %) too soft."""
    c = pad_contact(design, str(MJCF), design.pinch.finger, SINGLE_CTB_KG, PHYSICS_DT)
    load = design.finger.pad.load
    pen = _penetration(c.solref, c.solimp, c.effective_mass, load)
    assert pen == pytest.approx(c.indentation, rel=1e-6)
    half = _penetration(c.solref, c.solimp, c.effective_mass, 0.5**1.5 * load)
    assert half == pytest.approx(0.5 * c.indentation, rel=1e-6)


@pytest.mark.parametrize("d", [0.5, 0.9, 0.95])
def test_mujoco_resting_secant_goes_as_d_squared_over_one_minus_d(d):
    """The secant law the pad derivation rests on, against MuJoCo with a constant
    impedance (dmin = dmax = d)."""
    tc, zeta, mass, force = 0.01, 1.5, 0.05, 1.0
    pen = _penetration((tc, zeta), (d, d, 0.001, 0.5, 2.0), mass, force)
    expected = mass * d * d / ((1 - d) * d * d * tc * tc * zeta * zeta)
    assert force / pen == pytest.approx(expected, rel=1e-6)


def test_the_pad_figures_quoted_in_docs_trials_are_the_derived_ones(design):
    """docs/trials.md's pad paragraph quotes the indentation, tangent stiffness,
    effective mass and time constant of the derived contact (single CTB, 1 ms)."""
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "trials.md").read_text()
    para = text[text.index("Pads. The pad contact") :].split("\n\n")[0]
    c = pad_contact(design, str(MJCF), design.pinch.finger, SINGLE_CTB_KG, PHYSICS_DT)

    def quoted(pattern: str) -> float:
        return float(re.search(pattern, para.replace("\n", " ")).group(1))

    assert quoted(r"gives ([\d.]+) mm indentation") == pytest.approx(c.indentation * 1e3, abs=0.005)
    assert quoted(r"stiffness of ([\d.]+) kN/m") == pytest.approx(c.stiffness / 1e3, abs=0.05)
    assert quoted(r"about ([\d.]+) kg") == pytest.approx(c.effective_mass, abs=0.005)
    assert quoted(r"constant \(([\d.]+) ms") == pytest.approx(c.timeconst * 1e3, abs=0.05)
