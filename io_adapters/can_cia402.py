"""``can://INTERFACE/CHANNEL``: the emulated drive as a CANopen CiA 402 node (device side).

A :class:`canopen.LocalNode` holds the object dictionary of
:mod:`io_adapters.cia402_objects` and answers SDO requests; this endpoint adds what
canopen 2.4 leaves to the application on the device side: the SYNC consumer, the
RPDO consumer and the TPDO producer, over a python-can bus.

One drive cycle per SYNC.  At each SYNC the drive

1. sends TPDO1-3 holding the feedback of the cycle before (synchronous, type 1: the
   values :meth:`send_feedback` wrote since the SYNC before, when it wrote them exactly
   once; NMT OPERATIONAL only).  A loop that wrote none since (its cycle did not run)
   or two (it ran twice: it is not in step with SYNC) gets nothing sent, so the master
   sees an answer missing rather than taking a stale one, or one two cycles on, for the
   answer to its last SYNC,
2. latches the values received before it, by RPDO (NMT OPERATIONAL only) or by SDO
   (controlword, mode, targets, offsets) and wakes :meth:`recv_setpoint`, which turns
   them into a :class:`~io_adapters.messages.Setpoint`.

A SYNC may carry a counter byte (CiA 301, DLC 1; :mod:`io_adapters.can_master` counts
1-240): the TPDO1 it sends then has the manufacturer-specific statusword bits set to
say which SYNC sent it -- bit 8 (:data:`SW_ECHO`) and the counter's low two bits in bits
14-15 -- so a master can tell a late answer from a new one.  Those bits are 0 in TPDO1
otherwise, and never in the 6041h that SDO reads.

So the feedback of a setpoint reaches the master one SYNC later, as on a real CiA 402
network.  :attr:`last_sync_ns` is when the newest SYNC was latched
(``time.monotonic_ns``; 0 before the first): a loop that runs on its own clock locks
its cycle to it (``hil run`` does, :class:`hil.runtime.sync.SyncLock`), as a CiA 402
drive synchronises its control cycle to SYNC.  With no SYNC for ``sync_timeout_ms``
the drive starts its cycle on its own clock, every ``sync_timeout_ms``, sending its
TPDOs the same way (the newest values, however many cycles wrote them since): a master
that has not started SYNC yet (or stopped it) still sees the statusword move.  SYNC is
taken in PRE-OPERATIONAL and OPERATIONAL; SDO in every state.  The drive boots into
PRE-OPERATIONAL and sends its boot-up message when opened.

Setpoint from the latched objects: ``seq`` counts the cycles; ``controlword`` = 6040h;
``mode`` = 6060h (0, no mode, becomes MODE_CST with zero current); targets 607Ah,
60FFh, 60B1h as floats; ``iq_ref_a`` = (6071h in CST + 60B2h) per mille of 6075h;
``id_ref_a``, ``ud_v``, ``uq_v`` and ``t_ns`` = 0 (not on this wire).  Feedback into
the objects: 6041h statusword, 6061h = the mode of the cycle, 603Fh from ``fault``,
6064h ``encoder_counts`` (wrapped into INTEGER32), 606Ch ``velocity_counts_s``, 6078h
and 6077h ``iq_a`` in per mille (saturated), 60E4h:01 ``scale_counts``; 1001h bit 0
while the statusword shows FAULT.  SDO reads of these objects return the newest values.

Counted in :attr:`stats`: ``received`` cycles handed out, ``lost`` cycles that a newer
SYNC overwrote before :meth:`recv_setpoint` took them, ``malformed`` RPDO frames
dropped (a DLC other than the mapping's, stricter than CiA 301, which uses the first
bytes of a longer one; or a mode the drive does not accept).  The bus's receive thread
(python-can's ``Notifier``, run by canopen) is stopped by :meth:`close`.
"""

import threading
import time

import can
import canopen
from canopen.sdo import SdoAbortedError

from io_adapters.base import AdapterClosed, AdapterError, Endpoint, Role
from io_adapters.cia402_objects import (
    ACCEPTED_MODES,
    FAULT_CODE_BASE,
    I16,
    I32,
    NO_MODE,
    SDO_ABORT_VALUE_RANGE,
    SYNC_COB_ID,
    CanLink,
    amps,
    drive_object_dictionary,
    parse_can_url,
    permille,
    rpdo_layouts,
    saturate,
    tpdo_layouts,
    wrap_i32,
)
from io_adapters.messages import MODE_CST, Feedback, Setpoint

SW_FAULT = 1 << 3
#: TPDO1 statusword: bit 8 set when bits 14-15 hold the low two bits of the counter of
#: the SYNC that sent it (manufacturer-specific bits of CiA 402's 6041h)
SW_ECHO = 1 << 8
ECHO_SHIFT = 14
SW_ECHO_MASK = SW_ECHO | 3 << ECHO_SHIFT
U32_MASK = 0xFFFFFFFF
#: objects written by the master, in the order :meth:`CanDriveEndpoint._fill` reads them
INPUTS = ((0x6040, 0), (0x6060, 0), (0x607A, 0), (0x60B1, 0), (0x60FF, 0), (0x6071, 0),
          (0x60B2, 0))
ERROR_REGISTER = (0x1001, 0)
#: how long the receive thread waits in one bus read: the bound on :meth:`close`
NOTIFIER_CYCLE_S = 0.05


def open_bus(link: CanLink, **options) -> can.BusABC:
    """The python-can bus of ``link`` (``options`` go to ``can.Bus``); raises
    :class:`AdapterError` saying why it cannot be opened."""
    if link.port is not None:
        options["port"] = link.port
    try:
        return can.Bus(interface=link.interface, channel=link.channel, **options)
    except (can.CanError, OSError, ValueError) as e:
        raise AdapterError(f"{link.url!r}: cannot open the {link.interface} bus "
                           f"{link.channel!r}: {e}") from e


class CanDriveEndpoint(Endpoint):
    """The device side of ``can://`` (see the module docstring); ``from_url`` with the
    controller role returns :class:`io_adapters.can_master.CanMasterEndpoint`."""

    @classmethod
    def from_url(cls, url: str, role: Role | str) -> Endpoint:
        role = Role(role)
        link = parse_can_url(url, role)
        if role is Role.CONTROLLER:
            from io_adapters.can_master import CanMasterEndpoint
            return CanMasterEndpoint(link)
        return cls(link)

    def __init__(self, link: CanLink):
        super().__init__(Role.DEVICE)
        self.link = link
        self._free_run_s = link.sync_timeout_ms / 1e3
        self._rpdos = {p.cob_id: p for p in rpdo_layouts(link.node)}
        self._tpdos = tpdo_layouts(link.node)
        self._tpdo_msgs = tuple(can.Message(arbitration_id=p.cob_id, is_extended_id=False,
                                            data=bytearray(p.frame.size)) for p in self._tpdos)
        self._staged = tuple(bytearray(p.frame.size) for p in self._tpdos)
        self._image = {obj: 0 for p in (*self._rpdos.values(), *self._tpdos) for obj in p.objects}
        self._image[ERROR_REGISTER] = 0
        self._lock = threading.Lock()
        self._cycle = threading.Condition(self._lock)
        self._latched = (0,) * len(INPUTS)
        self._ready = False
        self._written = 0  # send_feedback calls since the last cycle started
        self.last_sync_ns = 0
        self._cycles = 0
        self._mode = NO_MODE
        self._last_cycle_s = time.monotonic()
        self.node = canopen.LocalNode(link.node, drive_object_dictionary(
            link.node, link.rated_current_ma, link.rated_torque_mnm))
        self.node.add_read_callback(self._on_sdo_read)
        self.node.add_write_callback(self._on_sdo_write)
        self.network = canopen.Network(open_bus(link))
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        try:
            self.network.add_node(self.node)
            self.network.subscribe(SYNC_COB_ID, self._on_sync)
            for cob_id in self._rpdos:
                self.network.subscribe(cob_id, self._on_rpdo)
            self.network.connect()
            self.node.nmt.state = "RESET"            # sends the boot-up message
            self.node.nmt.state = "PRE-OPERATIONAL"
        except (can.CanError, OSError) as e:
            self.network.disconnect()
            raise AdapterError(f"{link.url!r}: cannot start the CANopen node: {e}") from e

    @property
    def nmt_state(self) -> str:
        """The node's NMT state ("PRE-OPERATIONAL", "OPERATIONAL", ...)."""
        return self.node.nmt.state

    # -- the loop's side -----------------------------------------------------------------
    def _read(self, into: Setpoint, timeout_s: float | None) -> bool:
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cycle:
            while not self._ready:
                if self.network.notifier.exception is not None:
                    raise AdapterClosed(f"{self!r}: the bus failed: "
                                        f"{self.network.notifier.exception}")
                now = time.monotonic()
                due = self._last_cycle_s + self._free_run_s
                if now >= due:  # no SYNC for a while: the drive's own clock
                    self._start_cycle(now)
                    break
                if deadline is not None and now >= deadline:
                    return False
                self._cycle.wait((due if deadline is None else min(due, deadline)) - now)
            self._ready = False
            self._fill(into, self._latched)
        self.stats.received += 1
        return True

    def _fill(self, into: Setpoint, latched: tuple) -> None:
        controlword, mode, position, velocity_offset, velocity, torque, torque_offset = latched
        rated = self.link.rated_current_ma
        self._mode = mode
        into.seq = self._cycles & U32_MASK
        into.controlword = controlword
        into.target_position_counts = float(position)
        into.velocity_offset_counts_s = float(velocity_offset)
        into.target_velocity_counts_s = float(velocity)
        if mode == NO_MODE:
            into.mode, into.iq_ref_a = MODE_CST, 0.0
        else:
            into.mode = mode
            into.iq_ref_a = amps((torque if mode == MODE_CST else 0) + torque_offset, rated)
        into.id_ref_a = into.ud_v = into.uq_v = 0.0
        into.t_ns = 0

    def _write(self, fb: Feedback) -> bool:
        current = saturate(permille(fb.iq_a, self.link.rated_current_ma), I16)
        fault_code = FAULT_CODE_BASE + fb.fault if fb.fault else 0
        values = ((fb.statusword, self._mode, fault_code),
                  (wrap_i32(fb.encoder_counts), saturate(fb.velocity_counts_s, I32)),
                  (current, current, wrap_i32(fb.scale_counts)))
        with self._lock:
            for layout, staged, vals in zip(self._tpdos, self._staged, values):
                layout.frame.pack_into(staged, 0, *vals)
                self._image.update(zip(layout.objects, vals))
            self._image[ERROR_REGISTER] = 1 if fb.statusword & SW_FAULT else 0
            self._written += 1
        return True

    def _close(self) -> None:
        self.node.nmt.stop_heartbeat()
        self.network.disconnect()

    # -- the bus's side (canopen's receive thread) ---------------------------------------
    def _start_cycle(self, now: float, by_sync: bool = False,
                     counter: int | None = None) -> None:
        """Send the TPDOs, latch the inputs, wake the loop (the lock is held)."""
        fresh = self._written == 1 if by_sync else self._written > 0
        if fresh and self.node.nmt.state == "OPERATIONAL":
            with self.network.send_lock:
                for msg, staged in zip(self._tpdo_msgs, self._staged):
                    msg.data[:] = staged
                tpdo1 = self._tpdo_msgs[0].data  # statusword little-endian: bits 8-15
                tpdo1[1] &= ~SW_ECHO_MASK >> 8 & 0xFF
                if counter is not None:
                    tpdo1[1] |= (SW_ECHO | (counter & 3) << ECHO_SHIFT) >> 8
                for msg in self._tpdo_msgs:
                    self.network.bus.send(msg)
        self._written = 0
        if self._ready:
            self.stats.lost += 1
        self._latched = tuple(self._image[obj] for obj in INPUTS)
        self._ready = True
        self._cycles += 1
        self._last_cycle_s = now
        self._cycle.notify_all()

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.node.nmt.state in ("PRE-OPERATIONAL", "OPERATIONAL"):
            now_ns = time.monotonic_ns()
            with self._lock:
                self.last_sync_ns = now_ns
                self._start_cycle(now_ns * 1e-9, True, data[0] if len(data) == 1 else None)

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.node.nmt.state != "OPERATIONAL":
            return
        layout = self._rpdos[can_id]
        if len(data) != layout.frame.size:
            self.stats.malformed += 1
            return
        values = layout.frame.unpack(data)
        update = dict(zip(layout.objects, values))
        if update.get((0x6060, 0), NO_MODE) not in ACCEPTED_MODES:
            self.stats.malformed += 1
            return
        with self._lock:
            self._image.update(update)

    def _on_sdo_read(self, index: int, subindex: int, od) -> int | None:
        with self._lock:
            return self._image.get((index, subindex))

    def _on_sdo_write(self, index: int, subindex: int, od, data: bytes) -> None:
        key = (index, subindex)
        if key not in INPUTS:
            return
        value = od.decode_raw(data)
        if key == (0x6060, 0) and value not in ACCEPTED_MODES:
            raise SdoAbortedError(SDO_ABORT_VALUE_RANGE)
        with self._lock:
            self._image[key] = value
