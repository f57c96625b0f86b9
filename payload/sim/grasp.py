"""The scripted handle pinch: the finger pre-shape, first contact and where the CTB starts."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import mujoco
import numpy as np

from payload.design import FINGERS, SIDE_OF, Design
from payload.design.servo import joint_servo
from payload.sim.astrobee import design_vehicle, payload_mount
from payload.sim.config import WorldConfig
from payload.sim.errors import SimError
from payload.sim.pads import pose_payload

PINCH_CLEARANCE = 0.005
"""Least gap between the pads and the handle at the pre-shape [m]; a design that leaves
less makes :func:`pinch_grasp` refuse."""

PINCH_TORQUE_FRACTION = 5.0 / 6.0
"""Share of the current-capped torque the pinch asks of each MCP servo. Below the cap the
fingers act as springs, which lets the handle settle under the yaw couple of the staggered
opposing fingers (A/C and B/D are offset along x); saturated fingers push equally and the
handle keeps yawing. (Before the servo model, kp 3 N m/rad with a 0.05 rad squeeze asked
0.15 N m: the same 83 %.)"""


def pinch_squeeze(design: Design) -> float:
    """MCP flexion commanded past first contact for the pinch [rad]: the servo's
    proportional torque ``kp x squeeze`` is :data:`PINCH_TORQUE_FRACTION` of its torque cap
    (``kt x Goal Current``), both from the servo model (:mod:`payload.design.servo`)."""
    js = joint_servo(design, "finger")
    return PINCH_TORQUE_FRACTION * js.torque_cap / js.kp


class PinchGrasp(NamedTuple):
    """The scripted handle pinch, derived from the design and the handle.

    Attributes:
        open: Pre-shape (mcp_flex, mcp_abd, pip, dip) for every finger [rad].
        closed: Closing command for every finger [rad].
        contact_mcp: MCP flexion at which the pads first touch the handle [rad].
        rail: Rail position of the grasp [m].
        stage: Deployment of the grasp [m].
    """

    open: tuple[float, float, float, float]
    closed: tuple[float, float, float, float]
    contact_mcp: float
    rail: float
    stage: float

    def command_q(self, closed: bool) -> np.ndarray:
        """The 17 manipulation coordinates (paper order) for the open or closed pinch."""
        finger = self.closed if closed else self.open
        return np.array([*finger * len(FINGERS), self.rail])


class _PayloadKinematics:
    """Forward kinematics of the payload model alone (payload frame)."""

    def __init__(self, payload_mjcf: Path) -> None:
        self.model = mujoco.MjModel.from_xml_path(str(payload_mjcf))
        self.data = mujoco.MjData(self.model)

    def tips(self, finger: Sequence[float], rail: float, stage: float) -> np.ndarray:
        """Fingertip points of A, B, C, D, shape (4, 3) [m], all fingers at ``finger``."""
        m, d = self.model, self.data
        pose_payload(m, d, finger, rail, stage)
        mujoco.mj_kinematics(m, d)
        return np.array(
            [
                d.site_xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{f}_tip")]
                for f in FINGERS
            ]
        )


def pinch_grasp(design: Design, config: WorldConfig) -> PinchGrasp:
    """The handle pinch for this design and handle.

    The first-contact MCP flexion solves ``|y_tip| - r_pad = w_handle / 2`` (pad sphere on
    the handle's side face) by bisection on the payload model's kinematics; the closing
    command adds :func:`pinch_squeeze`.

    Raises:
        SimError: The pads cannot reach the handle from the pre-shape.
    """
    kin = _PayloadKinematics(config.payload_mjcf)
    rail, stage = design.home.rail, design.home.stage
    preshape = design.pinch.finger
    face = config.handle.width / 2.0 + design.finger.pad.radius

    side = np.array([1.0 if SIDE_OF[f] == 1 else -1.0 for f in FINGERS])  # +y is side 1

    def gap(mcp: float) -> float:
        tips = kin.tips((mcp, *preshape[1:]), rail, stage)
        return float(np.min(side * tips[:, 1])) - face

    # search the first 0.6 rad of closing: the pads cross the array's mid-plane within it
    lo = preshape[0]
    hi = min(lo + 0.6, design.finger.limits.mcp_flex.upper)
    if gap(lo) < PINCH_CLEARANCE:
        raise SimError(
            f"pinch_grasp: the pre-shape leaves {gap(lo) * 1e3:.1f} mm between the pads and "
            f"the handle, less than {PINCH_CLEARANCE * 1e3:.0f} mm (handle too wide?)"
        )
    if gap(hi) > 0.0:
        raise SimError("pinch_grasp: the fingertips cannot reach the handle")
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if gap(mid) > 0.0 else (lo, mid)
    contact = 0.5 * (lo + hi)
    closed = (contact + pinch_squeeze(design), *preshape[1:])
    return PinchGrasp(preshape, closed, contact, rail, stage)


def ctb_offset(design: Design, config: WorldConfig) -> np.ndarray:
    """Where the CTB centre starts in the Astrobee body frame, shape (3,) [m].

    The handle bar is centred on the four fingertips at the pinch pre-shape (deployed stage,
    home rail), so closing the fingers pinches it from both sides of the array.
    """
    size = config.ctb_size
    if size is None:
        raise SimError("ctb_offset: the world has no CTB")
    kin = _PayloadKinematics(config.payload_mjcf)
    tips = kin.tips(design.pinch.finger, design.home.rail, design.home.stage)
    tips = tips + payload_mount(design_vehicle(design))
    centre = tips.mean(axis=0)
    h = config.handle
    drop = h.height / 2.0 + h.standoff + size.height / 2.0
    return np.array([centre[0], centre[1], centre[2] - drop])
