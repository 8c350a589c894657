"""The bus as one side of ``can://`` sees it: every frame it sends or receives passes
through :class:`BusTap`, which counts what the frames cost on the wire per communication
cycle and, with the URL's ``log`` option, writes them with python-can's writer for the
file's suffix (``.asc``, ``.blf``, ``.trc``, ``.log``: what CAN tools open).

The cost of a frame is its worst-case length (:func:`io_adapters.can_bus_time.
worst_frame_bits`, bit stuffing included at its bound: an exact count per frame would cost
the receive thread more than the frame itself); a cycle runs from one SYNC to the next,
the SYNC counted in the cycle it opens (:class:`CycleLoad`).  The tap wraps the bus
python-can opened, so canopen's own sends (SDO answers, heartbeats, EMCY) are seen too.
:func:`open_bus` opens the bus of a ``can://`` URL behind a tap, for either side. """

import math
import threading
import time
from dataclasses import dataclass

import can

from io_adapters.base import AdapterError
from io_adapters.can_bus_time import worst_frame_bits
from io_adapters.can_catalog import SYNC_COB_ID
from io_adapters.can_loopback import LoopbackMulticastBus
from io_adapters.can_url import CanLink

_WORST = tuple(worst_frame_bits(n) for n in range(9))


@dataclass(slots=True)
class CycleLoad:
    """Bits on the bus per SYNC cycle, as the tap saw them (worst-case stuffing); the
    frames before the first SYNC (the master configuring the node by SDO) are in no cycle.

    Attributes:
        cycles: SYNC cycles closed.
        bits: the bits of the cycle running now.
        max_bits: the most bits a closed cycle of at most ``max_interval_s`` held (a
            longer one -- SYNC late, or stopped and started again -- is no communication
            cycle: it counts in the totals only).
        total_bits: the bits of every closed cycle.
        total_s: how long the closed cycles lasted together, s.
        max_interval_s: see ``max_bits`` (set by the endpoint from 1006h).
        opened_s: when the running cycle's SYNC came (monotonic s; None before the first).
    """
    cycles: int = 0
    bits: int = 0
    max_bits: int = 0
    total_bits: int = 0
    total_s: float = 0.0
    max_interval_s: float = math.inf
    opened_s: float | None = None

    def close(self, now_s: float) -> None:
        """A SYNC at ``now_s``: the running cycle ends, the next begins."""
        if self.opened_s is not None:
            interval = now_s - self.opened_s
            self.cycles += 1
            self.total_bits += self.bits
            self.total_s += interval
            if interval <= self.max_interval_s:
                self.max_bits = max(self.max_bits, self.bits)
        self.opened_s = now_s
        self.bits = 0


class BusTap(can.BusABC):
    """A python-can bus around ``bus`` that counts (and logs) every frame.

    Args:
        bus: the bus python-can opened (shut down with this one).
        log_path: where python-can's writer puts every frame, or None.

    Attributes:
        load: the bits per cycle (:class:`CycleLoad`).
    """

    def __init__(self, bus: can.BusABC, log_path: str | None = None):
        self.inner = bus
        self.channel_info = f"{bus.channel_info} (tapped)"
        self.load = CycleLoad()
        self._lock = threading.Lock()
        self._log = can.Logger(log_path) if log_path else None
        self._logged_s = 0.0  # the newest time stamp logged (time.time)
        super().__init__(channel=getattr(bus, "channel", None))

    def _account(self, msg: can.Message, received: bool) -> None:
        with self._lock:
            if msg.arbitration_id == SYNC_COB_ID:
                self.load.close(time.monotonic())
            self.load.bits += _WORST[min(len(msg.data), 8)]
            if self._log is not None:
                # our own frame stamped now, as a transmission; a received one keeps its
                # arrival time unless a frame logged before it is newer (the log's times
                # never go back, as CAN tools expect); the writer's own channel number
                # (a bus's channel name may end in digits that are no CAN channel)
                stamp = max(msg.timestamp if received else time.time(), self._logged_s)
                self._logged_s = stamp
                self._log.on_message_received(can.Message(
                    timestamp=stamp, arbitration_id=msg.arbitration_id,
                    is_extended_id=msg.is_extended_id, data=msg.data,
                    is_remote_frame=msg.is_remote_frame, is_rx=received))

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)
        self._account(msg, False)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        # the inner bus's own receive, not its recv(): one filtering and timeout loop (this
        # bus's) per frame is enough, and the receive thread handles every frame
        msg, filtered = self.inner._recv_internal(timeout)
        if msg is not None:
            self._account(msg, True)
        return msg, filtered

    def fileno(self) -> int:
        return self.inner.fileno()

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()
        with self._lock:
            if self._log is not None:
                self._log.stop()
                self._log = None


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
    try:
        return BusTap(bus, link.log)
    except (OSError, ValueError) as e:
        bus.shutdown()
        raise AdapterError(f"{link.url!r}: cannot write the log {link.log!r}: {e}") from e
