"""One CiA 402 node of the ``can://`` device endpoint (:mod:`io_adapters.can_cia402`):
its :class:`canopen.LocalNode`, PDO frames, process image, SDO checks and network
management.  The endpoint owns the lock, the bus, the drive's parameter objects and the
setpoint bounds; a node reaches them through its ``owner``."""

import math
import time

import can
import canopen
from canopen.sdo import SdoAbortedError

from io_adapters.cia402_objects import (
    HEARTBEAT_BASE,
    HEARTBEAT_CONSUMER,
    I16,
    I32,
    NO_MODE,
    PARAMETER_OBJECTS,
    SDO_ABORT_NO_SUBINDEX,
    SDO_ABORT_VALUE_HIGH,
    SDO_ABORT_VALUE_LOW,
    SDO_ABORT_VALUE_RANGE,
    CanLink,
    ObjectAccessError,
    amps,
    drive_object_dictionary,
    error_register,
    permille,
    rpdo_layouts,
    saturate,
    tpdo_layouts,
    wrap_i32,
)
from io_adapters.messages import (
    MODE_CSP,
    MODE_CST,
    MODE_CSV,
    REFUSED_MODE,
    Feedback,
    Setpoint,
    SetpointBounds,
)

SW_ECHO = 1 << 8
ECHO_SHIFT = 14
SW_ECHO_MASK = SW_ECHO | 3 << ECHO_SHIFT
#: objects written by the master, in the order :meth:`DriveNode.fill` reads them
INPUTS = ((0x6040, 0), (0x6060, 0), (0x607A, 0), (0x60B1, 0), (0x60FF, 0), (0x6071, 0),
          (0x60B2, 0))
ERROR_CODE = (0x603F, 0)
ERROR_REGISTER = (0x1001, 0)
#: modes a CiA 402 node on this wire can run (the drive's own bounds narrow them)
CAN_MODES = frozenset((MODE_CSP, MODE_CSV, MODE_CST))

class DriveNode:
    """One CiA 402 node of the endpoint (one axis): its :class:`canopen.LocalNode`, PDO
    frames, process image and network management.  Its state is guarded by the
    endpoint's ``lock``; the endpoint's ``objects`` and ``setpoint_bounds`` are read
    through ``owner``."""

    def __init__(self, axis: int, node_id: int, link: CanLink, owner):
        self.axis = axis
        self.owner = owner
        self.lock = owner._lock
        self.rated_ma = link.rated_current_ma
        self.rpdos = {p.cob_id: p for p in rpdo_layouts(node_id)}
        self.tpdos = tpdo_layouts(node_id)
        self.tpdo_msgs = tuple(can.Message(arbitration_id=p.cob_id, is_extended_id=False,
                                           data=bytearray(p.frame.size)) for p in self.tpdos)
        self.staged = tuple(bytearray(p.frame.size) for p in self.tpdos)
        self.image = {obj: 0 for p in (*self.rpdos.values(), *self.tpdos) for obj in p.objects}
        self.image[ERROR_REGISTER] = 0
        self.latched = (0,) * len(INPUTS)
        self.mode = NO_MODE
        self.refused = False      # a refusal not yet reported to the loop
        self.emcy_code = 0        # the error code the last EMCY announced
        self.reset_event = False  # an NMT reset not yet reported to the loop
        self.heartbeat_start = link.heartbeat_consumer
        #: the consumed heartbeat: (node-ID, consumer time s, monotonic time of the last
        #: one, NaN before the first), or None
        self.watch: tuple[int, float, float] | None = None
        self.local = canopen.LocalNode(node_id, drive_object_dictionary(
            node_id, link.rated_current_ma, link.rated_torque_mnm, link.heartbeat_consumer))
        self.local.add_read_callback(self.on_sdo_read)
        self.local.add_write_callback(self.on_sdo_write)

    # -- the loop's side (lock held) -------------------------------------------------------
    def fill(self, into: Setpoint, seq: int) -> None:
        """The latched objects as a setpoint (the lock is held)."""
        controlword, mode, position, velocity_offset, velocity, torque, torque_offset = \
            self.latched
        self.mode = mode
        into.seq = seq
        into.controlword = controlword
        into.target_position_counts = float(position)
        into.velocity_offset_counts_s = float(velocity_offset)
        into.target_velocity_counts_s = float(velocity)
        if mode == NO_MODE:
            into.mode, into.iq_ref_a = MODE_CST, 0.0
        else:
            into.mode = mode
            # the bound itself for a current beyond it by the wire's rounding (refusal())
            limit = self.bounds().current_a
            into.iq_ref_a = min(max(self._amps(mode, torque, torque_offset), -limit), limit)
        into.id_ref_a = into.ud_v = into.uq_v = 0.0
        into.t_ns = 0

    def _amps(self, mode: int, torque: int, torque_offset: int) -> float:
        return amps((torque if mode == MODE_CST else 0) + torque_offset, self.rated_ma)

    def stage(self, fb: Feedback) -> None:
        """Pack ``fb`` into the TPDO frames and the image (the lock is held)."""
        current = saturate(permille(fb.iq_a, self.rated_ma), I16)
        values = ((fb.statusword, self.mode, fb.fault),
                  (wrap_i32(fb.encoder_counts), saturate(fb.velocity_counts_s, I32)),
                  (current, current, wrap_i32(fb.scale_counts)))
        for layout, staged, vals in zip(self.tpdos, self.staged, values):
            layout.frame.pack_into(staged, 0, *vals)
            self.image.update(zip(layout.objects, vals))
        self.image[ERROR_REGISTER] = error_register(fb.fault)

    # -- the bus's side --------------------------------------------------------------------
    def send_tpdos(self, bus: can.BusABC, counter: int | None) -> int:
        """Send the staged TPDO1-3, TPDO1 with the SYNC echo when ``counter`` is given;
        how many the bus could not take (dropped)."""
        for msg, staged in zip(self.tpdo_msgs, self.staged):
            msg.data[:] = staged
        tpdo1 = self.tpdo_msgs[0].data  # statusword little-endian: bits 8-15
        tpdo1[1] &= ~SW_ECHO_MASK >> 8 & 0xFF
        if counter is not None:
            tpdo1[1] |= (SW_ECHO | (counter & 3) << ECHO_SHIFT) >> 8
        dropped = 0
        for msg in self.tpdo_msgs:
            try:
                bus.send(msg)
            except can.CanError:
                dropped += 1
        return dropped

    def emcy_due(self) -> tuple[int, int] | None:
        """(code, 1001h) of an EMCY to send now, if the error code changed (lock held)."""
        code = self.image[ERROR_CODE]
        if code == self.emcy_code or self.local.nmt.state not in ("PRE-OPERATIONAL",
                                                                 "OPERATIONAL"):
            return None
        self.emcy_code = code
        return code, self.image[ERROR_REGISTER]

    def bounds(self) -> SetpointBounds:
        b = self.owner.setpoint_bounds
        return b[self.axis] if self.axis < len(b) else b[0]

    def refusal(self, values: dict) -> int:
        """Why ``values`` (index -> value, merged over the image) cannot be taken, or 0:
        the axis's :class:`~io_adapters.messages.SetpointBounds` on the setpoint they make
        (no mode, the power-up value, counts as CST), a current beyond its bound by less
        than half a per-mille step (the wire's rounding) taken at the bound."""
        def get(key):
            return values.get(key, self.image[key])

        mode = get((0x6060, 0))
        if mode not in CAN_MODES and mode != NO_MODE:
            return REFUSED_MODE
        torque, offset = get((0x6071, 0)), get((0x60B2, 0))
        current = amps(max(abs(torque), abs(offset), abs(torque + offset)), self.rated_ma)
        bounds = self.bounds()
        if bounds.current_a < current <= bounds.current_a + 0.5e-6 * self.rated_ma:
            current = bounds.current_a
        return bounds.refusal(MODE_CST if mode == NO_MODE else mode, get((0x607A, 0)),
                              get((0x60FF, 0)), get((0x60B1, 0)), current, 0.0, 0.0, 0.0)

    def refuse(self, reason: int, fault: bool = True) -> None:
        """Count a refusal and, for process data (``fault``), keep it for the loop, whose
        drive faults on it (the lock is held)."""
        stats = self.owner.stats
        if reason == REFUSED_MODE:
            stats.refused_mode += 1
        else:
            stats.refused_range += 1
        self.refused = self.refused or fault

    def on_rpdo(self, data: bytearray, layout) -> bool:
        """Take one RPDO into the image; False (malformed) on a wrong DLC."""
        if len(data) != layout.frame.size:
            return False
        update = dict(zip(layout.objects, layout.frame.unpack(data)))
        with self.lock:
            reason = self.refusal(update)
            if reason:
                self.refuse(reason)
            else:
                self.image.update(update)
                self.owner._fresh = True
        return True

    def on_sdo_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """An SDO request, served unless the node is STOPPED (CiA 301: no SDO there)."""
        if self.local.nmt.state != "STOPPED":
            self.local.sdo.on_request(can_id, data, timestamp)

    def on_sdo_read(self, index: int, subindex: int, od) -> int | None:
        if subindex != od.subindex:
            raise SdoAbortedError(SDO_ABORT_NO_SUBINDEX)
        key = (index, subindex)
        objects = self.owner.objects
        if key in PARAMETER_OBJECTS and objects is not None:
            try:
                return objects.read(self.axis, index, subindex)
            except ObjectAccessError as e:
                raise SdoAbortedError(e.abort_code) from e
        with self.lock:
            return self.image.get(key)

    def on_sdo_write(self, index: int, subindex: int, od, data: bytes) -> None:
        if subindex != od.subindex:
            raise SdoAbortedError(SDO_ABORT_NO_SUBINDEX)
        key = (index, subindex)
        value = od.decode_raw(data)
        if key in INPUTS:
            self._write_input(key, value)
        elif key in PARAMETER_OBJECTS and self.owner.objects is not None:
            try:
                self.owner.objects.write(self.axis, index, subindex, value)
            except ObjectAccessError as e:
                raise SdoAbortedError(e.abort_code) from e
        elif key == HEARTBEAT_CONSUMER:
            self.consume_heartbeat(value)

    def _write_input(self, key: tuple[int, int], value: int) -> None:
        with self.lock:
            reason = self.refusal({key: value})
            if reason:  # the abort answers the master; the drive does not fault
                self.refuse(reason, fault=False)
                if reason == REFUSED_MODE:
                    raise SdoAbortedError(SDO_ABORT_VALUE_RANGE)
                raise SdoAbortedError(SDO_ABORT_VALUE_HIGH if value > 0 else SDO_ABORT_VALUE_LOW)
            self.image[key] = value
            self.owner._fresh = True

    # -- network management ----------------------------------------------------------------
    def consume_heartbeat(self, entry: int) -> None:
        """1016h:01 = ``entry``: watch node (bits 16-22)'s heartbeat for (bits 0-15) ms;
        0 in either: no consumer."""
        network = self.owner.network
        watched = self.watch
        if watched is not None:
            network.unsubscribe(HEARTBEAT_BASE + watched[0], self.on_heartbeat)
        node_id, ms = entry >> 16 & 0x7F, entry & 0xFFFF
        # one assignment: the loop's thread never sees a new consumer with an old time
        self.watch = (node_id, ms * 1e-3, math.nan) if node_id and ms else None
        if self.watch is not None:
            network.subscribe(HEARTBEAT_BASE + node_id, self.on_heartbeat)

    def on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        watched = self.watch
        if watched is not None:
            self.watch = (watched[0], watched[1], time.monotonic())

    def heartbeat_lost(self, now_s: float) -> bool:
        """The consumed heartbeat is overdue (monitoring starts with the first one)."""
        watched = self.watch
        return watched is not None and now_s - watched[2] > watched[1]

    def boot(self, application: bool) -> None:
        """NMT reset: the master's process data cleared (controlword 0: disable voltage,
        no mode), communication objects back to their start values (and the drive's
        parameters for a reset node), boot-up message, PRE-OPERATIONAL."""
        objects = self.owner.objects
        if application and objects is not None:
            objects.reset_application(self.axis)
        entry = self.heartbeat_start
        self.consume_heartbeat(0 if entry is None else entry[0] << 16 | entry[1])
        self.local.data_store.clear()
        with self.lock:  # the master's process data is gone: controlword 0, no mode
            self.image.update(dict.fromkeys(INPUTS, 0))
            self.latched = (0,) * len(INPUTS)
        nmt = self.local.nmt
        nmt.stop_heartbeat()
        nmt.state = "RESET"             # boot-up message
        nmt.state = "PRE-OPERATIONAL"   # heartbeat producer from 1017h (0: none)
