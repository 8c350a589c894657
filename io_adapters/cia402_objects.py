"""The emulated drive's CANopen object dictionary, as both sides of ``can://`` know it: the
default PDO mapping, the wire's units, the dictionary as canopen holds it
(:func:`drive_object_dictionary`) and the drive's side of its parameters
(:class:`ObjectAccess`).  Every object with its type, access, limits and default is in
:mod:`io_adapters.can_catalog`; the URL is :mod:`io_adapters.can_url`'s; a node's live
values are :mod:`io_adapters.can_dictionary`'s.

Default PDO mapping (COB-IDs of the predefined connection set, 200h/300h/400h/500h +
node-ID for RPDO1-4, 180h/280h/380h/480h + node-ID for TPDO1-4; little-endian, in this
order; a master may remap them by SDO, :mod:`io_adapters.can_pdo`)::

    RPDO1 type 255  6040h controlword U16, 6060h modes of operation I8        3 bytes
    RPDO2 type 1    607Ah target position I32, 60B1h velocity offset I32     8 bytes
    RPDO3 type 1    60FFh target velocity I32                                4 bytes
    RPDO4 type 1    6071h target torque I16, 60B2h torque offset I16         4 bytes
    TPDO1 type 1    6041h statusword U16, 6061h mode display I8,
                    603Fh error code U16                                     5 bytes
    TPDO2 type 1    6064h position actual I32, 606Ch velocity actual I32     8 bytes
    TPDO3 type 1    6078h current actual I16, 6077h torque actual I16,
                    60E4h:01 additional position actual I32                  8 bytes
    TPDO4           not valid, nothing mapped

Units on the wire: positions in the position unit of the factor group (608Fh, 6091h,
6092h; motor-encoder increments by default), speeds in position units per second,
accelerations in position units per second squared (the catalog's ``unit`` names the
scaled objects); 60E4h:01 is the linear scale in its own increments (0 without one);
currents and torques per mille of 6075h; times in ms unless named.  603Fh is the drive's
error code (0: none; the codes are :mod:`hil.drive.faults`'s) and 1001h its error register
(:func:`error_register`).

Modes (6060h): 1 profile position, 3 profile velocity, 6 homing, 8 cyclic synchronous
position, 9 cyclic synchronous velocity, 10 cyclic synchronous torque; 0 (no mode, the
power-up value) gives no torque.  6502h says which the drive of the axis takes.
"""

import math
import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from io_adapters.can_catalog import (
    BITS,
    COMPOUNDS,
    EMCY_BASE,
    HEARTBEAT_CONSUMER,
    INT_RANGE,
    STRUCT_CODE,
    VARIABLES,
    Spec,
    spec,
)

if TYPE_CHECKING:  # canopen (and python-can, asammdf behind it) loads where a dictionary
    # is built, not with the drive's objects: 0.65 s of every emulator start
    from canopen.objectdictionary import ObjectDictionary, ODVariable


class ObjectAccessError(Exception):
    """A write the drive refuses; ``abort_code`` is the SDO abort code to answer."""

    def __init__(self, abort_code: int, message: str):
        super().__init__(message)
        self.abort_code = abort_code


class ObjectAccess(Protocol):
    """The drive's side of its objects (:data:`~io_adapters.can_catalog.PARAMETERS`),
    given to the device endpoint by the drive's owner.  Called from the bus's receive
    thread: each call reads or sets the drive's values at once, which the drive uses from
    its next cycle.  Values are in the drive's wire units before the factor group's
    scaling (increments ...)."""

    def read(self, axis: int, index: int, subindex: int) -> int:
        """The object's value for ``axis`` (0-based)."""

    def write(self, axis: int, index: int, subindex: int, value: float) -> None:
        """Set the object; raises :class:`ObjectAccessError` to refuse."""

    def reset_application(self, axis: int) -> None:
        """NMT reset node: the objects of ``axis`` back to their power-on values."""

    def cycle_s(self, axis: int) -> float:
        """The drive's own cycle (its PWM period), s."""


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


# -- the default PDO mapping -----------------------------------------------------------

RPDO_MAP = (  # (transmission type, objects) of RPDO1-4
    (255, ((0x6040, 0), (0x6060, 0))),
    (1, ((0x607A, 0), (0x60B1, 0))),
    (1, ((0x60FF, 0),)),
    (1, ((0x6071, 0), (0x60B2, 0))),
)
TPDO_MAP = (  # TPDO1-4 (TPDO4 not valid)
    (1, ((0x6041, 0), (0x6061, 0), (0x603F, 0))),
    (1, ((0x6064, 0), (0x606C, 0))),
    (1, ((0x6078, 0), (0x6077, 0), (0x60E4, 1))),
    (1, ()),
)
RPDO_COB_BASE, TPDO_COB_BASE = 0x200, 0x180


@dataclass(frozen=True)
class PdoLayout:
    """One PDO as both sides pack it.

    Attributes:
        name: "RPDO1" ... "TPDO4".
        cob_id: its CAN identifier.
        objects: the mapped (index, subindex) pairs, in frame order.
        frame: the little-endian ``struct`` of the whole frame; ``frame.size`` is the DLC.
    """
    name: str
    cob_id: int
    objects: tuple[tuple[int, int], ...]
    frame: struct.Struct


def layout(name: str, cob_id: int, objects) -> PdoLayout:
    """The :class:`PdoLayout` of ``objects`` (whole objects, in frame order)."""
    codes = "".join(STRUCT_CODE[spec(*o).data_type] for o in objects)
    return PdoLayout(name, cob_id, tuple(objects), struct.Struct("<" + codes))


def _layouts(kind: str, cob_base: int, table, node: int) -> tuple[PdoLayout, ...]:
    return tuple(layout(f"{kind}{n + 1}", cob_base + 0x100 * n + node, objects)
                 for n, (_, objects) in enumerate(table) if objects)


def rpdo_layouts(node: int) -> tuple[PdoLayout, ...]:
    """RPDO1-4 of ``node`` as mapped by default (the frames the master sends)."""
    return _layouts("RPDO", RPDO_COB_BASE, RPDO_MAP, node)


def tpdo_layouts(node: int) -> tuple[PdoLayout, ...]:
    """The valid TPDOs of ``node`` as mapped by default (the frames the drive sends)."""
    return _layouts("TPDO", TPDO_COB_BASE, TPDO_MAP, node)


def mapping_entry(obj: tuple[int, int]) -> int:
    """The 32-bit mapping entry of a whole object: index, sub-index, length in bits."""
    return obj[0] << 16 | obj[1] << 8 | BITS[spec(*obj).data_type]


# -- the dictionary as canopen holds it ----------------------------------------------------

def _var(s: Spec, index: int, subindex: int, default: int) -> "ODVariable":
    from canopen.objectdictionary import ODVariable

    var = ODVariable(s.name, index, subindex)
    var.data_type = s.data_type
    var.access_type = s.access
    var.default = default
    var.pdo_mappable = s.pdo
    var.min, var.max = s.low, s.high
    return var


def drive_object_dictionary(node: int, rated_current_ma: int, rated_torque_mnm: int = 0,
                            heartbeat_consumer: tuple[int, int] | None = None,
                            values=None) -> "ObjectDictionary":
    """The dictionary of ``node`` (every object of :data:`VARIABLES` and
    :data:`COMPOUNDS`), with the default PDO mapping's values, the rated current and
    torque and the heartbeat consumer; ``values(index, subindex)`` (None: the catalog's)
    gives every other default."""
    defaults = {(0x1014, 0): EMCY_BASE + node, (0x6075, 0): rated_current_ma,
                (0x6076, 0): rated_torque_mnm,
                HEARTBEAT_CONSUMER: 0 if heartbeat_consumer is None
                else heartbeat_consumer[0] << 16 | heartbeat_consumer[1]}
    for kind, base, comm, mapping, table in (("RPDO", RPDO_COB_BASE, 0x1400, 0x1600, RPDO_MAP),
                                             ("TPDO", TPDO_COB_BASE, 0x1800, 0x1A00, TPDO_MAP)):
        for n, (trans_type, objects) in enumerate(table):
            valid = 0 if objects else 1 << 31
            defaults[comm + n, 1] = valid | base + 0x100 * n + node
            defaults[comm + n, 2] = trans_type
            defaults[mapping + n, 0] = len(objects)
            defaults.update({(mapping + n, k + 1): mapping_entry(o)
                             for k, o in enumerate(objects)})

    def value(index: int, subindex: int, s: Spec) -> int:
        if values is not None:
            return values(index, subindex)
        return defaults.get((index, subindex), s.default)

    from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord

    od = ObjectDictionary()
    od.node_id = node
    for index, s in VARIABLES.items():
        od.add_object(_var(s, index, 0, value(index, 0, s)))
    for index, comp in COMPOUNDS.items():
        obj = (ODRecord if comp.record else ODArray)(comp.name, index)
        for sub in (0, *comp.members):
            s = spec(index, sub)
            obj.add_member(_var(s, index, sub, value(index, sub, s)))
        od.add_object(obj)
    return od


# -- units ------------------------------------------------------------------------------

def amps(permille: int, rated_current_ma: int) -> float:
    """A per-mille current on the wire in A (exact integers, one rounding)."""
    return permille * rated_current_ma / 1e6


def permille(current_a: float, rated_current_ma: int) -> float:
    """A current in A as per mille of the rated current, unrounded."""
    return current_a * 1e6 / rated_current_ma


def saturate(value: float, data_type: int) -> int:
    """``value`` rounded into an integer wire type; non-finite values (a faulted plant)
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
