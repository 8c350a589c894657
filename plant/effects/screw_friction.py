"""Friction on the screw's rotation: its support bearings and its nut (issue 14 part 4).

Seed 000 puts rotational friction elements at the screw's end (its Table 1: "Ballscrew End
(BSE) ... Rot. frictional element") and sees static friction "on the guideways and the
ballscrew support bearings" (§5); seed 003 eq. 9 has the motor overcome a "Coulomb
friction torque and pre-load torque" T_b at the nut.  Neither gives a value.

Where each acts on the lumped chain (plant.effects.chain):

* a support bearing holds the screw against the ground: a Coulomb torque on the
  rotation of the screw's end node (node 1 at the motor, the last node at the far end);
  its viscous drag is the chain's ground damper there ([screw]
  bearing_viscous_nms_per_rad);
* the nut does not turn (the table's guides hold it), so the screw/nut relative motion is
  the screw's rotation at the nut, interpolated between the nodes j and j+1 around it with
  the nut's weight w (as :func:`plant.kernel.nut_coupling` does): a viscous torque and a
  Coulomb torque T_0 + mu (lead/2pi) |F_nut| act on that coordinate, spread back onto the
  two nodes with the same weights.  T_0 is the catalogues' preload (dynamic) torque, set by
  the nut's preload; mu makes it grow with the axial load.

Coulomb friction by velocity projection (a time-stepping, Moreau-type rule): the torque
that would stop the coordinate within this sub-step, -m_q (v_q/dt + a_q), limited to the
Coulomb level.  Below it the coordinate comes to rest and stays there (stiction with the
breakaway torque equal to the Coulomb level, no band to tune), above it the full Coulomb
torque opposes.  It needs the chain's forces of this sub-step in the scratch area, i.e.
the lumped (symplectic Euler) solver; the loader refuses these keys with TLM.  Unlike the
table's Karnopp model it has no Stribeck curve and no separate breakaway level.
"""

from numba import njit

from plant.layout import P_BRG_COULOMB, P_LEAD_RATIO, P_NUT_COULOMB, P_NUT_LOAD_FR, P_NUT_VISCOUS


@njit(cache=True, error_model="numpy", inline="always")
def coulomb_projection(p, po, s, so, n, i, w, level, dt):
    """Apply to nodes i, i+1 of a chain (params at ``po``, state at ``so``, ``n`` nodes) the
    Coulomb torque on the coordinate q = (1-w) x_i + w x_{i+1}: the torque that stops q in
    this sub-step, limited to ±``level`` (N·m); returns it (N·m, on q)."""
    vo = so + n
    fo = so + 2 * n
    m0 = p[po + i]
    m1 = p[po + i + 1]
    v = (1.0 - w) * s[vo + i] + w * s[vo + i + 1]
    acc = (1.0 - w) * s[fo + i] / m0 + w * s[fo + i + 1] / m1
    inv_mass = (1.0 - w) * (1.0 - w) / m0 + w * w / m1
    t = -(v / dt + acc) / inv_mass
    t = level if t > level else (-level if t < -level else t)
    s[fo + i] += (1.0 - w) * t
    s[fo + i + 1] += w * t
    return t


@njit(cache=True, error_model="numpy", inline="always")
def screw_friction(p, po, s, so, n, j, w, f_nut, dt):
    """Bearing and nut friction on the torsional chain (params at ``po``, state at ``so``,
    ``n`` nodes: motor, then the screw's nodes 1..n-1) for one sub-step, the chain's other
    forces already in its scratch area; the nut between screw nodes ``j`` and ``j+1``
    (chain nodes 1+j, 2+j) with weight ``w``, carrying ``f_nut`` (N)."""
    brg = p[P_BRG_COULOMB]
    if brg > 0.0:
        coulomb_projection(p, po, s, so, n, 1, 0.0, brg, dt)
        coulomb_projection(p, po, s, so, n, n - 2, 1.0, brg, dt)
    c = p[P_NUT_VISCOUS]
    if c > 0.0:
        vo = so + n
        t = -c * ((1.0 - w) * s[vo + 1 + j] + w * s[vo + 2 + j])
        s[so + 2 * n + 1 + j] += (1.0 - w) * t
        s[so + 2 * n + 2 + j] += w * t
    level = p[P_NUT_COULOMB] + p[P_NUT_LOAD_FR] * p[P_LEAD_RATIO] * abs(f_nut)
    if level > 0.0:
        coulomb_projection(p, po, s, so, n, 1 + j, w, level, dt)
