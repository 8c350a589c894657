"""Measurement delay: the measured signals reach the outputs N whole PWM periods late.

The signals the drive and the controller measure (motor encoder counts, linear-scale
counts, measured d and q currents) are sampled at the end of every PWM period into a
ring of N+1 slots per signal in the state vector (at ``P_SOFF_DELAY``)::

    so + c (N+1) + slot     signal c (0 encoder, 1 scale, 2 i_d, 3 i_q), slot 0..N

After a sample is written to slot ``head``, slot ``(head+1) mod (N+1)`` holds the
sample of N periods earlier, which is what the outputs show.  The ring is filled with
the present signals at reset, so the first N periods show the rest state.  The delay
lives on the PWM grid: a kernel call that ends inside a period shows the sample of the
last completed period, N periods back (a drive calls once per period, so it sees exactly
N periods).  A faulty encoder's reading (noise, lost counts: :mod:`plant.effects.faults`)
is what is sampled, with or without a delay.
"""

from numba import njit

from plant.effects.faults import encoder_reading
from plant.effects.sensors import counts
from plant.layout import (
    P_DELAY_N,
    P_ENC_COUNTS_PER_RAD,
    P_ENC_ORIGIN,
    P_ENC_ROUND,
    P_FAULTS,
    P_SCALE_ORIGIN,
    P_SCALE_RES,
    P_SOFF_DELAY,
    P_SOFF_ROT,
    S_DELAY_HEAD,
    S_ID_MEAS,
    S_IQ_MEAS,
    S_TABLE_X,
)

N_DELAYED = 4  # signals in the ring


def ring_size(n_periods: int) -> int:
    """State entries the ring of a delay of ``n_periods`` uses (0 without a delay)."""
    return N_DELAYED * (n_periods + 1) if n_periods > 0 else 0


@njit(cache=True, error_model="numpy")
def measured_now(p, s):
    """The undelayed measured signals: (encoder counts, scale counts, i_d, i_q in A)."""
    motor = s[int(p[P_SOFF_ROT])] - p[P_ENC_ORIGIN]
    if p[P_FAULTS] > 0.0:
        enc = encoder_reading(p, s, motor)
    else:
        enc = counts(motor, p[P_ENC_COUNTS_PER_RAD], p[P_ENC_ROUND])
    res = p[P_SCALE_RES]
    scale = (counts(s[S_TABLE_X] - p[P_SCALE_ORIGIN], 1.0 / res, p[P_ENC_ROUND])
             if res > 0.0 else 0.0)
    return enc, scale, s[S_ID_MEAS], s[S_IQ_MEAS]


@njit(cache=True, error_model="numpy")
def delay_push(p, s):
    """End of a PWM period: store the present measured signals as the newest sample."""
    n1 = int(p[P_DELAY_N]) + 1
    head = int(s[S_DELAY_HEAD]) + 1
    head = 0 if head >= n1 else head
    s[S_DELAY_HEAD] = head
    so = int(p[P_SOFF_DELAY])
    enc, scale, i_d, i_q = measured_now(p, s)
    s[so + head] = enc
    s[so + n1 + head] = scale
    s[so + 2 * n1 + head] = i_d
    s[so + 3 * n1 + head] = i_q


@njit(cache=True, error_model="numpy")
def delay_fill(p, s):
    """Fill every slot with the present measured signals (at reset)."""
    n1 = int(p[P_DELAY_N]) + 1
    s[S_DELAY_HEAD] = 0.0
    for _ in range(n1):
        delay_push(p, s)


@njit(cache=True, error_model="numpy")
def measured_delayed(p, s):
    """The measured signals of N PWM periods ago (as :func:`measured_now`)."""
    if p[P_DELAY_N] <= 0.0:
        return measured_now(p, s)
    n1 = int(p[P_DELAY_N]) + 1
    oldest = int(s[S_DELAY_HEAD]) + 1
    oldest = 0 if oldest >= n1 else oldest
    so = int(p[P_SOFF_DELAY])
    return s[so + oldest], s[so + n1 + oldest], s[so + 2 * n1 + oldest], s[so + 3 * n1 + oldest]
