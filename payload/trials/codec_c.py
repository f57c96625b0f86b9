"""The recording's step and hand-sample messages serialised in C, byte for byte.

At every flush the recorder encodes its batch of steps (:meth:`StepCodec.encode_batch
<payload.trials.codec.StepCodec.encode_batch>`): the grid and joint arithmetic in numpy
for the batch, then per step a ``payload.trials.HandSample`` and a ``payload.trials.Step``
message. Building those as protobuf objects field by field (and their lists of integers)
costs about 30 us a step in Python. Here the batch's messages are one C call that writes
their bytes from the batch's arrays, in protobuf's wire format as the protobuf runtime
writes these messages:

* fields in field-number order; a scalar (a varint, a bool, a double) only when it is not
  zero (a double: when its bits are not all zero, so ``-0.0`` is written); a packed
  repeated field only when it has elements; a set sub-message (the joints) always;
* ``sint64`` as zigzag varints.

:func:`compiled_steps` checks the kernel against the runtime's bytes on probe batches (the
caller's: every kind of step and joints) when it is built, and returns None (the protobuf
objects are built) without a C compiler, with ``PAYLOAD_NATIVE=0``, or on a single
differing byte.
"""

from __future__ import annotations

import ctypes
import itertools
import logging
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from payload import native
from payload.trials.jointcodec import IN_HANDS, N_JOINT_VALUES, ON_GRID, RAW, UNTRACKED
from payload.trials.stepmsg import HandSampleMsg, JointsMsg, StepMsg
from payload.trials.wire_c import WRITER_C, defines

log = logging.getLogger(__name__)

STEP_FLAGS: tuple[str, ...] = (
    "phase",
    "ctb_module",
    "left_tracked",
    "right_tracked",
    "contact",
    "pairs_in_cmd",
    "gridded",
    "grid_key",
)
"""A step's small numbers the serialiser takes, in their order (the C reads each as
``FLAG_<NAME>``): phase, CTB module, left and right tracked, contact, pairs in the
command, stored on the grid, a grid key."""

N_FLAGS = len(STEP_FLAGS)

STEP_BYTES = 8192
"""A bound on the bytes of one step's two messages (each at most about 2,400: two raw hands
of 75 doubles, 80 doubles and 64 ten-byte varints, with their tags)."""

SOURCE = r"""
/* after payload.trials.wire_c's writers; defined by the loader: N_JOINTS, STEP_BYTES,
   N_FLAGS, MAX_INTS (the longest packed integers), the joints' forms (UNTRACKED, ON_GRID,
   RAW, IN_HANDS: payload.trials.jointcodec's) and every field's number (STEP_*, HAND_*,
   JOINTS_*: payload.trials.stepmsg's messages) */

static unsigned char *packed_sint64(unsigned char *p, uint64_t number, const int64_t *v, int64_t n)
{
    unsigned char body[10 * MAX_INTS], *b = body;
    if (n <= 0) return p;
    for (int64_t i = 0; i < n; i++)
        b = varint(b, ((uint64_t)v[i] << 1) ^ (uint64_t)(v[i] >> 63));  /* zigzag */
    return field(p, number, body, b);
}

/* a payload.trials.Joints sub-message (always present) */
static unsigned char *joints(unsigned char *p, uint64_t number, int64_t kind, int64_t key,
                             const int64_t *ints, const double *raw, double grid)
{
    unsigned char body[16 + 10 * N_JOINTS + 8], *b = body;
    if (kind == ON_GRID) {
        b = dbl(b, JOINTS_GRID, grid);
        b = packed_sint64(b, JOINTS_DELTA, ints, N_JOINTS);
        b = scalar(b, JOINTS_KEY, key != 0);
    } else if (kind == RAW) {
        b = packed_doubles(b, JOINTS_RAW, raw, N_JOINTS);
    } else if (kind == UNTRACKED) {
        b = scalar(b, JOINTS_UNTRACKED, 1);
    } else {  /* IN_HANDS: the hand sample's joints */
        b = scalar(b, JOINTS_IN_HANDS, 1);
    }
    return field(p, number, body, b);
}

/* Per step i of n: its HandSample (when hand[2 i] >= 0) and its Step, into out (cap
   bytes); ends[2 i] and ends[2 i + 1] get the end offsets of the two (a step without a
   hand sample: its HandSample ends where it starts). Returns the bytes written, or -1
   (no room).

   seq[i], wall[i]: the step's sequence number and wall_time (0 when gridded);
   flags[N_FLAGS i ..]: STEP_FLAGS, each at its FLAG_<NAME>;
   doubles[nd i ..]: the packed double fields' values, field by field (numbers[f] and
     sizes[f]; a size 0 a scalar double; pair[f]: a pair field, stored unless pairs_in_cmd,
     the others unless gridded);
   grid[ng i ..]: the grid integers (gridded steps);
   joints code[2 i + s], key, ints[75 (2 i + s) ..], raw[..] of the step's hands;
   hand[2 i ..]: left and right tracked of the hand sample, or -1: none; stamp[i] its
     stamp; hcode, hkey, hints, hraw its joints as the step's. */
int64_t payload_encode_steps(
    int64_t n, const int64_t *seq, const double *wall, const int64_t *flags,
    int64_t nf, const int64_t *numbers, const int64_t *sizes, const int64_t *pair,
    int64_t nd, const double *doubles, int64_t ng, const int64_t *grid,
    const int64_t *code, const int64_t *key, const int64_t *ints, const double *raw,
    const int64_t *hand, const double *stamp, const int64_t *hcode, const int64_t *hkey,
    const int64_t *hints, const double *hraw, double joint_grid,
    unsigned char *out, int64_t cap, int64_t *ends)
{
    unsigned char *p = out;
    for (int64_t i = 0; i < n; i++) {
        if ((p - out) + STEP_BYTES > cap) return -1;
        if (hand[2 * i] >= 0) {  /* payload.trials.HandSample */
            p = scalar(p, HAND_SEQ, (uint64_t)seq[i]);
            p = dbl(p, HAND_STAMP, stamp[i]);
            p = scalar(p, HAND_LEFT_TRACKED, hand[2 * i] != 0);
            p = scalar(p, HAND_RIGHT_TRACKED, hand[2 * i + 1] != 0);
            for (int s = 0; s < 2; s++) {
                int64_t j = 2 * i + s;
                p = joints(p, s ? HAND_RIGHT : HAND_LEFT, hcode[j], hkey[j],
                           hints + N_JOINTS * j, hraw + N_JOINTS * j, joint_grid);
            }
        }
        ends[2 * i] = p - out;
        const int64_t *fl = flags + N_FLAGS * i;
        int64_t pairs = fl[FLAG_PAIRS_IN_CMD], gridded = fl[FLAG_GRIDDED];
        const double *v = doubles + nd * i;
        p = scalar(p, STEP_SEQ, (uint64_t)seq[i]);
        p = dbl(p, STEP_WALL_TIME, wall[i]);
        for (int pass = 0; pass < 2; pass++) {
            /* the double fields numbered below the phase (t), then the enums and bools,
               then the rest of the doubles: field-number order */
            if (pass == 1) {
                p = scalar(p, STEP_PHASE, (uint64_t)fl[FLAG_PHASE]);
                p = scalar(p, STEP_CTB_MODULE, (uint64_t)fl[FLAG_CTB_MODULE]);
                p = scalar(p, STEP_LEFT_TRACKED, fl[FLAG_LEFT_TRACKED] != 0);
                p = scalar(p, STEP_RIGHT_TRACKED, fl[FLAG_RIGHT_TRACKED] != 0);
                p = scalar(p, STEP_CONTACT, fl[FLAG_CONTACT] != 0);
                p = scalar(p, STEP_PAIRS_IN_CMD, pairs != 0);
            }
            const double *x = v;
            for (int64_t f = 0; f < nf; f++) {
                int64_t size = sizes[f] ? sizes[f] : 1;
                int stored = pair[f] ? !pairs : !gridded;
                if ((numbers[f] < STEP_PHASE) == (pass == 0) && stored)
                    p = sizes[f] ? packed_doubles(p, (uint64_t)numbers[f], x, sizes[f])
                                 : dbl(p, (uint64_t)numbers[f], x[0]);
                x += size;
            }
        }
        for (int s = 0; s < 2; s++) {
            int64_t j = 2 * i + s;
            p = joints(p, s ? STEP_RIGHT_JOINTS : STEP_LEFT_JOINTS, code[j], key[j],
                       ints + N_JOINTS * j, raw + N_JOINTS * j, joint_grid);
        }
        if (gridded) {
            p = packed_sint64(p, STEP_GRID, grid + ng * i, ng);
            p = scalar(p, STEP_GRID_KEY, fl[FLAG_GRID_KEY] != 0);
        }
        ends[2 * i + 1] = p - out;
    }
    return p - out;
}
"""


class CompiledSteps:
    """The batch serialiser of :data:`SOURCE` for one step layout.

    Args:
        lib: The kernel's library.
        fields: ``(number, size, pair)`` of each double field of a step, in order (size 0:
            a scalar); the doubles a step hands over are these fields' values in turn.
        grid_size: How many grid integers a gridded step stores.
    """

    def __init__(self, lib: ctypes.CDLL, fields: list[tuple[int, int, bool]], grid_size: int):
        fn = lib.payload_encode_steps
        fn.restype = ctypes.c_int64
        ptr, i64, f64 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
        fn.argtypes = [
            i64, ptr, ptr, ptr, i64, ptr, ptr, ptr, i64, ptr, i64, ptr,
            ptr, ptr, ptr, ptr, ptr, ptr, ptr, ptr, ptr, ptr, f64, ptr, i64, ptr,
        ]  # fmt: skip
        self._fn = fn
        table = np.array(fields, dtype=np.int64).reshape(-1, 3)
        self._numbers = np.ascontiguousarray(table[:, 0])
        self._sizes = np.ascontiguousarray(table[:, 1])
        self._pair = np.ascontiguousarray(table[:, 2])
        self.n_doubles = int(np.maximum(self._sizes, 1).sum())
        self.grid_size = int(grid_size)

    def __call__(self, arrays: dict[str, np.ndarray], joint_grid: float) -> list[bytes]:
        """The batch's messages: per step its hand sample's bytes (``b""``: none) and its
        step's bytes, in turn (2 n items).

        Args:
            arrays: The batch as arrays (n steps): ``seq`` (n,), ``wall`` (n,), ``flags``
                (n, :data:`N_FLAGS`), ``doubles`` (n, :attr:`n_doubles`), ``grid`` (n, grid size),
                ``code``/``key`` (n, 2), ``ints``/``raw`` (n, 2, joint values), ``hand`` (n, 2),
                ``stamp`` (n,), ``hcode``/``hkey`` (n, 2), ``hints``/``hraw`` (n, 2, 75).
            joint_grid: The joints' grid [m].

        Raises:
            ValueError: An array of another shape or type (the caller's error).
        """
        n = len(arrays["seq"])
        shapes = {
            "seq": (n,), "wall": (n,), "flags": (n, N_FLAGS), "doubles": (n, self.n_doubles),
            "grid": (n, self.grid_size), "code": (n, 2), "key": (n, 2),
            "ints": (n, 2, N_JOINT_VALUES), "raw": (n, 2, N_JOINT_VALUES), "hand": (n, 2),
            "stamp": (n,), "hcode": (n, 2), "hkey": (n, 2),
            "hints": (n, 2, N_JOINT_VALUES), "hraw": (n, 2, N_JOINT_VALUES),
        }  # fmt: skip
        floats = ("wall", "doubles", "raw", "stamp", "hraw")
        args = {}
        for name, shape in shapes.items():
            a = np.ascontiguousarray(arrays[name], np.float64 if name in floats else np.int64)
            if a.shape != shape:
                raise ValueError(f"encode_steps: {name} has shape {a.shape}, not {shape}")
            args[name] = a
        out = np.empty(max(1, n) * STEP_BYTES, dtype=np.uint8)
        ends = np.zeros(2 * n, dtype=np.int64)
        size = self._fn(
            n, args["seq"].ctypes.data, args["wall"].ctypes.data, args["flags"].ctypes.data,
            len(self._numbers), self._numbers.ctypes.data, self._sizes.ctypes.data,
            self._pair.ctypes.data, self.n_doubles, args["doubles"].ctypes.data,
            self.grid_size, args["grid"].ctypes.data, args["code"].ctypes.data,
            args["key"].ctypes.data, args["ints"].ctypes.data, args["raw"].ctypes.data,
            args["hand"].ctypes.data, args["stamp"].ctypes.data, args["hcode"].ctypes.data,
            args["hkey"].ctypes.data, args["hints"].ctypes.data, args["hraw"].ctypes.data,
            float(joint_grid), out.ctypes.data, len(out), ends.ctypes.data,
        )  # fmt: skip
        if size < 0:  # pragma: no cover - STEP_BYTES bounds a step's messages
            raise ValueError("encode_steps: a step's messages overflow STEP_BYTES")
        data = out[:size].tobytes()
        cuts = [0, *ends.tolist()]
        return [data[a:b] for a, b in itertools.pairwise(cuts)]


@native.reported("recording steps")
def compiled_steps(
    fields: list[tuple[int, int, bool]],
    grid_size: int,
    probes: Callable[[], Iterable[tuple[dict[str, np.ndarray], float, list[bytes]]]],
) -> CompiledSteps | None:
    """The compiled serialiser, or None to build the messages as protobuf objects: no
    compiler, ``PAYLOAD_NATIVE=0``, a failed build, or a self-check that differs in a byte
    from the protobuf runtime's on ``probes()``: batches (as :meth:`CompiledSteps.__call__`
    takes them, with the joints' grid) with the bytes the runtime gives them."""
    values = {
        "N_JOINTS": N_JOINT_VALUES,
        "STEP_BYTES": STEP_BYTES,
        "N_FLAGS": N_FLAGS,
        "MAX_INTS": max(N_JOINT_VALUES, grid_size),
        "UNTRACKED": UNTRACKED,
        "ON_GRID": ON_GRID,
        "RAW": RAW,
        "IN_HANDS": IN_HANDS,
        **{f"FLAG_{name.upper()}": i for i, name in enumerate(STEP_FLAGS)},
    }
    prelude = defines(values, {"STEP": StepMsg, "HAND": HandSampleMsg, "JOINTS": JointsMsg})
    lib = native.load_kernel(
        "steps", SOURCE, "the step messages kernel", log, prelude=prelude + WRITER_C
    )
    if lib is None:
        return None
    kernel = CompiledSteps(lib, fields, grid_size)
    for arrays, joint_grid, want in probes():
        got: Any = kernel(arrays, joint_grid)
        if got != want:
            log.warning("recording steps: protobuf (the compiled bytes differ)")
            return None
    return kernel


__all__ = ["N_FLAGS", "SOURCE", "STEP_BYTES", "STEP_FLAGS", "CompiledSteps", "compiled_steps"]
