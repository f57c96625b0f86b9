"""``payload bench hw``: the per-cycle cost of the bus against the wire time it implies."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from firmware_interface import protocol as P
from firmware_interface.driver import FEEDBACK_LEN, bring_up_notice, failed_start
from firmware_interface.errors import DynamixelError
from firmware_interface.options import latency_of
from payload.errors import RunAborted
from payload.schema import PayloadCommand


def cycle_wire_time(n_servos: int, baud: int, return_delay_s: float = 0.0) -> float:
    """Wire time of one cycle [s]: the goal sync write, the fast sync read and its reply."""
    write = len(P.build(P.BROADCAST_ID, P.SYNC_WRITE, bytes(4 + 5 * n_servos), stuffing=False))
    read = len(P.build(P.BROADCAST_ID, P.FAST_SYNC_READ, bytes(4 + n_servos), stuffing=False))
    reply = P.PACKET_HEAD + (FEEDBACK_LEN + P.FAST_RECORD_OVERHEAD) * n_servos
    return P.wire_time(write + read + reply, baud) + return_delay_s


def bench_hw(
    port: str | None,
    cycles: int,
    servos: str | None = None,
    latency_ms: float | None = None,
    say: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Time ``cycles`` cycles (send + read) after bring-up.

    Args:
        port: The bus; None starts an emulator in its own process.
        cycles: Cycles to time.
        servos: Servo map file.
        latency_ms: Reply timeout allowance (the SDK's LATENCY_TIMER) [ms]; default the
            adapter's, or the emulator's it starts (:func:`~firmware_interface.options.latency_of`).
        say: Told :func:`~firmware_interface.driver.bring_up_notice` before the bring-up
            (the rail and the stage move to their hard stops).

    Raises:
        BringUpFailed: The bring-up failed (a servo missing or faulted, homing, the bus).
        RunAborted: The bus failed while the cycles were timed.

    Returns:
        ``cycles``, ``cycle_mean_us``, ``cycle_p99_us``, ``wire_us``, ``ratio_to_wire``,
        ``retries``, ``baud``, ``guard_us`` and ``guard_cpu_us`` (the mean wall-clock
        and CPU time of the driver's collision check of one command,
        :mod:`firmware_interface.guard`, included in every cycle),
        plus ``cycle_median_us``, ``fallbacks``, ``load_1min`` and the CPU time per
        cycle of the host (``host_cpu_us``) and of the emulator (``emulator_cpu_us``):
        on a loaded machine the wall-clock cycle mostly waits for the scheduler, and
        wire + CPU is what an idle machine would see.
    """
    from firmware_interface.driver import DynamixelDriver
    from firmware_interface.emulator import EmulatorProcess
    from firmware_interface.servo_map import load_servo_map

    smap = load_servo_map(servos)
    emu = EmulatorProcess(servos) if port is None else None
    latency = latency_of(latency_ms, emu is not None)
    try:
        with DynamixelDriver(
            port or emu.port, smap, health_every=cycles + 10, latency_timer_ms=latency
        ) as drv:
            if say is not None:
                say(bring_up_notice(drv.device))
            with failed_start(drv.device):
                drv.bring_up()
            try:
                return _timed(drv, emu, smap, cycles)
            except DynamixelError as exc:  # the hardware's state, not the command line's
                raise RunAborted(f"bench on {drv.device} stopped: {exc}") from None
    finally:
        if emu is not None:
            emu.close()


def _timed(drv: Any, emu: Any, smap: Any, cycles: int) -> dict[str, Any]:
    """The timed cycles of :func:`bench_hw` on a brought-up driver, and the report."""
    state = drv.read()
    cmd = PayloadCommand(state.q, state.deploy, 0.0)
    for _ in range(20):  # warm up
        drv.send(cmd)
        drv.read()
    drv.retry_count = 0
    times = np.empty(cycles)
    cpu0 = time.process_time()
    emu0 = emu.request(op="cpu")["cpu_s"] if emu is not None else None
    for k in range(cycles):
        t0 = time.perf_counter()
        drv.send(cmd)
        drv.read()
        times[k] = time.perf_counter() - t0
    host_cpu = (time.process_time() - cpu0) / cycles
    emu_cpu = (emu.request(op="cpu")["cpu_s"] - emu0) / cycles if emu is not None else None
    retries, fallbacks = drv.retry_count, drv.fallbacks
    # the collision guard's check of one command (part of every send above)
    values = np.append(cmd.q, cmd.deploy)
    guard_us, guard_cpu_us = (
        drv.guard.cost_us(values, min(cycles, 500)) if drv.guard else (None, None)
    )
    device = "emulator" if emu is not None else drv.device
    wire = cycle_wire_time(len(smap.servos), smap.baud, smap.return_delay * 2e-6)
    mean = float(times.mean())
    return {
        "cycles": cycles,
        "cycle_mean_us": mean * 1e6,
        "cycle_p99_us": float(np.percentile(times, 99)) * 1e6,
        "wire_us": wire * 1e6,
        "ratio_to_wire": mean / wire,
        "retries": retries,
        "baud": smap.baud,
        "cycle_median_us": float(np.median(times)) * 1e6,
        "fallbacks": fallbacks,
        "device": device,
        "port": device,  # the device's field name before --device (kept)
        "host_cpu_us": host_cpu * 1e6,
        "emulator_cpu_us": emu_cpu * 1e6 if emu_cpu is not None else None,
        "guard_us": guard_us,
        "guard_cpu_us": guard_cpu_us,
        "load_1min": os.getloadavg()[0],
    }
