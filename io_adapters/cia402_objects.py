"""What both sides of the ``can://`` link share: the URL, the emulated drive's CiA 402
object dictionary, its static PDO mapping and the unit conversions.

URL::

    can://INTERFACE/CHANNEL?node=N&rated_current_ma=I[&axes=A][&rated_torque_mnm=T]
                           [&sync_timeout_ms=S][&heartbeat_consumer=ID:MS]
                           [&heartbeat=ID:MS][&port=P][&multicast_if=ADDR]

* INTERFACE/CHANNEL (python-can): ``virtual/NAME`` (any name; one process),
  ``udp_multicast/GROUP`` (an IPv4 or IPv6 multicast group address such as python-can's
  default 239.74.163.2; between processes, every process also receives its own
  frames), ``socketcan/vcan0`` (a SocketCAN interface, where the kernel has one).
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
  stated).  The torque objects carry the same per mille as the current: the wire
  carries currents, and this link takes torque proportional to the q current.
* ``sync_timeout_ms`` (device side, default 20): with no SYNC for this long the drive
  starts its cycle on its own clock, every ``sync_timeout_ms``, until SYNC returns.
* ``heartbeat_consumer`` (device side): 1016h:01 at start, the master's node-ID and its
  heartbeat time in ms (e.g. ``127:100``); a heartbeat that does not come within that
  time, once the first came, is a lost master (the drive reacts as 6007h says).  Default:
  no consumer; a master can set 1016h:01 by SDO.
* ``heartbeat`` (controller side): produce a heartbeat as node ID every MS ms (``127:50``).
* ``port`` (udp_multicast only; python-can's default 43113): the UDP port.
* ``multicast_if`` (udp_multicast only): the interface address the bus joins the group on
  and sends from, default ``127.0.0.1`` (IPv4 groups) or ``::1`` (IPv6): the bus stays on
  the loopback interface and drops every frame whose sender is not a loopback address.
  ``any`` is python-can's own behaviour (every interface, any sender): anyone on the
  network can then send this drive NMT commands and process data.  On the loopback
  interface a peer using python-can's own ``udp_multicast`` bus reaches the drive when the
  group is routed over ``lo`` (``ip route add GROUP/32 dev lo``).

PDO mapping (static: the mapping and communication objects are read-only;
COB-IDs of the predefined connection set, 200h/300h/400h/500h + node-ID for RPDO1-4,
180h/280h/380h + node-ID for TPDO1-3; little-endian, in this order)::

    RPDO1 type 255  6040h controlword U16, 6060h modes of operation I8        3 bytes
    RPDO2 type 1    607Ah target position I32, 60B1h velocity offset I32     8 bytes
    RPDO3 type 1    60FFh target velocity I32                                4 bytes
    RPDO4 type 1    6071h target torque I16, 60B2h torque offset I16         4 bytes
    TPDO1 type 1    6041h statusword U16, 6061h mode display I8,
                    603Fh error code U16                                     5 bytes
    TPDO2 type 1    6064h position actual I32, 606Ch velocity actual I32     8 bytes
    TPDO3 type 1    6078h current actual I16, 6077h torque actual I16,
                    60E4h:01 additional position actual I32                  8 bytes

RPDO1 is asynchronous (255) because a master sends the controlword when it changes
(canopen's ``BaseNode402`` does); the drive still reads every RPDO at the start of its
cycle.  Positions are increments of the motor encoder (position factor 1), speeds
increments/s; 60E4h:01 is the linear scale in its own increments (0 without one).
603Fh is the drive's error code (0: none; the codes are :mod:`hil.drive.faults`'s) and
1001h its error register (:func:`error_register`).  Modes 8 (CSP), 9 (CSV) and 10 (CST)
are supported (6502h = 380h); 0 (no mode, the power-up value) gives no torque.

Drive parameters (:data:`PARAMETER_OBJECTS`: 6007h, 605Ah, 605Eh, 6065h-6068h, 6072h,
607Dh, 6080h, 6084h, 6085h, and the read-only 60F4h following error actual and 60FDh
digital inputs) are the drive's own: the device endpoint reads and writes them through an
:class:`ObjectAccess` the drive gives it (the values, their units and their checks are the
drive's; a refused write is an SDO abort with the code the drive says).  Positions are
increments, speeds increments/s, accelerations increments/s², 6072h per mille of 6075h,
times in ms.  1016h:01 holds the heartbeat consumer, 1017h the heartbeat producer time.
Every SDO access to a sub-index an object does not have is aborted with 0609 0011h.
A third-party master can import this dictionary as an EDS file:
``canopen.export_od(drive_object_dictionary(...), "x.eds")``.
"""

import ipaddress
import math
import struct
from dataclasses import dataclass
from typing import Protocol
from urllib.parse import urlsplit

from canopen import objectdictionary as od_types
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable

from io_adapters.base import AdapterConfigError, Role, parse_options, positive_int

INTERFACES = ("socketcan", "udp_multicast", "virtual")
SYNC_COB_ID = 0x080
NMT_COB_ID = 0x000
HEARTBEAT_BASE = 0x700
NMT_START = 0x01
NMT_BOOT_UP = 0x00
NMT_PRE_OPERATIONAL = 0x7F
NMT_OPERATIONAL = 0x05
DEVICE_TYPE = 0x0002_0192  # CiA 402 (192h), servo drive (02h)
PRODUCT_CODE = 0x0000_0402
REVISION = 0x0001_0000
#: 6502h bits 7, 8, 9: CSP, CSV, CST
SUPPORTED_MODES_BITS = (1 << 7) | (1 << 8) | (1 << 9)
NO_MODE = 0
SDO_ABORT_NO_OBJECT = 0x0602_0000
SDO_ABORT_NO_SUBINDEX = 0x0609_0011
SDO_ABORT_VALUE_RANGE = 0x0609_0030
SDO_ABORT_VALUE_HIGH = 0x0609_0031
SDO_ABORT_VALUE_LOW = 0x0609_0032
SDO_ABORT_MAX_BELOW_MIN = 0x0609_0036
EMCY_BASE = 0x080

U8, I8 = od_types.UNSIGNED8, od_types.INTEGER8
U16, I16 = od_types.UNSIGNED16, od_types.INTEGER16
U32, I32 = od_types.UNSIGNED32, od_types.INTEGER32
INT_RANGE = {I16: (-2**15, 2**15 - 1), I32: (-2**31, 2**31 - 1)}

#: (index, subindex) -> (name, data type, access) of every process-data object
PROCESS_OBJECTS = {
    (0x603F, 0): ("Error code", U16, "ro"),
    (0x6040, 0): ("Controlword", U16, "rw"),
    (0x6041, 0): ("Statusword", U16, "ro"),
    (0x6060, 0): ("Modes of operation", I8, "rw"),
    (0x6061, 0): ("Modes of operation display", I8, "ro"),
    (0x6064, 0): ("Position actual value", I32, "ro"),
    (0x606C, 0): ("Velocity actual value", I32, "ro"),
    (0x6071, 0): ("Target torque", I16, "rw"),
    (0x6077, 0): ("Torque actual value", I16, "ro"),
    (0x6078, 0): ("Current actual value", I16, "ro"),
    (0x607A, 0): ("Target position", I32, "rw"),
    (0x60B1, 0): ("Velocity offset", I32, "rw"),
    (0x60B2, 0): ("Torque offset", I16, "rw"),
    (0x60E4, 1): ("Additional position actual value 1", I32, "ro"),
    (0x60FF, 0): ("Target velocity", I32, "rw"),
}
#: (index, subindex) -> (name, data type, access, default) of the drive's parameter objects
#: (defaults: CiA 402's; the drive answers with its own values through ObjectAccess)
PARAMETER_OBJECTS = {
    (0x6007, 0): ("Abort connection option code", I16, "rw", 1),
    (0x605A, 0): ("Quick stop option code", I16, "rw", 2),
    (0x605E, 0): ("Fault reaction option code", I16, "rw", 2),
    (0x6065, 0): ("Following error window", U32, "rw", 0xFFFFFFFF),
    (0x6066, 0): ("Following error time out", U16, "rw", 0),
    (0x6067, 0): ("Position window", U32, "rw", 0),
    (0x6068, 0): ("Position window time", U16, "rw", 0),
    (0x6072, 0): ("Max torque", U16, "rw", 1000),
    (0x607D, 1): ("Min position limit", I32, "rw", 0),  # canopen 2.4 exports a negative
    (0x607D, 2): ("Max position limit", I32, "rw", 0),  # default as 0x-80000000: not used
    (0x6080, 0): ("Max motor speed", U32, "rw", 0),
    (0x6084, 0): ("Profile deceleration", U32, "rw", 0),
    (0x6085, 0): ("Quick stop deceleration", U32, "rw", 0),
    (0x60F4, 0): ("Following error actual value", I32, "ro", 0),
    (0x60FD, 0): ("Digital inputs", U32, "ro", 0),
}
#: 60FDh bits: negative and positive limit switch (CiA 402)
DI_NEGATIVE_LIMIT, DI_POSITIVE_LIMIT = 1 << 0, 1 << 1
HEARTBEAT_CONSUMER = (0x1016, 1)


class ObjectAccessError(Exception):
    """A write the drive refuses; ``abort_code`` is the SDO abort code to answer."""

    def __init__(self, abort_code: int, message: str):
        super().__init__(message)
        self.abort_code = abort_code


class ObjectAccess(Protocol):
    """The drive's side of its parameter objects (:data:`PARAMETER_OBJECTS`), given to the
    device endpoint by the drive's owner.  Called from the bus's receive thread: each call
    reads or sets the drive's values at once, which the drive uses from its next cycle."""

    def read(self, axis: int, index: int, subindex: int) -> int:
        """The object's value for ``axis`` (0-based), in the object's wire unit."""

    def write(self, axis: int, index: int, subindex: int, value: int) -> None:
        """Set the object; raises :class:`ObjectAccessError` to refuse."""

    def reset_application(self, axis: int) -> None:
        """NMT reset node: the objects of ``axis`` back to their power-on values."""


def error_register(code: int) -> int:
    """1001h for the error code 603Fh ``code`` (CiA 301): 0 without an error, else the
    generic bit and the bit of the code's class (current 2xxxh, voltage 3xxxh, temperature
    4xxxh, communication 81xxh/82xxh, device profile 84xxh-86xxh, manufacturer FFxxh)."""
    if not code:
        return 0
    group = code >> 8
    if code >> 12 in (2, 3, 4):
        bit = 1 << (code >> 12) - 1
    elif group in (0x81, 0x82):
        bit = 0x10
    elif 0x84 <= group <= 0x86:
        bit = 0x20
    elif group == 0xFF:
        bit = 0x80
    else:
        bit = 0
    return 0x01 | bit


RPDO_MAP = (  # (transmission type, objects) of RPDO1-4
    (255, ((0x6040, 0), (0x6060, 0))),
    (1, ((0x607A, 0), (0x60B1, 0))),
    (1, ((0x60FF, 0),)),
    (1, ((0x6071, 0), (0x60B2, 0))),
)
TPDO_MAP = (  # TPDO1-3
    (1, ((0x6041, 0), (0x6061, 0), (0x603F, 0))),
    (1, ((0x6064, 0), (0x606C, 0))),
    (1, ((0x6078, 0), (0x6077, 0), (0x60E4, 1))),
)
RPDO_COB_BASE, TPDO_COB_BASE = 0x200, 0x180


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
    sync_timeout_ms: int = 20
    heartbeat_consumer: tuple[int, int] | None = None
    heartbeat: tuple[int, int] | None = None
    port: int | None = None
    multicast_if: str | None = None

    @property
    def nodes(self) -> tuple[int, ...]:
        """The node-IDs of the axes, in axis order."""
        return tuple(range(self.node, self.node + self.axes))


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
           "rated_torque_mnm": _u32, "sync_timeout_ms": positive_int,
           "heartbeat_consumer": _heartbeat, "heartbeat": _heartbeat, "port": _port,
           "multicast_if": _interface_address}


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


# -- object dictionary ------------------------------------------------------------------

def _var(name: str, index: int, data_type: int, access: str, default: int | None = None,
         subindex: int = 0) -> ODVariable:
    var = ODVariable(name, index, subindex)
    var.data_type = data_type
    var.access_type = access
    var.default = default
    return var


def _record(od: ObjectDictionary, name: str, index: int, members,
            count_name: str = "Highest sub-index supported") -> None:
    """A read-only record: sub-index 0 counts the members, then ``(name, type, value)``."""
    rec = ODRecord(name, index)
    rec.add_member(_var(count_name, index, U8, "ro", len(members)))
    for sub, (member, data_type, value) in enumerate(members, start=1):
        rec.add_member(_var(member, index, data_type, "ro", value, sub))
    od.add_object(rec)


def _pdo_objects(od: ObjectDictionary, kind: str, cob_base: int, comm_base: int,
                 map_base: int, table, node: int) -> None:
    for n, (trans_type, objects) in enumerate(table):
        _record(od, f"{kind}{n + 1} communication parameter", comm_base + n,
                [(f"COB-ID used by {kind}", U32, cob_base + 0x100 * n + node),
                 ("Transmission type", U8, trans_type)])
        _record(od, f"{kind}{n + 1} mapping parameter", map_base + n,
                [(f"Mapped object {k + 1}", U32,
                  index << 16 | sub << 8 | len(_process_var(index, sub)))
                 for k, (index, sub) in enumerate(objects)],
                count_name="Number of mapped objects")


def _process_var(index: int, subindex: int) -> ODVariable:
    name, data_type, access = PROCESS_OBJECTS[index, subindex]
    var = _var(name, index, data_type, access, 0, subindex)
    var.pdo_mappable = True
    return var


def _heartbeat_entry(consumer: tuple[int, int] | None) -> int:
    """1016h:01 of a consumer (node-ID in bits 16-23, time in ms in bits 0-15)."""
    return 0 if consumer is None else consumer[0] << 16 | consumer[1]


def drive_object_dictionary(node: int, rated_current_ma: int, rated_torque_mnm: int = 0,
                            heartbeat_consumer: tuple[int, int] | None = None
                            ) -> ObjectDictionary:
    """The emulated drive's object dictionary (CiA 301 communication objects, the CiA 402
    objects of the module docstring, the static PDO mapping for ``node``)."""
    od = ObjectDictionary()
    od.node_id = node
    od.add_object(_var("Device type", 0x1000, U32, "ro", DEVICE_TYPE))
    od.add_object(_var("Error register", 0x1001, U8, "ro", 0))
    od.add_object(_var("COB-ID SYNC", 0x1005, U32, "ro", SYNC_COB_ID))
    od.add_object(_var("COB-ID EMCY", 0x1014, U32, "ro", EMCY_BASE + node))
    consumers = ODArray("Consumer heartbeat time", 0x1016)
    consumers.add_member(_var("Highest sub-index supported", 0x1016, U8, "const", 1))
    consumers.add_member(_var("Consumer heartbeat time 1", 0x1016, U32, "rw",
                              _heartbeat_entry(heartbeat_consumer), 1))
    od.add_object(consumers)
    od.add_object(_var("Producer heartbeat time", 0x1017, U16, "rw", 0))
    _record(od, "Identity object", 0x1018, [
        ("Vendor-ID", U32, 0), ("Product code", U32, PRODUCT_CODE),
        ("Revision number", U32, REVISION), ("Serial number", U32, 0)])
    _pdo_objects(od, "RPDO", RPDO_COB_BASE, 0x1400, 0x1600, RPDO_MAP, node)
    _pdo_objects(od, "TPDO", TPDO_COB_BASE, 0x1800, 0x1A00, TPDO_MAP, node)
    for (index, sub) in PROCESS_OBJECTS:
        if sub == 0:
            od.add_object(_process_var(index, sub))
    extra = ODArray("Additional position actual value", 0x60E4)
    extra.add_member(_var("Highest sub-index supported", 0x60E4, U8, "const", 1))
    extra.add_member(_process_var(0x60E4, 1))
    od.add_object(extra)
    limits = ODArray("Software position limit", 0x607D)
    limits.add_member(_var("Highest sub-index supported", 0x607D, U8, "const", 2))
    for (index, sub), (name, data_type, access, default) in PARAMETER_OBJECTS.items():
        var = _var(name, index, data_type, access, default, sub)
        if index == 0x607D:
            limits.add_member(var)
        else:
            od.add_object(var)
    od.add_object(limits)
    od.add_object(_var("Motor rated current", 0x6075, U32, "ro", rated_current_ma))
    od.add_object(_var("Motor rated torque", 0x6076, U32, "ro", rated_torque_mnm))
    od.add_object(_var("Supported drive modes", 0x6502, U32, "ro", SUPPORTED_MODES_BITS))
    return od


# -- PDO layouts and units --------------------------------------------------------------

@dataclass(frozen=True)
class PdoLayout:
    """One PDO as both sides pack it.

    Attributes:
        name: "RPDO1" ... "TPDO3".
        cob_id: its CAN identifier for the node.
        objects: the mapped (index, subindex) pairs, in frame order.
        frame: the little-endian ``struct`` of the whole frame; ``frame.size`` is the DLC.
    """
    name: str
    cob_id: int
    objects: tuple[tuple[int, int], ...]
    frame: struct.Struct


def _layouts(kind: str, cob_base: int, table, node: int) -> tuple[PdoLayout, ...]:
    layouts = []
    for n, (_, objects) in enumerate(table):
        codes = "".join(ODVariable.STRUCT_TYPES[PROCESS_OBJECTS[o][1]].format[-1]
                        for o in objects)
        layouts.append(PdoLayout(f"{kind}{n + 1}", cob_base + 0x100 * n + node, objects,
                                 struct.Struct("<" + codes)))
    return tuple(layouts)


def rpdo_layouts(node: int) -> tuple[PdoLayout, ...]:
    """RPDO1-4 of ``node`` (the frames the master sends)."""
    return _layouts("RPDO", RPDO_COB_BASE, RPDO_MAP, node)


def tpdo_layouts(node: int) -> tuple[PdoLayout, ...]:
    """TPDO1-3 of ``node`` (the frames the drive sends)."""
    return _layouts("TPDO", TPDO_COB_BASE, TPDO_MAP, node)


def amps(permille: int, rated_current_ma: int) -> float:
    """A per-mille current on the wire in A (exact integers, one rounding)."""
    return permille * rated_current_ma / 1e6


def permille(current_a: float, rated_current_ma: int) -> float:
    """A current in A as per mille of the rated current, unrounded."""
    return current_a * 1e6 / rated_current_ma


def saturate(value: float, data_type: int) -> int:
    """``value`` rounded into a signed wire type; non-finite values (a faulted plant)
    become 0.  What the drive does with a value it cannot report."""
    if not math.isfinite(value):
        return 0
    lo, hi = INT_RANGE[data_type]
    return min(max(round(value), lo), hi)


def wrap_i32(value: float) -> int:
    """A position rounded and wrapped into INTEGER32, as an encoder counter overflows;
    non-finite values become 0."""
    if not math.isfinite(value):
        return 0
    return (round(value) + 2**31) % 2**32 - 2**31
