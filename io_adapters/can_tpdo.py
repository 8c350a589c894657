"""When a node's TPDOs go out, by their transmission types (CiA 301): synchronous ones at a
SYNC -- type 0 when their data changed, type n at every n-th SYNC since NMT start --
and event-driven ones (254, 255) when their data changed, no sooner than their inhibit
time after the last, and when their event timer runs out.  :class:`TpdoTimer` keeps, per
TPDO, what it last sent and when; the node packs the frames
(:meth:`io_adapters.can_node.DriveNode.pack`).
"""

import math
from collections.abc import Callable
from dataclasses import dataclass

import can

from io_adapters.can_pdo import PdoConfig

#: s: the difference of two monotonic times is rounded; an inhibit time or event timer
#: that has just run out counts as run out
TIME_EPS_S = 1e-9

Pack = Callable[..., bytes]  # (pdo, counter=None) -> the frame's bytes now


@dataclass
class TxState:
    """What a TPDO last sent: its bytes, when (monotonic s); SYNCs since NMT start."""
    data: bytes = b""
    sent_s: float = -math.inf
    syncs: int = 0


class TpdoTimer:
    """What each TPDO of one node last sent (:attr:`tx`, by TPDO number)."""

    def __init__(self):
        self.tx: dict[int, TxState] = {}

    def clear(self) -> None:
        """Nothing sent yet (an NMT reset)."""
        self.tx.clear()

    def restart(self) -> None:
        """NMT start: every TPDO counts its SYNCs afresh."""
        for state in self.tx.values():
            state.syncs = 0

    def _state(self, pdo: PdoConfig) -> TxState:
        state = self.tx.get(pdo.number)
        if state is None:
            state = self.tx[pdo.number] = TxState()
        return state

    @staticmethod
    def _message(pdo: PdoConfig, data: bytes) -> can.Message:
        return can.Message(arbitration_id=pdo.cob_id, is_extended_id=False, data=data)

    def sync_frames(self, tpdos: list[PdoConfig], pack: Pack, by_sync: bool,
                    counter: int | None, now_s: float) -> list[can.Message]:
        """The synchronous TPDOs due at a cycle start: at a SYNC (``by_sync``; its counter
        byte, if any, goes to ``pack``) as their types say, every one on the drive's own
        clock."""
        out = []
        for pdo in tpdos:
            if pdo.layout is None or pdo.event_driven:
                continue
            tx = self._state(pdo)
            if by_sync:
                tx.syncs += 1
            data = pack(pdo, counter if by_sync else None)
            due = (data != tx.data if pdo.trans_type == 0
                   else not by_sync or tx.syncs % pdo.trans_type == 0)
            if due:
                tx.data, tx.sent_s = data, now_s
                out.append(self._message(pdo, data))
        return out

    def event_frames(self, tpdos: list[PdoConfig], pack: Pack,
                     now_s: float) -> list[can.Message]:
        """The event-driven TPDOs due at ``now_s``: changed, and the inhibit time past
        since the last; or the event timer run out."""
        out = []
        for pdo in tpdos:
            if pdo.layout is None or not pdo.event_driven:
                continue
            tx = self._state(pdo)
            data = pack(pdo)
            since = now_s - tx.sent_s + TIME_EPS_S
            if ((data != tx.data and since >= pdo.inhibit_100us * 1e-4)
                    or (pdo.event_timer_ms and since >= pdo.event_timer_ms * 1e-3)):
                tx.data, tx.sent_s = data, now_s
                out.append(self._message(pdo, data))
        return out
