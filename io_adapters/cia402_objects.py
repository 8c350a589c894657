"""What both sides of the ``can://`` link share: the URL, the emulated drive's CiA 402
object dictionary, its static PDO mapping and the unit conversions.

URL::

    can://INTERFACE/CHANNEL?node=N&rated_current_ma=I[&axes=A][&rated_torque_mnm=T]
                           [&sync_timeout_ms=S][&port=P]

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
* ``port`` (udp_multicast only; python-can's default 43113): the UDP port.

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
603Fh is 0, or FF00h + the plant's fault status (FF01h: non-finite state, FF02h:
diverged).  Modes 8 (CSP), 9 (CSV) and 10 (CST) are supported (6502h = 380h); 0 (no
mode, the power-up value) gives no torque.  A third-party master can import this
dictionary as an EDS file: ``canopen.export_od(drive_object_dictionary(...), "x.eds")``.
"""

import math
import struct
from dataclasses import dataclass
from urllib.parse import urlsplit

from canopen import objectdictionary as od_types
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable

from io_adapters.base import AdapterConfigError, Role, parse_options, positive_int
from io_adapters.messages import MODE_CSP, MODE_CST, MODE_CSV

INTERFACES = ("socketcan", "udp_multicast", "virtual")
SYNC_COB_ID = 0x080
NMT_COB_ID = 0x000
HEARTBEAT_BASE = 0x700
NMT_START = 0x01
NMT_BOOT_UP = 0x00
NMT_PRE_OPERATIONAL = 0x7F
DEVICE_TYPE = 0x0002_0192  # CiA 402 (192h), servo drive (02h)
PRODUCT_CODE = 0x0000_0402
REVISION = 0x0001_0000
#: 6502h bits 7, 8, 9: CSP, CSV, CST
SUPPORTED_MODES_BITS = (1 << 7) | (1 << 8) | (1 << 9)
NO_MODE = 0
#: 6060h values the drive accepts (a write of any other is refused)
ACCEPTED_MODES = frozenset((NO_MODE, MODE_CSP, MODE_CSV, MODE_CST))
#: 603Fh for a plant fault status s is FAULT_CODE_BASE + s
FAULT_CODE_BASE = 0xFF00
SDO_ABORT_VALUE_RANGE = 0x0609_0030

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
    port: int | None = None

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


OPTIONS = {"node": _node_id, "axes": positive_int, "rated_current_ma": _u32,
           "rated_torque_mnm": _u32,
           "sync_timeout_ms": positive_int, "port": _port}


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
    if "port" in options and interface != "udp_multicast":
        raise AdapterConfigError(f"{url!r}: option port is for udp_multicast only")
    if "sync_timeout_ms" in options and role is not Role.DEVICE:
        raise AdapterConfigError(f"{url!r}: option sync_timeout_ms is for the device side")
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


def drive_object_dictionary(node: int, rated_current_ma: int,
                            rated_torque_mnm: int = 0) -> ObjectDictionary:
    """The emulated drive's object dictionary (CiA 301 communication objects, the CiA 402
    objects of the module docstring, the static PDO mapping for ``node``)."""
    od = ObjectDictionary()
    od.node_id = node
    od.add_object(_var("Device type", 0x1000, U32, "ro", DEVICE_TYPE))
    od.add_object(_var("Error register", 0x1001, U8, "ro", 0))
    od.add_object(_var("COB-ID SYNC", 0x1005, U32, "ro", SYNC_COB_ID))
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
