"""The emulated drive's CANopen objects, each with its type, access, limits and default:
the catalog both sides of ``can://`` and the EDS (:mod:`hil.eds`) are made from, and the
network's constants (COB-IDs, NMT commands and states, SDO abort codes).

:data:`VARIABLES` are the simple objects, :data:`COMPOUNDS` the records and arrays
(:func:`spec` finds either, sub-index 0 of a compound included; :func:`entries` lists
them all).  A :class:`Spec`'s ``default`` is CiA's, or the drive's power-on value where
the catalog knows it; a node answers its own values (:mod:`io_adapters.can_dictionary`).
:data:`INPUTS` are the master's process data, :data:`FEEDBACK` what the drive answers from
its feedback record, :data:`PARAMETERS` the drive's own objects (through
:class:`io_adapters.cia402_objects.ObjectAccess`).
"""

from dataclasses import dataclass

SYNC_COB_ID = 0x080
NMT_COB_ID = 0x000
EMCY_BASE = 0x080
HEARTBEAT_BASE = 0x700
NMT_START = 0x01
NMT_STOP = 0x02
NMT_PRE_OPERATIONAL_CMD = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82
NMT_BOOT_UP = 0x00
NMT_PRE_OPERATIONAL = 0x7F
NMT_OPERATIONAL = 0x05
DEVICE_TYPE = 0x0002_0192  # CiA 402 (192h), servo drive (02h)
#: 'HIL': not a vendor-ID CiA assigned (this emulator has none), but not the empty 0
VENDOR_ID = 0x0048_494C
PRODUCT_CODE = 0x0000_0402
REVISION = 0x0002_0000
VENDOR_NAME = "feeddrive-hil (emulator)"
PRODUCT_NAME = "Emulated CiA 402 feed drive"
#: modes of operation (6060h) beyond io_adapters.messages' cyclic ones
MODE_PP, MODE_PV, MODE_HM = 1, 3, 6
NO_MODE = 0
#: 6502h bit of each mode
MODE_BITS = {MODE_PP: 1 << 0, MODE_PV: 1 << 2, MODE_HM: 1 << 5, 8: 1 << 7, 9: 1 << 8,
             10: 1 << 9}

SDO_ABORT_COMMAND = 0x0504_0001
SDO_ABORT_NOT_WRITABLE = 0x0601_0002
SDO_ABORT_NO_OBJECT = 0x0602_0000
SDO_ABORT_NOT_MAPPABLE = 0x0604_0041
SDO_ABORT_PDO_LENGTH = 0x0604_0042
SDO_ABORT_INCOMPATIBLE = 0x0604_0043
SDO_ABORT_LENGTH_HIGH = 0x0607_0012
SDO_ABORT_NO_SUBINDEX = 0x0609_0011
SDO_ABORT_VALUE_RANGE = 0x0609_0030
SDO_ABORT_VALUE_HIGH = 0x0609_0031
SDO_ABORT_VALUE_LOW = 0x0609_0032
SDO_ABORT_MAX_BELOW_MIN = 0x0609_0036
SDO_ABORT_DEVICE_STATE = 0x0800_0022

#: CiA 301's data type codes (the object dictionary's 0002h-0007h, as canopen numbers
#: them), written out so that the drive's objects load without canopen and python-can
#: (and asammdf behind them): 0.65 s of every ``hil run`` start on another link
I8, I16, I32, U8, U16, U32 = 2, 3, 4, 5, 6, 7
#: each type's little-endian ``struct`` code (CiA 301: 1, 2 or 4 bytes)
STRUCT_CODE = {I8: "b", I16: "h", I32: "l", U8: "B", U16: "H", U32: "L"}
INT_RANGE = {U8: (0, 0xFF), I8: (-0x80, 0x7F), U16: (0, 0xFFFF), I16: (-2**15, 2**15 - 1),
             U32: (0, 0xFFFF_FFFF), I32: (-2**31, 2**31 - 1)}
BITS = {U8: 8, I8: 8, U16: 16, I16: 16, U32: 32, I32: 32}
#: the scaled units of the factor group
POSITION, VELOCITY, ACCELERATION = "position", "velocity", "acceleration"


@dataclass(frozen=True)
class Spec:
    """One object (or sub-index) of the dictionary.

    Attributes:
        name: CiA's name.
        data_type: a canopen data type (U8 ... I32).
        access: "ro", "rw" or "const".
        default: CiA's default, or the drive's power-on value where the catalog knows it
            (the node answers its own values, :mod:`io_adapters.can_dictionary`).
        low, high: the limits a write is checked against (inclusive); None: the type's
            range (or the drive's own bound, which the node supplies).
        pdo: mappable into a PDO (an RPDO if writable, a TPDO if readable).
        unit: POSITION, VELOCITY, ACCELERATION (scaled by the factor group) or "".
    """
    name: str
    data_type: int
    access: str = "ro"
    default: int = 0
    low: int | None = None
    high: int | None = None
    pdo: bool = False
    unit: str = ""

    @property
    def writable(self) -> bool:
        return self.access == "rw"


def _rw(name: str, data_type: int, default: int = 0, low: int | None = None,
        high: int | None = None, pdo: bool = False, unit: str = "") -> Spec:
    return Spec(name, data_type, "rw", default, low, high, pdo, unit)


def _pdo_in(name: str, data_type: int, unit: str = "") -> Spec:
    return Spec(name, data_type, "rw", 0, pdo=True, unit=unit)


def _pdo_out(name: str, data_type: int, unit: str = "") -> Spec:
    return Spec(name, data_type, "ro", 0, pdo=True, unit=unit)


#: simple objects: index -> Spec
VARIABLES = {
    0x1000: Spec("Device type", U32, default=DEVICE_TYPE),
    0x1001: Spec("Error register", U8),
    0x1005: Spec("COB-ID SYNC", U32, default=SYNC_COB_ID),
    0x1006: _rw("Communication cycle period", U32, 1000, 250, 10_000),
    0x1014: Spec("COB-ID EMCY", U32, default=EMCY_BASE),
    0x1017: _rw("Producer heartbeat time", U16),
    0x603F: _pdo_out("Error code", U16),
    0x6040: _pdo_in("Controlword", U16),
    0x6041: _pdo_out("Statusword", U16),
    0x6007: _rw("Abort connection option code", I16, 1, 0, 3),
    0x605A: _rw("Quick stop option code", I16, 2, 1, 8),
    0x605E: _rw("Fault reaction option code", I16, 2, 0, 4),
    0x6060: _pdo_in("Modes of operation", I8),
    0x6061: _pdo_out("Modes of operation display", I8),
    0x6062: _pdo_out("Position demand value", I32, POSITION),
    0x6064: _pdo_out("Position actual value", I32, POSITION),
    0x6065: _rw("Following error window", U32, 0xFFFF_FFFF, unit=POSITION),
    0x6066: _rw("Following error time out", U16),
    0x6067: _rw("Position window", U32, unit=POSITION),
    0x6068: _rw("Position window time", U16),
    0x606C: _pdo_out("Velocity actual value", I32, VELOCITY),
    0x6071: _pdo_in("Target torque", I16),
    0x6072: _rw("Max torque", U16, 1000, 1),
    0x6075: Spec("Motor rated current", U32),
    0x6076: Spec("Motor rated torque", U32),
    0x6077: _pdo_out("Torque actual value", I16),
    0x6078: _pdo_out("Current actual value", I16),
    0x607A: _pdo_in("Target position", I32, POSITION),
    0x607C: _rw("Home offset", I32, unit=POSITION),
    0x6080: _rw("Max motor speed", U32, unit=VELOCITY),
    0x6081: _rw("Profile velocity", U32, pdo=True, unit=VELOCITY),
    0x6083: _rw("Profile acceleration", U32, 1, 1, pdo=True, unit=ACCELERATION),
    0x6084: _rw("Profile deceleration", U32, 1, 1, pdo=True, unit=ACCELERATION),
    0x6085: _rw("Quick stop deceleration", U32, 1, 1, unit=ACCELERATION),
    0x6098: _rw("Homing method", I8, 0, 0, 37),
    0x609A: _rw("Homing acceleration", U32, 1, 1, unit=ACCELERATION),
    0x60B1: _pdo_in("Velocity offset", I32, VELOCITY),
    0x60B2: _pdo_in("Torque offset", I16),
    0x60F4: _pdo_out("Following error actual value", I32, POSITION),
    0x60FD: _pdo_out("Digital inputs", U32),
    0x60FF: _pdo_in("Target velocity", I32, VELOCITY),
    0x6502: Spec("Supported drive modes", U32),
}


@dataclass(frozen=True)
class Compound:
    """A record or array: sub-index 0 (its highest sub-index, ``const`` unless
    ``count_writable``) and ``members``."""
    name: str
    record: bool
    members: dict
    count_name: str = "Highest sub-index supported"
    count_writable: bool = False


def _pdo_comm(kind: str, n: int, tpdo: bool) -> Compound:
    members = {1: _rw(f"COB-ID used by {kind}", U32), 2: _rw("Transmission type", U8)}
    if tpdo:
        members |= {3: _rw("Inhibit time", U16), 5: _rw("Event timer", U16)}
    return Compound(f"{kind}{n} communication parameter", True, members)


def _pdo_map(kind: str, n: int) -> Compound:
    return Compound(f"{kind}{n} mapping parameter", True,
                    {k: _rw(f"Mapped object {k}", U32) for k in range(1, 9)},
                    "Number of mapped objects", True)


#: records and arrays: index -> Compound
COMPOUNDS = {
    0x1016: Compound("Consumer heartbeat time", False, {1: _rw("Consumer heartbeat time 1",
                                                               U32)}),
    0x1018: Compound("Identity object", True, {
        1: Spec("Vendor-ID", U32, default=VENDOR_ID),
        2: Spec("Product code", U32, default=PRODUCT_CODE),
        3: Spec("Revision number", U32, default=REVISION), 4: Spec("Serial number", U32)}),
    **{0x1400 + n: _pdo_comm("RPDO", n + 1, False) for n in range(4)},
    **{0x1600 + n: _pdo_map("RPDO", n + 1) for n in range(4)},
    **{0x1800 + n: _pdo_comm("TPDO", n + 1, True) for n in range(4)},
    **{0x1A00 + n: _pdo_map("TPDO", n + 1) for n in range(4)},
    0x607D: Compound("Software position limit", False, {
        1: _rw("Min position limit", I32, -2**31, unit=POSITION),
        2: _rw("Max position limit", I32, 2**31 - 1, unit=POSITION)}),
    0x608F: Compound("Position encoder resolution", False, {
        1: Spec("Encoder increments", U32, default=1), 2: Spec("Motor revolutions", U32,
                                                                 default=1)}),
    0x6091: Compound("Gear ratio", False, {1: _rw("Motor revolutions", U32, 1, 1),
                                           2: _rw("Shaft revolutions", U32, 1, 1)}),
    0x6092: Compound("Feed constant", False, {1: _rw("Feed", U32, 1, 1),
                                              2: _rw("Shaft revolutions", U32, 1, 1)}),
    0x6099: Compound("Homing speeds", False, {
        1: _rw("Speed during search for switch", U32, 1, 1, unit=VELOCITY),
        2: _rw("Speed during search for zero", U32, 1, 1, unit=VELOCITY)}),
    0x60C2: Compound("Interpolation time period", True, {
        1: _rw("Interpolation time period value", U8, 1),
        2: _rw("Interpolation time index", I8, -3, -6, -1)}),
    0x60E4: Compound("Additional position actual value", False, {
        1: _pdo_out("Additional position actual value 1", I32)}),
}


#: fault injection, a manufacturer-specific object of the test bench (no real drive has it):
#: sub-indices 1 to :data:`N_INJECTABLE` hold the level of each fault the emulator offers
#: (``hil.inject``'s order, each in its own integer unit), :data:`INJECT_RAMP_SUB` the ramp
#: time in ms that the next level writes take
FAULT_INJECTION = 0x2F00
N_INJECTABLE = 9
INJECT_RAMP_SUB = N_INJECTABLE + 1
COMPOUNDS[FAULT_INJECTION] = Compound("Fault injection", True, {
    **{k: _rw(f"Fault {k} level", I32) for k in range(1, N_INJECTABLE + 1)},
    INJECT_RAMP_SUB: _rw("Fault injection ramp time", U32)})


def spec(index: int, subindex: int) -> Spec | None:
    """The :class:`Spec` of an object or sub-index (sub-index 0 of a compound included),
    None when the dictionary has none."""
    if index in VARIABLES:
        return VARIABLES[index] if subindex == 0 else None
    comp = COMPOUNDS.get(index)
    if comp is None:
        return None
    if subindex == 0:
        return Spec(comp.count_name, U8, "rw" if comp.count_writable else "const",
                    max(comp.members), 0, 8 if comp.count_writable else None)
    return comp.members.get(subindex)


def entries() -> list[tuple[int, int]]:
    """Every (index, sub-index) of the dictionary, in index order."""
    keys = [(i, 0) for i in VARIABLES]
    for index, comp in COMPOUNDS.items():
        keys += [(index, 0)] + [(index, s) for s in comp.members]
    return sorted(keys)


#: the master's process data: latched by the drive at the start of each cycle
INPUTS = ((0x6040, 0), (0x6060, 0), (0x607A, 0), (0x60B1, 0), (0x60FF, 0), (0x6071, 0),
          (0x60B2, 0))
#: the objects the drive answers from its feedback record
FEEDBACK = ((0x6041, 0), (0x6061, 0), (0x603F, 0), (0x1001, 0), (0x6064, 0), (0x606C, 0),
            (0x6077, 0), (0x6078, 0), (0x60E4, 1))
#: the drive's own objects, read and written through :class:`ObjectAccess` (in the
#: drive's units: increments, increments/s, increments/s², ms, per mille, µs)
PARAMETERS = ((0x1006, 0), (0x6007, 0), (0x605A, 0), (0x605E, 0), (0x6062, 0), (0x6065, 0),
              (0x6066, 0), (0x6067, 0), (0x6068, 0), (0x6072, 0), (0x607C, 0), (0x607D, 1),
              (0x607D, 2), (0x6080, 0), (0x6081, 0), (0x6083, 0), (0x6084, 0), (0x6085, 0),
              (0x608F, 1), (0x608F, 2), (0x6098, 0), (0x6099, 1), (0x6099, 2), (0x609A, 0),
              (0x60C2, 1), (0x60C2, 2), (0x60F4, 0), (0x60FD, 0)) + tuple(
    (FAULT_INJECTION, k) for k in range(1, INJECT_RAMP_SUB + 1))
HEARTBEAT_CONSUMER = (0x1016, 1)
PRODUCER_HEARTBEAT = (0x1017, 0)
#: the values that mean "off" and are never scaled
UNSCALED_MARKS = {(0x6065, 0): (0xFFFF_FFFF,), (0x607D, 1): (-2**31,),
                  (0x607D, 2): (2**31 - 1,)}
