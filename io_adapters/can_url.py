"""The ``can://`` URL that both sides of the link parse.

::

    can://INTERFACE/CHANNEL?node=N&rated_current_ma=I[&axes=A][&rated_torque_mnm=T]
                           [&bitrate=B][&log=FILE][&sync_timeout_ms=S]
                           [&heartbeat_consumer=ID:MS][&heartbeat=ID:MS]
                           [&port=P][&multicast_if=ADDR]

* INTERFACE/CHANNEL (python-can): ``virtual/NAME`` (any name; this process only: ``hil
  run`` refuses it, :func:`in_process_only`), ``udp_multicast/GROUP`` (an IPv4 or IPv6
  multicast group address such as python-can's default 239.74.163.2; between
  processes), ``socketcan/vcan0`` (a SocketCAN interface, where the kernel has one).
* ``node`` (required): the drive's node-ID, 1-127.
* ``axes`` (default 1): the drives of a machine of several axes, one CiA 402 node per
  axis on the same bus, node-IDs ``node`` .. ``node + axes - 1`` in the machine's axis
  order (each with its own object dictionary, PDOs and SDO server; one SYNC cycles them
  all).  ``hil run`` and ``hil controller`` add it from the machine.  Every node takes
  the same ``rated_current_ma`` and ``rated_torque_mnm``.
* ``rated_current_ma`` (required): 6075h motor rated current, mA.  Currents on the
  wire are per mille of it (6071h, 60B2h, 6077h, 6078h), so one step is
  rated_current_ma / 1000 mA: 28 mA with ``rated_current_ma=28000``.
* ``rated_torque_mnm``: 6076h motor rated torque, mN·m, reported only (default 0: not
  stated).
* ``bitrate`` (default 1000000): the bus's bit rate, bit/s, one of CiA 301's (10000,
  20000, 50000, 125000, 250000, 500000, 800000, 1000000).  The device checks that its
  PDO configuration fits its communication cycle at this rate
  (:mod:`io_adapters.can_bus_time`) and counts the bits of every frame it sees.
* ``log`` (both sides): write every frame this side sends or receives to FILE with
  python-can's writer for its suffix: ``.asc`` (Vector ASCII), ``.blf`` (Vector binary
  logging format), ``.trc`` (PEAK) or ``.log`` (candump).
* ``sync_timeout_ms`` (device side, default 20): with no SYNC for this long the drive
  starts its cycle on its own clock, every ``sync_timeout_ms``, until SYNC returns.
* ``heartbeat_consumer`` (device side): 1016h:01 at start, the master's node-ID and its
  heartbeat time in ms (e.g. ``127:100``); default none (a master can set it by SDO).
* ``heartbeat`` (controller side): produce a heartbeat as node ID every MS ms (``127:50``).
* ``port`` (udp_multicast only; python-can's default 43113): the UDP port.
* ``multicast_if`` (udp_multicast only): the interface address the bus joins the group on
  and sends from, default ``127.0.0.1`` (IPv4 groups) or ``::1`` (IPv6)
  (:mod:`io_adapters.can_loopback`); ``any``: every interface, any sender.
"""

import ipaddress
from dataclasses import dataclass
from pathlib import PurePath
from urllib.parse import urlsplit

from io_adapters.base import AdapterConfigError, Role, parse_options, positive_int
from io_adapters.can_bus_time import BIT_RATES

INTERFACES = ("socketcan", "udp_multicast", "virtual")
#: python-can writers a log may use, by suffix
LOG_SUFFIXES = (".asc", ".blf", ".trc", ".log", ".mf4")
DEFAULT_BITRATE = 1_000_000


@dataclass(frozen=True)
class CanLink:
    """A parsed ``can://`` URL (see the module docstring)."""
    url: str
    interface: str
    channel: str
    node: int
    rated_current_ma: int
    axes: int = 1
    rated_torque_mnm: int = 0
    bitrate: int = DEFAULT_BITRATE
    log: str | None = None
    sync_timeout_ms: int = 20
    heartbeat_consumer: tuple[int, int] | None = None
    heartbeat: tuple[int, int] | None = None
    port: int | None = None
    multicast_if: str | None = None

    @property
    def nodes(self) -> tuple[int, ...]:
        """The node-IDs of the axes, in axis order."""
        return tuple(range(self.node, self.node + self.axes))


#: why ``hil run`` refuses a link :func:`in_process_only` finds
IN_PROCESS_ONLY = ("python-can's virtual bus joins the buses of one process: no master in "
                   "another process can reach hil run there (use can://udp_multicast/GROUP, "
                   "or socketcan/CHANNEL)")


def in_process_only(url: str) -> bool:
    """``url`` is a ``can://virtual/...`` link: python-can's virtual bus joins the buses
    of one process only, so a peer in another process can never reach it
    (:data:`IN_PROCESS_ONLY` says so)."""
    parts = urlsplit(url)
    return parts.scheme.lower() == "can" and parts.netloc == "virtual"


def _node_id(text: str) -> int:
    value = int(text)
    if not 1 <= value <= 127:
        raise ValueError(f"{value} is not a node-ID (1-127)")
    return value


def _port(text: str) -> int:
    value = int(text)
    if not 1 <= value <= 65535:
        raise ValueError(f"{value} is not a port (1-65535)")
    return value


def _u32(text: str) -> int:
    value = positive_int(text)
    if value > 0xFFFFFFFF:
        raise ValueError(f"{value} does not fit UNSIGNED32")
    return value


def _bitrate(text: str) -> int:
    value = int(text)
    if value not in BIT_RATES:
        raise ValueError(f"{value} bit/s is not a CiA 301 bit rate "
                         f"({', '.join(str(b) for b in BIT_RATES)})")
    return value


def _log_file(text: str) -> str:
    if PurePath(text).suffix.lower() not in LOG_SUFFIXES:
        raise ValueError(f"{text!r}: a CAN log is one of {', '.join(LOG_SUFFIXES)}")
    return text


def _heartbeat(text: str) -> tuple[int, int]:
    node, sep, ms = text.partition(":")
    if not sep:
        raise ValueError(f"{text!r} is not NODE:MS")
    node_id, period = _node_id(node), int(ms)
    if not 1 <= period <= 0xFFFF:
        raise ValueError(f"{period} ms is not a heartbeat time (1-65535 ms)")
    return node_id, period


def _interface_address(text: str) -> str:
    if text == "any":
        return text
    ipaddress.ip_address(text)  # ValueError names it
    return text


OPTIONS = {"node": _node_id, "axes": positive_int, "rated_current_ma": _u32,
           "rated_torque_mnm": _u32, "bitrate": _bitrate, "log": _log_file,
           "sync_timeout_ms": positive_int, "heartbeat_consumer": _heartbeat,
           "heartbeat": _heartbeat, "port": _port, "multicast_if": _interface_address}


def parse_can_url(url: str, role: Role) -> CanLink:
    """The :class:`CanLink` of ``url``; raises :class:`AdapterConfigError` naming the part
    that is wrong."""
    parts = urlsplit(url)
    interface, channel = parts.netloc, parts.path.lstrip("/")
    if parts.scheme.lower() != "can" or not channel or "/" in channel:
        raise AdapterConfigError(f"{url!r}: expected can://INTERFACE/CHANNEL?node=N&"
                                 f"rated_current_ma=I (INTERFACE: {', '.join(INTERFACES)})")
    if interface not in INTERFACES:
        raise AdapterConfigError(f"{url!r}: interface {interface!r} is not one of "
                                 f"{', '.join(INTERFACES)}")
    options = parse_options(url, parts.query, OPTIONS)
    for key in ("node", "rated_current_ma"):
        if key not in options:
            raise AdapterConfigError(f"{url!r}: option {key} is required")
    last = options["node"] + options.get("axes", 1) - 1
    if last > 127:
        raise AdapterConfigError(f"{url!r}: axes={options['axes']} from node={options['node']} "
                                 f"needs node-IDs up to {last}; the last is 127")
    for key in ("port", "multicast_if"):
        if key in options and interface != "udp_multicast":
            raise AdapterConfigError(f"{url!r}: option {key} is for udp_multicast only")
    for key, side in (("sync_timeout_ms", Role.DEVICE), ("heartbeat_consumer", Role.DEVICE),
                      ("heartbeat", Role.CONTROLLER)):
        if key in options and role is not side:
            raise AdapterConfigError(f"{url!r}: option {key} is for the {side.value} side")
    return CanLink(url, interface, channel, **options)
