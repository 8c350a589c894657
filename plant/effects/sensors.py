"""Sensors: encoder counts, linear scale, sampled and quantized current."""

import math

import numpy as np
from numba import njit

from plant.effects.rng import gaussian
from plant.layout import P_I_LSB, P_I_NOISE, P_SEED, S_RNG_COUNTER


@njit(cache=True, error_model="numpy")
def counts(position, per_unit):
    """Whole counts an incremental encoder shows at ``position`` (rad or m).

    ``per_unit`` is counts per rad (or per m); 0 means no such encoder.
    """
    if per_unit <= 0.0:
        return 0.0
    # np.floor keeps a NaN position NaN (math.floor would turn it into a huge integer)
    return np.floor(position * per_unit)


@njit(cache=True, error_model="numpy")
def measure_current(p, s, current):
    """Current as the drive's ADC sees it (A): Gaussian noise, then quantization.

    Advances the noise counter in ``s`` only when noise is configured.
    """
    i = current
    if p[P_I_NOISE] > 0.0:
        i += p[P_I_NOISE] * gaussian(p[P_SEED], s[S_RNG_COUNTER])
        s[S_RNG_COUNTER] += 2.0
    lsb = p[P_I_LSB]
    if lsb > 0.0:
        i = lsb * math.floor(i / lsb + 0.5)
    return i
