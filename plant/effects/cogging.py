"""Cogging / reluctance torque (force for linear motors), seed 001 and 002.

The disturbance is periodic in the electrical angle: a sum of harmonics whose
orders are in cycles per electrical revolution (seed 002 measured 1, 2 and 4 on
the LD386 linear motor: 1.39, 2.62 and 1.52 N).
"""

import math

from numba import njit

from plant.layout import P_COG_AMP, P_COG_N, P_COG_ORDER, P_COG_PHASE


@njit(cache=True, error_model="numpy", inline="always")
def cogging_torque(p, theta_e):
    """Cogging torque (N·m, or N) at electrical angle ``theta_e`` (rad)."""
    t = 0.0
    for k in range(int(p[P_COG_N])):
        t += p[P_COG_AMP + k] * math.sin(p[P_COG_ORDER + k] * theta_e + p[P_COG_PHASE + k])
    return t
