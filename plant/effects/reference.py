"""Reference sensors for homing: the home switch on the table and the encoder's index marks.

* **Home switch** (``O_HOME_SWITCH``): a cam on the table's travel, on (1.0) while the table
  is below its edge ``P_HOME_SWITCH`` (m), a negative home switch in CiA 402's terms: on
  screw and linear axes from the negative end of the stroke up to the edge, by default
  half an index period above the start of the travel (:class:`plant.model.Plant`: 5 mm
  on a 10 mm lead, between two index marks, as a machine builder sets the cam so that a
  homing never meets the edge and a mark at once).  On a rotary table (no stroke) it is
  on over the half turn below the edge (rad), so it changes once in each direction per
  table revolution.
* **Index marks** (``O_INDEX``): the encoder's reference mark, once per motor revolution
  (``P_INDEX_PERIOD`` rad, 2 pi when 0) or, on a linear motor, every ``P_INDEX_PERIOD`` m.
  The output is the number of marks below the measured encoder position,
  ``floor(counts / counts_per_mark)``: a drive that sees it change from k to k +- 1
  knows a mark lies at ``max(k, k +- 1) * counts_per_mark`` counts exactly, as the
  hardware latch of a real drive's touch probe gives it.  It is the measured encoder's,
  so it lags with ``[sensors] delay_s`` as the counts do.
"""

import math

import numpy as np
from numba import njit

from plant.layout import P_ENC_COUNTS_PER_RAD, P_HOME_SWITCH, P_INDEX_PERIOD, P_STROKE


@njit(cache=True, error_model="numpy")
def counts_per_mark(p):
    """Encoder counts between two index marks."""
    period = p[P_INDEX_PERIOD] if p[P_INDEX_PERIOD] > 0.0 else 2.0 * math.pi
    return round(period * p[P_ENC_COUNTS_PER_RAD])


@njit(cache=True, error_model="numpy")
def home_switch(p, x):
    """1.0 while the home switch is on at table position ``x`` (m, rad on rotary
    tables), else 0.0."""
    below = x - p[P_HOME_SWITCH]
    if p[P_STROKE] <= 0.0:  # a rotary table: the half turn below the edge
        return 1.0 if below - 2.0 * math.pi * math.floor(below / (2.0 * math.pi)) >= math.pi \
            else 0.0
    return 1.0 if below < 0.0 else 0.0


@njit(cache=True, error_model="numpy")
def index_marks(p, counts):
    """Index marks below the encoder position ``counts`` (a whole number; NaN stays NaN)."""
    per_mark = counts_per_mark(p)
    if per_mark <= 0.0:
        return 0.0
    # np.floor keeps a NaN position NaN (math.floor would turn it into a huge integer)
    return np.floor(counts / per_mark)
