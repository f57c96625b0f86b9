"""The recording's protobuf messages, declared in code.

``payload.trials.Step``, ``payload.trials.HandSample`` and ``payload.trials.Joints`` (and
the ``Phase`` and ``Module`` enums) as a ``FileDescriptorProto`` (no ``protoc`` needed),
their Python classes generated at import. What the fields hold and how the numbers are
coded: :mod:`payload.trials.codec`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from payload.envelope.pairs import pair_joints
from payload.schema import MANIPULATION_JOINTS
from payload.trials.records import FIELD_SPECS, MODULES, PHASES

PACKAGE = "payload.trials"

PAIR_L_INDEX = np.array([MANIPULATION_JOINTS.index(j) for j in pair_joints("L")])
"""Positions of pair L's joints (A then C) in the 17 manipulation coordinates."""
PAIR_R_INDEX = np.array([MANIPULATION_JOINTS.index(j) for j in pair_joints("R")])
"""Positions of pair R's joints (B then D)."""
RAIL_INDEX = MANIPULATION_JOINTS.index("rail")
"""Position of the rail in the 17 manipulation coordinates."""
PAIR_FIELDS = ("q_left", "q_right", "rail_cmd")
"""The step fields a ``Step`` leaves out when ``pairs_in_cmd`` is set."""

STEP_DOUBLES: tuple[tuple[str, int, tuple[int, ...]], ...] = tuple(
    (name, number, FIELD_SPECS[name][0])
    for name, number in (
        ("t", 3),
        ("q_left", 10),
        ("q_right", 11),
        ("rail_cmd", 12),
        ("twist_cmd", 13),
        ("q_cmd", 14),
        ("deploy_cmd", 15),
        ("q_meas", 16),
        ("deploy_meas", 17),
        ("astrobee_pos", 18),
        ("astrobee_quat", 19),
        ("astrobee_twist", 20),
        ("ctb_pos", 21),
        ("ctb_quat", 22),
    )
)
"""(name, field number, shape) of a ``Step``'s double fields, in field-number order (the
shapes the step record's; () a scalar double, else a packed repeated one)."""

_F = descriptor_pb2.FieldDescriptorProto


def _field(
    msg: descriptor_pb2.DescriptorProto,
    name: str,
    number: int,
    ftype: int,
    *,
    repeated: bool = False,
    type_name: str | None = None,
) -> None:
    f = msg.field.add(name=name, number=number, type=ftype)
    f.label = _F.LABEL_REPEATED if repeated else _F.LABEL_OPTIONAL
    if type_name is not None:
        f.type_name = type_name
    if repeated:
        f.options.packed = True


def _enum(fd: descriptor_pb2.FileDescriptorProto, name: str, values: tuple[str, ...]) -> None:
    e = fd.enum_type.add(name=name)
    for i, v in enumerate(values):
        e.value.add(name=f"{name.upper()}_{v.upper()}", number=i)


def _file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    fd = descriptor_pb2.FileDescriptorProto(
        name="payload/trials/step.proto", package=PACKAGE, syntax="proto3"
    )
    _enum(fd, "Phase", PHASES)  # the enums' values in number order: the record's
    _enum(fd, "Module", MODULES)
    j = fd.message_type.add(name="Joints")
    _field(j, "grid", 1, _F.TYPE_DOUBLE)
    _field(j, "delta", 2, _F.TYPE_SINT64, repeated=True)
    _field(j, "raw", 3, _F.TYPE_DOUBLE, repeated=True)
    _field(j, "untracked", 4, _F.TYPE_BOOL)
    _field(j, "key", 5, _F.TYPE_BOOL)
    _field(j, "in_hands", 6, _F.TYPE_BOOL)
    s = fd.message_type.add(name="Step")
    _field(s, "seq", 1, _F.TYPE_UINT64)
    _field(s, "wall_time", 2, _F.TYPE_DOUBLE)
    _field(s, "phase", 4, _F.TYPE_ENUM, type_name=f".{PACKAGE}.Phase")
    _field(s, "ctb_module", 5, _F.TYPE_ENUM, type_name=f".{PACKAGE}.Module")
    _field(s, "left_tracked", 6, _F.TYPE_BOOL)
    _field(s, "right_tracked", 7, _F.TYPE_BOOL)
    _field(s, "contact", 8, _F.TYPE_BOOL)
    for name, number, shape in STEP_DOUBLES:
        _field(s, name, number, _F.TYPE_DOUBLE, repeated=shape != ())
    _field(s, "pairs_in_cmd", 9, _F.TYPE_BOOL)
    _field(s, "left_joints", 30, _F.TYPE_MESSAGE, type_name=f".{PACKAGE}.Joints")
    _field(s, "right_joints", 31, _F.TYPE_MESSAGE, type_name=f".{PACKAGE}.Joints")
    _field(s, "grid", 40, _F.TYPE_SINT64, repeated=True)
    _field(s, "grid_key", 41, _F.TYPE_BOOL)
    h = fd.message_type.add(name="HandSample")
    _field(h, "seq", 1, _F.TYPE_UINT64)
    _field(h, "stamp", 2, _F.TYPE_DOUBLE)
    _field(h, "left_tracked", 3, _F.TYPE_BOOL)
    _field(h, "right_tracked", 4, _F.TYPE_BOOL)
    _field(h, "left", 5, _F.TYPE_MESSAGE, type_name=f".{PACKAGE}.Joints")
    _field(h, "right", 6, _F.TYPE_MESSAGE, type_name=f".{PACKAGE}.Joints")
    return fd


FILE_DESCRIPTOR = _file_descriptor()
_POOL = descriptor_pool.DescriptorPool()
_POOL.Add(FILE_DESCRIPTOR)
STEP_MESSAGE = f"{PACKAGE}.Step"
HANDS_MESSAGE = f"{PACKAGE}.HandSample"
JOINTS_MESSAGE = f"{PACKAGE}.Joints"
StepMsg: Any = message_factory.GetMessageClass(_POOL.FindMessageTypeByName(STEP_MESSAGE))
HandSampleMsg: Any = message_factory.GetMessageClass(_POOL.FindMessageTypeByName(HANDS_MESSAGE))
JointsMsg: Any = message_factory.GetMessageClass(_POOL.FindMessageTypeByName(JOINTS_MESSAGE))


def schema_data() -> bytes:
    """The ``FileDescriptorSet`` of these messages (the MCAP schema data)."""
    return descriptor_pb2.FileDescriptorSet(file=[FILE_DESCRIPTOR]).SerializeToString()


__all__ = [
    "FILE_DESCRIPTOR",
    "HANDS_MESSAGE",
    "JOINTS_MESSAGE",
    "PACKAGE",
    "PAIR_FIELDS",
    "PAIR_L_INDEX",
    "PAIR_R_INDEX",
    "RAIL_INDEX",
    "STEP_DOUBLES",
    "STEP_MESSAGE",
    "HandSampleMsg",
    "JointsMsg",
    "StepMsg",
    "schema_data",
]
