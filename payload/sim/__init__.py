"""Zero-gravity MuJoCo ISS simulator: Kibo, the hatch vestibule and Node 2, Astrobee with the
payload attached in its lower bays, a rigid Cargo Transfer Bag, the bounded-wrench vehicle
controller, the opposing-contact indicator and :class:`SimDriver` (the ``PayloadDriver``
protocol). Physics at 1 kHz under a 50 Hz control loop.

Names load on first use (module ``__getattr__``), so importing the package (or
a command module inside it) costs no numerical library.
"""

from __future__ import annotations

from payload.lazy import lazy_exports

_LAZY: dict[str, str] = {
    "SIDES": "payload.sim.contact",
    "Contact": "payload.sim.contact",
    "ContactMonitor": "payload.sim.contact",
    "opposing": "payload.sim.contact",
    "SimDriver": "payload.sim.driver",
    "WorldState": "payload.sim.readout",
    "DEFAULT_FLIGHT_MODE": "payload.sim.vehicle",
    "FLIGHT_MODES": "payload.sim.vehicle",
    "FlightMode": "payload.sim.vehicle",
    "JerkLimitedProfile": "payload.sim.vehicle",
    "MassProperties": "payload.sim.vehicle",
    "VehicleController": "payload.sim.vehicle",
    "VehicleError": "payload.sim.vehicle",
    "Wrench": "payload.sim.vehicle",
    "flight_mode": "payload.sim.vehicle",
    "min_time_to_speed": "payload.sim.vehicle",
    "CONTROL_DT": "payload.sim.world",
    "CTB_SIZES": "payload.sim.world",
    "PAYLOAD_PREFIX": "payload.sim.world",
    "PHYSICS_DT": "payload.sim.world",
    "SUBSTEPS": "payload.sim.world",
    "CtbSize": "payload.sim.world",
    "Handle": "payload.sim.world",
    "IssLayout": "payload.sim.world",
    "IssModule": "payload.sim.world",
    "PinchGrasp": "payload.sim.world",
    "SimError": "payload.sim.world",
    "World": "payload.sim.world",
    "WorldConfig": "payload.sim.world",
    "Zone": "payload.sim.world",
    "build_spec": "payload.sim.world",
    "build_world": "payload.sim.world",
    "pinch_grasp": "payload.sim.world",
    "servo_limits": "payload.sim.world",
}
"""Each public name and the module defining it."""

__all__ = sorted(_LAZY)


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
