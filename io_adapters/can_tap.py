"""The bus as one side of ``can://`` sees it: every frame it sends or receives passes
through :class:`BusTap`, which counts what the frames cost on the wire per communication
cycle and, with the URL's ``log`` option, writes them with python-can's writer for the
file's suffix (``.asc``, ``.blf``, ``.trc``, ``.log``: what CAN tools open).

The cost of a frame is its worst-case length (:func:`io_adapters.can_bus_time.
worst_frame_bits`, bit stuffing included at its bound: an exact count per frame would cost
the receive thread more than the frame itself); a cycle runs from one SYNC to the next,
the SYNC counted in the cycle it opens (:class:`CycleLoad`).  The tap wraps the bus
python-can opened, so canopen's own sends (SDO answers, heartbeats, EMCY) are seen too.
:func:`open_bus` opens the bus of a ``can://`` URL behind a tap, for either side.

**A bus carries what its bit rate allows.**  With a bit rate and a capacity set (the
device side: the bit rate, and its product with the communication cycle), the bus's room
fills at the bit rate up to one cycle's bits, and every frame on it, ours or received,
takes its bits from that room (:class:`CycleLoad`).  A frame of ours that does not fit
waits in the transmit queue, as a CAN controller's frames wait for the bus, and goes out,
oldest first, once the room has grown enough; with :data:`TX_QUEUE` frames of its node
waiting, a further one is lost (CiA 301's "CAN overrun, objects lost": the endpoint sends EMCY
8110h).  Frames received beyond the room were on the bus later than the tap saw them:
their bits are owed by the room, and count in the next cycle when a cycle cannot hold
them.  So no cycle holds more than the bus can carry in it, whether the master's SYNC
comes at 1006h or faster.

**The bus's time** (:meth:`BusTap.bus_time_s`): the newest arrival among the frames the
receive thread has taken (python-can's stamp: the kernel's receive time on
``udp_multicast`` and SocketCAN), or when it last found nothing left to take, whichever
is later.  A consumer judged on it (the heartbeat, CiA 301) sees the frames as the bus
delivered them: a receive thread that was held up has not yet seen the time pass. """

import importlib
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import can

from io_adapters.base import AdapterError
from io_adapters.can_bus_time import worst_frame_bits
from io_adapters.can_catalog import SYNC_COB_ID
from io_adapters.can_loopback import LoopbackMulticastBus
from io_adapters.can_url import CanLink

_WORST = tuple(worst_frame_bits(n) for n in range(9))
#: frames a node's CAN controller holds while the bus has no room (SocketCAN's default
#: txqueuelen for a CAN interface); one more is lost
TX_QUEUE = 10


@dataclass(slots=True)
class CycleLoad:
    """Bits on the bus per SYNC cycle, as the tap saw them (worst-case stuffing), and the
    bus's room for our frames; the frames before the first SYNC (the master configuring
    the node by SDO) are in no cycle.  Times are the bus's (python-can's clock,
    ``time.time``): a received frame's arrival stamp, a frame of ours when it is sent.

    The room is a token bucket: it fills at the bit rate, up to one communication cycle's
    bits (a cycle's frames may go out together after its SYNC), and every frame on the bus
    -- ours or received -- takes its bits from it.  So the bus never carries more than its
    bit rate, whatever the master's SYNC period against 1006h.

    Attributes:
        cycles: SYNC cycles closed.
        bits: the bits of the cycle running now (received beyond the capacity of the
            cycles before it included).
        max_bits: the most bits a closed cycle of at most ``max_interval_s`` held (a
            longer one -- SYNC late, or stopped and started again -- is no communication
            cycle: it counts in the totals only); at most ``capacity_bits``.
        max_share: the highest share of its capacity such a cycle held (at most 1).
        total_bits: the bits of every closed cycle.
        total_s: how long the closed cycles lasted together, s.
        max_interval_s: see ``max_bits`` (set by the endpoint from 1006h).
        bit_rate: the bus's bit rate, bit/s (set by the endpoint; inf: no bound).
        capacity_bits: the bits of one communication cycle (the bit rate times 1006h, set
            by the endpoint; inf: no bound).  A cycle carries at most this, or what the bit
            rate allows in its own interval if that is shorter (SYNC faster than 1006h);
            what it held beyond counts in the next.
        opened_s: when the running cycle's SYNC came (None before the first).
        credit_bits, credit_s: the room in the bucket, bits, as of ``credit_s`` (below
            zero: received frames were on the bus later than the tap saw them).
    """
    cycles: int = 0
    bits: int = 0
    max_bits: int = 0
    max_share: float = 0.0
    total_bits: int = 0
    total_s: float = 0.0
    max_interval_s: float = math.inf
    bit_rate: float = math.inf
    capacity_bits: float = math.inf
    opened_s: float | None = None
    credit_bits: float = 0.0
    credit_s: float = 0.0

    def _refill(self, now_s: float) -> None:
        if now_s > self.credit_s:
            self.credit_bits = min(self.capacity_bits,
                                   self.credit_bits + (now_s - self.credit_s) * self.bit_rate)
            self.credit_s = now_s

    def add(self, bits: int, at_s: float) -> None:
        """A frame of ``bits`` on the bus at ``at_s``.  A received frame the receive thread
        took late may be older than the room's last update (a frame of ours sent since):
        within a cycle of it, it still takes its bits; an older one does not, since the
        room would have filled to its cap in the time after it."""
        self.bits += bits
        if self.opened_s is not None and (
                at_s >= self.credit_s - self.capacity_bits / self.bit_rate):
            self._refill(at_s)
            # at most one cycle owed: frames stamped closer together than the bit rate
            # allows (a virtual bus, a flood) cannot stop ours for longer than a real bus
            # that carried them would
            self.credit_bits = max(self.credit_bits - bits, -self.capacity_bits)

    def room(self, bits: int, now_s: float) -> bool:
        """The bus has room for a frame of ``bits`` at ``now_s`` (any before the first
        SYNC)."""
        if self.opened_s is None:
            return True
        self._refill(now_s)
        return self.credit_bits >= bits

    def wait_s(self, bits: int, now_s: float) -> float:
        """How long from ``now_s`` until the bus has room for a frame of ``bits``, s."""
        if self.room(bits, now_s):
            return 0.0
        return (bits - self.credit_bits) / self.bit_rate

    def cycle_capacity(self, interval_s: float) -> float:
        """The most bits a cycle of ``interval_s`` carries (see ``capacity_bits``)."""
        if math.isinf(self.bit_rate):
            return self.capacity_bits
        return min(self.capacity_bits, self.bit_rate * max(0.0, interval_s))

    def close(self, now_s: float) -> None:
        """A SYNC at ``now_s``: the running cycle ends with what it could carry, the rest
        goes on in the next."""
        carried = 0
        if self.opened_s is None:
            self.credit_bits, self.credit_s = self.capacity_bits, now_s
        else:
            interval = max(0.0, now_s - self.opened_s)
            capacity = self.cycle_capacity(interval)
            carried = math.ceil(max(0.0, self.bits - capacity))
            kept = self.bits - carried
            self.cycles += 1
            self.total_bits += kept
            self.total_s += interval
            if interval <= self.max_interval_s:
                self.max_bits = max(self.max_bits, kept)
                if 0.0 < capacity < math.inf:
                    self.max_share = max(self.max_share, kept / capacity)
        self.opened_s = now_s
        self.bits = carried


def _bits(msg: can.Message) -> int:
    """A frame's length on the bus at the worst (module docstring)."""
    return _WORST[min(len(msg.data), 8)]


def _node(msg: can.Message) -> int:
    """The node-ID in a frame's COB-ID (CiA 301's predefined connection set)."""
    return msg.arbitration_id & 0x7F


@dataclass(slots=True)
class TxQueue:
    """Our frames that wait for room on the bus, and what the wait cost.  Each node the
    process emulates is a device of its own, with its own CAN controller: it holds
    :data:`TX_QUEUE` frames at most.

    Attributes:
        waiting: the frames of every node, oldest first (the bus takes them in order).
        queued: how many of them each node-ID holds.
        delayed: frames that waited for room before going out.
        lost: frames dropped with their node's queue full, by node-ID.
    """
    waiting: deque = field(default_factory=deque)
    queued: dict = field(default_factory=dict)
    delayed: int = 0
    lost: dict = field(default_factory=dict)

    def put(self, msg: can.Message) -> bool:
        """Queue ``msg``; False (and counted lost) when its node's queue is full."""
        node = _node(msg)
        if self.queued.get(node, 0) >= TX_QUEUE:
            self.lost[node] = self.lost.get(node, 0) + 1
            return False
        self.waiting.append(msg)
        self.queued[node] = self.queued.get(node, 0) + 1
        return True

    def take(self) -> can.Message:
        """The oldest waiting frame, taken off the queue."""
        msg = self.waiting.popleft()
        self.queued[_node(msg)] -= 1
        self.delayed += 1
        return msg


class BusTap(can.BusABC):
    """A python-can bus around ``bus`` that counts (and logs) every frame.

    Frames of ours that wait for room go out from a transmit thread of the tap's own
    (started with the first that waits), as a CAN controller sends its queue as soon as
    the bus is free, whether anything else happens on the bus or not.

    Args:
        bus: the bus python-can opened (shut down with this one).
        log_path: where python-can's writer puts every frame, or None.

    Attributes:
        load: the bits per cycle (:class:`CycleLoad`).
        tx: our frames waiting for the bus (:class:`TxQueue`).
    """

    def __init__(self, bus: can.BusABC, log_path: str | None = None):
        self.inner = bus
        self.channel_info = f"{bus.channel_info} (tapped)"
        self.load = CycleLoad()
        self.tx = TxQueue()
        self._lock = threading.Lock()
        self._queued = threading.Condition(self._lock)  # frames wait, or the tap closes
        # held from deciding that a frame goes out until it went: no frame of ours passes
        # one the transmit thread has taken from the queue
        self._sending = threading.Lock()
        self._transmitter: threading.Thread | None = None
        self._closed = False
        self._log = can.Logger(log_path) if log_path else None
        self._logged_s = 0.0  # the newest time stamp logged (time.time)
        # the newest arrival the receive thread took, and when it last found the bus
        # drained (python-can's clock, time.time; 0: not yet)
        self._arrival_s = self._drained_s = 0.0
        super().__init__(channel=getattr(bus, "channel", None))

    def _write_log(self, msg: can.Message, received: bool) -> None:
        """Log ``msg`` (the lock held): our own frame stamped now, as a transmission; a
        received one keeps its arrival time unless a frame logged before it is newer (the
        log's times never go back, as CAN tools expect); the writer's own channel number
        (a bus's channel name may end in digits that are no CAN channel)."""
        stamp = max(msg.timestamp if received else time.time(), self._logged_s)
        self._logged_s = stamp
        self._log.on_message_received(can.Message(
            timestamp=stamp, arbitration_id=msg.arbitration_id,
            is_extended_id=msg.is_extended_id, data=msg.data,
            is_remote_frame=msg.is_remote_frame, is_rx=received))

    def _sent(self, msg: can.Message, now_s: float) -> None:
        """Count (and log) a frame of ours that goes on the bus at ``now_s`` (the lock
        held)."""
        self.load.add(_bits(msg), now_s)
        if self._log is not None:
            self._write_log(msg, False)

    def _flush(self) -> float:
        """Send the waiting frames the bus has room for now, oldest first; returns how long
        until the next has room (0: none waits)."""
        with self._sending:
            with self._lock:
                now, going, wait = time.time(), [], 0.0
                while self.tx.waiting:
                    wait = self.load.wait_s(_bits(self.tx.waiting[0]), now)
                    if wait > 0.0:
                        break
                    msg = self.tx.take()
                    self._sent(msg, now)
                    going.append(msg)
            for msg in going:
                self._send_inner(msg)
        return wait

    def _transmit(self) -> None:
        """The transmit thread: the waiting frames, each once the bus has room for it
        (sooner when a frame on the bus gives the receive thread the chance,
        :meth:`_recv_internal`)."""
        while True:
            with self._queued:
                while not self.tx.waiting and not self._closed:
                    self._queued.wait()
                if self._closed:
                    return
            wait = self._flush()
            if wait > 0.0:
                with self._queued:
                    if not self._closed:
                        self._queued.wait(wait)

    def _send_inner(self, msg: can.Message, timeout: float | None = None) -> None:
        try:
            self.inner.send(msg, timeout)
        except can.CanError:  # nobody acknowledges: as a send that failed at once
            pass

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg`` now if the bus has room for it and nothing of ours waits, else
        queue it for the transmit thread (module docstring); a frame its node's queue
        cannot take is lost."""
        with self._sending:
            with self._lock:
                now = time.time()
                fits = not self.tx.waiting and self.load.room(_bits(msg),
                                                              now)
                if fits:
                    self._sent(msg, now)
                elif self.tx.put(msg):
                    if self._transmitter is None:
                        self._transmitter = threading.Thread(
                            target=self._transmit, name="can-tap-transmit", daemon=True)
                        self._transmitter.start()
                    self._queued.notify()
            if fits:
                self._send_inner(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        # the inner bus's own receive, not its recv(): one filtering and timeout loop (this
        # bus's) per frame is enough, and the receive thread handles every frame
        msg, filtered = self.inner._recv_internal(timeout)
        now = time.time()
        with self._lock:
            if msg is None:
                self._drained_s = now
            else:
                if msg.arbitration_id == SYNC_COB_ID:
                    self.load.close(msg.timestamp)
                self.load.add(_bits(msg), msg.timestamp)
                self._arrival_s = max(self._arrival_s, msg.timestamp)
                if self._log is not None:
                    self._write_log(msg, True)
            waiting = bool(self.tx.waiting)
        if waiting:  # the frames that have room now go without waiting for the thread
            self._flush()
        return msg, filtered

    def bus_time_s(self) -> float:
        """The bus's time as the receive thread has seen it (module docstring), on
        python-can's clock (time.time); 0 before anything was received or looked for."""
        return max(self._arrival_s, self._drained_s)

    def fileno(self) -> int:
        return self.inner.fileno()

    def shutdown(self) -> None:
        with self._queued:
            self._closed = True
            self._queued.notify()
        if self._transmitter is not None:
            self._transmitter.join()
        super().shutdown()
        self.inner.shutdown()
        with self._lock:
            if self._log is not None:
                self._log.stop()
                self._log = None


def mf4_writer_ready() -> None:
    """Make python-can's MF4 writer usable in this process.  Importing asammdf before
    python-can's MF4 module leaves that module without it: asammdf imports python-can,
    whose MF4 module then finds asammdf half-imported and turns itself off.  Once asammdf
    is whole the module is loaded again (its writer class reads the module's names)."""
    from can.io import mf4

    if mf4.asammdf is None:
        importlib.reload(mf4)


def open_bus(link: CanLink, **options) -> can.BusABC:
    """The python-can bus of ``link`` (``options`` go to ``can.Bus``) behind a
    :class:`BusTap`; ``udp_multicast`` stays on the loopback
    interface unless ``multicast_if`` says otherwise (:mod:`io_adapters.can_loopback`).
    Raises :class:`AdapterError` saying why it cannot be opened."""
    if link.port is not None:
        options["port"] = link.port
    try:
        if link.interface == "udp_multicast" and link.multicast_if != "any":
            address = link.multicast_if or ("::1" if ":" in link.channel else "127.0.0.1")
            bus = LoopbackMulticastBus(link.channel, address, **options)
        else:
            bus = can.Bus(interface=link.interface, channel=link.channel, **options)
    except (can.CanError, OSError, ValueError) as e:
        raise AdapterError(f"{link.url!r}: cannot open the {link.interface} bus "
                           f"{link.channel!r}: {e}") from e
    if link.log is not None and link.log.lower().endswith(".mf4"):
        mf4_writer_ready()
    try:
        return BusTap(bus, link.log)
    except (OSError, ValueError) as e:
        bus.shutdown()
        raise AdapterError(f"{link.url!r}: cannot write the log {link.log!r}: {e}") from e
