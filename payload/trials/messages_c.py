"""The recording's most frequent Foxglove messages serialised in C, byte for byte.

At every fifth control step a trial's recording gets a ``foxglove.FrameTransforms`` (``/tf``:
a transform per link) and two ``foxglove.JointStates`` (the commanded and the measured
joints). Building them as protobuf objects field by field and serialising them costs about
90 and 25 us a message in Python. Here each is one C call that writes the serialised bytes
directly, in protobuf's wire format as the protobuf runtime writes these messages:

* fields in field-number order; a set sub-message (``timestamp``, ``translation``,
  ``rotation``, each joint) always, even when empty;
* a double of implicit presence (``Vector3``, ``Quaternion``) only when its bits are not
  zero (so ``-0.0`` is written, ``0.0`` is not), a double of explicit presence
  (``JointState.position``) always; integers (``Timestamp``) as varints when not zero;
* the frame and joint names as the runtime serialises them, taken once from the runtime
  itself (a message holding the names alone).

:func:`compiled_messages` checks the kernel against the runtime's ``SerializeToString``
on probe messages (random values, zeros of both signs, the recording's own names) when it
is built, and returns None (the protobuf objects are built) without a C compiler, with
``PAYLOAD_NATIVE=0``, or on a single differing byte. The values written are the ones the
Python code would set: the caller rounds them as before.
"""

from __future__ import annotations

import ctypes
import logging
import threading
from collections.abc import Callable, Sequence

import numpy as np
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.JointState_pb2 import JointState
from foxglove_schemas_protobuf.JointStates_pb2 import JointStates
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp

from payload import native
from payload.trials.wire_c import WRITER_C, defines

log = logging.getLogger(__name__)

ITEM_BYTES = 1024
"""The most bytes one transform or joint may take serialised (its names included): longer
names are left to the protobuf runtime."""

REST_BYTES = 124
"""A bound on the bytes of one item besides its names (tags, lengths, a timestamp, seven
doubles: 88 at most): ``ITEM_BYTES - REST_BYTES`` is the room for the names."""

SOURCE = r"""
/* after payload.trials.wire_c's writers; ITEM_BYTES, REST_BYTES and the messages' field
   numbers (TS_*, TF_*, TFS_*, V_*, Q_*, JS_*, J_*: the schemas' own) are defined by the
   loader */

/* google.protobuf.Timestamp's body */
static unsigned char *stamp(unsigned char *p, int64_t seconds, int64_t nanos)
{
    return scalar(scalar(p, TS_SECONDS, (uint64_t)seconds), TS_NANOS, (uint64_t)nanos);
}

/* foxglove.FrameTransforms: per transform i, the timestamp, the names (names[off[i],
   off[i + 1]): the serialised parent and child fields), the translation (poses[7 i ..])
   and the rotation (poses: x y z, then w x y z) into out (cap bytes); returns the length
   written, or -1 (names too long, or no room) */
int64_t payload_frame_transforms(int64_t n, const double *poses, const unsigned char *names,
                                 const int64_t *off, int64_t seconds, int64_t nanos,
                                 unsigned char *out, int64_t cap)
{
    unsigned char ts[24], body[ITEM_BYTES], sub[64], *p = out;
    unsigned char *ts_end = stamp(ts, seconds, nanos);
    for (int64_t i = 0; i < n; i++) {
        const double *v = poses + 7 * i;
        int64_t len = off[i + 1] - off[i];
        if (len > ITEM_BYTES - REST_BYTES || (p - out) + len + REST_BYTES > cap) return -1;
        unsigned char *b = field(body, TF_TIMESTAMP, ts, ts_end);
        memcpy(b, names + off[i], (size_t)(off[i + 1] - off[i]));
        b += off[i + 1] - off[i];
        unsigned char *s = dbl(dbl(dbl(sub, V_X, v[0]), V_Y, v[1]), V_Z, v[2]);
        b = field(b, TF_TRANSLATION, sub, s);
        s = dbl(dbl(dbl(dbl(sub, Q_X, v[4]), Q_Y, v[5]), Q_Z, v[6]), Q_W, v[3]);
        b = field(b, TF_ROTATION, sub, s);
        p = field(p, TFS_TRANSFORMS, body, b);
    }
    return p - out;
}

/* foxglove.JointStates: the timestamp, then per joint its name (names[off[i], off[i + 1]):
   the serialised name field) and its position into out (cap bytes); returns the length
   written, or -1 */
int64_t payload_joint_states(int64_t n, const double *positions, const unsigned char *names,
                             const int64_t *off, int64_t seconds, int64_t nanos,
                             unsigned char *out, int64_t cap)
{
    unsigned char ts[24], body[ITEM_BYTES], *p = out;
    p = field(p, JS_TIMESTAMP, ts, stamp(ts, seconds, nanos));
    for (int64_t i = 0; i < n; i++) {
        int64_t len = off[i + 1] - off[i];
        if (len > ITEM_BYTES - REST_BYTES || (p - out) + len + REST_BYTES > cap) return -1;
        memcpy(body, names + off[i], (size_t)(off[i + 1] - off[i]));
        /* the position has explicit presence: written even when zero */
        unsigned char *b = le64(tag(body + (off[i + 1] - off[i]), J_POSITION, 1), positions[i]);
        p = field(p, JS_JOINTS, body, b);
    }
    return p - out;
}
"""


def _names(chunks: Sequence[bytes]) -> tuple[bytes, np.ndarray]:
    """The chunks concatenated, and their offsets (n + 1,)."""
    off = np.zeros(len(chunks) + 1, dtype=np.int64)
    off[1:] = np.cumsum([len(c) for c in chunks])
    return b"".join(chunks), off


class CompiledMessages:
    """The ``/tf`` and joint-state messages of one recording's frames and joints.

    Args:
        lib: The kernel's library.
        frames: (parent, child) frame names of each transform, in order.
        joints: The joint names, in order.
    """

    def __init__(
        self, lib: ctypes.CDLL, frames: Sequence[tuple[str, str]], joints: Sequence[str]
    ) -> None:
        # the name fields as the protobuf runtime serialises them
        self._tf_names = _names(
            [FrameTransform(parent_frame_id=p, child_frame_id=c).SerializeToString()
             for p, c in frames]
        )  # fmt: skip
        self._joint_names = _names([JointState(name=n).SerializeToString() for n in joints])
        self.n_frames, self.n_joints = len(frames), len(joints)
        ptr, i64 = ctypes.c_void_p, ctypes.c_int64
        for fn in (lib.payload_frame_transforms, lib.payload_joint_states):
            fn.restype = i64
            fn.argtypes = [i64, ptr, ctypes.c_char_p, ptr, i64, i64, ptr, i64]
        self._tf, self._js = lib.payload_frame_transforms, lib.payload_joint_states
        # room for every message: the timestamp, and per item its names and the rest
        self._tf_out = ctypes.create_string_buffer(
            len(self._tf_names[0]) + REST_BYTES * (len(frames) + 1)
        )
        self._js_out = ctypes.create_string_buffer(
            len(self._joint_names[0]) + REST_BYTES * (len(joints) + 1)
        )
        self._lock = threading.Lock()  # the buffers are shared by the calls

    def _call(
        self, fn: Callable, n: int, values: np.ndarray, names: tuple, stamp: tuple[int, int],
        out: ctypes.Array,
    ) -> bytes | None:  # fmt: skip
        v = np.ascontiguousarray(values, dtype=np.float64)
        with self._lock:
            size = fn(n, v.ctypes.data, names[0], names[1].ctypes.data, *stamp, out, len(out))
            return None if size < 0 else ctypes.string_at(out, size)

    def frame_transforms(self, poses: np.ndarray, stamp: tuple[int, int]) -> bytes | None:
        """The serialised ``FrameTransforms`` of ``poses`` (N, 7: position, quaternion w x
        y z) at ``stamp`` (seconds, nanos), or None (a name too long: build the message)."""
        if poses.shape != (self.n_frames, 7):
            return None
        return self._call(self._tf, self.n_frames, poses, self._tf_names, stamp, self._tf_out)

    def joint_states(self, positions: np.ndarray, stamp: tuple[int, int]) -> bytes | None:
        """The serialised ``JointStates`` of ``positions`` (J,) at ``stamp``, or None."""
        if positions.shape != (self.n_joints,):
            return None
        return self._call(
            self._js, self.n_joints, positions, self._joint_names, stamp, self._js_out
        )


def load_library() -> ctypes.CDLL | None:
    """The kernel's library (None: the protobuf objects are to be built; the log says
    why)."""
    prelude = defines(
        {"ITEM_BYTES": ITEM_BYTES, "REST_BYTES": REST_BYTES},
        {
            "TS": Timestamp, "TF": FrameTransform, "TFS": FrameTransforms, "V": Vector3,
            "Q": Quaternion, "JS": JointStates, "J": JointState,
        },
    )  # fmt: skip
    return native.load_kernel(
        "messages", SOURCE, "the Foxglove messages kernel", log, prelude=prelude + WRITER_C
    )


@native.reported("Foxglove messages")
def compiled_messages(
    frames: Sequence[tuple[str, str]],
    joints: Sequence[str],
    transforms: Callable[[np.ndarray, int], bytes],
    joint_states: Callable[[np.ndarray, int], bytes],
    split: Callable[[int], tuple[int, int]],
) -> CompiledMessages | None:
    """The compiled messages, or None to build them as protobuf objects: no compiler,
    ``PAYLOAD_NATIVE=0``, a failed build, or a self-check against ``transforms(poses,
    ns)`` and ``joint_states(positions, ns)`` (the runtime's serialisation of the messages
    the Python code builds at log time ``ns``, which ``split`` makes the kernel's (seconds,
    nanos)) that differs in a byte, on random values (some zero, of either sign) and log
    times (some on whole seconds)."""
    lib = load_library()
    if lib is None:
        return None
    kernel = CompiledMessages(lib, frames, joints)
    rng = np.random.default_rng(0)
    for k in range(60):
        ns = int(rng.integers(0, 10**12)) if k else 0
        if k % 4 == 1:
            ns -= split(ns)[1]  # on a whole second: no nanos written
        poses = rng.normal(size=(len(frames), 7)) * (rng.random((len(frames), 7)) < 0.8)
        poses[rng.random(poses.shape) < 0.1] = -0.0
        positions = rng.normal(size=len(joints)) * (rng.random(len(joints)) < 0.8)
        positions[rng.random(len(joints)) < 0.1] = -0.0
        stamp = split(ns)
        if kernel.frame_transforms(poses, stamp) != transforms(poses, ns) or kernel.joint_states(
            positions, stamp
        ) != joint_states(positions, ns):
            log.warning("Foxglove messages: protobuf (the compiled bytes differ)")
            return None
    return kernel


__all__ = [
    "ITEM_BYTES",
    "REST_BYTES",
    "SOURCE",
    "CompiledMessages",
    "compiled_messages",
    "load_library",
]
