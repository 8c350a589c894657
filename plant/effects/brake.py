"""The motor's holding brake: a friction brake between the rotor (a linear motor's mover)
and the frame, closed or open as the plant's input ``I_BRAKE`` says.

Closed, it acts as Coulomb friction on the chain's first node by velocity projection, as
the screw's bearing friction does (:mod:`plant.effects.screw_friction`): the torque that
would stop the node within this sub-step, -m (v/dt + a), limited to the holding torque.
Below that level the node comes to rest and stays (the brake holds), above it the full
holding torque opposes (the brake slips).  It needs the chain's forces of this sub-step in
the scratch area, every other force on the node included: the lumped solver, called just
before the node's update.
"""

from numba import njit


@njit(cache=True, error_model="numpy", inline="always")
def holding_brake(p, po, s, so, n, level, dt):
    """Apply the closed brake's torque (at most ±``level``, N·m or N) to node 0 of a chain
    (params at ``po``, state at ``so``, ``n`` nodes) for one sub-step; returns it."""
    m = p[po]
    t = -(s[so + n] / dt + s[so + 2 * n] / m) * m
    t = level if t > level else (-level if t < -level else t)
    s[so + 2 * n] += t
    return t
