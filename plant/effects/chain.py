"""A one-dimensional chain of lumped inertias joined by spring-dampers.

The same code carries the torsional chain (motor rotor, coupling, screw
segments; coordinates in rad) and the axial chain of the ball screw
(coordinates in m).  Node ``i`` and node ``i+1`` are joined by link ``i``;
every node may also be tied to the ground (bearings) by a spring and a damper.

Params block of a chain of ``n`` nodes, starting at offset ``po``::

    po + 0      .. po + n     m       node inertia (kg·m² or kg)
    po + n      .. po + 2n    c_gnd   damper to ground (N·m·s/rad or N·s/m)
    po + 2n     .. po + 3n    k_gnd   spring to ground (N·m/rad or N/m)
    po + 3n     .. po + 4n-1  k_link  link stiffness
    po + 4n-1   .. po + 5n-2  c_link  link damping
    po + 5n-2   .. po + 6n-3  gap     link backlash, total dead-zone width (rad or m)

State block, starting at offset ``so``::

    so + 0    .. so + n     x      node positions
    so + n    .. so + 2n    v      node velocities
    so + 2n   .. so + 3n    f      force scratch: external forces are added here
                                   by the caller before the update
    so + 3n   .. so + 5n-2  waves  TLM wave variables (plant.effects.tlm)

Lumped stepping is semi-implicit (symplectic) Euler: velocities from the
forces at the start of the sub-step, positions from the new velocities.  It is
stable for ``omega_max * dt < 2`` without damping and conserves a slightly
perturbed energy, so an undamped chain neither gains nor loses energy over
long runs; its frequency error is ``(omega * dt)**2 / 24`` (relative).
"""

from numba import njit

from plant.effects.index import offset


def params_size(n: int) -> int:
    """Number of params entries a chain of ``n`` nodes uses."""
    return 6 * n - 3 if n > 0 else 0


def state_size(n: int) -> int:
    """Number of state entries a chain of ``n`` nodes uses."""
    return 5 * n - 2 if n > 0 else 0


@njit(cache=True, error_model="numpy", inline="always")
def dead_zone(delta, gap):
    """Spring deflection left after a backlash gap of total width ``gap``."""
    if gap <= 0.0:
        return delta
    half = 0.5 * gap
    if delta > half:
        return delta - half
    if delta < -half:
        return delta + half
    return 0.0


@njit(cache=True, error_model="numpy", inline="always")
def chain_internal_forces(p, po, s, so, n):
    """Write the chain's own spring, damper and ground forces into the scratch area.

    Overwrites ``s[so+2n : so+3n]``; external forces are added afterwards.  The
    link force is carried to the next node in a local variable rather than
    through memory, which keeps the loop free of store-to-load stalls.  The blocks'
    offsets are taken once as non-negative (:func:`plant.effects.index.offset`), so
    no access in the loop wraps; ``n`` >= 1.
    """
    xo = offset(so)
    vo = offset(so + n)
    fo = offset(so + 2 * n)
    c_gnd = offset(po + n)
    k_gnd = offset(po + 2 * n)
    k_link = offset(po + 3 * n)
    c_link = offset(po + 4 * n - 1)
    gaps = offset(po + 5 * n - 2)
    last = offset(n - 1)
    carry = 0.0
    x = s[xo]
    v = s[vo]
    for i in range(n - 1):
        x_next = s[xo + i + 1]
        v_next = s[vo + i + 1]
        gap = p[gaps + i]
        de = dead_zone(x_next - x, gap)
        fl = p[k_link + i] * de
        if de != 0.0 or gap <= 0.0:
            fl += p[c_link + i] * (v_next - v)
        s[fo + i] = carry + fl - p[k_gnd + i] * x - p[c_gnd + i] * v
        carry = -fl
        x = x_next
        v = v_next
    s[fo + last] = carry - p[k_gnd + last] * x - p[c_gnd + last] * v


@njit(cache=True, error_model="numpy", inline="always")
def chain_step(p, po, s, so, n, dt, hold):
    """Semi-implicit Euler update from the forces in the scratch area:
    v += dt * f / m, then x += dt * v.  Node ``hold`` (-1: none) is held at rest
    for this sub-step (Karnopp stiction on that node)."""
    vo = so + n
    fo = so + 2 * n
    for i in range(n):
        v = s[vo + i] + dt * s[fo + i] / p[po + i]
        if i == hold:
            v = 0.0
        s[vo + i] = v
        s[so + i] += dt * v


@njit(cache=True, error_model="numpy")
def chain_energy(p, po, s, so, n):
    """Kinetic plus elastic energy of the chain in J (backlash gaps respected)."""
    e = 0.0
    for i in range(n):
        v = s[so + n + i]
        x = s[so + i]
        e += 0.5 * p[po + i] * v * v + 0.5 * p[po + 2 * n + i] * x * x
    for i in range(n - 1):
        de = dead_zone(s[so + i + 1] - s[so + i], p[po + 5 * n - 2 + i])
        e += 0.5 * p[po + 3 * n + i] * de * de
    return e


@njit(cache=True, error_model="numpy", inline="always")
def chain_clear_forces(s, so, n):
    """Zero the force scratch area (the TLM solver takes external forces only)."""
    for i in range(n):
        s[so + 2 * n + i] = 0.0
