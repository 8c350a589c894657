"""``can://INTERFACE/CHANNEL``, controller side: a small CiA 402 master for one drive,
or one per axis (``axes=N``: nodes ``node`` .. ``node + N - 1``, a
:class:`~io_adapters.messages.SetpointGroup` and
:class:`~io_adapters.messages.FeedbackGroup` of N axes, axis i on node ``node + i``).

Plain python-can, no receive thread: :meth:`send_setpoint` sends the RPDOs of the
setpoint's mode (of every axis, each node's in turn, after checking them all) and then
one SYNC; :meth:`recv_feedback` reads the bus until TPDO1-3 of every node have arrived
and turns them into a :class:`~io_adapters.messages.Feedback` (per axis; a group's
common fields are axis 0's).  The master
takes only the drive's TPDOs and heartbeat and skips every other frame, so it never takes
its own RPDOs or SYNC for input (``udp_multicast`` hands every process its own frames).
On ``socketcan`` the kernel filters for it; on the other buses it reads every frame and
skips them itself: python-can filters those in software, and its ``recv(0)`` returns
None on meeting a filtered frame with more frames queued behind it, so a poll per cycle
would fall behind the master's own echoes.
The default PDO mapping and the units are those of :mod:`io_adapters.cia402_objects`, the
URL :mod:`io_adapters.can_url`'s; the master leaves the drive's mapping as it is.

Setpoint to RPDOs, per mode (6060h = ``mode``)::

    CSP  RPDO1 (6040h, 6060h), RPDO2 (607Ah, 60B1h), RPDO4 (6071h = 0, 60B2h = iq_ref_a)
    CSV  RPDO1, RPDO3 (60FFh), RPDO4 (6071h = 0, 60B2h = iq_ref_a)
    CST  RPDO1, RPDO4 (6071h = iq_ref_a, 60B2h = 0)

Positions and speeds are rounded to whole increments; currents to per mille of
``rated_current_ma``.  A setpoint the wire cannot carry raises
:class:`~io_adapters.base.FrameError` when sent, naming the field: another mode
(MODE_VOLTAGE), a non-zero ``id_ref_a``, a non-finite value or one outside its object's
range.

TPDOs to Feedback: ``statusword`` 6041h, ``fault`` the drive's error code 603Fh,
``encoder_counts`` 6064h, ``velocity_counts_s`` 606Ch, ``iq_a`` 6078h per mille,
``scale_counts`` 60E4h:01; ``time_s`` and ``id_a`` are 0 (not on this wire).  The drive
sends at SYNC k the feedback of the cycle SYNC k-1 started, so ``seq`` is the seq of the
setpoint sent with SYNC k-1.  Each SYNC carries a counter byte (CiA 301, 1-240) and the
drive echoes which SYNC sent a TPDO set (:data:`io_adapters.can_node.SW_ECHO`, bits 8,
14-15 of the statusword, removed here), so a set that comes late is labelled with the
SYNC it answers, not taken for the answer to the last one; without the echo (another
drive) the set is taken for the answer to the last SYNC sent.  The drive's clock is not
on the wire either: ``sp_t_ns`` = ``sp_rx_ns`` and ``t_ns`` are the ``t_ns`` of the
setpoints sent with SYNC k-1 and SYNC k (stamped as their RPDOs and SYNC went out), so
:meth:`~io_adapters.messages.Feedback.round_trip_ns` is the time from sending SYNC k to
taking the TPDO set it brought back.

A node that starts with a PDO configuration the bus cannot carry (its EMCY FF20h) makes
:meth:`recv_feedback` raise :class:`~io_adapters.base.AdapterError` with the load it
needs.

With ``heartbeat=ID:MS`` the master produces a heartbeat (700h + ID, state OPERATIONAL)
at most every MS ms, sent after a SYNC, for a drive that consumes it (1016h).
The master sends NMT "start remote node" when opened and again whenever the drive
reports boot-up or PRE-OPERATIONAL (its heartbeat), so either side may start first.
Counted in :attr:`stats`: ``malformed`` TPDOs (wrong DLC, remote frames), ``lost`` TPDO
sets left incomplete (a TPDO came again before the other two).
"""

import math
import time

import can

from io_adapters.base import AdapterError, Endpoint, FrameError, Role
from io_adapters.can_catalog import (
    EMCY_BASE,
    HEARTBEAT_BASE,
    INT_RANGE,
    NMT_BOOT_UP,
    NMT_COB_ID,
    NMT_OPERATIONAL,
    NMT_PRE_OPERATIONAL,
    NMT_START,
    SYNC_COB_ID,
    spec,
)
from io_adapters.can_cia402 import CanDriveEndpoint
from io_adapters.can_node import ECHO_SHIFT, EMCY_PLAN_OVERLOAD, SW_ECHO, SW_ECHO_MASK
from io_adapters.can_tap import open_bus
from io_adapters.can_url import CanLink
from io_adapters.cia402_objects import amps, permille, rpdo_layouts, tpdo_layouts
from io_adapters.messages import (
    MODE_CSP,
    MODE_CST,
    MODE_CSV,
    Feedback,
    FeedbackGroup,
    Setpoint,
    SetpointGroup,
    axis_records,
)

#: RPDOs (0-based) sent in each mode, RPDO1 first
MODE_RPDOS = {MODE_CSP: (0, 1, 3), MODE_CSV: (0, 2, 3), MODE_CST: (0, 3)}
#: the SYNC counter runs 1 .. this (CiA 301's largest overflow value, a multiple of 4)
SYNC_COUNTER_MAX = 240
STANDARD_ID_MASK = 0x7FF


def _wire_int(sp: Setpoint, name: str, field: str, wire_value: float,
              obj: tuple[int, int]) -> int:
    """``wire_value`` (``sp.field`` in wire units) rounded into the type of ``obj``;
    FrameError naming the record ``name`` and the field if it does not fit."""
    lo, hi = INT_RANGE[spec(*obj).data_type]
    if not math.isfinite(wire_value) or not lo <= round(wire_value) <= hi:
        raise FrameError(f"{name}.{field}={getattr(sp, field)!r} does not fit "
                         f"{obj[0]:04X}h ({lo} to {hi} on the wire)")
    return round(wire_value)


class CanMasterEndpoint(Endpoint):
    """The controller side of ``can://`` (see the module docstring); opened through
    :meth:`io_adapters.can_cia402.CanDriveEndpoint.from_url`.

    What a loop needs to know of this link (:mod:`hil.runtime.sync`):

    Attributes:
        sync_producer: each setpoint sent ends with SYNC, which starts the drive's cycle;
            the drive locks its cycle to it, not the master to the drive.
        feedback_delay_ticks: the feedback read before the setpoint of cycle k answers
            the setpoint of cycle k-2 (the drive answers SYNC k-1 at SYNC k): one tick
            more than lock-step timing.
        drive_clock: False: the drive's time (``Feedback.time_s``) is not on this wire.
        lag_is_age: True: a set labelled with an older SYNC than that (it came late) is
            that many cycles old, since the drive echoes the SYNC that sent it; a loop
            extrapolates it over the excess as over a missing one.
    """

    sync_producer = True
    feedback_delay_ticks = 1
    drive_clock = False
    lag_is_age = True

    @classmethod
    def from_url(cls, url: str, role: Role | str) -> Endpoint:
        return CanDriveEndpoint.from_url(url, role)

    def __init__(self, link: CanLink):
        super().__init__(Role.CONTROLLER)
        self.link = link
        self._rpdos = tuple(rpdo_layouts(n) for n in link.nodes)
        self._rpdo_msgs = tuple(tuple(can.Message(arbitration_id=p.cob_id, is_extended_id=False,
                                                  data=bytearray(p.frame.size)) for p in pdos)
                                for pdos in self._rpdos)
        self._sync = can.Message(arbitration_id=SYNC_COB_ID, is_extended_id=False,
                                 data=bytearray(1))
        self._n = 0                    # SYNCs sent
        self._history = [(0, 0)] * 8   # (seq, t_ns) of SYNC n at n & 7
        self._starts = {n: can.Message(arbitration_id=NMT_COB_ID, is_extended_id=False,
                                       data=bytes((NMT_START, n))) for n in link.nodes}
        # TPDO1-3 of axis a are slots 3a .. 3a + 2
        self._tpdos = tuple(p for n in link.nodes for p in tpdo_layouts(n))
        self._tpdo_slot = {p.cob_id: k for k, p in enumerate(self._tpdos)}
        self._per_axis = len(self._tpdos) // link.axes
        self._heartbeats = {HEARTBEAT_BASE + n: n for n in link.nodes}
        self._emcys = {EMCY_BASE + n: n for n in link.nodes}
        self._heartbeat = None if link.heartbeat is None else can.Message(
            arbitration_id=HEARTBEAT_BASE + link.heartbeat[0], is_extended_id=False,
            data=bytes((NMT_OPERATIONAL,)))
        self._heartbeat_s = 0.0 if link.heartbeat is None else link.heartbeat[1] * 1e-3
        self._heartbeat_due = 0.0
        self._values: list[tuple] = [()] * len(self._tpdos)
        self._got = 0
        self._all = (1 << len(self._tpdos)) - 1
        self._seq = [0, 0]      # seq of the setpoints sent with the last two SYNCs
        self._sync_ns = [0, 0]  # and when those SYNCs were sent
        wanted = [*self._tpdo_slot, *self._heartbeats, *self._emcys]
        self.bus = open_bus(link, can_filters=[
            {"can_id": i, "can_mask": STANDARD_ID_MASK, "extended": False} for i in wanted]
            if link.interface == "socketcan" else None)
        try:
            for start in self._starts.values():
                self._bus_send(start)
        except AdapterError:
            self.bus.shutdown()
            raise

    def _bus_send(self, msg: can.Message) -> None:
        try:
            self.bus.send(msg)
        except can.CanError as e:
            raise AdapterError(f"{self!r}: send failed: {e}") from e

    def _records(self, message, what: str) -> tuple:
        records = axis_records(message)
        if len(records) != self.link.axes:
            raise FrameError(f"{what} of {len(records)} axes; this link has {self.link.axes} "
                             f"(axes={self.link.axes})")
        return records

    # -- setpoint to RPDOs + SYNC --------------------------------------------------------
    def _pack(self, sp: Setpoint, name: str, axis: int) -> tuple[int, ...]:
        """Pack the RPDOs of ``sp`` for the node of ``axis``; returns which to send.
        FrameError naming ``name`` and the field if the wire cannot carry it."""
        pdos = MODE_RPDOS.get(sp.mode)
        if pdos is None:
            raise FrameError(f"{name}.mode={sp.mode}: a CiA 402 drive on CAN takes "
                             f"CSP ({MODE_CSP}), CSV ({MODE_CSV}) or CST ({MODE_CST})")
        if sp.id_ref_a != 0.0:
            raise FrameError(f"{name}.id_ref_a={sp.id_ref_a!r}: no CiA 402 object "
                             "carries a d-current setpoint")
        if not 0 <= sp.controlword <= 0xFFFF:
            raise FrameError(f"{name}.controlword={sp.controlword!r} does not fit 6040h "
                             "(0 to 65535 on the wire)")
        current = _wire_int(sp, name, "iq_ref_a",
                            permille(sp.iq_ref_a, self.link.rated_current_ma), (0x6071, 0))
        torque, offset = (current, 0) if sp.mode == MODE_CST else (0, current)
        values = ((sp.controlword, sp.mode),
                  (_wire_int(sp, name, "target_position_counts", sp.target_position_counts,
                             (0x607A, 0)),
                   _wire_int(sp, name, "velocity_offset_counts_s", sp.velocity_offset_counts_s,
                             (0x60B1, 0))),
                  (_wire_int(sp, name, "target_velocity_counts_s", sp.target_velocity_counts_s,
                             (0x60FF, 0)),),
                  (torque, offset))
        for k in pdos:
            self._rpdos[axis][k].frame.pack_into(self._rpdo_msgs[axis][k].data, 0, *values[k])
        return pdos

    def _write(self, sp: Setpoint | SetpointGroup) -> bool:
        records = self._records(sp, "a setpoint")
        names = (("Setpoint",) if len(records) == 1 and records[0] is sp
                 else tuple(f"SetpointGroup.axes[{a}]" for a in range(len(records))))
        # every axis checked and packed before the first frame goes out
        sends = [self._pack(rec, name, a) for a, (rec, name) in enumerate(zip(records, names))]
        for msgs, pdos in zip(self._rpdo_msgs, sends):
            for k in pdos:
                self._bus_send(msgs[k])
        self._sync.data[0] = self._n % SYNC_COUNTER_MAX + 1  # = n + 1 modulo 4
        self._bus_send(self._sync)
        if self._heartbeat is not None and (now := time.monotonic()) >= self._heartbeat_due:
            self._bus_send(self._heartbeat)
            self._heartbeat_due = now + self._heartbeat_s
        self._n += 1
        self._seq[:] = self._seq[1], sp.seq
        self._sync_ns[:] = self._sync_ns[1], sp.t_ns
        self._history[self._n & 7] = (sp.seq, sp.t_ns)
        return True

    # -- TPDOs to feedback ---------------------------------------------------------------
    def _read(self, into: Feedback | FeedbackGroup, timeout_s: float | None) -> bool:
        records = self._records(into, "feedback")
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        wait = timeout_s
        try:
            while (msg := self.bus.recv(wait)) is not None:
                if self._accept(msg, into, records):
                    return True
                if deadline is not None:
                    wait = max(0.0, deadline - time.monotonic())
        except can.CanError as e:
            raise AdapterError(f"{self!r}: receive failed: {e}") from e
        return False

    def _accept(self, msg: can.Message, into, records: tuple) -> bool:
        """Take one frame; True once it completes the TPDO sets of every node, written
        into ``into``."""
        can_id = msg.arbitration_id
        node = self._heartbeats.get(can_id)
        if node is not None:
            if msg.data and msg.data[0] & 0x7F in (NMT_BOOT_UP, NMT_PRE_OPERATIONAL):
                self._bus_send(self._starts[node])
            return False
        node = self._emcys.get(can_id)
        if node is not None:
            self._check_emcy(node, msg.data)
            return False
        slot = self._tpdo_slot.get(can_id)
        if slot is None:
            return False
        layout = self._tpdos[slot]
        if msg.is_remote_frame or len(msg.data) != layout.frame.size:
            self.stats.malformed += 1
            return False
        bit = 1 << slot
        if self._got & bit:
            self.stats.lost += 1
            self._got = 0
        self._values[slot] = layout.frame.unpack(msg.data)
        self._got |= bit
        if self._got != self._all:
            return False
        self._got = 0
        for a, rec in enumerate(records):
            self._fill(rec, self._values[a * self._per_axis:(a + 1) * self._per_axis])
        if into is not records[0]:  # a group: the common fields are axis 0's
            first = records[0]
            into.seq, into.time_s = first.seq, first.time_s
            into.sp_t_ns, into.sp_rx_ns, into.t_ns = first.sp_t_ns, first.sp_rx_ns, first.t_ns
            into.tick_ns = 0
        self.stats.received += 1
        return True

    def _check_emcy(self, node: int, data: bytearray) -> None:
        """A node started with a PDO configuration the bus cannot carry (EMCY FF20h with
        the load in per mille and the cycle in µs): its answers will come late or not at
        all, so this master stops with an AdapterError saying why."""
        if len(data) == 8 and int.from_bytes(data[:2], "little") == EMCY_PLAN_OVERLOAD:
            load = int.from_bytes(data[3:5], "little") / 10
            cycle_us = int.from_bytes(data[5:8], "little")
            raise AdapterError(f"{self!r}: node {node}'s PDO configuration needs {load:g} % "
                               f"of the {cycle_us} µs communication cycle (1006h) at "
                               f"{self.link.bitrate} bit/s: its frames would wait and be "
                               "lost; map fewer PDOs or lengthen 1006h")

    def _fill(self, into: Feedback, values: list[tuple]) -> None:
        (statusword, _mode, error_code), (position, velocity), (current, _, scale) = values
        if statusword & SW_ECHO:
            # the drive says which SYNC sent this set: the last one sent with that
            # counter modulo 4 (a set 4 or more SYNCs late is taken for a newer one)
            n = self._n - (self._n - (statusword >> ECHO_SHIFT) & 3)
            into.seq, into.sp_t_ns = self._history[n - 1 & 7]
            into.t_ns = self._history[n & 7][1]
        else:
            into.seq, into.sp_t_ns, into.t_ns = self._seq[0], self._sync_ns[0], self._sync_ns[1]
        into.sp_rx_ns = into.sp_t_ns
        into.statusword = statusword & ~SW_ECHO_MASK
        into.fault = error_code
        into.time_s = 0.0
        into.encoder_counts = float(position)
        into.velocity_counts_s = float(velocity)
        into.iq_a = amps(current, self.link.rated_current_ma)
        into.id_a = 0.0
        into.scale_counts = float(scale)

    def _close(self) -> None:
        self.bus.shutdown()
