"""``can://INTERFACE/CHANNEL``: the emulated drive as a CANopen CiA 402 node (device side),
or the drives of several axes as one node each (``axes=N``, nodes ``node`` ..
``node + N - 1``, each with its own object dictionary and PDOs; one SYNC cycles them all
and the loop reads and writes them as one :class:`~io_adapters.messages.SetpointGroup`
and :class:`~io_adapters.messages.FeedbackGroup`).

Each node (:class:`~io_adapters.can_node.DriveNode`): a :class:`canopen.LocalNode` holds
the object dictionary of :mod:`io_adapters.cia402_objects` and answers SDO requests;
this endpoint adds what canopen 2.4 leaves to the application on the device side: the
SYNC consumer, the RPDO consumer and the TPDO producer, over a python-can bus seen
through a :class:`~io_adapters.can_tap.BusTap` (the bus load per cycle, the URL's log).

**The cycle.**  The drive's loop runs at its own rate (the PWM period) and calls
:meth:`recv_setpoint` every tick (without waiting, but for the tick due to take a SYNC,
which may wait a little for a late one: :class:`hil.runtime.sync.SyncLock`); the master's
process data reach it once per communication cycle, at SYNC.  At each SYNC (in
PRE-OPERATIONAL or OPERATIONAL) the endpoint

1. sends the synchronous TPDOs due (OPERATIONAL nodes only; type 0 when their data
   changed, type n at every n-th SYNC) with the newest feedback the loop wrote -- none if
   the loop wrote none since the SYNC before (its ticks did not run: the master sees an
   answer missing rather than a stale one), and none either where a SYNC comes every
   drive cycle (the mean interval under :data:`ONE_TICK` cycles, ``hil controller``'s
   link) and two or more ticks ran since the one before: the second ran on a stale
   setpoint, which a master that compares with the lock-step simulation must see,
2. latches the master's process data received before it, by RPDO (OPERATIONAL only, any
   transmission type) or by SDO (controlword, mode, targets, offsets), and hands them to
   the next :meth:`recv_setpoint`, which turns them into a
   :class:`~io_adapters.messages.Setpoint` in increments and returns True when new process
   data came since the SYNC before (the cycle is *heard*).

Between SYNCs :meth:`recv_setpoint` returns False and leaves the record as it was: the
drive runs on the setpoint of the cycle and interpolates its cyclic targets over the
interpolation time period 60C2h (:mod:`hil.drive.interpolation`), which a node sets to its
communication cycle period 1006h.  :attr:`heard_for_s` says how long one heard cycle
stands for the master (1.5 cycles: the SYNC's jitter), so the watchdog does not count
the ticks between SYNCs as silence.  Event-driven TPDOs (254/255) go out from
:meth:`send_feedback` when their data change (no sooner than their inhibit time after
the last) and when their event timer runs out.

A SYNC may carry a counter byte (CiA 301, DLC 1; :mod:`io_adapters.can_master` counts
1-240): a synchronous TPDO holding the statusword then has its manufacturer-specific
bits set to say which SYNC sent it -- bit 8 (:data:`~io_adapters.can_node.SW_ECHO`) and
the counter's low two bits in bits 14-15 -- so a master can tell a late answer from a new
one.  Those bits are 0 otherwise, and never in the 6041h that SDO reads.

With no SYNC for ``sync_timeout_ms`` the endpoint starts a cycle on its own clock, every
``sync_timeout_ms``, sending the synchronous TPDOs and latching the process data the same
way; such a cycle is never heard.  :attr:`last_sync_ns` is when the newest SYNC was latched
(``time.monotonic_ns``; 0 before the first): the loop aligns its ticks to it
(:class:`hil.runtime.sync.SyncLock`).

**Network management** (:meth:`link_conditions`, which the drive's watchdog reads every
tick): NMT stop puts a node in STOPPED (no PDO, no SYNC, no SDO: LINK_STOPPED while it
lasts); NMT reset node and reset communication are reported once (LINK_RESET), then the
node boots again: boot-up message, PRE-OPERATIONAL, its communication objects (PDO
mapping, 1016h, 1017h) back to their start values, and for a reset node the drive's
objects and the factor group too.  NMT start always starts the node (CiA 301's commands
are unconditional); when the PDO configuration of the nodes then OPERATIONAL does not fit
the communication cycle at the bus's bit rate (:meth:`bus_plan`, every frame at its
rate), the node says so in the EMCY FF20h with the load it needs
(:data:`~io_adapters.can_node.EMCY_PLAN_OVERLOAD`).  The bus then carries what it can:
our frames wait in their node's transmit queue while the bus has no room (it fills at the
bit rate, whoever sends the SYNC when), and with the queue full they are lost, counted,
and reported by the EMCY 8110h "CAN overrun"
(:mod:`io_adapters.can_tap`; its error reset once a cycle loses none).  A heartbeat
consumer (1016h:01, the ``heartbeat_consumer`` option or an SDO write) watches the
master's heartbeat from the first one on: none within the consumer time on the bus's
time (the frames' arrival as the receive thread took them,
:meth:`~io_adapters.can_tap.BusTap.bus_time_s`: a starved emulator does not take the
master for silent) is LINK_HEARTBEAT_LOST until the next one.  What the drive does then
is its abort connection option code 6007h.
An error code that changes in the feedback (603Fh) is sent as an EMCY (80h + node-ID:
code, 1001h, five zero bytes) at the next cycle start; its clearing as the EMCY "error
reset" (code 0).

**Refused**, as on every transport (:attr:`~io_adapters.base.Endpoint.setpoint_bounds`;
a node offers the profile modes beside the cyclic ones where the drive runs CSP,
:func:`~io_adapters.can_dictionary.offered_modes`): an RPDO or SDO write with a mode the
drive does not take (``refused_mode``; SDO abort 0609
0030h) or a value beyond its bound (``refused_range``; SDO abort 0609 0031h/0032h): the
image keeps its last accepted values; a refused RPDO is named in :attr:`refused_axes` at
the next :meth:`recv_setpoint` (the drive faults, FF10h), a refused SDO write is answered
with its abort only.  A frame the bus cannot take is dropped and counted in
``send_dropped``.  Counted in :attr:`stats` (:class:`CanStats`): ``received`` cycles heard,
``timeouts`` polls that found no new cycle, ``lost`` cycles a newer SYNC overwrote before
:meth:`recv_setpoint` took them, ``malformed`` frames dropped (an RPDO of a DLC other than
the mapping's, stricter than CiA 301, which the EMCY 8210h reports,
:mod:`io_adapters.can_node`; an SDO request of another length than 8 bytes), the bus's
load per cycle and the refused starts.  The bus's receive thread (python-can's
``Notifier``, run by canopen) is stopped by :meth:`close`.
"""

import ipaddress
import threading
import time
from dataclasses import dataclass

import can
import canopen

from io_adapters.base import (
    LINK_HEARTBEAT_LOST,
    LINK_RESET,
    LINK_STOPPED,
    AdapterClosed,
    AdapterError,
    AdapterStats,
    Endpoint,
    Role,
)
from io_adapters.can_bus_time import BusPlan, per_cycle, plan_cycle
from io_adapters.can_catalog import INPUTS, NMT_COB_ID, SYNC_COB_ID
from io_adapters.can_node import DriveNode
from io_adapters.can_tap import open_bus
from io_adapters.can_url import CanLink, parse_can_url
from io_adapters.cia402_objects import ObjectAccess
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
#: one heard cycle stands for the master this many communication cycle periods
HEARD_CYCLES = 1.5
#: a SYNC interval longer than this many communication cycle periods is a late or
#: resumed SYNC, not a cycle: left out of the most bits per cycle
LONG_CYCLE = 1.5
#: SYNCs whose intervals make the mean the endpoint keeps
SYNC_MEAN_SAMPLES = 16
#: a mean SYNC interval under this many drive cycles is one tick per SYNC
ONE_TICK = 1.5


@dataclass(slots=True)
class CanStats(AdapterStats):
    """:class:`~io_adapters.base.AdapterStats` and the bus.

    Attributes:
        sync_cycles: SYNC cycles the bus tap closed.
        bus_bits_per_cycle_max: the most bits one SYNC cycle held (every frame this side
            sent or received, worst-case stuffing; cycles longer than :data:`LONG_CYCLE`
            periods left out).
        bus_load_max: the highest share of its capacity one such cycle held: of the
            communication cycle 1006h at the bit rate, or of its own interval where SYNC
            came sooner (1.0: the whole cycle, at most: :mod:`io_adapters.can_tap`).
        bus_load_mean: every cycle's bits over the time the cycles lasted, as a share of
            the bit rate.
        starts_over_plan: NMT starts whose PDO configuration did not fit the cycle (EMCY
            FF20h).
        bus_plan_load: the load of the configuration at the last NMT start
            (:meth:`CanDriveEndpoint.bus_plan`), as a share of the cycle.
        frames_delayed: our frames that waited for room on the bus.
        frames_lost: our frames lost with the transmit queue full (EMCY 8110h).
    """
    sync_cycles: int = 0
    bus_bits_per_cycle_max: int = 0
    bus_load_max: float = 0.0
    bus_load_mean: float = 0.0
    starts_over_plan: int = 0
    bus_plan_load: float = 0.0
    frames_delayed: int = 0
    frames_lost: int = 0


class CanDriveEndpoint(Endpoint):
    """The device side of ``can://`` (see the module docstring); ``from_url`` with the
    controller role returns :class:`io_adapters.can_master.CanMasterEndpoint`.

    With ``axes=N`` (N > 1) it is N nodes (``node`` .. ``node + N - 1``) and takes a
    :class:`~io_adapters.messages.SetpointGroup` and
    :class:`~io_adapters.messages.FeedbackGroup` of N axes, axis i on node ``node + i``;
    one SYNC starts the cycle of every node.

    Attributes:
        cycles: cycles started so far (by SYNC or on the drive's own clock).
        taken: cycles handed to the loop by :meth:`recv_setpoint`, heard or not.
        rated_current_a: 6075h in A, the reference of the per-mille currents.
        last_sync_ns: when the newest SYNC was latched (monotonic ns; 0: none yet).
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
        self.stats = CanStats()
        self._objects: ObjectAccess | None = None
        self.rated_current_a = link.rated_current_ma / 1e3
        self._free_run_s = link.sync_timeout_ms / 1e3
        self._lock = threading.Lock()
        self._cycle = threading.Condition(self._lock)
        self._ready = False
        self._heard = False   # the cycle ready for the loop was heard
        self._fresh = False   # process data taken since the last cycle started
        self._staged = 0      # send_feedback calls since the last cycle started
        self._sync_interval_s = 0.0  # SYNC to SYNC, averaged over SYNC_MEAN_SAMPLES
        self._sync_arrival_s = 0.0  # the newest SYNC's arrival (python-can's stamp)
        self._rpdo_of: dict = {}
        self.last_sync_ns = 0
        self.cycles = 0
        self.taken = 0
        self._last_cycle_s = time.monotonic()
        self._nodes = tuple(DriveNode(a, n, link, self) for a, n in enumerate(link.nodes))
        self._by_id = {n.local.id: n for n in self._nodes}
        #: the canopen LocalNode of each axis; ``node`` is the first
        self.nodes = tuple(n.local for n in self._nodes)
        self.node = self.nodes[0]
        self.bus = open_bus(link)
        self.network = canopen.Network(self.bus)
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        try:
            for n in self._nodes:
                self.network.add_node(n.local)
                sdo, nmt = n.local.sdo, n.local.nmt
                # requests go through the node: no SDO when STOPPED, a start checked
                self.network.unsubscribe(sdo.rx_cobid, sdo.on_request)
                self.network.subscribe(sdo.rx_cobid, n.on_sdo_request)
                self.network.unsubscribe(NMT_COB_ID, nmt.on_command)
            self.network.subscribe(SYNC_COB_ID, self._on_sync)
            self.network.subscribe(NMT_COB_ID, self._on_nmt)
            self.network.connect()
            for n in self._nodes:
                n.boot(application=False)
        except (can.CanError, OSError) as e:
            self.network.disconnect()
            raise AdapterError(f"{link.url!r}: cannot start the CANopen node: {e}") from e

    # -- what the loop and the drive's owner see -------------------------------------------
    @property
    def objects(self) -> ObjectAccess | None:
        """The drive's objects (:class:`~io_adapters.cia402_objects.ObjectAccess`), set by
        the drive's owner; None: the dictionary's defaults, stored as written.  Setting
        them gives each node the drive's 1006h and encoder resolution, and the drive the
        node's 60C2h (:meth:`~io_adapters.can_dictionary.NodeDictionary.refresh`)."""
        return self._objects

    @objects.setter
    def objects(self, objects: ObjectAccess | None) -> None:
        self._objects = objects
        with self._lock:
            for n in self._nodes:
                n.dict.refresh()

    @property
    def heard_for_s(self) -> float:
        """How long a heard cycle stands for the master, s: :data:`HEARD_CYCLES`
        communication cycle periods (1006h, the shortest of the nodes')."""
        return HEARD_CYCLES * min(n.dict.cycle_s for n in self._nodes)

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

    def bus_plan(self, starting: DriveNode | None = None) -> BusPlan:
        """The worst communication cycle of the nodes OPERATIONAL (and ``starting``):
        SYNC with its counter, every valid PDO (:meth:`~io_adapters.can_pdo.PdoSet.
        frames`) and each heartbeat produced, over the shortest 1006h at the bit rate."""
        nodes = [n for n in self._nodes if n.operational or n is starting]
        cycle = min(n.dict.cycle_s for n in self._nodes)
        frames = [("SYNC", 1.0, 1)]
        for n in nodes:
            drive_cycle = (self._objects.cycle_s(n.axis) if self._objects is not None
                           else cycle)
            frames += n.dict.pdos.frames(cycle, drive_cycle)
            if n.dict.producer_ms:
                frames.append((f"heartbeat of node {n.local.id}",
                               per_cycle(n.dict.producer_ms * 1e-3, cycle), 1))
        return plan_cycle(frames, cycle, self.link.bitrate)

    def link_conditions(self, axis: int) -> int:
        """LINK_STOPPED while the node is in NMT STOPPED, LINK_RESET once after an NMT
        reset, LINK_HEARTBEAT_LOST while the consumed heartbeat is overdue."""
        node = self._nodes[axis]
        conditions = LINK_STOPPED if node.local.nmt.state == "STOPPED" else 0
        if node.reset_event:
            node.reset_event = False
            conditions |= LINK_RESET
        if node.watch is not None and node.heartbeat_lost(self.bus.bus_time_s()):
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
        now = time.monotonic()
        frames = []
        with self._lock:
            for rec, node in zip(records, self._nodes):
                node.stage(rec)
                if node.operational:
                    frames += node.event_frames(now)
            self._staged += 1
        self._send_all(frames)
        return True

    def _send_all(self, frames: list) -> None:
        """Send ``frames``; one the bus cannot take (a full transmit queue: nobody
        acknowledges) is dropped and counted."""
        if not frames:
            return
        with self.network.send_lock:
            for msg in frames:
                try:
                    self.bus.send(msg)
                except can.CanError:
                    self.stats.send_dropped += 1

    def _close(self) -> None:
        for node in self.nodes:
            node.nmt.stop_heartbeat()
        self.network.disconnect()

    # -- the bus's side (canopen's receive thread) ---------------------------------------
    def pdos_changed(self) -> None:
        """Subscribe the valid RPDOs' COB-IDs (after a remapping or a reset)."""
        wanted = {pdo.cob_id: (node, pdo) for node in self._nodes
                  for pdo in node.dict.pdos.rpdos if pdo.layout is not None}
        for cob_id in set(self._rpdo_of) - set(wanted):
            self.network.unsubscribe(cob_id, self._on_rpdo)
        for cob_id in set(wanted) - set(self._rpdo_of):
            self.network.subscribe(cob_id, self._on_rpdo)
        self._rpdo_of = wanted

    def _start_cycle(self, now: float, by_sync: bool = False,
                     counter: int | None = None) -> None:
        """Send the TPDOs due, latch the inputs, wake the loop (the lock is held)."""
        frames = []
        if self._staged == 1 or (self._staged and not (by_sync and self._one_tick_per_sync())):
            for node in self._nodes:
                if node.operational:
                    frames += node.sync_frames(by_sync, counter, now)
        lost = self.bus.tx.lost
        for node in self._nodes:
            due = node.emcy_due()
            if due is not None:
                node.send_emcy(*due)
            overrun = node.overrun_emcy(lost.get(node.local.id, 0))
            if overrun is not None:
                node.send_emcy(*overrun)
        self._send_all(frames)
        self._staged = 0
        if self._ready:
            self.stats.lost += 1
        for node in self._nodes:
            node.latched = tuple(node.image[key] for key in INPUTS)
        self._heard = by_sync and self._fresh
        self._fresh = False
        self._ready = True
        self.cycles += 1
        self._last_cycle_s = now
        self._cycle.notify_all()

    def _update_load(self) -> None:
        load, stats = self.bus.load, self.stats
        cycle = min(n.dict.cycle_s for n in self._nodes)
        load.max_interval_s = LONG_CYCLE * cycle
        load.capacity_bits = self.link.bitrate * cycle
        load.bit_rate = self.link.bitrate
        stats.sync_cycles = load.cycles
        stats.bus_bits_per_cycle_max = load.max_bits
        stats.bus_load_max = load.max_share
        stats.bus_load_mean = load.total_bits / max(1e-9, self.link.bitrate * load.total_s)
        stats.frames_delayed = self.bus.tx.delayed
        stats.frames_lost = sum(self.bus.tx.lost.values())

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if any(n.nmt.state in ("PRE-OPERATIONAL", "OPERATIONAL") for n in self.nodes):
            now_ns = time.monotonic_ns()
            with self._lock:
                if self._sync_arrival_s:
                    # as the bus delivered them: a receive thread held up takes a queue
                    # of SYNCs at once, which are no shorter cycles for it
                    interval = timestamp - self._sync_arrival_s
                    self._sync_interval_s += (interval - self._sync_interval_s) / (
                        1 if not self._sync_interval_s else SYNC_MEAN_SAMPLES)
                self._sync_arrival_s = timestamp
                self.last_sync_ns = now_ns
                self._start_cycle(now_ns * 1e-9, True, data[0] if len(data) == 1 else None)
                self._update_load()

    def _one_tick_per_sync(self) -> bool:
        """The SYNC comes every drive cycle (its mean interval under 1.5 of them): each
        SYNC's answer is the one tick its predecessor's setpoint ran."""
        if self._objects is None or not self._sync_interval_s:
            return False
        drive_cycle = min(self._objects.cycle_s(n.axis) for n in self._nodes)
        return self._sync_interval_s < ONE_TICK * drive_cycle

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        node, pdo = self._rpdo_of[can_id]
        if node.operational and not node.on_rpdo(data, pdo):
            self.stats.malformed += 1

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) != 2:
            return
        for node in self._nodes if data[1] == 0 else (self._by_id.get(data[1]),):
            if node is not None:
                node.on_nmt(data[0], data, timestamp)
