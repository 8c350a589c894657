"""A node's PDO configuration as CiA 301 has a master change it by SDO.

Each of RPDO1-4 and TPDO1-4 has a communication parameter (14xxh / 18xxh: sub 1 COB-ID,
bit 31 set = not valid; sub 2 transmission type; TPDOs sub 3 inhibit time in 100 µs and
sub 5 event timer in ms) and a mapping parameter (16xxh / 1Axxh: sub 0 the number of
objects mapped, subs 1-8 their entries, index << 16 | sub-index << 8 | length in bits).
The defaults are :mod:`io_adapters.cia402_objects`' mapping.  A master remaps a PDO in
CiA 301's order: make it not valid (COB-ID bit 31), write 0 to the number of objects,
write the entries, write their number, make it valid.  Each write is checked, and
refused with CiA 301's abort code:

=========================================================  ============
write                                                      abort code
=========================================================  ============
any PDO parameter while the node is not PRE-OPERATIONAL     0800 0022h
an entry while the PDO is valid or its number is not 0     0800 0022h
the number of objects while the PDO is valid               0800 0022h
an entry naming no object of the dictionary                0602 0000h
an entry naming an object that cannot be mapped there      0604 0041h
  (not PDO-mappable, the wrong direction, a length other
  than the object's own: no dummy or partial mapping)
the number of objects beyond 8                             0609 0031h
objects of more than 64 bits together                      0604 0042h
a COB-ID with bit 29 (extended frame) or bits 11-28 set,   0609 0030h
  a restricted CAN-ID (CiA 301 Table 7), or another
  CAN-ID while the PDO is valid
a transmission type of 241-253 (RTR-only types are not     0609 0030h
  offered)
the inhibit time while the TPDO is valid                   0609 0030h
=========================================================  ============

Transmission types: RPDOs 0-240 (synchronous) and 254/255 (event-driven) are both taken
at the start of the drive's next cycle (:mod:`io_adapters.can_cia402`); TPDOs 0 go out at
a SYNC when their data changed, 1-240 at every n-th SYNC, 254/255 when their data change
(no sooner than the inhibit time after the last) and when the event timer runs out.
"""

from dataclasses import dataclass, field

from io_adapters.can_bus_time import per_cycle
from io_adapters.can_catalog import (
    BITS,
    SDO_ABORT_DEVICE_STATE,
    SDO_ABORT_NO_OBJECT,
    SDO_ABORT_NOT_MAPPABLE,
    SDO_ABORT_PDO_LENGTH,
    SDO_ABORT_VALUE_HIGH,
    SDO_ABORT_VALUE_RANGE,
    spec,
)
from io_adapters.cia402_objects import (
    RPDO_COB_BASE,
    RPDO_MAP,
    TPDO_COB_BASE,
    TPDO_MAP,
    ObjectAccessError,
    PdoLayout,
    layout,
    mapping_entry,
)

NOT_VALID = 1 << 31
NO_RTR = 1 << 30
EXTENDED = 1 << 29
CAN_ID_MASK = 0x7FF
EVENT_TYPES = (254, 255)
MAX_ENTRIES = 8
#: CiA 301 Table 7: CAN-IDs no PDO may use (NMT, SYNC/EMCY, TIME, SDO, NMT error control)
RESTRICTED_IDS = ((0x000, 0x000), (0x001, 0x07F), (0x101, 0x180), (0x581, 0x5FF),
                  (0x601, 0x67F), (0x6E0, 0x6FF), (0x701, 0x77F), (0x780, 0x7FF))
COMM_BASE = {"RPDO": 0x1400, "TPDO": 0x1800}
MAP_BASE = {"RPDO": 0x1600, "TPDO": 0x1A00}


def _refuse(code: int, message: str) -> ObjectAccessError:
    return ObjectAccessError(code, message)


def restricted(can_id: int) -> bool:
    return any(lo <= can_id <= hi for lo, hi in RESTRICTED_IDS)


@dataclass
class PdoConfig:
    """One PDO's parameters (see the module docstring).

    Attributes:
        kind: "RPDO" or "TPDO".
        number: 1-4.
        cob_id: the CAN-ID (11 bits).
        valid: COB-ID bit 31 clear.
        no_rtr: COB-ID bit 30 (kept as written; no remote frames are answered).
        trans_type: 0-240, 254 or 255.
        inhibit_100us: TPDO inhibit time, 100 µs.
        event_timer_ms: TPDO event timer, ms (0: none).
        entries: the eight mapping entries.
        count: the number of entries in use (sub-index 0).
        layout: the frame of the valid, mapped PDO (None otherwise).
    """
    kind: str
    number: int
    cob_id: int
    valid: bool
    trans_type: int
    entries: list[int] = field(default_factory=lambda: [0] * MAX_ENTRIES)
    count: int = 0
    no_rtr: bool = False
    inhibit_100us: int = 0
    event_timer_ms: int = 0
    layout: PdoLayout | None = None

    @property
    def name(self) -> str:
        return f"{self.kind}{self.number}"

    @property
    def objects(self) -> tuple[tuple[int, int], ...]:
        return tuple((e >> 16, e >> 8 & 0xFF) for e in self.entries[:self.count])

    @property
    def event_driven(self) -> bool:
        return self.trans_type in EVENT_TYPES

    def refresh(self) -> None:
        self.layout = (layout(self.name, self.cob_id, self.objects)
                       if self.valid and self.count else None)

    def frame_bytes(self) -> int:
        return sum(e & 0xFF for e in self.entries[:self.count]) // 8


def default_pdos(node: int) -> tuple[list[PdoConfig], list[PdoConfig]]:
    """RPDO1-4 and TPDO1-4 of ``node`` as mapped by default."""
    def make(kind, base, table):
        pdos = []
        for n, (trans_type, objects) in enumerate(table):
            entries = [mapping_entry(o) for o in objects] + [0] * (MAX_ENTRIES - len(objects))
            pdo = PdoConfig(kind, n + 1, base + 0x100 * n + node, bool(objects), trans_type,
                            entries, len(objects))
            pdo.refresh()
            pdos.append(pdo)
        return pdos
    return make("RPDO", RPDO_COB_BASE, RPDO_MAP), make("TPDO", TPDO_COB_BASE, TPDO_MAP)


class PdoSet:
    """RPDO1-4 and TPDO1-4 of one node: their parameters by SDO, their frames.

    Args:
        node: the node-ID (the predefined connection set's COB-IDs).
    """

    def __init__(self, node: int):
        self.node = node
        self.reset()

    def reset(self) -> None:
        """Back to the default mapping (NMT reset communication)."""
        self.rpdos, self.tpdos = default_pdos(self.node)

    def owner(self, index: int) -> tuple[PdoConfig, bool] | None:
        """(the PDO, whether ``index`` is its mapping parameter) of a PDO object, or None."""
        for kind, pdos in (("RPDO", self.rpdos), ("TPDO", self.tpdos)):
            for base, is_map in ((COMM_BASE[kind], False), (MAP_BASE[kind], True)):
                if base <= index < base + len(pdos):
                    return pdos[index - base], is_map
        return None

    def read(self, index: int, subindex: int) -> int:
        pdo, is_map = self.owner(index)
        if is_map:
            return pdo.count if subindex == 0 else pdo.entries[subindex - 1]
        return {1: (NOT_VALID if not pdo.valid else 0) | (NO_RTR if pdo.no_rtr else 0)
                | pdo.cob_id, 2: pdo.trans_type, 3: pdo.inhibit_100us,
                5: pdo.event_timer_ms}[subindex]

    def write(self, index: int, subindex: int, value: int, pre_operational: bool) -> None:
        """Write a PDO parameter; :class:`ObjectAccessError` with the abort code if the
        write is refused (nothing changed then)."""
        pdo, is_map = self.owner(index)
        if not pre_operational:
            raise _refuse(SDO_ABORT_DEVICE_STATE, f"{index:04X}h: {pdo.name} can be "
                          "configured in PRE-OPERATIONAL only")
        if is_map:
            self._write_mapping(pdo, subindex, value)
        else:
            self._write_comm(pdo, subindex, value)
        pdo.refresh()

    def _write_comm(self, pdo: PdoConfig, subindex: int, value: int) -> None:
        if subindex == 1:
            can_id = value & CAN_ID_MASK
            if value & EXTENDED or value & ~(NOT_VALID | NO_RTR | EXTENDED | CAN_ID_MASK):
                raise _refuse(SDO_ABORT_VALUE_RANGE, f"{pdo.name} COB-ID {value:#010x}: "
                              "11-bit CAN-IDs only")
            valid = not value & NOT_VALID
            if pdo.valid and valid and can_id != pdo.cob_id:
                raise _refuse(SDO_ABORT_VALUE_RANGE, f"{pdo.name} is valid: make it not "
                              "valid (bit 31) before changing its CAN-ID")
            if valid and restricted(can_id):
                raise _refuse(SDO_ABORT_VALUE_RANGE, f"{pdo.name}: CAN-ID {can_id:03X}h is "
                              "restricted (CiA 301 Table 7)")
            pdo.cob_id, pdo.valid, pdo.no_rtr = can_id, valid, bool(value & NO_RTR)
        elif subindex == 2:
            if not (value <= 240 or value in EVENT_TYPES):
                raise _refuse(SDO_ABORT_VALUE_RANGE, f"{pdo.name}: transmission type {value} "
                              "not offered (0-240, 254, 255)")
            pdo.trans_type = value
        elif subindex == 3:
            if pdo.valid:
                raise _refuse(SDO_ABORT_VALUE_RANGE, f"{pdo.name} is valid: its inhibit "
                              "time cannot change")
            pdo.inhibit_100us = value
        else:
            pdo.event_timer_ms = value

    def _write_mapping(self, pdo: PdoConfig, subindex: int, value: int) -> None:
        if pdo.valid:
            raise _refuse(SDO_ABORT_DEVICE_STATE, f"{pdo.name} is valid: make it not valid "
                          "before mapping it")
        if subindex == 0:
            if value > MAX_ENTRIES:
                raise _refuse(SDO_ABORT_VALUE_HIGH, f"{pdo.name}: {value} objects (8 at most)")
            for entry in pdo.entries[:value]:
                self._check_entry(pdo, entry)
            bits = sum(e & 0xFF for e in pdo.entries[:value])
            if bits > 64:
                raise _refuse(SDO_ABORT_PDO_LENGTH, f"{pdo.name}: {bits} bits mapped (64 "
                              "at most)")
            pdo.count = value
            return
        if pdo.count:
            raise _refuse(SDO_ABORT_DEVICE_STATE, f"{pdo.name}: write 0 to "
                          f"{MAP_BASE[pdo.kind] + pdo.number - 1:04X}h:00 before its entries")
        if value:
            self._check_entry(pdo, value)
        pdo.entries[subindex - 1] = value

    @staticmethod
    def _check_entry(pdo: PdoConfig, entry: int) -> None:
        index, sub, bits = entry >> 16, entry >> 8 & 0xFF, entry & 0xFF
        s = spec(index, sub)
        if s is None:
            raise _refuse(SDO_ABORT_NO_OBJECT, f"{pdo.name}: no object {index:04X}h:{sub:02X}")
        direction_ok = s.writable if pdo.kind == "RPDO" else s.access != "wo"
        if not (s.pdo and direction_ok and bits == BITS[s.data_type]):
            raise _refuse(SDO_ABORT_NOT_MAPPABLE, f"{pdo.name}: {index:04X}h:{sub:02X} "
                          f"({bits} bits) cannot be mapped into an {pdo.kind}")

    def frames(self, cycle_s: float, drive_cycle_s: float) -> list[tuple[str, float, int]]:
        """(what, frames per cycle at most, bytes) of every valid PDO: each RPDO and each
        synchronous TPDO once per cycle, an event-driven TPDO as often as its inhibit time
        (or, without one, the drive's cycle) lets it change."""
        out = []
        for pdo in self.rpdos + self.tpdos:
            if not pdo.valid:
                continue
            n = 1.0
            if pdo.kind == "TPDO" and pdo.event_driven:
                n = per_cycle(max(pdo.inhibit_100us * 1e-4, drive_cycle_s), cycle_s)
            out.append((f"{pdo.name} of node {self.node}", n, pdo.frame_bytes()))
        return out
