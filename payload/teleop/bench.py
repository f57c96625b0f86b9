"""``payload bench teleop``: latency of the live interface through an emulated Quest 3.

The whole product runs as in use (the server, the default trial scene, the 50 Hz loop
paced to the wall clock) and the page runs unchanged in headless Chromium with Meta's
iwer emulating a Quest 3 with hands. The emulated operator follows the calibration
prompts and then flies forward with the left wrist. Reported, from the server's own
counters: the age of each frame on arrival (page clock synchronised at connect) and the
end-to-end latency from an XR frame to the command sent to the driver, median and p99.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from payload.cliutil import load_average
from payload.teleop.live import LiveHub, percentiles
from payload.teleop.server import TeleopServer


def _loads() -> dict[str, list[float]]:
    """The load averages at the run's end, under the bench's own older name (``load``) and
    every bench's (``load_average``)."""
    now = load_average()
    return {"load": now, "load_average": now}


def run_bench(make_session: Callable[[LiveHub], Any], seconds: float = 20.0) -> dict[str, Any]:
    """Run the emulated session; returns the figures (see the module docstring).

    Args:
        make_session: Makes the live session from the hub (the command line passes
            :class:`payload.trials.live.LiveSession`, from the layer above).
        seconds: Teleoperation time to measure [s].
    """
    import threading

    from payload.teleop.emulate import EmulatedQuest

    hub = LiveHub()
    session = make_session(hub)
    server = TeleopServer(hub, port=0, scene=session.scene).start()
    worker = threading.Thread(target=session.run, name="teleop-loop", daemon=True)
    worker.start()
    try:
        with EmulatedQuest(server.url()) as quest:

            def server_state() -> dict[str, Any]:
                with hub.lock:
                    return {**hub.snapshot, "state": hub.state}

            quest.follow_calibration(timeout=180, state=server_state)
            with hub.lock:  # measure teleoperation only
                hub.frame_age_ms.clear()
                hub.latency_ms.clear()
                overruns0, steps0 = hub.loop_overruns, session.steps
            sent0 = quest.debug()["sent"]
            quest.gesture("neutral", forward=0.15)
            time.sleep(seconds)
            with hub.lock:
                ages, lat = list(hub.frame_age_ms), list(hub.latency_ms)
                overruns, steps = hub.loop_overruns - overruns0, session.steps - steps0
            sent = quest.debug()["sent"]
    finally:
        hub.stop.set()
        worker.join(30)
        server.stop()
        session.close()
    return {
        "seconds": seconds,
        "frames": len(ages),
        "page_frames_sent": sent,  # since the page opened, calibration included
        "page_frames_sent_measured": sent - sent0,  # in the measured time, as ``frames``
        "frame_age_ms": percentiles(ages),
        "latency_ms": percentiles(lat),
        "steps": steps,
        "loop_overruns": overruns,
        **_loads(),
    }


def run_filter_bench(seconds: float = 8.0) -> dict[str, Any]:
    """The base safety filter's cost per control step, timed inside the filter, while
    the loaded stack is flown at Kibo's side wall under a full-speed request (the filter
    acting most of the run) and then across mid-Kibo (the identity).

    Returns:
        ``{"median_us", "p99_us", "cpu_median_us", "cpu_p99_us", "constraints",
        "active_steps", "steps", "load"}``: per-step wall-clock time [us] over every step,
        the same in the thread's CPU time (what the step costs without waiting for a
        core on a loaded machine), the most constraints in one QP.
    """
    import numpy as np

    from payload.schema import VehicleTwist
    from payload.sim.stack import hold_ctb, place_stack
    from payload.sim.world import build_world
    from payload.teleop.base_filter import BaseSafetyFilter
    from payload.teleop.channels import BaseConfig

    world = build_world()
    held = hold_ctb(world)
    times, cpu, most, active = [], [], 0, 0
    for pos, v0, request in (
        ((1.6, 7.0, 0.25), (0.06, 0.0, 0.0), (0.2, 0.0, 0.0)),
        ((1.5, 7.0, 0.25), (0.0, -0.05, 0.0), (0.0, -0.05, 0.0)),
    ):
        sim = place_stack(world, held, pos, v0)
        c = sim.controller
        filt = BaseSafetyFilter(world, BaseConfig(), c.accel_max, float(c.jerk[0]))

        def timed(twist: Any, data: Any, filt: Any = filt) -> Any:
            wall, own = time.perf_counter(), time.thread_time()
            out = filt(twist, data)
            cpu.append((time.thread_time() - own) * 1e6)
            times.append((time.perf_counter() - wall) * 1e6)
            return out

        sim.twist_filter = timed
        for _ in range(round(seconds * 25)):
            rot = sim.data.xmat[world.astrobee].reshape(3, 3)
            sim.command_twist(VehicleTwist(rot.T @ np.asarray(request), np.zeros(3), 0.0))
            sim.step()
            most = max(most, filt.status.constraints)
            active += filt.status.active
    return {
        "median_us": float(np.median(times)),
        "p99_us": float(np.percentile(times, 99)),
        "cpu_median_us": float(np.median(cpu)),
        "cpu_p99_us": float(np.percentile(cpu, 99)),
        "constraints": most,
        "active_steps": active,
        "steps": len(times),
        **_loads(),
    }
