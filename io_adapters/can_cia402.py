"""``can://INTERFACE/CHANNEL``: the emulated drive as a CANopen CiA 402 node (device side),
or the drives of several axes as one node each (``axes=N``, nodes ``node`` ..
``node + N - 1``, each with its own object dictionary and PDOs; one SYNC cycles them all
and the loop reads and writes them as one :class:`~io_adapters.messages.SetpointGroup`
and :class:`~io_adapters.messages.FeedbackGroup`).

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
taken while a node is in PRE-OPERATIONAL or OPERATIONAL; SDO in every state.  The drive boots into
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
from io_adapters.messages import (
    MODE_CST,
    Feedback,
    FeedbackGroup,
    Setpoint,
    SetpointGroup,
    axis_records,
)

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


class _DriveNode:
    """One CiA 402 node of the endpoint (one axis): its :class:`canopen.LocalNode`, PDO
    frames and process image.  Its state is guarded by the endpoint's ``lock``."""

    def __init__(self, node_id: int, link: CanLink, lock: threading.Lock):
        self.lock = lock
        self.rpdos = {p.cob_id: p for p in rpdo_layouts(node_id)}
        self.tpdos = tpdo_layouts(node_id)
        self.tpdo_msgs = tuple(can.Message(arbitration_id=p.cob_id, is_extended_id=False,
                                           data=bytearray(p.frame.size)) for p in self.tpdos)
        self.staged = tuple(bytearray(p.frame.size) for p in self.tpdos)
        self.image = {obj: 0 for p in (*self.rpdos.values(), *self.tpdos) for obj in p.objects}
        self.image[ERROR_REGISTER] = 0
        self.latched = (0,) * len(INPUTS)
        self.mode = NO_MODE
        self.local = canopen.LocalNode(node_id, drive_object_dictionary(
            node_id, link.rated_current_ma, link.rated_torque_mnm))
        self.local.add_read_callback(self.on_sdo_read)
        self.local.add_write_callback(self.on_sdo_write)

    def fill(self, into: Setpoint, seq: int, rated_ma: int) -> None:
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
            into.iq_ref_a = amps((torque if mode == MODE_CST else 0) + torque_offset, rated_ma)
        into.id_ref_a = into.ud_v = into.uq_v = 0.0
        into.t_ns = 0

    def stage(self, fb: Feedback, rated_ma: int) -> None:
        """Pack ``fb`` into the TPDO frames and the image (the lock is held)."""
        current = saturate(permille(fb.iq_a, rated_ma), I16)
        fault_code = FAULT_CODE_BASE + fb.fault if fb.fault else 0
        values = ((fb.statusword, self.mode, fault_code),
                  (wrap_i32(fb.encoder_counts), saturate(fb.velocity_counts_s, I32)),
                  (current, current, wrap_i32(fb.scale_counts)))
        for layout, staged, vals in zip(self.tpdos, self.staged, values):
            layout.frame.pack_into(staged, 0, *vals)
            self.image.update(zip(layout.objects, vals))
        self.image[ERROR_REGISTER] = 1 if fb.statusword & SW_FAULT else 0

    def send_tpdos(self, bus: can.BusABC, counter: int | None) -> None:
        """Send the staged TPDO1-3, TPDO1 with the SYNC echo when ``counter`` is given."""
        for msg, staged in zip(self.tpdo_msgs, self.staged):
            msg.data[:] = staged
        tpdo1 = self.tpdo_msgs[0].data  # statusword little-endian: bits 8-15
        tpdo1[1] &= ~SW_ECHO_MASK >> 8 & 0xFF
        if counter is not None:
            tpdo1[1] |= (SW_ECHO | (counter & 3) << ECHO_SHIFT) >> 8
        for msg in self.tpdo_msgs:
            bus.send(msg)

    def on_rpdo(self, data: bytearray, layout) -> bool:
        """Take one RPDO into the image; False (malformed) on a wrong DLC or mode."""
        if len(data) != layout.frame.size:
            return False
        update = dict(zip(layout.objects, layout.frame.unpack(data)))
        if update.get((0x6060, 0), NO_MODE) not in ACCEPTED_MODES:
            return False
        with self.lock:
            self.image.update(update)
        return True

    def on_sdo_read(self, index: int, subindex: int, od) -> int | None:
        with self.lock:
            return self.image.get((index, subindex))

    def on_sdo_write(self, index: int, subindex: int, od, data: bytes) -> None:
        key = (index, subindex)
        if key not in INPUTS:
            return
        value = od.decode_raw(data)
        if key == (0x6060, 0) and value not in ACCEPTED_MODES:
            raise SdoAbortedError(SDO_ABORT_VALUE_RANGE)
        with self.lock:
            self.image[key] = value


class CanDriveEndpoint(Endpoint):
    """The device side of ``can://`` (see the module docstring); ``from_url`` with the
    controller role returns :class:`io_adapters.can_master.CanMasterEndpoint`.

    With ``axes=N`` (N > 1) it is N nodes (``node`` .. ``node + N - 1``) and takes a
    :class:`~io_adapters.messages.SetpointGroup` and
    :class:`~io_adapters.messages.FeedbackGroup` of N axes, axis i on node ``node + i``;
    one SYNC starts the cycle of every node.
    """

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
        self._lock = threading.Lock()
        self._cycle = threading.Condition(self._lock)
        self._nodes = tuple(_DriveNode(n, link, self._lock) for n in link.nodes)
        self._rpdo_of = {cob_id: (node, layout) for node in self._nodes
                         for cob_id, layout in node.rpdos.items()}
        self._ready = False
        self._written = 0  # send_feedback calls since the last cycle started
        self.last_sync_ns = 0
        self._cycles = 0
        self._last_cycle_s = time.monotonic()
        #: the canopen LocalNode of each axis; ``node`` is the first
        self.nodes = tuple(n.local for n in self._nodes)
        self.node = self.nodes[0]
        self.network = canopen.Network(open_bus(link))
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        try:
            for node in self.nodes:
                self.network.add_node(node)
            self.network.subscribe(SYNC_COB_ID, self._on_sync)
            for cob_id in self._rpdo_of:
                self.network.subscribe(cob_id, self._on_rpdo)
            self.network.connect()
            for node in self.nodes:
                node.nmt.state = "RESET"            # sends the boot-up message
                node.nmt.state = "PRE-OPERATIONAL"
        except (can.CanError, OSError) as e:
            self.network.disconnect()
            raise AdapterError(f"{link.url!r}: cannot start the CANopen node: {e}") from e

    @property
    def nmt_state(self) -> str:
        """The (first) node's NMT state ("PRE-OPERATIONAL", "OPERATIONAL", ...)."""
        return self.node.nmt.state

    def _records(self, message, what: str) -> tuple:
        records = axis_records(message)
        if len(records) != len(self._nodes):
            raise AdapterError(f"{self!r}: {what} of {len(records)} axes; this link has "
                               f"{len(self._nodes)} (axes={self.link.axes})")
        return records

    # -- the loop's side -----------------------------------------------------------------
    def _read(self, into: Setpoint | SetpointGroup, timeout_s: float | None) -> bool:
        records = self._records(into, "a setpoint")
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
            seq = self._cycles & U32_MASK
            for rec, node in zip(records, self._nodes):
                node.fill(rec, seq, self.link.rated_current_ma)
            into.seq, into.t_ns = seq, 0
        self.stats.received += 1
        return True

    def _write(self, fb: Feedback | FeedbackGroup) -> bool:
        records = self._records(fb, "feedback")
        with self._lock:
            for rec, node in zip(records, self._nodes):
                node.stage(rec, self.link.rated_current_ma)
            self._written += 1
        return True

    def _close(self) -> None:
        for node in self.nodes:
            node.nmt.stop_heartbeat()
        self.network.disconnect()

    # -- the bus's side (canopen's receive thread) ---------------------------------------
    def _start_cycle(self, now: float, by_sync: bool = False,
                     counter: int | None = None) -> None:
        """Send the TPDOs, latch the inputs, wake the loop (the lock is held)."""
        fresh = self._written == 1 if by_sync else self._written > 0
        if fresh:
            with self.network.send_lock:
                for node in self._nodes:
                    if node.local.nmt.state == "OPERATIONAL":
                        node.send_tpdos(self.network.bus, counter)
        self._written = 0
        if self._ready:
            self.stats.lost += 1
        for node in self._nodes:
            node.latched = tuple(node.image[obj] for obj in INPUTS)
        self._ready = True
        self._cycles += 1
        self._last_cycle_s = now
        self._cycle.notify_all()

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if any(n.nmt.state in ("PRE-OPERATIONAL", "OPERATIONAL") for n in self.nodes):
            now_ns = time.monotonic_ns()
            with self._lock:
                self.last_sync_ns = now_ns
                self._start_cycle(now_ns * 1e-9, True, data[0] if len(data) == 1 else None)

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        node, layout = self._rpdo_of[can_id]
        if node.local.nmt.state == "OPERATIONAL" and not node.on_rpdo(data, layout):
            self.stats.malformed += 1
