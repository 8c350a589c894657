"""What travels between a controller and the emulated drive, whatever the transport.

Every adapter carries these two records; how it encodes them is its own business
(see each adapter module for its wire schema).

One :class:`Setpoint` goes from the controller to the drive and one
:class:`Feedback` comes back every cycle.  Both are small mutable records
that their owner allocates once and overwrites every cycle.  Feedback carries
raw sensor values (encoder and scale counts, the sampled current) as a real
drive reports them; the controller converts them with its own machine data.
"""

from dataclasses import dataclass

#: CiA 402 modes of operation used on the wire (6060h values)
MODE_CST = 10  # cyclic synchronous torque: here the q-current setpoint in A
#: manufacturer-specific mode (negative values are reserved for vendors in CiA 402):
#: d-q voltage setpoints, for controllers that close the current loop themselves
MODE_VOLTAGE = -1


@dataclass(slots=True)
class Setpoint:
    """Controller -> drive, one per cycle.

    Attributes:
        seq: sequence number (wraps at 2**32).
        controlword: CiA 402 controlword (6040h).
        mode: MODE_CST or MODE_VOLTAGE.
        iq_ref_a, id_ref_a: current setpoints in A (MODE_CST).
        ud_v, uq_v: voltage setpoints in V (MODE_VOLTAGE).
    """
    seq: int = 0
    controlword: int = 0
    mode: int = MODE_CST
    iq_ref_a: float = 0.0
    id_ref_a: float = 0.0
    ud_v: float = 0.0
    uq_v: float = 0.0


@dataclass(slots=True)
class Feedback:
    """Drive -> controller, one per cycle.

    Attributes:
        seq: sequence number of the setpoint this answers.
        statusword: CiA 402 statusword (6041h).
        time_s: drive time at the end of the cycle.
        encoder_counts: motor encoder, whole counts.
        scale_counts: linear scale, whole counts (0 without a scale).
        iq_a, id_a: sampled currents in A.
        fault: the plant's fault status (0 = none; plant.layout STATUS_*).
    """
    seq: int = 0
    statusword: int = 0
    time_s: float = 0.0
    encoder_counts: float = 0.0
    scale_counts: float = 0.0
    iq_a: float = 0.0
    id_a: float = 0.0
    fault: int = 0
