"""What travels between a controller and the emulated drive, whatever the transport.

Every adapter carries these two records; how it encodes them is its own business
(see each adapter module for its wire schema).

One :class:`Setpoint` goes from the controller to the drive and one
:class:`Feedback` comes back every cycle.  Both are small mutable records
that their owner allocates once and overwrites every cycle.  Feedback carries
raw sensor values (encoder and scale counts, the sampled current) as a real
drive reports them; the controller converts them with its own machine data.

Timestamps are integer nanoseconds of ``time.monotonic_ns()`` on the machine
that takes them; the adapters stamp them, so a loop never sets them.  Only
differences of two stamps from the same machine mean anything, which is why
:meth:`Feedback.round_trip_ns` pairs them that way.  Fields marked *local*
are stamped by the receiving adapter and never sent.
"""

import math
from dataclasses import dataclass
from typing import NamedTuple

#: CiA 402 modes of operation used on the wire (6060h values)
MODE_CSP = 8  # cyclic synchronous position: the drive closes position and speed loops
MODE_CSV = 9  # cyclic synchronous velocity: the drive closes the speed loop
MODE_CST = 10  # cyclic synchronous torque: here the q-current setpoint in A
#: manufacturer-specific mode (negative values are reserved for vendors in CiA 402):
#: d-q voltage setpoints, for controllers that close the current loop themselves
MODE_VOLTAGE = -1

#: 60FDh digital inputs (:attr:`Feedback.digital_inputs`): negative and positive limit
#: switch, home switch (CiA 402)
DI_NEGATIVE_LIMIT, DI_POSITIVE_LIMIT, DI_HOME_SWITCH = 1 << 0, 1 << 1, 1 << 2

#: why an adapter refused a setpoint (:meth:`SetpointBounds.refusal`; 0: taken)
REFUSED_NONFINITE = 1  # a NaN or infinite value in any float field
REFUSED_MODE = 2       # a mode (6060h) the drive does not take
REFUSED_RANGE = 3      # a value beyond the drive's bound


@dataclass(slots=True)
class Setpoint:
    """Controller -> drive, one per cycle.

    Attributes:
        seq: sequence number (wraps at 2**32).
        controlword: CiA 402 controlword (6040h).
        mode: MODE_CSP, MODE_CSV, MODE_CST or MODE_VOLTAGE.
        target_position_counts: position setpoint in motor-encoder increments (MODE_CSP;
            CiA 402 607Ah with the position factor 1).
        target_velocity_counts_s: speed setpoint in increments/s (MODE_CSV; 60FFh).
        velocity_offset_counts_s: speed feed-forward in increments/s (MODE_CSP; 60B1h).
        iq_ref_a, id_ref_a: current setpoints in A (MODE_CST; in MODE_CSP and MODE_CSV
            iq_ref_a is added to the drive's speed-controller output as a feed-forward).
        ud_v, uq_v: voltage setpoints in V (MODE_VOLTAGE).
        t_ns: controller clock when the adapter sent it, ns (set by ``send_setpoint``).
        rx_ns: *local*, drive clock when the adapter received it, ns (set by
            ``recv_setpoint``).
    """
    seq: int = 0
    controlword: int = 0
    mode: int = MODE_CST
    target_position_counts: float = 0.0
    target_velocity_counts_s: float = 0.0
    velocity_offset_counts_s: float = 0.0
    iq_ref_a: float = 0.0
    id_ref_a: float = 0.0
    ud_v: float = 0.0
    uq_v: float = 0.0
    t_ns: int = 0
    rx_ns: int = 0


@dataclass(slots=True)
class Feedback:
    """Drive -> controller, one per cycle.

    Attributes:
        seq: sequence number of the setpoint this answers.
        statusword: CiA 402 statusword (6041h).
        time_s: drive time at the end of the cycle.
        encoder_counts: motor encoder, whole counts (CiA 402 position actual, 6064h).
        scale_counts: linear scale, whole counts (0 without a scale).
        velocity_counts_s: the drive's speed actual value, increments/s (606Ch): the
            encoder difference over the drive's speed cycle.
        iq_a, id_a: sampled currents in A.
        fault: the drive's error code, CiA 402 603Fh (0 = none; hil.drive.faults).
        digital_inputs: CiA 402 60FDh: bit 0 negative and bit 1 positive limit switch,
            bit 2 home switch (:data:`DI_NEGATIVE_LIMIT` ...).
        index_marks: the encoder's index marks below its position, a whole number: it
            changes by one each time the axis passes a mark.
        index_counts: where the mark last passed lies, in the units of ``encoder_counts``
            (its position actual value; 0.0 until one is passed): what a drive's
            reference-mark latch gives.
        sp_t_ns: ``t_ns`` of the latest setpoint the drive's adapter received
            (controller clock, ns; set by ``send_feedback``).
        sp_rx_ns: drive clock when that setpoint arrived, ns (set by ``send_feedback``).
        t_ns: drive clock when the adapter sent this feedback, ns (set by ``send_feedback``).
        tick_ns: drive clock at the start of the tick that read the setpoint and produced
            this feedback, ns (set by the drive's loop; 0: the drive does not say).  Gives a
            controller the drive's tick phase, which arrival stamps do not.
        rx_ns: *local*, controller clock when the adapter received it, ns (set by
            ``recv_feedback``).
    """
    seq: int = 0
    statusword: int = 0
    time_s: float = 0.0
    encoder_counts: float = 0.0
    scale_counts: float = 0.0
    velocity_counts_s: float = 0.0
    iq_a: float = 0.0
    id_a: float = 0.0
    fault: int = 0
    digital_inputs: int = 0
    index_marks: int = 0
    index_counts: float = 0.0
    sp_t_ns: int = 0
    sp_rx_ns: int = 0
    t_ns: int = 0
    tick_ns: int = 0
    rx_ns: int = 0

    def round_trip_ns(self) -> int:
        """Transport round trip of the setpoint this feedback answers, ns: from the
        controller sending it to the controller receiving this feedback, less the time
        the drive held it, ``(rx_ns - sp_t_ns) - (t_ns - sp_rx_ns)``."""
        return (self.rx_ns - self.sp_t_ns) - (self.t_ns - self.sp_rx_ns)


@dataclass(frozen=True, slots=True)
class SetpointBounds:
    """What one drive takes, wire units; ``SetpointBounds()`` = finite values, any mode of
    MODE_CSP/CSV/CST/VOLTAGE, counts within 2**53 (beyond, increments are not exact in
    float64).  Every bound is inclusive (``|v| <= bound`` is taken) and holds for its
    fields whatever the mode, so a bad value in a field the mode does not use is refused
    too.  An adapter refuses a setpoint that :meth:`refusal` does not take (see
    :attr:`io_adapters.base.Endpoint.setpoint_bounds`).

    Attributes:
        position_counts: bound of ``|target_position_counts|``, increments.
        velocity_counts_s: bound of ``|target_velocity_counts_s|`` and
            ``|velocity_offset_counts_s|``, increments/s.
        current_a: bound of ``|iq_ref_a|`` and ``|id_ref_a|``, A.
        voltage_v: bound of ``|ud_v|`` and ``|uq_v|``, V.
        modes: the modes of operation (6060h values, ``MODE_*``) taken.
    """
    position_counts: float = 2.0**53
    velocity_counts_s: float = 2.0**53
    current_a: float = math.inf
    voltage_v: float = math.inf
    modes: frozenset = frozenset((MODE_CSP, MODE_CSV, MODE_CST, MODE_VOLTAGE))

    def __post_init__(self):
        for name in ("position_counts", "velocity_counts_s", "current_a", "voltage_v"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value >= 0.0):  # NaN fails too
                raise ValueError(f"SetpointBounds.{name}={value!r}: expected a number >= 0 "
                                 f"(inf: no bound)")
        if not all(type(m) is int for m in self.modes):
            raise ValueError(f"SetpointBounds.modes={self.modes!r}: expected 6060h values "
                             f"(int, MODE_*)")
        object.__setattr__(self, "modes", frozenset(self.modes))

    def refusal(self, mode: int, position: float, velocity: float, velocity_offset: float,
                iq: float, id_: float, ud: float, uq: float) -> int:
        """0 when taken, else REFUSED_NONFINITE (checked first, every field, whatever the
        mode), REFUSED_MODE, REFUSED_RANGE (every field, whatever the mode).  The values
        are a setpoint's fields in wire units (:class:`Setpoint`): mode of operation,
        position (increments), velocity and velocity offset (increments/s), q and d
        current (A), d and q voltage (V)."""
        # x * 0.0 is 0.0 for every finite x and NaN for NaN and +-inf, so one sum tests
        # all seven (a sum of the values themselves could overflow to inf)
        if (position * 0.0 + velocity * 0.0 + velocity_offset * 0.0 + iq * 0.0 + id_ * 0.0
                + ud * 0.0 + uq * 0.0) != 0.0:
            return REFUSED_NONFINITE
        if mode not in self.modes:
            return REFUSED_MODE
        if (abs(position) > self.position_counts or abs(velocity) > self.velocity_counts_s
                or abs(velocity_offset) > self.velocity_counts_s or abs(iq) > self.current_a
                or abs(id_) > self.current_a or abs(ud) > self.voltage_v
                or abs(uq) > self.voltage_v):
            return REFUSED_RANGE
        return 0


@dataclass(slots=True)
class SetpointGroup:
    """Controller -> drives of several axes, one message per cycle (wire version 2).

    ``axes`` holds one :class:`Setpoint` per axis, in the machine's axis order; of each only
    the per-axis fields travel (controlword, mode, targets, offsets, currents, voltages).
    The message's own ``seq``, ``t_ns`` and ``rx_ns`` mean what they mean on a
    :class:`Setpoint`; decoding copies ``seq`` into every axis's record, so each drive sees
    the cycle's number.  ``controlword`` reads axis 0's and sets every axis's (the whole
    machine disabled or enabled at once, as the runtime's alignment and safe state do).
    """
    axes: tuple[Setpoint, ...]
    seq: int = 0
    t_ns: int = 0
    rx_ns: int = 0

    @property
    def controlword(self) -> int:
        return self.axes[0].controlword

    @controlword.setter
    def controlword(self, value: int) -> None:
        for sp in self.axes:
            sp.controlword = value


@dataclass(slots=True)
class FeedbackGroup:
    """Drives -> controller for several axes, one message per cycle (wire version 2).

    ``axes`` holds one :class:`Feedback` per axis; of each only the per-axis fields travel
    (statusword, fault, encoder and scale counts, speed actual value, currents).  The
    message's ``seq``, ``time_s`` and stamps mean what they mean on a :class:`Feedback`
    (one drive cycle stepped every axis, so they are common); decoding copies ``seq``,
    ``time_s`` and the stamps into every axis's record.
    """
    axes: tuple[Feedback, ...]
    seq: int = 0
    time_s: float = 0.0
    sp_t_ns: int = 0
    sp_rx_ns: int = 0
    t_ns: int = 0
    tick_ns: int = 0
    rx_ns: int = 0

    def round_trip_ns(self) -> int:
        """As :meth:`Feedback.round_trip_ns`."""
        return (self.rx_ns - self.sp_t_ns) - (self.t_ns - self.sp_rx_ns)


class InjectRequest(NamedTuple):
    """A controller's request to inject a fault into the emulated axis (a test bench's
    message, no drive's: UDP and serial carry it, :mod:`io_adapters.codec`; on CAN it is a
    write of object 2F00h).  The adapter checks only its form; what the fault and its
    keys mean, and whether they are valid, is the emulator's business (``hil.inject``).

    Attributes:
        axis: the axis, 0-based in the machine's order.
        fault: the fault's name, as in the machine file's ``[inject.NAME]``.
        settings: its keys and values (numbers), as in that table.
    """
    axis: int
    fault: str
    settings: dict


def message_pair(n_axes: int) -> tuple[Setpoint | SetpointGroup, Feedback | FeedbackGroup]:
    """A fresh setpoint and feedback message for ``n_axes`` axes: the plain records for one
    axis (wire version 1, what every single-axis peer speaks), groups for more."""
    if n_axes < 1:
        raise ValueError(f"n_axes must be >= 1, got {n_axes}")
    if n_axes == 1:
        return Setpoint(), Feedback()
    return (SetpointGroup(tuple(Setpoint() for _ in range(n_axes))),
            FeedbackGroup(tuple(Feedback() for _ in range(n_axes))))


def axis_records(message) -> tuple:
    """The per-axis records of a message: ``(message,)`` for a plain record, else its axes."""
    return message.axes if isinstance(message, (SetpointGroup, FeedbackGroup)) else (message,)
