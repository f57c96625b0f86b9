"""Protobuf's wire format written in C: the helpers the message kernels share.

:data:`WRITER_C` is the prelude of the kernels that serialise messages byte for byte as
the protobuf runtime does (:mod:`payload.trials.messages_c`, :mod:`payload.trials.codec_c`):
varints, tags by field number and wire type, a scalar only when it is not zero, a double
of implicit presence only when its bits are not all zero (so ``-0.0`` is written and
``0.0`` is not), little-endian doubles, length-delimited fields and packed doubles.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

WRITER_C = r"""
#include <string.h>

static unsigned char *varint(unsigned char *p, uint64_t v)
{
    while (v >= 0x80) { *p++ = (unsigned char)(v | 0x80); v >>= 7; }
    *p++ = (unsigned char)v;
    return p;
}

/* a field's key: its number and wire type (0 varint, 1 64-bit, 2 length-delimited) */
static unsigned char *tag(unsigned char *p, uint64_t number, unsigned wire)
{
    return varint(p, (number << 3) | wire);
}

/* a varint scalar (an enum, an integer, a bool) of implicit presence: when not zero */
static unsigned char *scalar(unsigned char *p, uint64_t number, uint64_t v)
{
    if (!v) return p;
    return varint(tag(p, number, 0), v);
}

static unsigned char *le64(unsigned char *p, double x)
{
    uint64_t bits;
    memcpy(&bits, &x, 8);
    for (int i = 0; i < 8; i++) *p++ = (unsigned char)(bits >> (8 * i));  /* little-endian */
    return p;
}

/* a double of implicit presence: written when its bits are not all zero */
static unsigned char *dbl(unsigned char *p, uint64_t number, double x)
{
    uint64_t bits;
    memcpy(&bits, &x, 8);
    if (!bits) return p;
    return le64(tag(p, number, 1), x);
}

/* a length-delimited field (a sub-message, a string) from the body in [body, end) */
static unsigned char *field(unsigned char *p, uint64_t number, const unsigned char *body,
                            const unsigned char *end)
{
    p = varint(tag(p, number, 2), (uint64_t)(end - body));
    memmove(p, body, (size_t)(end - body));
    return p + (end - body);
}

static unsigned char *packed_doubles(unsigned char *p, uint64_t number, const double *v, int64_t n)
{
    if (n <= 0) return p;
    p = varint(tag(p, number, 2), (uint64_t)(8 * n));
    for (int64_t i = 0; i < n; i++) p = le64(p, v[i]);
    return p;
}
"""
"""The shared writers (C; a kernel's source follows it)."""


def defines(values: Mapping[str, int], messages: Mapping[str, Any]) -> str:
    """A kernel's ``#define`` lines: ``values`` as they are, then every field number of
    ``messages`` (prefix -> protobuf message class) as ``PREFIX_FIELD``, from the
    messages' descriptors."""
    numbers = {
        f"{prefix}_{field.name.upper()}": field.number
        for prefix, message in messages.items()
        for field in message.DESCRIPTOR.fields
    }
    return "".join(f"#define {name} {value}\n" for name, value in {**values, **numbers}.items())


__all__ = ["WRITER_C", "defines"]
