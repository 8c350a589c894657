"""Transmission-line-modelling (TLM) solver for the chains of plant.effects.chain.

Seed paper 003 (Moreno-Castaneda / Pislaru) models the feed drive as TLM
links and stubs: pulses are scattered at the nodes and the reflected pulses
are the incident pulses of the next step.  This module uses the standard
mechanical form of that idea (transmission-line elements of the Hopsan
simulator, Krus et al.); params and state use the layout of
``plant.effects.chain``.

Links.  Spring link ``i`` (stiffness ``k``, joining node ``i`` = end a and
node ``i+1`` = end b) is a lossless transmission line with a transit time of
exactly one sub-step ``dt`` and characteristic impedance ``Z = k*dt`` (N·s/m
or N·m·s/rad), so that its compliance ``dt/Z`` is ``1/k``.  ``F`` is the
compressive force in the line, ``u`` the velocity of an end *into* the line
(``u_a = v[i]``, ``u_b = -v[i+1]``); the line pushes node ``i`` with ``-F_a``
and node ``i+1`` with ``+F_b``.  Each end is a Thevenin source and the wave
variables ``c`` travel across in one sub-step::

    F_a(t) = c_a(t) + Z u_a(t)          c_a(t+dt) = c_b(t) + 2 Z u_b(t)
    F_b(t) = c_b(t) + Z u_b(t)          c_b(t+dt) = c_a(t) + 2 Z u_a(t)

Waves in the state block (``m = n - 1`` links)::

    so + 3n     .. so + 4n-1   c_a   wave arriving at the link's node-i end (N or N·m)
    so + 4n-1   .. so + 5n-2   c_b   wave arriving at the link's node-(i+1) end

Nodes.  With the waves of ``t+dt`` known, every node is solved on its own by
implicit (backward) Euler for its new velocity: a scalar linear equation, so
the step is explicit and needs no matrix solve.  Positions follow from
``x += dt * v_new`` as in the lumped stepper.

Parasitic inertia.  A line of transit time ``dt`` is a rod of inertia
``Z*dt = k*dt**2``.  Half of it is charged to each end: node ``i`` is given
the inertia ``max(m_i - dt**2 (k_left + k_right) / 2, 0)``, so the total
inertia is exact wherever the line inertia is smaller than the node inertia
(for a uniform chain: ``omega_max*dt <= 2``, the lumped stability limit;
at equality the nodes are massless and the TLM chain is the continuous rod
with one segment per wave transit).  Beyond that a node carries the excess
``dt**2 (k_left + k_right) / 2 - m_i``: stable, but the waves cannot cross a
segment faster than in one sub-step, so frequencies come out too low.

Damping.  Ground dampers are implicit in the node solve.  The link damper
acts on each node with the node's own new velocity and the neighbour's
velocity of the previous sub-step (the information the line delivers):
``c*(v_nb(t) - v_i(t+dt))``.  Both choices are passive.

Stability and energy.  Lines are lossless, node solves are backward Euler,
so the storage function of ``tlm_energy`` never increases without external
forces, for any ``dt > 0``: the solver is unconditionally stable.  The price
is numerical damping, about ``omega*dt/4`` of critical per mode, and a phase
error of order ``(omega*dt)**2``; the lagged link damper adds an inertia-like
error of relative order ``c*dt/m``.

Not supported: link backlash (``gap > 0``) is ignored here; the config loader
refuses TLM for chains with gaps.
"""

from numba import njit

from plant.effects.index import offset


@njit(cache=True, error_model="numpy", inline="always")
def node_inertia(p, po, n, i, dt):
    """Inertia of node ``i`` with the half line inertias subtracted (kg·m² or kg), >= 0."""
    par = 0.0
    if i > 0:
        par += p[po + 3 * n + i - 1]
    if i < n - 1:
        par += p[po + 3 * n + i]
    m = p[po + i] - 0.5 * dt * dt * par
    return m if m > 0.0 else 0.0


@njit(cache=True, error_model="numpy")
def tlm_init(p, po, s, so, n, dt):
    """Set the waves from the present x and v; a chain at rest keeps its spring forces.

    Each line is given the port force ``F = -k*dx + Z*(v[i+1]-v[i])/2`` at both
    ends (``dx = x[i+1]-x[i]``).  This makes the invariant
    ``(c_a+c_b)/2 + k*dx - Z*(v[i+1]-v[i])`` of the stepper zero, so the line
    force equals ``k*dx`` whenever the link comes to rest.
    """
    for i in range(n - 1):
        k = p[po + 3 * n + i]
        z = k * dt
        va = s[so + n + i]
        vb = s[so + n + i + 1]
        f = -k * (s[so + i + 1] - s[so + i]) + 0.5 * z * (vb - va)
        s[so + 3 * n + i] = f - z * va
        s[so + 4 * n - 1 + i] = f + z * vb


@njit(cache=True, error_model="numpy", inline="always")
def tlm_waves(p, po, s, so, n, dt):
    """Carry the waves across every line: incident waves of t+dt from ends at t."""
    vo = offset(so + n)
    wa = offset(so + 3 * n)
    wb = offset(so + 4 * n - 1)
    k_link = offset(po + 3 * n)
    for i in range(n - 1):
        z = p[k_link + i] * dt
        ca = s[wa + i]
        s[wa + i] = s[wb + i] - 2.0 * z * s[vo + i + 1]
        s[wb + i] = ca + 2.0 * z * s[vo + i]


@njit(cache=True, error_model="numpy", inline="always")
def tlm_nodes(p, po, s, so, n, dt):
    """Backward-Euler solve of every node against its lines' Thevenin sources.

    Node i: ``m (v' - v)/dt = f_ext + c_b[i-1] - c_a[i] - (Z[i-1] + Z[i]) v'
    - k_gnd (x + dt v') - c_gnd v' + c[i-1](v[i-1] - v') + c[i](v[i+1] - v')``
    with ``m`` from ``node_inertia`` and the neighbours' old velocities;
    then ``x += dt v'``.  The blocks' offsets are taken once as non-negative
    (:func:`plant.effects.index.offset`); the left neighbour's entries are read at
    ``i - 1`` only for ``i > 0``.
    """
    xo = offset(so)
    vo = offset(so + n)
    fo = offset(so + 2 * n)
    wa = offset(so + 3 * n)
    wb = offset(so + 4 * n - 1)
    c_gnd = offset(po + n)
    k_gnd = offset(po + 2 * n)
    k_link = offset(po + 3 * n)
    c_link = offset(po + 4 * n - 1)
    v_left = 0.0
    for i in range(n):
        v = s[vo + i]
        m = node_inertia(p, po, n, i, dt)
        kg = p[k_gnd + i]
        num = m * v / dt + s[fo + i] - kg * s[xo + i]
        den = m / dt + p[c_gnd + i] + kg * dt
        if i > 0:
            left = offset(i - 1)
            c = p[c_link + left]
            num += s[wb + left] + c * v_left
            den += p[k_link + left] * dt + c
        if i < n - 1:
            c = p[c_link + i]
            num += c * s[vo + i + 1] - s[wa + i]
            den += p[k_link + i] * dt + c
        v_new = num / den
        s[vo + i] = v_new
        s[xo + i] += dt * v_new
        v_left = v


@njit(cache=True, error_model="numpy")
def tlm_step(p, po, s, so, n, dt):
    """Advance the chain by one sub-step ``dt`` (s).

    On entry ``s[so+2n : so+3n]`` holds only the external forces on the nodes
    (held constant over the sub-step); it is left unchanged.  Updates x, v and
    the waves.
    """
    tlm_waves(p, po, s, so, n, dt)
    tlm_nodes(p, po, s, so, n, dt)


@njit(cache=True, error_model="numpy")
def tlm_energy(p, po, s, so, n, dt):
    """Stored energy of the TLM chain in J; never increases without external forces.

    Kinetic energy with the ``node_inertia`` values, ground springs, the
    lines' pulses in flight ``(c_a(t+dt)**2 + c_b(t+dt)**2) / (4k)`` and the
    lagged link dampers' ``c*dt*(v[i]**2 + v[i+1]**2)/2``.  Tends to
    ``chain.chain_energy`` as ``dt`` goes to 0.
    """
    e = 0.0
    for i in range(n):
        v = s[so + n + i]
        x = s[so + i]
        e += 0.5 * node_inertia(p, po, n, i, dt) * v * v + 0.5 * p[po + 2 * n + i] * x * x
    for i in range(n - 1):
        k = p[po + 3 * n + i]
        va = s[so + n + i]
        vb = s[so + n + i + 1]
        if k > 0.0:
            ca = s[so + 4 * n - 1 + i] - 2.0 * k * dt * vb
            cb = s[so + 3 * n + i] + 2.0 * k * dt * va
            e += (ca * ca + cb * cb) / (4.0 * k)
        e += 0.5 * p[po + 4 * n - 1 + i] * dt * (va * va + vb * vb)
    return e
