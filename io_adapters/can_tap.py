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

**A bus carries what its bit rate allows.**  With a capacity set (the device side: the bit
rate times the communication cycle), a cycle holds at most that many bits.  A frame of
ours that does not fit waits in the transmit queue, as a CAN controller's frames wait for
the bus, and goes out, oldest first, when a new cycle has room: after the next SYNC, or
once a cycle's time has passed without one (an idle bus); with :data:`TX_QUEUE` frames
waiting, a further one is lost (CiA 301's "CAN overrun, objects lost": the endpoint sends
EMCY 8110h).  Frames received beyond the capacity were on the bus later than the tap saw
them: their bits count in the next cycle.  So no cycle holds more than the bus can carry.

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
#: frames our CAN controller holds while the bus has no room (SocketCAN's default
#: txqueuelen for a CAN interface); one more is lost
TX_QUEUE = 10


@dataclass(slots=True)
class CycleLoad:
    """Bits on the bus per SYNC cycle, as the tap saw them (worst-case stuffing); the
    frames before the first SYNC (the master configuring the node by SDO) are in no cycle.

    Attributes:
        cycles: SYNC cycles closed.
        bits: the bits of the cycle running now (received beyond the capacity of the
            cycles before it included).
        max_bits: the most bits a closed cycle of at most ``max_interval_s`` held (a
            longer one -- SYNC late, or stopped and started again -- is no communication
            cycle: it counts in the totals only); at most ``capacity_bits``.
        total_bits: the bits of every closed cycle.
        total_s: how long the closed cycles lasted together, s.
        max_interval_s: see ``max_bits`` (set by the endpoint from 1006h).
        capacity_bits: the most bits a cycle carries (the bit rate times 1006h, set by the
            endpoint; inf: no bound).
        period_s: the communication cycle (1006h, set by the endpoint): a window of the
            bus's room is this long when no SYNC starts the next.
        opened_s: when the running cycle's SYNC came (monotonic s; None before the first).
        window_s, window_bits: when the bus's present window of room began (a SYNC, or a
            cycle's time after the last window) and the bits in it.
    """
    cycles: int = 0
    bits: int = 0
    max_bits: int = 0
    total_bits: int = 0
    total_s: float = 0.0
    max_interval_s: float = math.inf
    capacity_bits: float = math.inf
    period_s: float = math.inf
    opened_s: float | None = None
    window_s: float = 0.0
    window_bits: int = 0

    def add(self, bits: int) -> None:
        self.bits += bits
        self.window_bits += bits

    def room(self, bits: int, now_s: float) -> bool:
        """A frame of ``bits`` fits the bus's present window at ``now_s`` (any does before
        the first SYNC)."""
        if self.opened_s is None:
            return True
        if now_s - self.window_s >= self.period_s:  # a cycle's time passed without a SYNC
            self.window_s, self.window_bits = now_s, 0
        return self.window_bits + bits <= self.capacity_bits

    def close(self, now_s: float) -> None:
        """A SYNC at ``now_s``: the running cycle ends with what it could carry, the rest
        goes on in the next."""
        carried = 0
        if self.opened_s is not None:
            interval = now_s - self.opened_s
            carried = int(max(0.0, self.bits - self.capacity_bits))
            kept = self.bits - carried
            self.cycles += 1
            self.total_bits += kept
            self.total_s += interval
            if interval <= self.max_interval_s:
                self.max_bits = max(self.max_bits, kept)
        self.opened_s = self.window_s = now_s
        self.bits = self.window_bits = carried


@dataclass(slots=True)
class TxQueue:
    """Our frames that wait for room on the bus (:data:`TX_QUEUE` at most), and what the
    wait cost.

    Attributes:
        waiting: the frames, oldest first.
        delayed: frames that went out in a later cycle than the one they were sent in.
        lost: frames dropped with the queue full, by the node-ID of their COB-ID.
    """
    waiting: deque = field(default_factory=deque)
    delayed: int = 0
    lost: dict = field(default_factory=dict)


class BusTap(can.BusABC):
    """A python-can bus around ``bus`` that counts (and logs) every frame.

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

    def _sent(self, msg: can.Message) -> None:
        """Count (and log) a frame of ours that goes on the bus now (the lock held)."""
        self.load.add(_WORST[min(len(msg.data), 8)])
        if self._log is not None:
            self._write_log(msg, False)

    def _due(self, now_s: float) -> list[can.Message]:
        """The waiting frames the bus has room for now, oldest first, taken from the
        queue and counted (the lock held)."""
        tx, going = self.tx, []
        while tx.waiting and self.load.room(_WORST[min(len(tx.waiting[0].data), 8)], now_s):
            msg = tx.waiting.popleft()
            self._sent(msg)
            tx.delayed += 1
            going.append(msg)
        return going

    def _send_inner(self, going: list[can.Message]) -> None:
        for msg in going:
            try:
                self.inner.send(msg)
            except can.CanError:  # nobody acknowledges: as a send that failed at once
                continue

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg`` now if the bus has room for it and nothing of ours waits, else
        queue it (module docstring); a frame the queue cannot take is lost."""
        now = time.monotonic()
        with self._lock:
            tx = self.tx
            going = self._due(now) if tx.waiting else []
            fits = not tx.waiting and self.load.room(_WORST[min(len(msg.data), 8)], now)
            if fits:
                self._sent(msg)
            elif len(tx.waiting) < TX_QUEUE:
                tx.waiting.append(msg)
            else:
                node = msg.arbitration_id & 0x7F
                tx.lost[node] = tx.lost.get(node, 0) + 1
        self._send_inner(going)
        if fits:
            self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        # the inner bus's own receive, not its recv(): one filtering and timeout loop (this
        # bus's) per frame is enough, and the receive thread handles every frame
        msg, filtered = self.inner._recv_internal(timeout)
        now = time.monotonic()
        with self._lock:
            if msg is None:
                self._drained_s = time.time()
            else:
                if msg.arbitration_id == SYNC_COB_ID:
                    self.load.close(now)
                self.load.add(_WORST[min(len(msg.data), 8)])
                self._arrival_s = max(self._arrival_s, msg.timestamp)
                if self._log is not None:
                    self._write_log(msg, True)
            going = self._due(now) if self.tx.waiting else []
        self._send_inner(going)
        return msg, filtered

    def bus_time_s(self) -> float:
        """The bus's time as the receive thread has seen it (module docstring), on
        python-can's clock (time.time); 0 before anything was received or looked for."""
        return max(self._arrival_s, self._drained_s)

    def fileno(self) -> int:
        return self.inner.fileno()

    def shutdown(self) -> None:
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
