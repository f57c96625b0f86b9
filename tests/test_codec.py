"""Schema-3 recordings: lossless hand-joint coding, the Foxglove channels (decoded with the
mcap reader and foxglove-schemas-protobuf, transforms checked against MuJoCo's forward
kinematics), schema-1 (JSON) and schema-2 (lossless doubles) recordings still reading,
the conversion of schema 1, and newer versions refused."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from payload.teleop.hands import Hand, HandFrame
from payload.trials.codec import (
    HAND_GRID_M,
    STEP_GRIDS,
    JointsCodec,
    JointsMsg,
    StepCodec,
    StepMsg,
    quantize_joints,
    same_joints,
)
from payload.trials.recorder import (
    SCHEMA_VERSION,
    STEP_SCHEMA,
    RecordingError,
    StepRecord,
    TrialRecorder,
    random_step,
    read_hand_frames,
    read_recording,
    recording_version,
)
from payload.trials.records import FIELD_SPECS, QUAT_MIN_NORM

DT = 0.02


def _roundtrip(codec_in: JointsCodec, codec_out: JointsCodec, joints: np.ndarray) -> np.ndarray:
    msg = JointsMsg()
    codec_in.encode(joints, msg)
    return codec_out.decode(JointsMsg.FromString(msg.SerializeToString()))


def test_joints_codec_is_lossless_on_and_off_the_grid() -> None:
    rng = np.random.default_rng(0)
    enc, dec = JointsCodec(), JointsCodec()
    for k in range(30):
        x = rng.normal(scale=0.3, size=(25, 3)) + 1.0
        if k % 3 == 0:
            x = quantize_joints(x)  # on the grid: small deltas
        if k == 7:
            x[:] = np.nan
        back = _roundtrip(enc, dec, x)
        assert np.array_equal(back, x, equal_nan=True)
        if k % 10 == 5:  # a flush: the next message stands alone
            enc.key()
    # a grid frame after a grid frame costs ~2 bytes per coordinate, a raw one 8
    a = quantize_joints(rng.normal(size=(25, 3)))
    b = quantize_joints(a + HAND_GRID_M * rng.integers(-100, 100, size=(25, 3)))
    enc = JointsCodec()
    m1, m2 = JointsMsg(), JointsMsg()
    enc.encode(a, m1)
    enc.encode(b, m2)
    assert m2.ByteSize() <= 2 * 75 + 8
    raw = JointsMsg()
    JointsCodec().encode(rng.normal(size=(25, 3)), raw)
    assert raw.ByteSize() >= 8 * 75


def test_a_batch_encodes_to_the_bytes_of_one_step_at_a_time() -> None:
    """The recorder's flush encodes its steps as a batch: the same hand-sample and step
    bytes as encode_hands/encode_step called step by step, through keys, steps without
    a hand frame, joints that differ from the frame's, untracked and off-grid hands, and
    a non-finite number that breaks the delta chain."""
    rng = np.random.default_rng(17)
    items = []
    for k in range(60):
        step = random_step(rng, (k + 1) * DT)
        joints = [quantize_joints(rng.normal(size=(25, 3)) * 0.1) for _ in range(2)]
        if k % 7 == 3:
            joints[0] = rng.normal(size=(25, 3))  # off the grid: raw
        tracked = [k % 11 != 5, True]
        hands = [Hand(j if t else np.full((25, 3), np.nan), t) for j, t in zip(joints, tracked)]
        frame = None if k % 9 == 4 else HandFrame(k * DT, hands[0], hands[1])
        fields = {"left_joints": hands[0].joints, "right_joints": hands[1].joints}
        if k % 5 == 2:  # the step's own joints differ from the frame's
            fields["right_joints"] = quantize_joints(rng.normal(size=(25, 3)) * 0.1)
        step = dataclasses.replace(step, **fields)
        if k == 33:  # a non-finite number (past the record's checks): doubles, then a key
            object.__setattr__(step, "ctb_pos", np.array([np.nan, 0.0, 0.0]))
        items.append((step, k, 1.7e9 + k * DT, frame))
    for cut in ((0, 60), (0, 1), (5, 41)):
        one, batch = StepCodec(), StepCodec()
        want = []
        for step, seq, wall, frame in items[cut[0] : cut[1]]:
            refs = (False, False)
            hands_bytes = None
            if frame is not None:
                refs = (
                    same_joints(frame.left.joints, step.left_joints),
                    same_joints(frame.right.joints, step.right_joints),
                )
                hands_bytes = one.encode_hands(frame, seq)
            want.append((hands_bytes, one.encode_step(step, seq, wall, refs)))
        assert batch.encode_batch(items[cut[0] : cut[1]]) == want
    msgs = [StepMsg.FromString(w[1]) for w in want]
    assert any(w[0] is None for w in want) and any(m.left_joints.in_hands for m in msgs)
    assert len(msgs[33 - 5].grid) == 0 and msgs[34 - 5].grid_key


def _same_arrays(a, b) -> list[str]:
    """The fields of two recordings whose values differ in any bit (dtype and shape too)."""
    bad = []
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            same = x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
        else:
            same = x == y
        if not same:
            bad.append(f.name)
    return bad


def test_a_kept_recording_is_what_the_reader_reads_back(tmp_path: Path) -> None:
    """A trial scores the recording its recorder kept instead of reading the file: every
    array bit for bit what read_recording decodes from the file (and the same metadata),
    through flushes, steps stored as doubles (a number off the grid's range), pair fields
    stored apart from q_cmd, untracked hands, hand frames whose joints differ from the
    step's (or equal them but for the sign of zero), off-grid, negative-zero and
    beyond-the-integers joints, phase and module names of other lengths in other
    flushes, and a run that dies (its "aborted" metadata). A recorder that wrote no step
    has no recording (the reader refuses its file)."""
    rng = np.random.default_rng(5)
    path = tmp_path / "log.mcap"
    phases = ("calibration", "acquisition", "turn", "arrival")
    modules = ("kibo", "hatch", "node2", "outside")
    with pytest.raises(RuntimeError), TrialRecorder(path, keep=True, flush_period_s=0.1) as rec:
        rec.write_meta({"seed": 3, "pair": (1, 2.5), "nested": {"a": [0.1, None]}})
        for k in range(300):
            fields: dict = {"phase": phases[k // 80], "ctb_module": modules[k // 75]}
            if k % 7 == 0:  # the pairs are q_cmd's entries: stored as a flag
                q = rng.normal(size=17)
                fields.update(
                    q_cmd=q,
                    q_left=q[[0, 1, 2, 3, 8, 9, 10, 11]],
                    q_right=q[[4, 5, 6, 7, 12, 13, 14, 15]],
                    rail_cmd=float(q[-1]),
                )
            if k % 5 == 0:
                fields["left_joints"] = np.full((25, 3), np.nan)
            if k % 3 == 0:
                fields["right_joints"] = quantize_joints(rng.normal(scale=0.05, size=(25, 3)))
            if k % 11 == 0:
                fields["right_joints"] = -np.zeros((25, 3))  # on the grid, read back as +0
            if k in (100, 101):
                fields["ctb_pos"] = np.array([1e30, 0.0, 0.0])  # beyond the grid: doubles
            if k == 150:
                fields["left_joints"] = np.full((25, 3), 1e14)  # beyond int64 multiples: raw
            step = random_step(rng, (k + 1) * DT, **fields)
            if k % 2 == 0:
                left = step.left_joints if k % 4 else quantize_joints(rng.normal(size=(25, 3)))
                right = step.right_joints
                if k % 11 == 0:  # the step's -0 against the frame's +0: the frame's is stored
                    right = np.zeros((25, 3))
                rec.write_hands(HandFrame(k * DT, Hand(left, True), Hand(right, True)))
            rec.write(step)
        rec.write_meta({"closing": True, "seed": 4})
        with pytest.raises(RecordingError, match="close the recorder"):
            rec.recording()
        raise RuntimeError("the run dies")
    kept, read = rec.recording(), read_recording(path)
    assert len(kept) == 300 and _same_arrays(kept, read) == []
    assert kept.meta["seed"] == 4 and kept.meta["pair"] == [1, 2.5]
    assert "the run dies" in kept.meta["aborted"] and set(kept.ctb_module) == set(modules)
    assert kept.left_joints[150, 0, 0] == 1e14 and np.signbit(read.right_joints[0]).sum() == 0
    with TrialRecorder(tmp_path / "other.mcap") as plain:
        plain.write(random_step(rng, DT))
    with pytest.raises(RecordingError, match="not asked to keep"):
        plain.recording()
    with TrialRecorder(tmp_path / "empty.mcap", keep=True) as empty:
        empty.write_meta({"seed": 1})
    with pytest.raises(RecordingError, match="no step was written"):
        empty.recording()
    with pytest.raises(RecordingError):
        read_recording(tmp_path / "empty.mcap")


def test_delta_joints_without_their_key_are_refused() -> None:
    enc = JointsCodec()
    x = quantize_joints(np.ones((25, 3)))
    _roundtrip(enc, JointsCodec(), x)
    msg = JointsMsg()
    enc.encode(quantize_joints(x + 3 * HAND_GRID_M), msg)  # a delta message
    assert not msg.key
    with pytest.raises(ValueError, match="not in the file"):
        JointsCodec().decode(msg)


def test_hand_frames_replay_bit_for_bit(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    path = tmp_path / "log.mcap"
    frames = []
    with TrialRecorder(path, flush_period_s=0.1) as rec:
        for k in range(80):
            left = Hand(quantize_joints(rng.normal(size=(25, 3))))
            right = Hand.untracked() if k % 9 == 0 else Hand(rng.normal(size=(25, 3)))
            fr = HandFrame(k * DT + 0.003, left, right)
            frames.append(fr)
            rec.write_hands(fr)
            rec.write(
                random_step(
                    rng,
                    k * DT,
                    left_joints=left.joints,
                    right_joints=right.joints,
                    right_tracked=right.tracked,
                )
            )
    _, back = read_hand_frames(path)
    assert len(back) == 80
    for a, b in zip(frames, back):
        assert a.stamp == b.stamp and a.right.tracked == b.right.tracked
        assert np.array_equal(a.left.joints, b.left.joints)
        assert np.array_equal(a.right.joints, b.right.joints, equal_nan=True)
    rec_back = read_recording(path)
    np.testing.assert_array_equal(rec_back.left_joints, np.array([f.left.joints for f in frames]))


@pytest.fixture(scope="module")
def foxglove_recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list, object]:
    from payload.sim.world import build_world
    from payload.trials.foxglove import FoxgloveScene

    world = build_world(None)
    rng = np.random.default_rng(2)
    path = tmp_path_factory.mktemp("fox") / "log.mcap"
    lo, hi = world.model.jnt_range[world.model.dof_jntid[world.dof]].T
    steps = []
    with TrialRecorder(path, scene=FoxgloveScene(world)) as rec:
        for k in range(60):
            q = rng.uniform(lo, hi)
            st = random_step(rng, k * DT, q_meas=q, contact=k > 30, phase="acquisition")
            steps.append(st)
            rec.write(st)
    return path, steps, world


def test_the_scene_drawn_once_is_the_scene_drawn_each_time(foxglove_recording) -> None:
    """The /scene message restamped from the one drawn first: the bytes of the scene drawn
    anew from the model at that time (it depends on the model alone)."""
    from payload.trials.foxglove import FoxgloveScene

    _, _, world = foxglove_recording
    scene = FoxgloveScene(world)
    for ns in (10**9, 1_700_000_000_123_456_789, 0, 5 * 10**9 + 1):
        got = scene.scene(ns).SerializeToString()
        assert got == scene._scene(ns).SerializeToString()
        assert all(e.timestamp.ToNanoseconds() == ns for e in scene.scene(ns).entities)


def test_foxglove_channels_decode_with_the_standard_schemas(foxglove_recording) -> None:
    """mcap's reader with mcap_protobuf's decoder gives foxglove-schemas-protobuf messages
    for every channel, with the fields Foxglove needs set."""
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
    from foxglove_schemas_protobuf.JointStates_pb2 import JointStates
    from foxglove_schemas_protobuf.Log_pb2 import Log
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
    from mcap_protobuf.decoder import DecoderFactory

    path, steps, _ = foxglove_recording
    by_topic: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            by_topic.setdefault(channel.topic, []).append((schema, message, decoded))
    expect = {
        "/tf": ("foxglove.FrameTransforms", FrameTransforms),
        "/scene": ("foxglove.SceneUpdate", SceneUpdate),
        "/payload/joints/commanded": ("foxglove.JointStates", JointStates),
        "/payload/joints/measured": ("foxglove.JointStates", JointStates),
        "/trial/events": ("foxglove.Log", Log),
    }
    for topic, (name, cls) in expect.items():
        assert topic in by_topic, topic
        for schema, _, decoded in by_topic[topic]:
            assert schema.name == name
            # the decoded message re-parses as the package's own class: same schema
            cls.FromString(decoded.SerializeToString())
    assert len(by_topic["/tf"]) == 12  # 60 steps at 10 Hz
    scene = SceneUpdate.FromString(by_topic["/scene"][0][2].SerializeToString())
    frames = {e.frame_id for e in scene.entities}
    assert {"world", "astrobee", "ctb"} <= frames and "payload/A_distal" in frames
    assert sum(len(e.cubes) for e in scene.entities if e.frame_id == "world") > 10
    tf = by_topic["/tf"][0][2]
    children = {t.child_frame_id: t.parent_frame_id for t in tf.transforms}
    assert children["astrobee"] == "world" and children["ctb"] == "world"
    node = "payload/A_distal"
    while node != "world":  # every payload link chains back to the world
        node = children[node]
    events = [d.message for _, _, d in by_topic["/trial/events"]]
    assert events[:3] == ["phase: acquisition", "opposing contact: off", "opposing contact: on"]
    js = by_topic["/payload/joints/measured"][1][2]
    np.testing.assert_allclose([j.position for j in js.joints][:17], steps[5].q_meas, atol=1e-6)
    # every channel on one timeline: the same log time for a step on every channel
    step_times = [m.log_time for _, m, _ in by_topic["/trial/step"]]
    assert by_topic["/tf"][1][1].log_time == step_times[5]


def _quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    u = np.array([x, y, z])
    return v + 2 * np.cross(u, np.cross(u, v) + w * v)


def test_foxglove_transforms_compose_to_mujoco_body_poses(foxglove_recording) -> None:
    """Chaining the recorded parent -> child transforms (composed here with plain quaternion
    algebra) lands every payload link where MuJoCo's own kinematics puts it."""
    from mcap_protobuf.decoder import DecoderFactory

    path, steps, world = foxglove_recording
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        tfs = [d for _, _, _, d in reader.iter_decoded_messages(topics=["/tf"])]
    k = 3
    tf, st = tfs[k], steps[5 * k]
    rel = {
        t.child_frame_id: (
            t.parent_frame_id,
            np.array([t.translation.x, t.translation.y, t.translation.z]),
            np.array([t.rotation.w, t.rotation.x, t.rotation.y, t.rotation.z]),
        )
        for t in tf.transforms
    }

    def world_pose(frame: str) -> tuple[np.ndarray, np.ndarray]:
        if frame == "world":
            return np.zeros(3), np.array([1.0, 0, 0, 0])
        parent, p, q = rel[frame]
        pp, pq = world_pose(parent)
        out = np.zeros(4)
        mujoco.mju_mulQuat(out, pq, q)
        return pp + _quat_rotate(pq, p), out

    m = world.model
    d = mujoco.MjData(m)
    a = world.astrobee_qpos
    d.qpos[a : a + 3], d.qpos[a + 3 : a + 7] = st.astrobee_pos, st.astrobee_quat
    d.qpos[world.qpos] = st.q_meas
    d.qpos[world.stage_qpos] = st.deploy_meas
    d.qpos[world.ctb_qpos : world.ctb_qpos + 3] = st.ctb_pos
    d.qpos[world.ctb_qpos + 3 : world.ctb_qpos + 7] = st.ctb_quat
    mujoco.mj_kinematics(m, d)
    for name in ("astrobee", "payload/A_distal", "payload/D_distal", "ctb"):
        pos, quat = world_pose(name)
        # the channel rounds to ~1e-6 (VIEW_RESOLUTION) per link: a few links deep
        np.testing.assert_allclose(pos, d.body(name).xpos, atol=2e-5)
        # each component is rounded by up to half of VIEW_RESOLUTION (2**-20), so the
        # quaternion dot product can fall short of 1 by about that much per link
        assert abs(abs(float(quat @ d.body(name).xquat)) - 1.0) < 8 * 2.0**-20


def test_the_compiled_frame_poses_are_numpys(foxglove_recording) -> None:
    """The /tf poses through the kernel (numpy's dgemv, MuJoCo's quaternion functions)
    and through the numpy loop, at random measured states: the same bits, so the same
    message bytes."""
    from payload.trials.foxglove import FoxgloveScene

    _, _, world = foxglove_recording
    compiled, python = FoxgloveScene(world), FoxgloveScene(world)
    assert compiled._poses_kernel is not None
    python.__dict__["_poses_made"] = (python.data, python.model, None)  # the numpy loop
    assert python._poses_kernel is None
    rng = np.random.default_rng(21)
    lo, hi = world.model.jnt_range[world.model.dof_jntid[world.dof]].T
    for k in range(300):
        q = rng.uniform(lo, hi)
        st = random_step(rng, k * DT, q_meas=q, ctb_quat=rng.normal(size=4) / 2.0)
        compiled.kinematics(st)
        poses = compiled._poses_kernel()
        assert poses.tobytes() == compiled._poses_numpy().tobytes()
        ns = 1_700_000_000_000_000_000 + k * 20_000_000
        assert (
            compiled.transforms(st, ns).SerializeToString()
            == python.transforms(st, ns).SerializeToString()
        )


def test_the_frame_poses_follow_a_scene_given_other_data(foxglove_recording) -> None:
    """A scene whose ``data`` is replaced poses the links of the new data, through a kernel
    made for it as through the numpy loop (a kernel kept for the old data would read poses
    nothing updates any more)."""
    import mujoco

    from payload.trials.foxglove import FoxgloveScene

    _, _, world = foxglove_recording
    rng = np.random.default_rng(4)
    scene = FoxgloveScene(world)
    st = random_step(rng, 0.0)
    before = scene._poses(st).tobytes()
    old = scene._poses_kernel
    scene.data = mujoco.MjData(world.model)
    moved = random_step(rng, DT)
    poses = scene._poses(moved)
    assert scene._poses_kernel is not old
    assert poses.tobytes() == scene._poses_numpy().tobytes() != before


def test_frame_poses_with_other_bits_are_refused(foxglove_recording, monkeypatch, refused_kernel):
    """A kernel that forgets the transpose (the parent's rotation, not its inverse) fails
    its self-check and the numpy loop runs; so does any kernel with PAYLOAD_NATIVE=0."""
    from payload.trials import foxglove_c
    from payload.trials.foxglove import FoxgloveScene

    _, _, world = foxglove_recording
    with refused_kernel(foxglove_c, "mv(COL_MAJOR,", "mv(ROW_MAJOR,"):
        assert FoxgloveScene(world)._poses_kernel is None
    monkeypatch.undo()
    monkeypatch.setenv("PAYLOAD_NATIVE", "0")
    assert FoxgloveScene(world)._poses_kernel is None


def test_the_compiled_messages_are_the_protobuf_runtimes(foxglove_recording) -> None:
    """The /tf and joint-state bytes written in C against the protobuf runtime's
    serialisation of the messages built field by field, at random states with zeros of
    both signs and at whole seconds; and read back by the runtime's parser, the values
    themselves (to the bit) and the names."""
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
    from foxglove_schemas_protobuf.JointStates_pb2 import JointStates

    from payload.trials.foxglove import JOINT_NAMES, FoxgloveScene, split_ns

    _, _, world = foxglove_recording
    scene = FoxgloveScene(world)
    kernel = scene._messages_kernel
    assert kernel is not None
    rng = np.random.default_rng(22)
    lo, hi = world.model.jnt_range[world.model.dof_jntid[world.dof]].T
    for k in range(200):
        st = random_step(rng, k * DT, q_meas=rng.uniform(lo, hi))
        poses = scene._poses(st)
        poses[rng.random(poses.shape) < 0.05] = (0.0, -0.0)[k % 2]
        ns = 1_000_000_000 * k if k % 5 == 0 else int(rng.integers(0, 2**62))
        tf = kernel.frame_transforms(poses, split_ns(ns))
        assert tf == scene._frame_transforms(poses, ns).SerializeToString()
        back = FrameTransforms.FromString(tf)
        assert [(t.parent_frame_id, t.child_frame_id) for t in back.transforms] == list(
            zip(scene._parent_names, scene._link_names)
        )
        got = np.array(
            [[t.translation.x, t.translation.y, t.translation.z, t.rotation.w, t.rotation.x,
              t.rotation.y, t.rotation.z] for t in back.transforms]
        )  # fmt: skip
        assert got.tobytes() == poses.tobytes()  # a -0.0 is written, an omitted 0.0 reads 0.0
        assert back.transforms[0].timestamp.ToNanoseconds() == ns
        values = rng.normal(size=len(JOINT_NAMES)) * (rng.random(len(JOINT_NAMES)) < 0.7)
        js = kernel.joint_states(values, split_ns(ns))
        assert js == scene.joint_states(values, ns).SerializeToString()
        back = JointStates.FromString(js)
        assert [j.name for j in back.joints] == list(JOINT_NAMES)
        assert np.array([j.position for j in back.joints]).tobytes() == values.tobytes()


def test_names_too_long_for_the_message_kernel_go_to_the_runtime(foxglove_recording) -> None:
    """A frame or joint name longer than the kernel's item buffer: the kernel answers None
    and the recording's message is built by the protobuf runtime (whose bytes it is)."""
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
    from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
    from google.protobuf.timestamp_pb2 import Timestamp

    from payload.trials import messages_c
    from payload.trials.foxglove import split_ns

    lib = messages_c.load_library()
    long = "x" * messages_c.ITEM_BYTES
    kernel = messages_c.CompiledMessages(lib, [("world", "a"), ("a", long)], ["j", long])
    stamp = split_ns(1_500_000_000)
    assert kernel.frame_transforms(np.zeros((2, 7)), stamp) is None
    assert kernel.joint_states(np.zeros(2), stamp) is None
    short = messages_c.CompiledMessages(lib, [("world", "a")], ["j"])
    want = FrameTransforms(transforms=[FrameTransform(
        timestamp=Timestamp(seconds=stamp[0], nanos=stamp[1]), parent_frame_id="world",
        child_frame_id="a", translation=Vector3(), rotation=Quaternion())])  # fmt: skip
    assert short.frame_transforms(np.zeros((1, 7)), stamp) == want.SerializeToString()


def test_messages_with_other_bytes_are_refused(foxglove_recording, refused_kernel) -> None:
    """A kernel that writes the zero doubles the runtime leaves out fails its self-check,
    and the recording's messages are built as protobuf objects."""
    from payload.trials import messages_c
    from payload.trials.foxglove import FoxgloveScene

    _, _, world = foxglove_recording
    with refused_kernel(messages_c, "if (!bits) return p;", "", attr="WRITER_C"):
        assert FoxgloveScene(world)._messages_kernel is None


def _write_v1(path: Path, steps: list, chunk_size: int = 1024 * 1024) -> None:
    """A schema-1 recording as the previous recorder wrote it (JSON steps)."""
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=chunk_size)
        w.start(profile="", library="payload-workbench")
        sid = w.register_schema(
            name="payload.trials.StepRecord",
            encoding="jsonschema",
            data=json.dumps(STEP_SCHEMA).encode(),
        )
        cid = w.register_channel(topic="/trial/step", message_encoding="json", schema_id=sid)
        w.add_metadata("payload.trial", {"seed": "4"})
        for k, s in enumerate(steps):
            msg = {"seq": k, "wall_time": 1e9 + k, **s.to_json_dict()}
            w.add_message(
                channel_id=cid,
                log_time=k,
                publish_time=k,
                data=json.dumps(msg, allow_nan=False).encode(),
                sequence=k,
            )
        w.finish()


def test_schema1_recordings_read_and_convert(tmp_path: Path, capsys) -> None:
    from payload.cli import main

    rng = np.random.default_rng(3)
    steps = [random_step(rng, k * DT) for k in range(40)]
    trial = tmp_path / "camp" / "trial-0004"
    trial.mkdir(parents=True)
    path = trial / "log.mcap"
    _write_v1(path, steps)
    assert recording_version(path) == 1
    old = read_recording(path)
    assert len(old) == 40 and old.meta == {"seed": 4}
    assert main(["trials", "convert", str(tmp_path / "camp"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["converted"] == [str(path)]
    assert recording_version(path) == SCHEMA_VERSION == 3 and (trial / "log.v1.mcap").exists()
    new = read_recording(path)
    for name in ("left_joints", "phase", "contact", "ctb_module"):
        assert np.array_equal(getattr(old, name), getattr(new, name)), name
    # the numbers to their stated resolution: half a grid step (plus the last bit)
    for name, grid, _ in STEP_GRIDS:
        a, b = getattr(old, name), getattr(new, name)
        assert np.all(np.abs(a - b) <= grid / 2 + 4e-16 * np.abs(a)), name
    assert new.meta == old.meta
    # again: nothing to do, said so; a second backup is never overwritten
    assert main(["trials", "convert", str(path)]) == 0
    assert "already schema version 3" in capsys.readouterr().out
    _write_v1(path, steps)
    assert main(["trials", "convert", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()  # one line (no "convert it" notice)
    assert len(err) == 1 and "log.v1.mcap: exists" in err[0], err
    # --force never overwrites a backup that is another original; the same one, again
    backup = trial / "log.v1.mcap"
    original = backup.read_bytes()
    _write_v1(path, steps[:30])
    assert main(["trials", "convert", str(path), "--force"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds another recording" in err[0], err
    assert backup.read_bytes() == original
    assert recording_version(path) == 1 and len(read_recording(path)) == 30
    path.write_bytes(original)
    assert main(["trials", "convert", str(path), "--force"]) == 0
    capsys.readouterr()
    assert backup.read_bytes() == original and recording_version(path) == SCHEMA_VERSION


def test_convert_json_counts_by_what_it_did_not_by_the_path(tmp_path: Path, capsys) -> None:
    """A folder named ``converted`` (say, where converted campaigns are kept): a schema-1
    file in it is converted, a current one left as it is, and ``--json`` lists each under
    what was done to it, whatever the words in its path."""
    from payload.cli import main

    rng = np.random.default_rng(7)
    root = tmp_path / "converted"
    old, new = root / "trial-0001" / "log.mcap", root / "trial-0002" / "log.mcap"
    old.parent.mkdir(parents=True)
    new.parent.mkdir(parents=True)
    _write_v1(old, [random_step(rng, k * DT) for k in range(10)])
    with TrialRecorder(new) as rec:
        for k in range(10):
            rec.write(random_step(rng, k * DT))
    assert main(["trials", "convert", str(root), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["converted"] == [str(old)] and info["skipped"] == [str(new)], info


def test_a_cut_short_schema1_recording_stays_unfinished_once_converted(
    tmp_path: Path, capsys
) -> None:
    """A schema-1 recording whose writer was killed (no footer) converts to a closed file
    that still reads as unfinished (``complete`` False, the ``cut_short`` metadata), so
    ``trials summarize`` does not score it as a finished trial."""
    from payload.cli import main
    from payload.trials.reading import CUT_SHORT

    rng = np.random.default_rng(5)
    trial = tmp_path / "camp" / "trial-0004"
    trial.mkdir(parents=True)
    path = trial / "log.mcap"
    _write_v1(path, [random_step(rng, k * DT) for k in range(40)], chunk_size=4096)
    whole = path.read_bytes()
    path.write_bytes(whole[: len(whole) * 2 // 3])  # killed: the summary and footer lost
    torn = read_recording(path)
    assert not torn.complete and 0 < len(torn) < 40
    assert main(["trials", "convert", str(path)]) == 0
    capsys.readouterr()
    converted = read_recording(path)
    assert recording_version(path) == SCHEMA_VERSION
    assert not converted.complete and CUT_SHORT in converted.meta
    assert len(converted) == len(torn)
    assert main(["trials", "summarize", str(tmp_path / "camp"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["errors"] == 1 and "cut short" in summary["trials"][0]["error"]


def _step_messages(path: Path) -> list:
    with path.open("rb") as f:
        return [
            StepMsg.FromString(m.data)
            for _, ch, m in make_reader(f).iter_messages()
            if ch.topic == "/trial/step"
        ]


def test_schema2_recordings_read_and_newer_versions_are_refused(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    """Version 3 is the gridded step numbers (a generic decoder sees empty doubles);
    a version-2 file (every number a lossless double) reads exactly as written; a file
    newer than the reader is refused with one line, by the reader and by convert."""
    from payload.cli import main
    from payload.trials import codec, stepgrid
    from payload.trials import recorder as recorder_module

    rng = np.random.default_rng(5)
    steps = [random_step(rng, (k + 1) * DT) for k in range(30)]

    def write(path: Path) -> None:
        with TrialRecorder(path) as rec:
            rec.write_meta({"seed": 5})
            for s in steps:
                rec.write(s)

    current = tmp_path / "v3" / "log.mcap"
    write(current)
    assert recording_version(current) == SCHEMA_VERSION == 3
    msgs = _step_messages(current)
    assert all(len(m.grid) > 0 and len(m.astrobee_pos) == 0 for m in msgs)

    old = tmp_path / "v2" / "log.mcap"
    with monkeypatch.context() as mp:  # what the version-2 recorder wrote
        mp.setattr(recorder_module, "SCHEMA_VERSION", 2)
        none = np.zeros(len(steps), dtype=bool)  # no step on the grid: all doubles
        mp.setattr(
            codec.StepCodec,
            "_grid_batch",
            lambda self, fields, walls: stepgrid.GridRows(
                none[: len(walls)],
                none[: len(walls)],
                np.zeros((len(walls), stepgrid.GRID.size), np.int64),
                None,
            ),
        )
        write(old)
    assert recording_version(old) == 2
    msgs = _step_messages(old)
    assert all(len(m.grid) == 0 and len(m.astrobee_pos) == 3 for m in msgs)
    rec = read_recording(old)
    assert len(rec) == len(steps) and rec.meta == {"seed": 5}
    for name in ("t", "astrobee_pos", "astrobee_quat", "q_meas", "twist_cmd", "left_joints"):
        want = np.array([getattr(s, name) for s in steps])
        assert np.array_equal(getattr(rec, name), want), name  # lossless: every bit
    assert main(["trials", "convert", str(old)]) == 0
    assert "already schema version 2" in capsys.readouterr().out

    newer = tmp_path / "v9" / "log.mcap"
    with monkeypatch.context() as mp:
        mp.setattr(recorder_module, "SCHEMA_VERSION", 9)
        write(newer)
    with pytest.raises(RecordingError, match="schema version 9 is newer"):
        read_recording(newer)
    assert main(["trials", "convert", str(newer)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "schema version 9 is newer" in err[0]


def test_a_non_finite_typed_step_is_named_by_the_reader(tmp_path: Path) -> None:
    """Typed rows are checked by column; a bad one is still named by step and field."""
    rng = np.random.default_rng(6)
    path = tmp_path / "log.mcap"
    with TrialRecorder(path) as rec:
        for k in range(40):
            step = random_step(rng, (k + 1) * DT)
            if k == 30:  # what a foreign writer could store: the validation bypassed
                object.__setattr__(step, "ctb_pos", np.array([0.0, np.nan, 0.0]))
            rec.write(step)
    with pytest.raises(RecordingError, match=r"step 30: ctb_pos: \[1\]: expected a finite"):
        read_recording(path)


def _fields(step: StepRecord) -> dict:
    """A step's fields, as the loop hands them to a step's making: writable copies."""
    return {k: v.copy() if isinstance(v, np.ndarray) else v for k, v in vars(step).items()}


def _remaking(made: list[str]) -> Callable[[StepRecord], StepRecord]:
    """A build that makes a step again from its fields, and makes a flush's steps as one
    batch (``many``); ``made`` gets "one" or "many" at each call."""

    def remade(step: StepRecord) -> StepRecord:
        made.append("one")
        return StepRecord(**_fields(step))

    def many(calls: list) -> list:
        made.append("many")
        return StepRecord.many([_fields(st) for (st,) in calls])

    remade.many = many  # type: ignore[attr-defined]
    return remade


def _recorded(path: Path, world: object, steps: list, frames: list, build: Any) -> bytes:
    """The file a recorder with the Foxglove scene writes of these steps and hand frames on
    a fixed clock, each step written now (``build`` None) or made at the flush by
    ``build(step)`` (``write_later``)."""
    from payload.trials.foxglove import FoxgloveScene

    ticks = iter(range(10**6))
    with TrialRecorder(path, scene=FoxgloveScene(world), keep=True) as rec:
        rec._clock = lambda: 1_700_000_000_000_000_000 + 20_000_000 * next(ticks)
        for st, fr in zip(steps, frames):
            if fr is not None:
                rec.write_hands(fr)
            if build is None:
                rec.write(st)
            else:
                rec.write_later(st.t, build, st)
    return path.read_bytes()


def _same_steps(got: list, want: list) -> None:
    """The same steps to the bit (:func:`_same_arrays`), each field of the same type and
    each array read-only."""
    assert len(got) == len(want)
    for a, b in zip(got, want):
        assert _same_arrays(a, b) == []
        for x, y in zip(vars(a).values(), vars(b).values()):
            assert type(x) is type(y)
            assert not isinstance(x, np.ndarray) or not (x.flags.writeable or y.flags.writeable)


def test_steps_made_as_a_batch_are_the_steps_made_one_at_a_time(monkeypatch) -> None:
    """``StepRecord.many`` makes what ``StepRecord(**fields)`` makes of each, to the bit, or
    raises its error: the loop's steps in one buffer without a step's own checks (NaN in an
    untracked hand allowed); numbers numpy converts (lists, integers, float32) in the
    batch; scalars of another type and a quaternion near zero made one at a time; a bad
    field anywhere in the batch raises as that step alone does."""
    rng = np.random.default_rng(12)
    steps = [random_step(rng, k * DT) for k in range(12)]
    fields = [_fields(st) for st in steps]
    fields[3]["left_joints"][4] = np.nan  # an untracked joint: allowed
    fields[3]["left_tracked"] = False
    one = [StepRecord(**f) for f in fields]
    own_checks = []
    made_alone = StepRecord.__post_init__
    monkeypatch.setattr(
        StepRecord, "__post_init__", lambda self: own_checks.append(1) or made_alone(self)
    )
    _same_steps(StepRecord.many(fields), one)
    assert own_checks == []  # the batch, not the steps one by one
    assert StepRecord.many([]) == []
    shape = {name: spec[0] for name, spec in FIELD_SPECS.items()}
    small = QUAT_MIN_NORM * np.eye(4)[1]  # a quaternion of a norm times this
    # numbers numpy converts for the batch as a step's own conversion does: the batch
    convert = [("ctb_pos", [1.0, 2.0, 3.0]), ("q_meas", np.arange(shape["q_meas"][0])),
               ("astrobee_pos", np.ones(3, dtype=np.float32) / 3)]  # fmt: skip
    # scalars of another type, a quaternion within ten times the check's norm: alone
    alone = [("rail_cmd", 1), ("left_tracked", np.bool_(True)), ("t", np.float64(0.1)),
             ("astrobee_quat", 5 * small)]  # fmt: skip
    for (name, value), batch in [(c, True) for c in convert] + [(c, False) for c in alone]:
        changed = [dict(f) for f in fields]
        changed[5][name] = value
        want = [StepRecord(**f) for f in changed]
        own_checks.clear()
        _same_steps(StepRecord.many(changed), want)
        assert own_checks == ([] if batch else [1] * len(changed)), name
    for name, value in [
        ("right_joints", np.full(shape["right_joints"], np.inf)),
        ("q_meas", np.full(shape["q_meas"], np.nan)),
        ("twist_cmd", np.zeros(shape["twist_cmd"][0] - 1)),
        ("ctb_quat", np.zeros(4)),
        ("ctb_quat", 0.5 * small),
        ("phase", "lunch"),
        ("ctb_module", "columbus"),
        ("deploy_cmd", float("nan")),
        ("contact", 1),
    ]:
        bad = [dict(f) for f in fields]
        bad[7][name] = value
        with pytest.raises(RecordingError) as alone_error:
            StepRecord(**bad[7])
        with pytest.raises(RecordingError) as batch_error:
            StepRecord.many(bad)
        assert str(batch_error.value) == str(alone_error.value), name
    extra, missing = [dict(f) for f in fields], [dict(f) for f in fields]
    extra[2]["extra"] = 1.0
    del missing[2]["t"]
    for bad in (extra, missing):
        with pytest.raises(TypeError) as alone_type:
            StepRecord(**bad[2])
        with pytest.raises(TypeError) as batch_type:
            StepRecord.many(bad)
        assert str(batch_type.value) == str(alone_type.value)


def test_a_flush_made_as_a_batch_writes_what_steps_made_one_at_a_time_write(
    foxglove_recording, tmp_path, monkeypatch
) -> None:
    """A build that makes a flush's steps as a batch (its ``many``) writes the file that
    steps written at once write, byte for byte; if the batch fails, the steps are made one
    at a time, and the one that fails is named, the steps before it written; a batch that
    makes its steps at other times than said is not taken."""
    _, steps, world = foxglove_recording
    frames = [
        None if k % 5 == 1 else HandFrame(st.t, Hand(st.left_joints), Hand(st.right_joints))
        for k, st in enumerate(steps)
    ]
    now = _recorded(tmp_path / "now.mcap", world, steps, frames, None)
    made: list[str] = []
    remade = _remaking(made)
    assert _recorded(tmp_path / "many.mcap", world, steps, frames, remade) == now
    assert "many" in made and "one" not in made  # each flush's steps as one batch

    nan_joints = np.full(FIELD_SPECS["q_meas"][0], np.nan)

    def fields_of(st: StepRecord) -> dict:  # the tenth step's measured joints not finite
        return {**_fields(st), "q_meas": nan_joints} if st.t == steps[9].t else _fields(st)

    def build(st: StepRecord) -> StepRecord:
        return StepRecord(**fields_of(st))

    build.many = lambda calls: StepRecord.many([fields_of(st) for (st,) in calls])  # type: ignore[attr-defined]
    with TrialRecorder(tmp_path / "bad.mcap") as rec:
        rec.write(steps[0])
        for st in steps[1:15]:
            rec.write_later(st.t, build, st)
        with pytest.raises(RecordingError, match=rf"step at t = {steps[9].t} s: .*q_meas"):
            rec.flush()
    back = read_recording(tmp_path / "bad.mcap")
    assert back.t.tolist() == [st.t for st in steps[:9]]
    # a batch that makes a step at another time than said: the steps made one at a time
    monkeypatch.setattr(
        remade, "many", lambda calls: [dataclasses.replace(st, t=st.t + 1) for (st,) in calls]
    )
    made.clear()
    assert _recorded(tmp_path / "late.mcap", world, steps, frames, remade) == now
    assert made == ["one"] * len(steps)


def test_a_step_made_at_the_flush_is_the_step_written_at_once(foxglove_recording, tmp_path):
    """``write_later(t, build, *args)`` writes what ``write(build(*args))`` writes: the
    same file, byte for byte, on the same clock (hand samples, steps whose joints are the
    frame's and steps with their own, the Foxglove channels), and keeps the same columns."""
    _, steps, world = foxglove_recording
    rng = np.random.default_rng(8)
    other = rng.normal(size=(len(steps), 25, 3))
    frames = [  # every seventh step without a frame; the left hand the step's own joints
        None if k % 7 == 3 else HandFrame(st.t, Hand(st.left_joints), Hand(other[k]))
        for k, st in enumerate(steps)
    ]
    now = _recorded(tmp_path / "now.mcap", world, steps, frames, None)
    # a new StepRecord, made at the flush
    assert _recorded(tmp_path / "later.mcap", world, steps, frames, dataclasses.replace) == now
    assert len(read_recording(tmp_path / "later.mcap")) == len(steps)


def test_a_step_that_cannot_be_made_at_the_flush(tmp_path: Path) -> None:
    """A deferred step that fails: the steps before it are in the file, the error names its
    time, the recorder takes no more steps; the time order is checked when written."""
    rng = np.random.default_rng(3)
    steps = [random_step(rng, k * DT) for k in range(30)]
    path = tmp_path / "log.mcap"

    def bad(st):  # a step the recorder refuses: a non-finite measured joint
        return dataclasses.replace(st, q_meas=np.full(17, np.nan))

    with TrialRecorder(path) as rec:
        rec.write(steps[0])  # the first step is flushed at once
        with pytest.raises(RecordingError, match="not after"):
            rec.write_later(0.0, dataclasses.replace, steps[0])
        for st in steps[1:12]:
            rec.write_later(st.t, dataclasses.replace, st)
        rec.write_later(steps[12].t, bad, steps[12])
        rec.write_later(steps[13].t, dataclasses.replace, steps[13])
        with pytest.raises(RecordingError, match=rf"step at t = {steps[12].t} s: .*q_meas"):
            rec.flush()
        with pytest.raises(RecordingError, match="no more steps"):
            rec.write(steps[14])
        rec.write_meta({"after": True})  # metadata still goes in
    back = read_recording(path)
    assert len(back) == 12
    want = np.array([st.q_meas for st in steps[:12]])
    np.testing.assert_allclose(back.q_meas, want, rtol=0, atol=5e-9)  # on the 10 nrad grid
    assert back.meta["after"] is True

    # a step that fails at the last flush, in close(): the file is finished, marked aborted;
    # a build's own error (not the recorder's) is named with its step's time, and chained
    def broken(st):
        raise TypeError("a bug in the build")

    with pytest.raises(RecordingError, match=r"t = 0.1 s: TypeError: a bug") as caught:
        with TrialRecorder(tmp_path / "closing.mcap") as rec:
            for st in steps[:5]:
                rec.write_later(st.t, dataclasses.replace, st)
            rec.write_later(steps[5].t, broken, steps[5])
            rec.write_later(steps[6].t, dataclasses.replace, steps[6])
    assert isinstance(caught.value.__cause__, TypeError)
    back = read_recording(tmp_path / "closing.mcap")
    assert back.complete and len(back) == 5 and "a bug in the build" in back.meta["aborted"]
    # a build that makes another step than the time said, or no step, is refused too
    for k, (build, said) in enumerate(
        [(lambda: steps[3], "made the step at t = 0.06 s"), (lambda: {}, "made a dict")]
    ):
        with TrialRecorder(tmp_path / f"{k}.mcap") as rec:  # the first step flushes at once
            with pytest.raises(RecordingError, match=f"step at t = 1.0 s: {said}"):
                rec.write_later(1.0, build)


def test_compare_channels_sees_every_message_but_the_clock(foxglove_recording, tmp_path):
    """Two recordings of the same steps and hand frames made at other wall-clock times
    compare identical on every channel; a different hand frame (its step the same) is
    found on /trial/hands alone, and `trials compare --require-identical` fails on it."""
    import time

    from payload.cli import main
    from payload.trials.compare import compare_channels, compare_steps
    from payload.trials.foxglove import FoxgloveScene

    _, steps, world = foxglove_recording
    rng = np.random.default_rng(5)
    frames = [
        HandFrame(k * DT, Hand(rng.normal(size=(25, 3))), Hand.untracked()) for k in range(60)
    ]
    odd = HandFrame(frames[17].stamp, Hand(rng.normal(size=(25, 3))), Hand.untracked())

    def record(path: Path, shift_ns: int, swap: bool) -> Path:
        with TrialRecorder(path, scene=FoxgloveScene(world)) as rec:
            rec._clock = lambda: time.time_ns() + shift_ns
            for k, st in enumerate(steps):
                rec.write_hands(odd if swap and k == 17 else frames[k])
                rec.write(st)
                if shift_ns and k == 23:
                    rec.flush()  # as the wall clock may decide: the hands' deltas restart
        return path

    a = record(tmp_path / "a" / "trial-0000" / "log.mcap", 0, False)
    b = record(tmp_path / "b" / "trial-0000" / "log.mcap", 3_600_000_000_000, False)
    c = record(tmp_path / "c" / "trial-0000" / "log.mcap", 0, True)
    same = compare_channels(a, b)
    assert same["identical"]
    # a cut-short copy reads as its complete prefix: fewer messages, not a crash
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(a.read_bytes()[: a.stat().st_size * 2 // 3])
    short = compare_channels(a, cut)
    assert not short["identical"]
    assert 0 < short["channels"]["/tf"]["messages_b"] < short["channels"]["/tf"]["messages_a"]
    assert {"/tf", "/scene", "/trial/hands", "/trial/events"} <= set(same["channels"])
    assert same["channels"]["/tf"]["messages_a"] == 12
    other = compare_channels(a, c)
    assert not other["identical"] and compare_steps(a, c)["identical"]
    assert {t for t, ch in other["channels"].items() if ch["differing"]} == {"/trial/hands"}
    assert other["channels"]["/trial/hands"]["differing"] == 1
    for run in "abc":
        (tmp_path / run / "trial-0000" / "metrics.json").write_text('{"success": true}')
    runs = [str(tmp_path / "a"), str(tmp_path / "b"), "--require-identical"]
    assert main(["trials", "compare", *runs]) == 0
    runs[1] = str(tmp_path / "c")
    assert main(["trials", "compare", *runs]) == 1
    # a trial in one run only is a difference
    (tmp_path / "b" / "trial-0001").mkdir()
    (tmp_path / "b" / "trial-0001" / "metrics.json").write_text('{"success": true}')
    runs[1] = str(tmp_path / "b")
    assert main(["trials", "compare", *runs]) == 1


def test_trial_force_replaces_a_schema1_trial_and_its_hands(tmp_path: Path, monkeypatch) -> None:
    """A schema-1 trial kept its hands in ``hands.jsonl`` beside its ``log.mcap``: unlike a
    live session's, that folder is a trial's, and ``trial --force`` replaces it whole."""
    from payload.trials import runner

    trial = tmp_path / "trial"
    trial.mkdir()
    _write_v1(trial / "log.mcap", [random_step(np.random.default_rng(0), 0.0)])
    (trial / "hands.jsonl").write_text("{}\n")

    def finished(seed: int, source: object, out: Path, **kwargs: object) -> dict:
        (out / "log.mcap").write_bytes(b"new")
        return {"seed": seed}

    monkeypatch.setattr(runner, "_run_trial", finished)
    runner.run_trial(0, out_dir=trial, force=True, max_time=1.0)
    assert sorted(p.name for p in trial.iterdir()) == ["log.mcap"]
    assert (trial / "log.mcap").read_bytes() == b"new"
