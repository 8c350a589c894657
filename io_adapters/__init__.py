"""Transports between a controller and the emulator.

The data flow is controller -> adapter -> loop -> plant -> adapter -> controller;
``io_adapters`` imports nothing from ``plant`` or ``hil``.  Every adapter carries
the two records of :mod:`io_adapters.messages` and fills the contract of
:class:`~io_adapters.base.Endpoint`.  Open one by URL, with the side it plays::

    with open_endpoint("udp://127.0.0.1:5005", "device") as ep:
        if ep.recv_setpoint(sp, timeout_s=0.001):
            ...
            ep.send_feedback(fb)

Schemes (:mod:`io_adapters.registry`; transport modules are imported only when
opened): ``udp://HOST:PORT`` (:mod:`io_adapters.udp`), ``serial://PATH`` or
``serial://fd/N`` (:mod:`io_adapters.serial_link`), and whatever :func:`register`
or the entry-point group ``feeddrive_hil.adapters`` adds.  Both built-in
transports carry the msgpack messages of :mod:`io_adapters.codec`.
"""

from io_adapters.base import (
    AdapterClosed,
    AdapterConfigError,
    AdapterError,
    AdapterStats,
    AdapterTimeout,
    Endpoint,
    FrameError,
    Role,
)
from io_adapters.messages import MODE_CST, MODE_VOLTAGE, Feedback, Setpoint
from io_adapters.registry import known_schemes, open_endpoint, register

__all__ = [
    "MODE_CST",
    "MODE_VOLTAGE",
    "AdapterClosed",
    "AdapterConfigError",
    "AdapterError",
    "AdapterStats",
    "AdapterTimeout",
    "Endpoint",
    "Feedback",
    "FrameError",
    "Role",
    "Setpoint",
    "known_schemes",
    "open_endpoint",
    "register",
]
