"""The safety side of a trial: station contacts, the base filter's record, the keep-in boxes.

:class:`SafetyScene` wraps the recording's Foxglove scene (it is handed to the recorder in
its place) and adds, at every step, one JSON message on ``/safety/filter`` (plottable in
Foxglove: the filter's clearance, the binding shape and obstacle face, how much it changed
the command, and the station contact and clearance measured by
:class:`~payload.sim.station.StationMonitor`), and the keep-in boxes as a
``foxglove.SceneUpdate`` on ``/safety/keepin``. :meth:`SafetyScene.summary` gives the
trial's ``station_contacts``, ``min_station_clearance_mm`` (at most
``station_clearance_cap_mm``, the distance beyond which none is measured) and
``filter_active_s``.

The recorder writes its messages in batches, up to a second after the step, so each
step's record is taken at the step (:meth:`SafetyScene.observe`, called by whoever runs
the loop) and written with the step. :func:`recording_scene` is the scene of every
recording the simulator makes: a synthetic trial's and a live session's.
"""

from __future__ import annotations

import json
import math
from collections import deque
from typing import Any

from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from mcap_protobuf.schema import build_file_descriptor_set

from payload.schema import CONTROL_DT
from payload.sim.station import CLEARANCE_CAP, StationMonitor
from payload.sim.zones import StationZones, station_zones
from payload.trials.records import RecordingError

FILTER_TOPIC = "/safety/filter"
KEEPIN_TOPIC = "/safety/keepin"

_FILTER_SCHEMA = {
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "control time [s]"},
        "active": {"type": "boolean", "description": "the filter changed the command"},
        "filter_clearance_m": {
            "type": "number",
            "description": "least distance of the "
            "filter's sample points to the keep-in boundary [m]",
        },
        "shape": {"type": "string", "description": "astrobee, payload or ctb"},
        "face": {"type": "string", "description": "binding keep-in face"},
        "change_mps": {"type": "number", "description": "|filtered - requested| velocity"},
        "yaw_change_radps": {"type": "number", "description": "filtered - requested yaw rate"},
        "constraints": {"type": "integer"},
        "station_contact": {"type": "boolean"},
        "station_clearance_m": {"type": "number", "description": "MuJoCo distance, capped"},
    },
}


def keepin_boxes(zones: StationZones | None = None, layout: Any = None) -> list[dict[str, Any]]:
    """The keep-in (and keep-out) boxes for drawing: ``name``, ``lo``, ``hi`` [m],
    ``safe`` (true: keep-in). The Meshcat replay and the Foxglove scene read this."""
    zones = zones or station_zones(layout)
    out = [
        {"name": name, "lo": list(lo), "hi": list(hi), "safe": True}
        for name, (lo, hi) in zip(zones.names, zones.keepin)
    ]
    out += [
        {"name": f"keepout{i}", "lo": list(lo), "hi": list(hi), "safe": False}
        for i, (lo, hi) in enumerate(zones.keepout)
    ]
    return out


class SafetyScene:
    """The recording's Foxglove scene plus the safety channels (see the module docstring).

    Args:
        scene: The :class:`~payload.trials.foxglove.FoxgloveScene` it wraps.
        driver: The simulator driver (its data is read at each step; its
            ``twist_filter``, if any, is the base safety filter).
        zones: The keep-in boxes to draw (default: the world's layout).
    """

    def __init__(self, scene: Any, driver: Any, zones: StationZones | None = None) -> None:
        self.scene = scene
        self.driver = driver
        self.monitor = StationMonitor(driver.world)
        self.zones = zones or station_zones(driver.world.layout)
        self.channels: dict[str, int] = {}
        self.contacts = 0
        self.least = CLEARANCE_CAP
        self.active_steps = 0
        self._next_boxes_ns = 0
        self._observed: deque[dict[str, Any]] = deque()  # taken, not yet written

    def start(self, writer: Any) -> None:
        """Register the wrapped scene's channels and the safety channels."""
        self.scene.start(writer)
        schema = writer.register_schema(
            name="payload.SafetyFilter",
            encoding="jsonschema",
            data=json.dumps(_FILTER_SCHEMA).encode(),
        )
        self.channels[FILTER_TOPIC] = writer.register_channel(
            topic=FILTER_TOPIC, message_encoding="json", schema_id=schema
        )
        boxes = writer.register_schema(
            name=SceneUpdate.DESCRIPTOR.full_name,
            encoding="protobuf",
            data=build_file_descriptor_set(SceneUpdate).SerializeToString(),
        )
        self.channels[KEEPIN_TOPIC] = writer.register_channel(
            topic=KEEPIN_TOPIC, message_encoding="protobuf", schema_id=boxes
        )

    def observe(self, t: float) -> None:
        """Take the safety record of the control step at time ``t`` [s] from the
        simulator's state and the filter's status now (call it once per step, before the
        step is written); it is written, and counted, with that step."""
        reading = self.monitor.read(self.driver.data)
        record: dict[str, Any] = {
            "t": t,
            "station_contact": reading.contact,
            "station_clearance_m": reading.clearance,
        }
        status = getattr(getattr(self.driver, "twist_filter", None), "status", None)
        if status is not None:
            record.update(
                active=bool(status.active),
                filter_clearance_m=status.clearance if math.isfinite(status.clearance) else None,
                shape=status.shape,
                face=status.face,
                change_mps=status.change,
                yaw_change_radps=status.yaw_change,
                constraints=status.constraints,
            )
        self._observed.append(record)

    def discard(self) -> None:
        """Forget the records taken and not written (steps that will not be recorded)."""
        self._observed.clear()

    def write(self, writer: Any, step: Any, ns: int) -> None:
        """The wrapped scene's messages, then this step's safety record.

        Raises:
            RecordingError: The step's record was not taken (:meth:`observe`).
        """
        self.scene.write(writer, step, ns)
        if not self._observed or self._observed[0]["t"] != step.t:
            raise RecordingError(f"safety record of the step at t = {step.t} s was not taken")
        record = self._observed.popleft()
        self.contacts += record["station_contact"]
        self.least = min(self.least, record["station_clearance_m"])
        self.active_steps += bool(record.get("active", False))
        writer.add_message(
            channel_id=self.channels[FILTER_TOPIC],
            log_time=ns,
            publish_time=ns,
            data=json.dumps(record).encode(),
        )
        if ns >= self._next_boxes_ns:
            from payload.trials.foxglove import SCENE_PERIOD_S

            writer.add_message(
                channel_id=self.channels[KEEPIN_TOPIC],
                log_time=ns,
                publish_time=ns,
                data=self.boxes(ns).SerializeToString(),
            )
            self._next_boxes_ns = ns + round(SCENE_PERIOD_S * 1e9)

    def boxes(self, ns: int) -> SceneUpdate:
        """The keep-in boxes (green) and keep-out boxes (red), translucent, frame ``world``."""
        from payload.trials.foxglove import timestamp

        entity = SceneEntity(
            timestamp=timestamp(ns),
            frame_id="world",
            id="safety/keepin",
            frame_locked=True,
        )
        for box in keepin_boxes(self.zones):
            lo, hi = box["lo"], box["hi"]
            rgba = (0.2, 0.8, 0.3, 0.12) if box["safe"] else (0.9, 0.2, 0.2, 0.3)
            entity.cubes.append(
                CubePrimitive(
                    pose=Pose(
                        position=Vector3(**{k: (lo[i] + hi[i]) / 2 for i, k in enumerate("xyz")}),
                        orientation=Quaternion(w=1.0),
                    ),
                    size=Vector3(**{k: hi[i] - lo[i] for i, k in enumerate("xyz")}),
                    color=Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3]),
                )
            )
        return SceneUpdate(entities=[entity])

    def summary(self) -> dict[str, Any]:
        """The trial's station and filter figures (for ``metrics.json``), over every step
        written.

        Raises:
            RecordingError: Records taken and not written yet (flush the recorder first,
                or :meth:`discard` them): the figures would leave those steps out.
        """
        if self._observed:
            raise RecordingError(
                f"summary(): {len(self._observed)} safety records taken and not written "
                "yet (flush the recorder first)"
            )
        return {
            "station_contacts": int(self.contacts),
            "min_station_clearance_mm": round(self.least * 1e3, 1),
            "filter_active_s": round(self.active_steps * CONTROL_DT, 2),
            "station_clearance_cap_mm": round(CLEARANCE_CAP * 1e3, 1),
        }


def recording_scene(driver: Any, module_rects: list[dict[str, Any]]) -> SafetyScene:
    """The scene of a recording the simulator makes (a trial or a live session): the
    Foxglove channels and the safety channels, with the keep-in boxes of the driver's
    base filter if it has one (else the world's layout).

    Args:
        driver: The simulator driver.
        module_rects: The modules' rectangles (:func:`payload.trials.preparation.module_rects`).
    """
    from payload.trials.foxglove import FoxgloveScene

    zones = getattr(getattr(driver, "twist_filter", None), "zones", None)
    return SafetyScene(FoxgloveScene(driver.world, module_rects), driver, zones)


__all__ = ["FILTER_TOPIC", "KEEPIN_TOPIC", "SafetyScene", "keepin_boxes", "recording_scene"]
