"""The recording's step and hand-sample messages written in C: the protobuf runtime's
bytes, refused on a differing byte, and what the runtime refuses left to it."""

from __future__ import annotations

import numpy as np
import pytest

from payload.trials.codec import HandSampleMsg, StepCodec, StepMsg


def test_the_compiled_step_messages_are_the_protobuf_runtimes() -> None:
    """A batch's hand-sample and step bytes written in C, against the runtime's
    serialisation of the same messages encoded one at a time (``encode_hands`` and
    ``encode_step``, not the batch's arithmetic the kernel's own check compares with;
    every kind of step: on the grid and as doubles, pairs in the command or not, joints
    on the grid, raw, untracked and in the hand sample, with and without a frame, zeros
    of both signs), and read back by the runtime's parser to the same numbers."""
    from payload.trials import codec

    kernel = codec._steps_kernel()
    assert kernel is not None  # a compiler is here
    rng = np.random.default_rng(23)
    compiled, runtime = StepCodec(), StepCodec()
    for b in range(4):
        items = [codec._probe_item(rng, int(k)) for k in rng.integers(0, 400, size=30)]
        items = [(st, 30 * b + i, wall, frame) for i, (st, _, wall, frame) in enumerate(items)]
        got = compiled.encode_batch(items)
        want = []
        for step, seq, wall, frame in items:
            refs = (False, False)
            if frame is not None:
                refs = (
                    codec.same_joints(frame.left.joints, step.left_joints),
                    codec.same_joints(frame.right.joints, step.right_joints),
                )
            hands = None if frame is None else runtime.encode_hands(frame, seq)
            want.append((hands, runtime.encode_step(step, seq, wall, refs)))
        assert got == want
        for (step, seq, _, frame), (hands, data) in zip(items, got):
            m = StepMsg.FromString(data)
            assert m.seq == seq and m.contact == step.contact
            if not m.pairs_in_cmd:
                assert np.array(m.q_left).tobytes() == step.q_left.tobytes()
            if frame is not None:
                assert HandSampleMsg.FromString(hands).stamp == frame.stamp
        if b % 2:
            compiled.key()
            runtime.key()


def test_step_messages_with_other_bytes_are_refused(refused_kernel, monkeypatch) -> None:
    """A kernel that writes the zero doubles the runtime leaves out fails its self-check,
    and a batch's messages are built as protobuf objects (the same bytes); so with
    PAYLOAD_NATIVE=0."""
    from payload.trials import codec, codec_c

    rng = np.random.default_rng(24)
    items = [codec._probe_item(rng, k) for k in range(40)]
    want = StepCodec().encode_batch(items)
    with refused_kernel(
        codec_c, "if (!bits) return p;", "", attr="WRITER_C", forget=codec._steps_kernel
    ):
        assert codec._steps_kernel() is None
        assert StepCodec().encode_batch(items) == want
    monkeypatch.setenv("PAYLOAD_NATIVE", "0")
    codec._steps_kernel.cache_clear()
    try:
        assert codec._steps_kernel() is None
    finally:
        codec._steps_kernel.cache_clear()


def test_a_batch_with_a_negative_sequence_number_is_refused_as_the_runtime_refuses() -> None:
    """The compiled serialiser leaves a negative sequence number to the runtime, which
    refuses it (a uint64 field); an empty batch encodes to nothing."""
    from payload.trials import codec

    rng = np.random.default_rng(25)
    items = [codec._probe_item(rng, k) for k in range(3)]
    items[1] = (items[1][0], -1, items[1][2], items[1][3])
    with pytest.raises(ValueError):
        StepCodec().encode_batch(items)
    columns: list = []
    assert StepCodec().encode_batch([], columns) == [] and len(columns[0]["t"]) == 0
