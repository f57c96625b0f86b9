"""A scripted loaded stack: the payload holding the CTB in the scripted handle pinch,
moved rigidly anywhere along the route (for the safety filter's tests and bench)."""

from __future__ import annotations

from typing import Any, NamedTuple

import mujoco
import numpy as np

from payload.schema import PayloadCommand
from payload.sim.driver import SimDriver
from payload.sim.errors import SimError


class HeldStack(NamedTuple):
    """What a driver holds once the pinch has closed (copied into new drivers).

    Attributes:
        qpos: Generalised positions, shape (nq,).
        ctrl: Actuator targets, shape (nu,).
        goal: The driver's payload goal, shape (18,).
        target: The driver's slewed payload targets, shape (18,).
    """

    qpos: np.ndarray
    ctrl: np.ndarray
    goal: np.ndarray
    target: np.ndarray


def hold_ctb(world: Any) -> HeldStack:
    """Pre-shape, then close the scripted pinch on the CTB's handle (2.5 s simulated).

    Raises:
        SimError: The pinch did not close on both sides.
    """
    sim = SimDriver(world)
    pinch = world.pinch
    sim.send(PayloadCommand(pinch.command_q(False), pinch.stage, 0.0))
    sim.step(50)
    sim.send(PayloadCommand(pinch.command_q(True), pinch.stage, sim.time))
    if not sim.step(75).opposing_contact:
        raise SimError("hold_ctb: the scripted pinch did not close on the handle")
    return HeldStack(
        sim.data.qpos.copy(), sim.data.ctrl.copy(), sim._goal.copy(), sim._target.copy()
    )


def place_stack(
    world: Any, held: HeldStack, pos: Any, velocity: Any = (0.0, 0.0, 0.0)
) -> SimDriver:
    """A driver with the held stack moved rigidly so Astrobee's centre is at ``pos`` (3,)
    [m], Astrobee and the CTB moving at ``velocity`` (3,) [m/s, world], not rotating."""
    sim = SimDriver(world)
    d = sim.data
    d.qpos[:] = held.qpos
    d.ctrl[:] = held.ctrl
    sim._goal, sim._target = held.goal.copy(), held.target.copy()
    a, c = world.astrobee_qpos, world.ctb_qpos
    offset = np.asarray(pos, float) - d.qpos[a : a + 3]
    d.qpos[a : a + 3] += offset
    d.qpos[c : c + 3] += offset
    d.qvel[:] = 0.0
    d.qvel[world.astrobee_dof : world.astrobee_dof + 3] = velocity
    d.qvel[world.ctb_dof : world.ctb_dof + 3] = velocity
    mujoco.mj_forward(sim.model, d)
    return sim


__all__ = ["HeldStack", "hold_ctb", "place_stack"]
