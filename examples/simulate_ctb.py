"""Fly Astrobee with the payload deployed over a CTB: the simulator example of docs/simulator.md.

Run it from the project root (``python examples/simulate_ctb.py``; about a second). The
fingers hold their measured posture while the vehicle is asked for 5 cm/s forward for
6.5 s (the vehicle controller bounds the acceleration by the flight mode and the
propulsion). It prints one JSON object with a sample every 0.5 s: time, Astrobee's
position and orientation (w, x, y, z) in the world, and its body-frame velocity.
"""

from __future__ import annotations

import json

import numpy as np

from payload.schema import PayloadCommand, VehicleTwist
from payload.sim import SimDriver

with SimDriver() as sim:  # deployed, CTB under the fingers, route start
    held = sim.read()  # PayloadState: hold the measured posture
    command = PayloadCommand(held.q, held.deploy, stamp=0.0)
    twist = VehicleTwist(np.array([0.05, 0.0, 0.0]), np.zeros(3), stamp=0.0)
    sim.send(command)  # PayloadCommand (17 joints in paper order + deploy)
    sim.command_twist(twist)  # VehicleTwist in the body frame; None = drift
    states = [sim.step(25) for _ in range(13)]  # 0.5 s each: poses, twist, contacts, module
    measured = sim.read()  # PayloadState

samples = [
    {
        "time": s.time,
        "position": s.astrobee_pos.tolist(),
        "quaternion": s.astrobee_quat.tolist(),
        "body_velocity": s.astrobee_linear.tolist(),
        "opposing_contact": s.opposing_contact,
    }
    for s in states
]
print(json.dumps({"commanded_speed": 0.05, "samples": samples, "deploy": measured.deploy}))
