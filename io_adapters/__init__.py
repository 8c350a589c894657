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

What a drive takes is the device endpoint's ``setpoint_bounds`` (one
:class:`SetpointBounds` per axis, or one for all); a setpoint beyond them, or with a
non-finite value, is refused (``stats.refused_*``, ``refused_axes``) and never reaches
the caller's record.  Sends never wait for the peer (``stats.send_dropped``).
"""

from io_adapters.base import (
    LINK_HEARTBEAT_LOST,
    LINK_RESET,
    LINK_STOPPED,
    AdapterClosed,
    AdapterConfigError,
    AdapterError,
    AdapterStats,
    AdapterTimeout,
    Endpoint,
    FrameError,
    Role,
)
from io_adapters.messages import (
    MODE_CST,
    MODE_VOLTAGE,
    REFUSED_MODE,
    REFUSED_NONFINITE,
    REFUSED_RANGE,
    Feedback,
    Setpoint,
    SetpointBounds,
)
from io_adapters.registry import known_schemes, open_endpoint, register

__all__ = [
    "LINK_HEARTBEAT_LOST",
    "LINK_RESET",
    "LINK_STOPPED",
    "MODE_CST",
    "MODE_VOLTAGE",
    "REFUSED_MODE",
    "REFUSED_NONFINITE",
    "REFUSED_RANGE",
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
    "SetpointBounds",
    "known_schemes",
    "open_endpoint",
    "register",
]
