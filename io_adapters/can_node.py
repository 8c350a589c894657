"""One CiA 402 node of the ``can://`` device endpoint (:mod:`io_adapters.can_cia402`):
its :class:`canopen.LocalNode`, the master's process data and the drive's feedback, the
PDO frames, the SDO checks, the EMCYs and network management.  The node's other objects
are its :class:`~io_adapters.can_dictionary.NodeDictionary`'s, its SDO server
:class:`~io_adapters.can_sdo.NodeSdoServer`.  The endpoint owns the lock, the bus, the
drive's objects and the setpoint bounds; a node reaches them through ``owner``.

**An RPDO of the wrong length** (a DLC other than its mapping's, shorter or longer) is not
processed: it is counted ``malformed`` and dropped, and reported by the EMCY 8210h "PDO
not processed due to length error" (CiA 301; not 8220h "PDO length exceeded", which is
for a longer PDO whose mapped bytes a device takes): 1001h with the generic bit 0 and the
communication bit 4, bytes 3-5 the RPDO's number, the DLC received and the DLC of its
mapping, bytes 6-7 zero.  One EMCY per error: the RPDO's error stands, and 1001h keeps the
two bits, until a frame of the right length comes for it; when no RPDO's error stands any
more, the EMCY "error reset" (0000h, 1001h without them) says so; an NMT reset clears
them.  A wrong frame does not fault the drive: its process data did not come, and the
watchdog judges the missing setpoint as it judges any silence (a cycle with no new
process data is not heard).
"""

import math

import can
import canopen
from canopen.sdo import SdoAbortedError

from io_adapters.can_catalog import (
    HEARTBEAT_BASE,
    HEARTBEAT_CONSUMER,
    I16,
    I32,
    INPUTS,
    MODE_HM,
    MODE_PP,
    MODE_PV,
    NMT_RESET_COMMUNICATION,
    NMT_RESET_NODE,
    NMT_START,
    NO_MODE,
    SDO_ABORT_VALUE_HIGH,
    SDO_ABORT_VALUE_LOW,
    SDO_ABORT_VALUE_RANGE,
)
from io_adapters.can_dictionary import NodeDictionary
from io_adapters.can_pdo import PdoConfig
from io_adapters.can_sdo import SDO_FRAME_BYTES, NodeSdoServer
from io_adapters.can_tpdo import TpdoTimer
from io_adapters.can_url import CanLink
from io_adapters.cia402_objects import (
    ObjectAccessError,
    amps,
    drive_object_dictionary,
    error_register,
    permille,
    saturate,
    wrap_i32,
)
from io_adapters.messages import (
    MODE_CSP,
    MODE_CST,
    REFUSED_MODE,
    REFUSED_RANGE,
    Feedback,
    Setpoint,
    SetpointBounds,
)

SW_ECHO = 1 << 8
ECHO_SHIFT = 14
SW_ECHO_MASK = SW_ECHO | 3 << ECHO_SHIFT
STATUSWORD = (0x6041, 0)
ERROR_CODE = (0x603F, 0)
#: the EMCY of an NMT start whose PDO configuration needs more of the communication cycle
#: than the bus carries (a device-specific code: CiA 301 has one for frames lost, not for
#: a plan that will lose them; the node starts all the same, as NMT commands are
#: unconditional); bytes 3-4 the load needed in per mille, 5-7 the cycle in µs
EMCY_PLAN_OVERLOAD = 0xFF20
#: the EMCY of frames of ours lost with the transmit queue full (CiA 301: CAN overrun,
#: objects lost); bytes 3-4 the frames lost so far (saturating)
EMCY_CAN_OVERRUN = 0x8110
#: the EMCY of an RPDO of the wrong length (CiA 301: PDO not processed due to length
#: error); bytes 3-5 the RPDO's number, the DLC received, the DLC of its mapping
EMCY_PDO_LENGTH = 0x8210
#: the mode whose bounds a profile mode is checked against (it runs the same loops)
CHECKED_AS = {NO_MODE: MODE_CST, MODE_PP: MODE_CSP, MODE_PV: MODE_CSP, MODE_HM: MODE_CSP}


class DriveNode:
    """One CiA 402 node (one axis): see the module docstring.  Its state is guarded by
    the endpoint's ``lock``.

    Attributes:
        dict: the node's other objects (:class:`NodeDictionary`).
        image: the master's process data as written (wire values), by (index, sub).
        latched: the image at the start of the cycle the loop takes next.
        staged: the newest feedback the loop wrote.
        mode: the mode of operation of the last cycle (6061h).
        refused: a refused RPDO not yet reported to the loop.
        reset_event: an NMT reset not yet reported to the loop.
        watch: the consumed heartbeat (node-ID, consumer time s, monotonic time of the
            last one, NaN before the first), or None.
        length_errors: the numbers of the RPDOs whose last frame had the wrong length.
    """

    def __init__(self, axis: int, node_id: int, link: CanLink, owner):
        self.axis = axis
        self.owner = owner
        self.lock = owner._lock
        self.rated_ma = link.rated_current_ma
        self.dict = NodeDictionary(node_id, link, axis, owner)
        self.image = dict.fromkeys(INPUTS, 0)
        self.latched = (0,) * len(INPUTS)
        self.staged = Feedback()
        self.mode = NO_MODE
        self.refused = False
        self.emcy_code = 0
        self.plan_overloaded = False  # the last NMT start's plan did not fit: EMCY standing
        self.overrun = False  # frames were lost: EMCY 8110h standing
        self.lost_seen = 0  # the frames lost by the time the last cycle started
        self.reset_event = False
        self.watch: tuple[int, float, float] | None = None
        self.length_errors: set[int] = set()
        self.tpdo = TpdoTimer()
        self._getters = self._feedback_getters()
        self.local = canopen.LocalNode(node_id, drive_object_dictionary(
            node_id, link.rated_current_ma, link.rated_torque_mnm, link.heartbeat_consumer))
        self.local.sdo = NodeSdoServer(self.local.sdo.rx_cobid, self.local.sdo.tx_cobid,
                                       self.local)
        self.local.add_read_callback(self.on_sdo_read)
        self.local.add_write_callback(self.on_sdo_write)

    @property
    def operational(self) -> bool:
        return self.local.nmt.state == "OPERATIONAL"

    # -- the loop's side (lock held) -------------------------------------------------------
    def fill(self, into: Setpoint, seq: int) -> None:
        """The latched objects as a setpoint, in increments (the lock is held)."""
        controlword, mode, position, velocity_offset, velocity, torque, torque_offset = \
            self.latched
        factor = self.dict.factor
        self.mode = mode
        into.seq = seq
        into.controlword = controlword
        into.target_position_counts = position * factor
        into.velocity_offset_counts_s = velocity_offset * factor
        into.target_velocity_counts_s = velocity * factor
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
        """Keep ``fb`` as the newest feedback (the lock is held)."""
        s = self.staged
        s.statusword, s.fault = fb.statusword, fb.fault
        s.encoder_counts, s.scale_counts = fb.encoder_counts, fb.scale_counts
        s.velocity_counts_s, s.iq_a = fb.velocity_counts_s, fb.iq_a

    # -- values ----------------------------------------------------------------------------
    def _feedback_getters(self) -> dict:
        """(index, sub-index) -> the object's wire value from the staged feedback."""
        d, rated = self.dict, self.rated_ma

        def current(fb: Feedback) -> int:
            return saturate(permille(fb.iq_a, rated), I16)

        return {STATUSWORD: lambda fb: fb.statusword & ~SW_ECHO_MASK & 0xFFFF,
                (0x6061, 0): lambda fb: self.mode,
                ERROR_CODE: lambda fb: fb.fault,
                (0x1001, 0): lambda fb: self.register(fb.fault),
                (0x6064, 0): lambda fb: wrap_i32(fb.encoder_counts / d.factor),
                (0x606C, 0): lambda fb: saturate(fb.velocity_counts_s / d.factor, I32),
                (0x6077, 0): current, (0x6078, 0): current,
                (0x60E4, 1): lambda fb: wrap_i32(fb.scale_counts)}

    def value(self, key: tuple[int, int]) -> int:
        """An object's value as the wire carries it (the lock is held)."""
        getter = self._getters.get(key)
        if getter is not None:
            return getter(self.staged)
        if key in self.image:
            return self.image[key]
        return self.dict.read(*key)

    def pack(self, pdo: PdoConfig, counter: int | None = None) -> bytes:
        """The frame of a valid TPDO now; a statusword in it carries the SYNC echo when
        ``counter`` is given (see :mod:`io_adapters.can_cia402`)."""
        values = []
        for key in pdo.layout.objects:
            v = self.value(key)
            if key == STATUSWORD and counter is not None:
                v |= SW_ECHO | (counter & 3) << ECHO_SHIFT
            values.append(v)
        return pdo.layout.frame.pack(*values)

    # -- TPDOs -------------------------------------------------------------------------------
    def sync_frames(self, by_sync: bool, counter: int | None, now_s: float) -> list:
        """The synchronous TPDOs due at this cycle start (every one on the drive's own
        clock), as messages (the lock is held)."""
        return self.tpdo.sync_frames(self.dict.pdos.tpdos, self.pack, by_sync, counter, now_s)

    def event_frames(self, now_s: float) -> list:
        """The event-driven TPDOs due now (the lock is held)."""
        return self.tpdo.event_frames(self.dict.pdos.tpdos, self.pack, now_s)

    # -- EMCY --------------------------------------------------------------------------------
    def register(self, fault: int) -> int:
        """1001h with the drive's error code ``fault``: its bits, and the communication
        bits while an RPDO's length error stands (see the module docstring)."""
        length = error_register(EMCY_PDO_LENGTH) if self.length_errors else 0
        return error_register(fault) | length

    def emcy_due(self) -> tuple[int, int] | None:
        """(code, 1001h) of an EMCY to send now, if the error code changed (lock held)."""
        code = self.staged.fault
        if code == self.emcy_code or self.local.nmt.state not in ("PRE-OPERATIONAL",
                                                                 "OPERATIONAL"):
            return None
        self.emcy_code = code
        return code, self.register(code)

    def send_emcy(self, code: int, register: int, data: bytes = b"") -> None:
        """Send the EMCY ``code`` (0: error reset) with the error register and ``data``, its
        manufacturer-specific bytes (3-7, zero-padded); one the bus cannot take is dropped
        and counted in ``send_dropped``."""
        try:
            self.local.emcy.send(code, register, data)
        except can.CanError:
            self.owner.stats.send_dropped += 1

    def _length_checked(self, pdo: PdoConfig, dlc: int) -> None:
        """Keep whether ``pdo``'s frame of ``dlc`` bytes had the wrong length; the EMCY
        8210h when the RPDO's error starts, the error reset when the node's last one ends
        (the lock is held)."""
        mapped = pdo.layout.frame.size
        wrong = dlc != mapped
        if wrong == (pdo.number in self.length_errors):
            return
        if wrong:
            self.length_errors.add(pdo.number)
            self.send_emcy(EMCY_PDO_LENGTH, self.register(self.emcy_code),
                           bytes((pdo.number, dlc, mapped)))
        else:
            self.length_errors.discard(pdo.number)
            if not self.length_errors:
                self.send_emcy(0, self.register(self.emcy_code))

    # -- refusals ----------------------------------------------------------------------------
    def bounds(self) -> SetpointBounds:
        return self.dict.bounds()

    def refusal(self, values: dict) -> int:
        """Why ``values`` (key -> wire value, merged over the image) cannot be taken, or 0:
        a mode this node does not take, or the axis's
        :class:`~io_adapters.messages.SetpointBounds` on the setpoint they make (no mode,
        the power-up value, counts as CST; a profile mode as CSP, whose loops it needs), a
        current beyond its bound by less than half a per-mille step (the wire's rounding)
        taken at the bound."""
        def get(key):
            return values.get(key, self.image[key])

        mode = get((0x6060, 0))
        if mode != NO_MODE and mode not in self.dict.modes():
            return REFUSED_MODE
        torque, offset = get((0x6071, 0)), get((0x60B2, 0))
        current = amps(max(abs(torque), abs(offset), abs(torque + offset)), self.rated_ma)
        bounds = self.bounds()
        if bounds.current_a < current <= bounds.current_a + 0.5e-6 * self.rated_ma:
            current = bounds.current_a
        factor = self.dict.factor
        return bounds.refusal(CHECKED_AS.get(mode, mode), get((0x607A, 0)) * factor,
                              get((0x60FF, 0)) * factor, get((0x60B1, 0)) * factor,
                              current, 0.0, 0.0, 0.0)

    def refuse(self, reason: int, fault: bool = True) -> None:
        """Count a refusal and, for process data (``fault``), keep it for the loop, whose
        drive faults on it (the lock is held)."""
        stats = self.owner.stats
        if reason == REFUSED_MODE:
            stats.refused_mode += 1
        else:
            stats.refused_range += 1
        self.refused = self.refused or fault

    # -- the bus's side ----------------------------------------------------------------------
    def on_rpdo(self, data: bytearray, pdo: PdoConfig) -> bool:
        """Take one RPDO: its inputs into the image, the drive's objects mapped in it
        written at once; False (malformed) on a DLC other than the mapping's, which the
        EMCY 8210h reports (see the module docstring)."""
        layout = pdo.layout
        with self.lock:
            self._length_checked(pdo, len(data))
        if len(data) != layout.frame.size:
            return False
        update = dict(zip(layout.objects, layout.frame.unpack(data)))
        inputs = {k: v for k, v in update.items() if k in self.image}
        with self.lock:
            reason = self.refusal(inputs)
            if not reason:
                reason = self._write_mapped(update)
            if reason:
                self.refuse(reason)
            else:
                self.image.update(inputs)
                self.owner._fresh = True
        return True

    def _write_mapped(self, update: dict) -> int:
        """Write the drive's objects an RPDO carries; REFUSED_RANGE if one is refused."""
        for key, value in update.items():
            if key in self.image:
                continue
            try:
                self.dict.check_limits(*key, value)
                self.dict.write(*key, value, pre_operational=False)
            except ObjectAccessError:
                return REFUSED_RANGE
        return 0

    def on_sdo_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """An SDO request, served unless the node is STOPPED (CiA 301: no SDO there); one of
        another length than CiA 301's 8 bytes is counted ``malformed`` and dropped, as
        CANopenNode does (no answer: its multiplexer may not even be there).  A response
        the bus cannot take is counted in ``send_dropped``."""
        if self.local.nmt.state == "STOPPED":
            return
        if len(data) != SDO_FRAME_BYTES:
            self.owner.stats.malformed += 1
            return
        try:
            self.local.sdo.on_request(can_id, data, timestamp)
        except can.CanError:
            self.owner.stats.send_dropped += 1

    def on_sdo_read(self, index: int, subindex: int, od) -> int | None:
        key = (index, subindex)
        try:
            if key in self._getters or key in self.image:
                with self.lock:
                    return self.value(key)
            return self.dict.read(index, subindex)
        except ObjectAccessError as e:
            raise SdoAbortedError(e.abort_code) from e

    def on_sdo_write(self, index: int, subindex: int, od, data: bytes) -> None:
        key = (index, subindex)
        value = od.decode_raw(data)
        if key in self.image:
            self._write_input(key, value)
            return
        try:
            self.dict.check_limits(index, subindex, value)
            self.dict.write(index, subindex, value,
                            self.local.nmt.state == "PRE-OPERATIONAL")
        except ObjectAccessError as e:
            raise SdoAbortedError(e.abort_code) from e
        if self.dict.pdos.owner(index) is not None:
            self.owner.pdos_changed()
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

    # -- network management ------------------------------------------------------------------
    def on_nmt(self, command: int, data: bytearray, timestamp: float) -> None:
        """An NMT command for this node (CiA 301: unconditional): a start whose PDO plan
        the bus cannot carry starts all the same and says so in EMCY FF20h (its frames
        will wait, and be lost: 8110h then); a reset boots the node again; the rest is
        canopen's."""
        if command == NMT_START and self.local.nmt.state != "OPERATIONAL":
            plan = self.owner.bus_plan(starting=self)
            self.owner.stats.bus_plan_load = plan.load
            if not plan.fits:
                self.owner.stats.starts_over_plan += 1
                load = min(round(plan.load * 1000), 0xFFFF)
                cycle = round(plan.cycle_s * 1e6)
                self.send_emcy(EMCY_PLAN_OVERLOAD, error_register(EMCY_PLAN_OVERLOAD),
                               load.to_bytes(2, "little") + cycle.to_bytes(3, "little"))
                self.plan_overloaded = True
            elif self.plan_overloaded:  # the EMCY's error is gone: error reset
                self.plan_overloaded = False
                self.send_emcy(0, self.register(self.emcy_code))
            self.tpdo.restart()
        self.local.nmt.on_command(0, data, timestamp)
        if command in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
            self.reset_event = True
            self.boot(application=command == NMT_RESET_NODE)

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
        if watched is not None:  # when the bus delivered it (python-can's clock)
            self.watch = (watched[0], watched[1], timestamp)

    def heartbeat_lost(self, bus_time_s: float) -> bool:
        """The consumed heartbeat is overdue at the bus's time ``bus_time_s``
        (:meth:`~io_adapters.can_tap.BusTap.bus_time_s`: a receive thread held up has not
        seen the time pass); monitoring starts with the first one."""
        watched = self.watch
        return watched is not None and bus_time_s - watched[2] > watched[1]

    def overrun_emcy(self, lost: int) -> tuple[int, int, bytes] | None:
        """(code, 1001h, data) of the EMCY to send at a cycle's start for ``lost``, this
        node's frames lost so far: 8110h when frames were lost since the last cycle, the
        error reset once a cycle lost none (lock held)."""
        new, self.lost_seen = lost > self.lost_seen, lost
        if new == self.overrun or self.local.nmt.state not in ("PRE-OPERATIONAL",
                                                              "OPERATIONAL"):
            return None
        self.overrun = new
        if new:
            return (EMCY_CAN_OVERRUN, error_register(EMCY_CAN_OVERRUN),
                    min(lost, 0xFFFF).to_bytes(2, "little"))
        return 0, self.register(self.emcy_code), b""

    def boot(self, application: bool) -> None:
        """NMT reset: the master's process data cleared (controlword 0: disable voltage,
        no mode), communication objects back to their start values (and the drive's
        objects and the factor group for a reset node), boot-up message, PRE-OPERATIONAL."""
        objects = self.owner.objects
        if application and objects is not None:
            objects.reset_application(self.axis)
        with self.lock:  # the master's process data is gone: controlword 0, no mode
            self.dict.reset(application)
            self.image.update(dict.fromkeys(INPUTS, 0))
            self.latched = (0,) * len(INPUTS)
            self.tpdo.clear()
            self.length_errors.clear()
        self.consume_heartbeat(self.dict.consumer_entry)
        self.local.data_store.clear()
        self.owner.pdos_changed()
        nmt = self.local.nmt
        nmt.stop_heartbeat()
        nmt.state = "RESET"             # boot-up message
        nmt.state = "PRE-OPERATIONAL"   # heartbeat producer from 1017h (0: none)
