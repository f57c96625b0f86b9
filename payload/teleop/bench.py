"""``payload bench teleop``: latency of the live interface through an emulated Quest 3.

The whole product runs as in use (the server, the default trial scene, the 50 Hz loop
paced to the wall clock) and the page runs unchanged in headless Chromium with Meta's
iwer emulating a Quest 3 with hands. The emulated operator follows the calibration
prompts and then flies forward with the left wrist. Reported, from the server's own
counters: the age of each frame on arrival (page clock synchronised at connect) and the
end-to-end latency from an XR frame to the command sent to the driver, median and p99.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

from payload.teleop.live import LiveHub, percentiles
from payload.teleop.server import TeleopServer


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
        "page_frames_sent": sent,
        "frame_age_ms": percentiles(ages),
        "latency_ms": percentiles(lat),
        "steps": steps,
        "loop_overruns": overruns,
        "load": [round(x, 2) for x in os.getloadavg()],
    }
