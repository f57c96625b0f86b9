"""Read a trial's recording: every step as numpy arrays, and the Foxglove channels.

Run it from the project root on a trial's recording (``python examples/read_recording.py
runs/trial-0003/log.mcap``). It prints one JSON object: the step count, the seed, whether
the file was closed, the measured joints of every step (paper order), the measured
joints of the Foxglove channel by name (10 Hz), and the safety channel's records.
"""

from __future__ import annotations

import json
import sys

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from payload.trials import read_recording

path = sys.argv[1]  # a trial's log.mcap, e.g. runs/trial-0003/log.mcap
rec = read_recording(path)  # every step as numpy arrays (a killed run's file too)
t, position, joints = rec.t, rec.astrobee_pos, rec.q_meas  # (N,), (N, 3), (N, 17)
contact, phase = rec.contact, rec.phase  # opposing contact, task phase: (N,) each

with open(path, "rb") as f:  # the Foxglove channels need the file's summary: a closed file
    reader = make_reader(f, decoder_factories=[DecoderFactory()])
    topics = ["/payload/joints/measured"]
    measured = [
        {j.name: j.position for j in states.joints}
        for _, _, _, states in reader.iter_decoded_messages(topics=topics)
    ]
    f.seek(0)  # the JSON channel, read raw (the protobuf decoders do not decode JSON)
    safety = [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(["/safety/filter"])]

print(
    json.dumps(
        {
            "steps": len(rec),
            "seed": rec.meta.get("seed"),
            "complete": rec.complete,
            "q_meas": joints.tolist(),
            "measured": measured,
            "safety": safety,
        }
    )
)
