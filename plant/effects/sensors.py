"""Sensors: encoder counts, linear scale, sampled, quantized and clipped current.

Two conventions of the counts are machine-file keys ([sensors] encoder_rounding,
encoder_zero_at_start): a count is floor(x) or floor(x + 1/2) of the position in counts x,
and x is taken from the position at the last reset (the encoder's grid starts there) or
from 0.  Both hold for the motor encoder and the linear scale alike.
"""

import math

import numpy as np
from numba import njit

from plant.effects.rng import gaussian
from plant.layout import P_I_FULL_SCALE, P_I_LSB, P_I_NOISE, P_SEED, S_RNG_COUNTER


@njit(cache=True, error_model="numpy", inline="always")
def whole_counts(x, rounding):
    """The whole count shown at ``x`` counts: floor(x) for ``rounding`` 0 (an incremental
    encoder's edge counter), floor(x + 1/2) for 1 (the nearest count, halves up)."""
    # np.floor keeps a NaN position NaN (math.floor would turn it into a huge integer)
    if rounding > 0.0:
        return np.floor(x + 0.5)
    return np.floor(x)


@njit(cache=True, error_model="numpy")
def counts(position, per_unit, rounding):
    """Whole counts an encoder shows at ``position`` (rad or m, from its count 0).

    ``per_unit`` is counts per rad (or per m); 0 means no such encoder.  ``rounding``:
    P_ENC_ROUND (see :func:`whole_counts`).
    """
    if per_unit <= 0.0:
        return 0.0
    return whole_counts(position * per_unit, rounding)


@njit(cache=True, error_model="numpy")
def measure_current(p, s, current):
    """Current as the drive's ADC sees it (A): Gaussian noise, then quantization, then the
    full scale P_I_FULL_SCALE (0: none) clips it to +-full scale.

    Advances the noise counter in ``s`` only when noise is configured.
    """
    i = current
    if p[P_I_NOISE] > 0.0:
        i += p[P_I_NOISE] * gaussian(p[P_SEED], s[S_RNG_COUNTER])
        s[S_RNG_COUNTER] += 2.0
    lsb = p[P_I_LSB]
    if lsb > 0.0:
        i = lsb * math.floor(i / lsb + 0.5)
    full = p[P_I_FULL_SCALE]
    if full > 0.0:
        i = full if i > full else (-full if i < -full else i)
    return i
