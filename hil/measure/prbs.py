"""Maximum-length pseudo-random binary sequences (PRBS) as excitation signals.

A Fibonacci linear-feedback shift register of order n runs through all 2^n - 1 non-zero
states when its feedback polynomial is primitive; its output bit sequence a[k] then has
period N = 2^n - 1, holds 2^(n-1) ones and 2^(n-1) - 1 zeros, and, mapped to ±A, has the
two-level circular autocorrelation N·A² at lag 0 and -A² at every other lag: a flat
spectrum |U_k|² = (N + 1)·A² at every non-zero frequency bin.

The polynomial x^n + sum(x^e) + 1 gives the recurrence a[k + n] = XOR over e of a[k + e],
with a[k] for e = 0 (the constant term).  Polynomials: the maximal-length tap table of
Xilinx application note XAPP 052 (P. Alfke, "Efficient Shift Registers, LFSR Counters,
and Long Pseudo-Random Sequence Generators", 1996, taps n, m, ... read as x^n + x^m + ... + 1);
trinomials where one is primitive, pentanomials else.

The measuring functions of a SINUMERIK drive set the excitation bandwidth by holding each
bit for several controller cycles; ``hold`` does the same here: the spectrum then follows
sinc²(f·hold·dt) with its first zero at 1 / (hold·dt).
"""

from dataclasses import dataclass

import numpy as np

#: order n -> exponents of the middle terms and the constant term of the primitive
#: feedback polynomial x^n + ... + 1 (XAPP 052 table).
POLYNOMIALS: dict[int, tuple[int, ...]] = {
    5: (3, 0),                # x^5 + x^3 + 1
    6: (5, 0),                # x^6 + x^5 + 1
    7: (6, 0),                # x^7 + x^6 + 1
    8: (6, 5, 4, 0),          # x^8 + x^6 + x^5 + x^4 + 1
    9: (5, 0),                # x^9 + x^5 + 1
    10: (7, 0),               # x^10 + x^7 + 1
    11: (9, 0),               # x^11 + x^9 + 1
    12: (6, 4, 1, 0),         # x^12 + x^6 + x^4 + x + 1
    13: (4, 3, 1, 0),         # x^13 + x^4 + x^3 + x + 1
    14: (5, 3, 1, 0),         # x^14 + x^5 + x^3 + x + 1
    15: (14, 0),              # x^15 + x^14 + 1
    16: (15, 13, 4, 0),       # x^16 + x^15 + x^13 + x^4 + 1
    17: (14, 0),              # x^17 + x^14 + 1
    18: (11, 0),              # x^18 + x^11 + 1
    19: (6, 2, 1, 0),         # x^19 + x^6 + x^2 + x + 1
    20: (17, 0),              # x^20 + x^17 + 1
}


class ExcitationError(ValueError):
    """An excitation was asked for with an impossible order, amplitude or timing."""


@dataclass(frozen=True)
class Excitation:
    """A PRBS excitation signal, ready to be added to a setpoint cycle by cycle.

    ``signal`` has shape (periods · sequence_length · hold,), values ±amplitude in the
    unit of the setpoint it excites; sample k is applied at time k · dt_s.
    """

    signal: np.ndarray
    dt_s: float
    bit_period_s: float
    sequence_length: int
    hold: int
    periods: int
    amplitude: float
    order: int

    @property
    def period_samples(self) -> int:
        """Samples in one period of the sequence: sequence_length · hold."""
        return self.sequence_length * self.hold


def mls_bits(order: int) -> np.ndarray:
    """One period of the maximum-length sequence of ``order`` (5..20), as uint8 bits of
    shape (2^order - 1,), starting from the all-ones register state."""
    if order not in POLYNOMIALS:
        raise ExcitationError(f"PRBS order {order} not in {min(POLYNOMIALS)}..{max(POLYNOMIALS)}")
    mask = sum(1 << e for e in POLYNOMIALS[order])
    length = (1 << order) - 1
    register = length
    bits = np.empty(length, dtype=np.uint8)
    for k in range(length):
        bits[k] = register & 1
        feedback = (register & mask).bit_count() & 1
        register = (register >> 1) | (feedback << (order - 1))
    return bits


def prbs(order: int, amplitude: float, dt_s: float, *, hold: int = 1,
         periods: int = 2) -> Excitation:
    """A ±``amplitude`` PRBS of ``order`` (period 2^order - 1 bits), each bit held for
    ``hold`` samples of ``dt_s`` seconds, repeated ``periods`` times (the first period is
    usually discarded as transient, the others averaged)."""
    if not amplitude > 0.0 or not np.isfinite(amplitude):
        raise ExcitationError(f"PRBS amplitude must be positive and finite, got {amplitude}")
    if not dt_s > 0.0 or not np.isfinite(dt_s):
        raise ExcitationError(f"PRBS sample time must be positive, got {dt_s} s")
    if hold < 1 or periods < 1:
        raise ExcitationError(f"PRBS hold and periods must be >= 1, got {hold} and {periods}")
    bits = mls_bits(order)
    one_period = np.repeat(np.where(bits == 1, amplitude, -amplitude), hold)
    return Excitation(signal=np.tile(one_period, periods), dt_s=float(dt_s),
                      bit_period_s=hold * float(dt_s), sequence_length=bits.size, hold=hold,
                      periods=periods, amplitude=float(amplitude), order=order)
