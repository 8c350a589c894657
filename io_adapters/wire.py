"""How a message endpoint lays its messages out in bytes: a :class:`Wire`.

Two wires carry the same records (:mod:`io_adapters.messages`) with the same handshake,
sequence check and refusals (:mod:`io_adapters.msgpack_endpoint`):

* ``msgpack`` (the default): msgpack arrays, :mod:`io_adapters.codec`;
* ``fixed``: a fixed little-endian layout of C structs, :mod:`io_adapters.codec_fixed`,
  for clients written in C (a LinuxCNC HAL component, a PLC runtime, a Simulink or
  LabVIEW UDP block).

A URL selects one with ``wire=NAME`` (:func:`wire_named`); both sides of a link must use
the same.  The decoded form is the same for both (the msgpack wire's arrays, header
first), so everything after decoding is shared.
"""

import importlib
from collections.abc import Callable
from typing import NamedTuple

#: wire name -> "module:attribute" of its :class:`Wire`, imported when first used
WIRES = {"msgpack": "io_adapters.msgpack_endpoint:MSGPACK_WIRE",
         "fixed": "io_adapters.codec_fixed:FIXED_WIRE"}


class Wire(NamedTuple):
    """The byte layout of one wire: functions of :mod:`io_adapters.codec`'s signatures.

    Attributes:
        name: the wire's name in a URL.
        encode: ``(record, session, frame) -> bytes``.
        decode: ``(data, record_type, n_axes) -> tuple``: the checked array of a record,
            of the handshake message its receiver takes, or (setpoints) an INJECT;
            :class:`~io_adapters.base.FrameError` otherwise.
        fill: ``(into, values)``: write a decoded record into ``into``.
        finite: ``(values, record_type) -> bool``: every float of a decoded record is
            finite.
        encode_hello: ``(session, frame) -> bytes``.
        decode_hello: ``(data) -> tuple``.
        encode_welcome: ``(session, frame, accepted) -> bytes``.
        encode_inject: ``(session, frame, request) -> bytes``.
        hello_leads: the first bytes a HELLO can start with (a stranger's datagram that
            starts otherwise is not decoded).
    """
    name: str
    encode: Callable
    decode: Callable
    fill: Callable
    finite: Callable
    encode_hello: Callable
    decode_hello: Callable
    encode_welcome: Callable
    encode_inject: Callable
    hello_leads: frozenset


def wire_named(name: str) -> Wire:
    """The wire called ``name`` (a URL option's value); ValueError naming the known ones."""
    target = WIRES.get(name)
    if target is None:
        raise ValueError(f"unknown wire {name!r}; known: {', '.join(sorted(WIRES))}")
    module, _, attribute = target.partition(":")
    return getattr(importlib.import_module(module), attribute)
