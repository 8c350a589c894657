"""``can://INTERFACE/CHANNEL``: the emulated drive as a CANopen CiA 402 node (device side),
or the drives of several axes as one node each (``axes=N``, nodes ``node`` ..
``node + N - 1``, each with its own object dictionary and PDOs; one SYNC cycles them all
and the loop reads and writes them as one :class:`~io_adapters.messages.SetpointGroup`
and :class:`~io_adapters.messages.FeedbackGroup`).

Each node (:class:`~io_adapters.can_node.DriveNode`): a :class:`canopen.LocalNode` holds
the object dictionary of :mod:`io_adapters.cia402_objects` and answers SDO requests;
this endpoint adds what canopen 2.4 leaves to the application on the device side: the
SYNC consumer, the RPDO consumer and the TPDO producer, over a python-can bus.

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
1-240): the TPDO1 it sends then has the manufacturer-specific statusword bits set to say
which SYNC sent it -- bit 8 (:data:`~io_adapters.can_node.SW_ECHO`) and the counter's
low two bits in bits 14-15 -- so a master can tell a late answer from a new one.  Those
bits are 0 in TPDO1 otherwise, and never in the 6041h that SDO reads.

So the feedback of a setpoint reaches the master one SYNC later, as on a real CiA 402
network.  A cycle counts as *heard* (:meth:`recv_setpoint` returns True) only when a SYNC
started it and new process data came since the cycle before (an RPDO taken in
OPERATIONAL, or an SDO write to one of the inputs); a cycle the drive starts on its own
clock, or a SYNC with nothing new before it, is run (the loop gets the latched setpoint)
but returns False, so the drive's watchdog counts it as silence (SYNC/RPDO timeout).
:attr:`last_sync_ns` is when the newest SYNC was latched (``time.monotonic_ns``; 0
before the first): a loop that runs on its own clock locks
its cycle to it (``hil run`` does, :class:`hil.runtime.sync.SyncLock`), as a CiA 402
drive synchronises its control cycle to SYNC.  With no SYNC for ``sync_timeout_ms``
the drive starts its cycle on its own clock, every ``sync_timeout_ms``, sending its
TPDOs the same way (the newest values, however many cycles wrote them since): a master
that has not started SYNC yet (or stopped it) still sees the statusword move.  SYNC is
taken while a node is in PRE-OPERATIONAL or OPERATIONAL, SDO in every state but STOPPED
(CiA 301; a request there goes unanswered).  The drive
boots into PRE-OPERATIONAL and sends its boot-up message when opened.

Network management and the lost master (:meth:`link_conditions`, which the drive's watchdog
reads every tick): NMT stop puts a node in STOPPED (no PDO, no SYNC: LINK_STOPPED while
it lasts); NMT reset node and reset communication are reported once (LINK_RESET), then
the node boots again: boot-up message, PRE-OPERATIONAL, its communication objects (1016h,
1017h) back to their start values, and for a reset node the drive's parameter objects too
(:meth:`~io_adapters.cia402_objects.ObjectAccess.reset_application`).  A heartbeat
consumer (1016h:01, the ``heartbeat_consumer`` option or an SDO write) watches the
master's heartbeat from the first one on: none within the consumer time is
LINK_HEARTBEAT_LOST until the next one.  What the drive does then is its abort connection
option code 6007h.  An error code that changes in the feedback (603Fh) is sent as an EMCY
(80h + node-ID: code, 1001h, five zero bytes) at the next cycle start; its clearing as the
EMCY "error reset" (code 0).

Setpoint from the latched objects: ``seq`` counts the cycles; ``controlword`` = 6040h;
``mode`` = 6060h (0, no mode, becomes MODE_CST with zero current); targets 607Ah,
60FFh, 60B1h as floats; ``iq_ref_a`` = (6071h in CST + 60B2h) per mille of 6075h;
``id_ref_a``, ``ud_v``, ``uq_v`` and ``t_ns`` = 0 (not on this wire).  Feedback into
the objects: 6041h statusword, 6061h = the mode of the cycle, 603Fh = ``fault`` (the
drive's error code), 1001h from it, 6064h ``encoder_counts`` (wrapped into INTEGER32),
606Ch ``velocity_counts_s``, 6078h and 6077h ``iq_a`` in per mille (saturated),
60E4h:01 ``scale_counts``.  SDO reads of these objects return the newest values; the
parameter objects are the drive's (:attr:`CanDriveEndpoint.objects`).

Refused, as on every transport (:attr:`~io_adapters.base.Endpoint.setpoint_bounds`): an
RPDO or SDO write with a mode the drive does not take (``refused_mode``; SDO abort 0609
0030h) or a value beyond its bound (``refused_range``; SDO abort 0609 0031h/0032h): the
image keeps its last accepted values; a refused RPDO is named in :attr:`refused_axes` at
the next :meth:`recv_setpoint` (the drive faults, FF10h), a refused SDO write is
answered with its abort only, as a drive answers a bad parameter.  A frame the bus
cannot take (a full transmit queue) is dropped and counted in ``send_dropped``.  Counted
in :attr:`stats`: ``received`` cycles heard, ``timeouts`` the others, ``lost`` cycles
that a newer SYNC overwrote before :meth:`recv_setpoint` took them, ``malformed`` RPDO
frames dropped (a DLC other than the mapping's, stricter than CiA 301, which uses the
first bytes of a longer one).  The bus's receive thread (python-can's ``Notifier``, run
by canopen) is stopped by :meth:`close`.  """

import ipaddress
import threading
import time

import can
import canopen

from io_adapters.base import (
    LINK_HEARTBEAT_LOST,
    LINK_RESET,
    LINK_STOPPED,
    AdapterClosed,
    AdapterError,
    Endpoint,
    Role,
)
from io_adapters.can_loopback import LoopbackMulticastBus
from io_adapters.can_node import INPUTS, DriveNode
from io_adapters.cia402_objects import (
    NMT_COB_ID,
    SYNC_COB_ID,
    CanLink,
    ObjectAccess,
    parse_can_url,
)
from io_adapters.messages import (
    Feedback,
    FeedbackGroup,
    Setpoint,
    SetpointGroup,
    axis_records,
)

U32_MASK = 0xFFFFFFFF
#: how long the receive thread waits in one bus read: the bound on :meth:`close`
NOTIFIER_CYCLE_S = 0.05
NMT_RESET_NODE, NMT_RESET_COMMUNICATION = 0x81, 0x82


def open_bus(link: CanLink, **options) -> can.BusABC:
    """The python-can bus of ``link`` (``options`` go to ``can.Bus``); ``udp_multicast``
    stays on the loopback interface unless ``multicast_if`` says otherwise
    (:mod:`io_adapters.can_loopback`).  Raises :class:`AdapterError` saying why it cannot
    be opened."""
    if link.port is not None:
        options["port"] = link.port
    try:
        if link.interface == "udp_multicast" and link.multicast_if != "any":
            address = link.multicast_if or ("::1" if ":" in link.channel else "127.0.0.1")
            return LoopbackMulticastBus(link.channel, address, **options)
        return can.Bus(interface=link.interface, channel=link.channel, **options)
    except (can.CanError, OSError, ValueError) as e:
        raise AdapterError(f"{link.url!r}: cannot open the {link.interface} bus "
                           f"{link.channel!r}: {e}") from e


class CanDriveEndpoint(Endpoint):
    """The device side of ``can://`` (see the module docstring); ``from_url`` with the
    controller role returns :class:`io_adapters.can_master.CanMasterEndpoint`.

    With ``axes=N`` (N > 1) it is N nodes (``node`` .. ``node + N - 1``) and takes a
    :class:`~io_adapters.messages.SetpointGroup` and
    :class:`~io_adapters.messages.FeedbackGroup` of N axes, axis i on node ``node + i``;
    one SYNC starts the cycle of every node.

    Attributes:
        objects: the drive's parameter objects (:class:`~io_adapters.cia402_objects.
            ObjectAccess`), set by the drive's owner; None: the dictionary's defaults,
            stored as written.
        cycles: cycles started so far (by SYNC or on the drive's own clock).
        taken: cycles handed to the loop by :meth:`recv_setpoint`, heard or not (a loop
            that runs its drive on every cycle, rather than on its own clock, counts them).
        rated_current_a: 6075h in A, the reference of the per-mille currents.
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
        self.objects: ObjectAccess | None = None
        self.rated_current_a = link.rated_current_ma / 1e3
        self._free_run_s = link.sync_timeout_ms / 1e3
        self._lock = threading.Lock()
        self._cycle = threading.Condition(self._lock)
        self._nodes = tuple(DriveNode(a, n, link, self) for a, n in enumerate(link.nodes))
        self._by_id = {n.local.id: n for n in self._nodes}
        self._rpdo_of = {cob_id: (node, layout) for node in self._nodes
                         for cob_id, layout in node.rpdos.items()}
        self._ready = False
        self._heard = False   # the cycle ready for the loop was heard
        self._fresh = False   # process data taken since the last cycle started
        self._written = 0     # send_feedback calls since the last cycle started
        self.last_sync_ns = 0
        self.cycles = 0
        self.taken = 0
        self._last_cycle_s = time.monotonic()
        #: the canopen LocalNode of each axis; ``node`` is the first
        self.nodes = tuple(n.local for n in self._nodes)
        self.node = self.nodes[0]
        self.network = canopen.Network(open_bus(link))
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        try:
            for n in self._nodes:
                self.network.add_node(n.local)
                sdo = n.local.sdo  # its requests go through the node (no SDO when STOPPED)
                self.network.unsubscribe(sdo.rx_cobid, sdo.on_request)
                self.network.subscribe(sdo.rx_cobid, n.on_sdo_request)
            self.network.subscribe(SYNC_COB_ID, self._on_sync)
            self.network.subscribe(NMT_COB_ID, self._on_nmt)  # after canopen's own
            for cob_id in self._rpdo_of:
                self.network.subscribe(cob_id, self._on_rpdo)
            self.network.connect()
            for n in self._nodes:
                n.boot(application=False)
        except (can.CanError, OSError) as e:
            self.network.disconnect()
            raise AdapterError(f"{link.url!r}: cannot start the CANopen node: {e}") from e

    @property
    def exposed(self) -> bool:
        """The bus reaches beyond this machine (``udp_multicast`` with ``multicast_if`` not
        a loopback address)."""
        link = self.link
        if link.interface != "udp_multicast" or link.multicast_if is None:
            return False
        return link.multicast_if == "any" or not ipaddress.ip_address(
            link.multicast_if).is_loopback

    @property
    def nmt_state(self) -> str:
        """The (first) node's NMT state ("PRE-OPERATIONAL", "OPERATIONAL", ...)."""
        return self.node.nmt.state

    def link_conditions(self, axis: int) -> int:
        """LINK_STOPPED while the node is in NMT STOPPED, LINK_RESET once after an NMT
        reset, LINK_HEARTBEAT_LOST while the consumed heartbeat is overdue."""
        node = self._nodes[axis]
        conditions = LINK_STOPPED if node.local.nmt.state == "STOPPED" else 0
        if node.reset_event:
            node.reset_event = False
            conditions |= LINK_RESET
        if node.watch is not None and node.heartbeat_lost(time.monotonic()):
            conditions |= LINK_HEARTBEAT_LOST
        return conditions

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
            seq = self.cycles & U32_MASK
            for a, (rec, node) in enumerate(zip(records, self._nodes)):
                node.fill(rec, seq)
                if node.refused:
                    node.refused = False
                    self.refused_axes |= 1 << a
            into.seq, into.t_ns = seq, 0
            heard = self._heard
            self.taken += 1
        if heard:
            self.stats.received += 1
        return heard

    def _write(self, fb: Feedback | FeedbackGroup) -> bool:
        records = self._records(fb, "feedback")
        with self._lock:
            for rec, node in zip(records, self._nodes):
                node.stage(rec)
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
        # a frame the bus cannot take (a full transmit queue: nobody acknowledges) is
        # dropped and counted; the cycle's bookkeeping below always runs
        if fresh:
            with self.network.send_lock:
                for node in self._nodes:
                    if node.local.nmt.state == "OPERATIONAL":
                        self.stats.send_dropped += node.send_tpdos(self.network.bus, counter)
        for node in self._nodes:
            due = node.emcy_due()
            if due is not None:
                try:
                    node.local.emcy.send(*due)
                except can.CanError:
                    self.stats.send_dropped += 1
        self._written = 0
        if self._ready:
            self.stats.lost += 1
        for node in self._nodes:
            node.latched = tuple(node.image[obj] for obj in INPUTS)
        self._heard = by_sync and self._fresh
        self._fresh = False
        self._ready = True
        self.cycles += 1
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

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """After canopen's own NMT handling: a reset boots the node again."""
        if len(data) != 2 or data[0] not in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
            return
        for node in self._nodes if data[1] == 0 else (self._by_id.get(data[1]),):
            if node is not None:
                node.reset_event = True
                node.boot(application=data[0] == NMT_RESET_NODE)
