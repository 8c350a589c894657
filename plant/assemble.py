"""From a checked machine file to the kernel's flat arrays, and the linearised mechanics.

:func:`build` fills the params vector (layout in :mod:`plant.layout`) and
picks the integration sub-step; :func:`mechanics_matrices` assembles the mass,
stiffness and damping matrices of the same mechanics for modal analysis (used
to choose the sub-step and, in the tests, as an independent check of the
kernel's forces).

Sub-step choice: the mechanical chains are stepped with semi-implicit Euler,
stable for omega_max*dt < 2 and with a relative frequency error of about
(omega*dt)^2/24.  The automatic sub-step is the PWM period divided by the
smallest whole number n with omega_max*dt <= max_omega_dt (default 0.5: the
stiffest mode is off by at most 1 %, the modes a controller sees, far below
it, by much less).  The dampers are explicit too: a damper c on a mass m decays
as 1 - dt c/m per sub-step, unstable beyond dt c/m = 2, so omega_max is the larger
of the stiffest natural frequency and the largest |s| of the damped mechanics
(:func:`mechanics_rate`, issue 14 part 2).  The electrical states use exact exponential
decay and impose no limit.  A table with a stroke adds its end stops: the chains' modes with a stop
in contact and the contact's own rate (:mod:`plant.end_stops`) count toward omega_max.
The count of sub-steps is bounded (:mod:`plant.substeps`): a machine file asking for more
is refused with the largest stiffness that fits.
"""

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from plant import layout as L
from plant.config import MachineConfig, delay_periods
from plant.effects.chain import params_size, state_size
from plant.effects.delay import ring_size
from plant.effects.pmsm import first_order_kick_weights
from plant.end_stops import EndStops, check_substep, end_stops
from plant.errors import ConfigError
from plant.substeps import MAX_SUB_PER_PWM, PLANT_LIMIT, refusal

_MOTOR = {"dq": L.MOTOR_DQ, "first_order": L.MOTOR_FIRST_ORDER,
          "commutation": L.MOTOR_COMMUTATION}
_MECH = {"rigid": L.MECH_RIGID, "two_mass": L.MECH_TWO_MASS, "screw": L.MECH_SCREW}
_SOLVER = {"lumped": L.SOLVER_LUMPED, "tlm": L.SOLVER_TLM}


@dataclass(frozen=True)
class Chain:
    """A chain's arrays (see :mod:`plant.effects.chain`), each of shape (n,) or (n-1,)."""
    m: np.ndarray
    c_gnd: np.ndarray
    k_gnd: np.ndarray
    k_link: np.ndarray
    c_link: np.ndarray
    gap: np.ndarray

    @property
    def n(self) -> int:
        return self.m.size

    def packed(self) -> np.ndarray:
        return np.concatenate([self.m, self.c_gnd, self.k_gnd, self.k_link, self.c_link,
                               self.gap])


@dataclass(frozen=True)
class Built:
    """Kernel arrays of one axis.

    Attributes:
        params: shape (P_COUNT + chain params,), float64.
        state_size: length of the state vector.
        rot: torsional chain (node 0 is the motor; m for linear motors).
        ax: axial screw chain, or None.
        ratio: table travel per motor-side unit (m/rad for screws, 1 otherwise).
        dt: sub-step in s.
        sub_per_pwm: sub-steps per PWM period.
        omega_max: highest mechanical natural frequency in rad/s (end-stop contact
            included).
        end_stops: the table's end stops and limit switches, or None (rotary table).
    """
    params: np.ndarray
    state_size: int
    rot: Chain
    ax: Chain | None
    ratio: float
    dt: float
    sub_per_pwm: int
    omega_max: float
    end_stops: EndStops | None


def _uniform_rod(n_seg, node_mass, link_k, link_c):
    """Lumped rod of n_seg segments: n_seg+1 nodes, half masses at the ends."""
    m = np.full(n_seg + 1, node_mass)
    m[0] *= 0.5
    m[-1] *= 0.5
    return m, np.full(n_seg, link_k), np.full(n_seg, link_c)


def polar_moment(d: float) -> float:
    """m^4: polar area moment pi d^4 / 32 of a solid round shaft of diameter ``d`` (m)."""
    return math.pi * d ** 4 / 32.0


def area(d: float) -> float:
    """m^2: cross-section pi d^2 / 4 of a solid round shaft of diameter ``d`` (m)."""
    return math.pi * d ** 2 / 4.0


def voltage_limit(cfg: MachineConfig) -> float:
    """V: the largest voltage the converter applies.  The d-q vector of the dq model:
    U_dc/sqrt(3) with space-vector PWM (the line-to-line voltage reaches U_dc), U_dc/2 with
    sine PWM ([motor] modulation); the coil voltage of the commutation model: U_dc, seed 001
    eq. 2's U_Z; 0 for the first-order current loop, which takes no voltage."""
    mo = cfg.motor
    if mo.model == "commutation":
        return mo.dc_link_v
    if mo.model == "dq":
        return mo.dc_link_v / math.sqrt(3.0) if mo.modulation == "svpwm" else 0.5 * mo.dc_link_v
    return 0.0


def transmission_ratio(cfg: MachineConfig) -> float:
    """Table travel per unit of motor-side coordinate: lead/2pi for screws, else 1."""
    return cfg.mechanics.lead_m / (2.0 * math.pi) if cfg.machine.kind == "screw" else 1.0


def build_chains(cfg: MachineConfig) -> tuple[Chain, Chain | None]:
    """The torsional chain (motor first) and, for the screw model, the axial chain."""
    mo, me, kind = cfg.motor, cfg.mechanics, cfg.machine.kind
    ratio = transmission_ratio(cfg)
    motor_m = mo.mass_kg if kind == "linear" else mo.inertia_kgm2
    table_m = cfg.table.mass_kg if cfg.table is not None else 0.0
    empty = np.zeros(0)
    if me.model == "rigid":
        m = np.array([motor_m + me.load_inertia_kgm2 + table_m * ratio ** 2])
        return Chain(m, np.array([mo.viscous_nms_per_rad]), np.zeros(1), empty, empty,
                     empty), None
    cp = cfg.coupling
    if me.model == "two_mass":
        m = np.array([motor_m + 0.5 * cp.inertia_kgm2,
                      0.5 * cp.inertia_kgm2 + me.load_inertia_kgm2 + table_m * ratio ** 2])
        return Chain(m, np.array([mo.viscous_nms_per_rad, 0.0]), np.zeros(2),
                     np.array([cp.stiffness_nm_per_rad]), np.array([cp.damping_nms_per_rad]),
                     np.array([cp.backlash_rad])), None
    sc = cfg.screw
    n = sc.segments
    # the inertia and the stiffness each from the diameter the machine file chose for it
    d_m, d_k = sc.diameter(sc.inertia_diameter), sc.diameter(sc.stiffness_diameter)
    seg = sc.length_m / n
    ms, ks, cs = _uniform_rod(n, sc.density_kg_m3 * polar_moment(d_m) * seg,
                              sc.shear_modulus_pa * polar_moment(d_k) / seg,
                              sc.torsional_damping_nms_per_rad)
    m = np.concatenate([[motor_m + 0.5 * cp.inertia_kgm2], ms])
    m[1] += 0.5 * cp.inertia_kgm2 + me.load_inertia_kgm2
    c_gnd = np.zeros(n + 2)
    c_gnd[0] = mo.viscous_nms_per_rad
    c_gnd[1] += sc.bearing_viscous_nms_per_rad
    c_gnd[-1] += sc.bearing_viscous_nms_per_rad
    rot = Chain(m, c_gnd, np.zeros(n + 2), np.concatenate([[cp.stiffness_nm_per_rad], ks]),
                np.concatenate([[cp.damping_nms_per_rad], cs]), np.zeros(n + 1))
    ma, ka, ca = _uniform_rod(n, sc.density_kg_m3 * area(d_m) * seg,
                              sc.youngs_modulus_pa * area(d_k) / seg, sc.axial_damping_ns_per_m)
    k_gnd = np.zeros(n + 1)
    c_gnd = np.zeros(n + 1)
    k_gnd[0] = sc.thrust_bearing_stiffness_n_per_m
    c_gnd[0] = sc.thrust_bearing_damping_ns_per_m
    if sc.support == "fixed-fixed":
        k_gnd[-1] = sc.thrust_bearing_stiffness_n_per_m
        c_gnd[-1] = sc.thrust_bearing_damping_ns_per_m
    return rot, Chain(ma, c_gnd, k_gnd, ka, ca, np.zeros(n))


def reflected_inertia(cfg: MachineConfig) -> float:
    """Total inertia moved by the motor, reflected to the motor coordinate (kg·m², or kg for
    linear motors): every torsional node plus the table through the lead."""
    rot, ax = build_chains(cfg)
    table = cfg.table.mass_kg * transmission_ratio(cfg) ** 2 if ax is not None else 0.0
    return float(rot.m.sum()) + table


def _chain_matrices(ch: Chain):
    n = ch.n
    M = np.diag(ch.m)
    K = np.diag(ch.k_gnd.astype(float))
    C = np.diag(ch.c_gnd.astype(float))
    for i in range(n - 1):
        for A, v in ((K, ch.k_link[i]), (C, ch.c_link[i])):
            A[i, i] += v
            A[i + 1, i + 1] += v
            A[i, i + 1] -= v
            A[i + 1, i] -= v
    return M, K, C


def mechanics_matrices(cfg: MachineConfig, table_pos: float = 0.0, end_stop_k: float = 0.0):
    """Linearised mechanics M q'' + C q' + K q = f about table position ``table_pos`` (m).

    Coordinates q: torsional nodes (rad; m for linear motors), then for the
    screw model the axial screw nodes (m) and the table (m).  Backlash gaps
    and friction are left out (linear model in contact); ``end_stop_k`` (N/m) ties
    the table to the ground, an end stop in contact (its damper left out).
    Returns (M, C, K), each of shape (n, n).
    """
    rot, ax = build_chains(cfg)
    Mr, Kr, Cr = _chain_matrices(rot)
    if ax is None:
        # the table moves with the last node: the contact reaches it through the lead
        Kr[-1, -1] += end_stop_k * transmission_ratio(cfg) ** 2
        return Mr, Cr, Kr
    Ma, Ka, Ca = _chain_matrices(ax)
    nr, na = rot.n, ax.n
    n = nr + na + 1
    M = np.zeros((n, n))
    K = np.zeros((n, n))
    C = np.zeros((n, n))
    M[:nr, :nr], K[:nr, :nr], C[:nr, :nr] = Mr, Kr, Cr
    M[nr:nr + na, nr:nr + na], K[nr:nr + na, nr:nr + na], C[nr:nr + na, nr:nr + na] = Ma, Ka, Ca
    M[-1, -1] = cfg.table.mass_kg
    sc = cfg.screw
    seg = sc.length_m / sc.segments
    pos = (sc.nut_offset_m + table_pos) / seg
    j = min(max(int(pos), 0), na - 2)
    w = min(max(pos - j, 0.0), 1.0)
    g = np.zeros(n)  # nut deflection = g . q
    ratio = transmission_ratio(cfg)
    g[1 + j] += (1.0 - w) * ratio
    g[2 + j] += w * ratio
    # the nut's viscous torque on the screw's rotation there (plant.effects.screw_friction)
    turn = np.zeros(nr)
    turn[1 + j], turn[2 + j] = 1.0 - w, w
    C[:nr, :nr] += sc.nut_viscous_nms_per_rad * np.outer(turn, turn)
    g[nr + j] += 1.0 - w
    g[nr + j + 1] += w
    g[-1] = -1.0
    K += sc.nut_stiffness_n_per_m * np.outer(g, g)
    C += sc.nut_damping_ns_per_m * np.outer(g, g)
    K[-1, -1] += end_stop_k
    return M, C, K


def natural_frequencies(cfg: MachineConfig, table_pos: float = 0.0,
                        end_stop_k: float = 0.0) -> np.ndarray:
    """Undamped natural frequencies (rad/s), ascending, rigid-body modes included as 0;
    ``end_stop_k`` (N/m): an end stop of that stiffness in contact."""
    M, _, K = mechanics_matrices(cfg, table_pos, end_stop_k)
    lam = scipy.linalg.eigh(K, M, eigvals_only=True)
    return np.sqrt(np.clip(lam, 0.0, None))


def mechanics_rate(cfg: MachineConfig, table_pos: float = 0.0) -> float:
    """rad/s: the largest |s| of the linearised mechanics' state matrix [[0, I], [-M^-1 K,
    -M^-1 C]] about ``table_pos`` (m).  Undamped, or lightly damped, it is the stiffest
    natural frequency; a heavy damper adds its own rate c/m, which explicit Euler carries
    only for dt c/m < 2 (a nut damping of 4e5 N*s/m on the Arrow 500 X: far beyond the
    springs' frequencies)."""
    M, C, K = mechanics_matrices(cfg, table_pos)
    n = M.shape[0]
    a = np.zeros((2 * n, 2 * n))
    a[:n, n:] = np.eye(n)
    a[n:, :n] = -np.linalg.solve(M, K)
    a[n:, n:] = -np.linalg.solve(M, C)
    return float(np.abs(np.linalg.eigvals(a)).max())


def _omega_max(cfg: MachineConfig) -> float:
    """rad/s: the rate the sub-step must carry over the travel, the stiffest undamped natural
    frequency or :func:`mechanics_rate`, whichever is larger (non-proportional damping can
    put the stiffest |s| a few per cent below the undamped frequency; the frequency still
    sets the accuracy of the lightly damped modes)."""
    places = np.linspace(0.0, cfg.table.travel_m, 5) if cfg.mechanics.model == "screw" else [0.0]
    return max(max(natural_frequencies(cfg, x)[-1], mechanics_rate(cfg, x)) for x in places)


def _contact_mass(cfg: MachineConfig, rot: Chain) -> float:
    """kg: the table in the screw model, else the last node's inertia through the lead."""
    if cfg.mechanics.model == "screw":
        return cfg.table.mass_kg
    return float(rot.m[-1]) / transmission_ratio(cfg) ** 2


def _contact_omega(cfg: MachineConfig, stops: EndStops, chains: bool = True) -> float:
    """rad/s: the contact's rate and (``chains``) the highest mode with a stop in contact."""
    if not chains:
        return stops.rate
    return max(stops.rate, *(natural_frequencies(cfg, x, stops.stiffness)[-1]
                             for x in (stops.stop_neg, stops.stop_pos)))


def _substep_with_stops(cfg: MachineConfig, stops: EndStops, omega_chains: float, dt: float,
                        n: int) -> tuple[float, int, float]:
    """(dt, n, omega_max) once the end stops count; an explicit sub-step they make
    unstable is refused (:func:`plant.end_stops.check_substep`)."""
    omega = max(omega_chains, _contact_omega(cfg, stops))
    if cfg.simulation.substep_s <= 0.0:
        return *choose_substep(cfg, omega), omega
    lumped = cfg.mechanics.solver == "lumped"
    check_substep(cfg.path, cfg.table, stops, dt, lambda st: _contact_omega(cfg, st, lumped))
    return dt, n, omega


def choose_substep(cfg: MachineConfig, omega_max: float) -> tuple[float, int]:
    """(dt in s, sub-steps per PWM period) following the module's rule."""
    period = 1.0 / cfg.motor.pwm_frequency_hz
    sim = cfg.simulation
    if sim.substep_s > 0.0:
        n = round(period / sim.substep_s)
        if n < 1 or abs(n * sim.substep_s - period) > 1e-9 * period:
            raise ConfigError(f"{cfg.path}: [simulation] substep_s = {sim.substep_s:g} s must "
                              f"divide the PWM period {period:g} s a whole number of times")
        dt = period / n
        if cfg.mechanics.solver == "lumped" and omega_max * dt >= 2.0:
            raise ConfigError(f"{cfg.path}: [simulation] substep_s = {sim.substep_s:g} s is "
                              f"unstable: the stiffest mode ({omega_max / 2 / math.pi:.0f} Hz) "
                              f"needs dt < {2.0 / omega_max:.3g} s")
        return dt, n
    n = max(1, math.ceil(period * omega_max / sim.max_omega_dt))
    return period / n, n


def _substep_choice(cfg: MachineConfig) -> tuple[float, int, float, EndStops | None]:
    """(dt in s, sub-steps per PWM period, omega_max in rad/s, the end stops or None)
    following the module's rule, before any bound on the count."""
    omega_max = _omega_max(cfg)
    dt, n_sub = choose_substep(cfg, omega_max)
    stops = None
    if cfg.table is not None:
        rot, _ = build_chains(cfg)
        stops = end_stops(cfg.table, _contact_mass(cfg, rot), cfg.simulation.max_omega_dt / dt)
        dt, n_sub, omega_max = _substep_with_stops(cfg, stops, omega_max, dt, n_sub)
    return dt, n_sub, omega_max, stops


def check_substep_count(cfg: MachineConfig, n_max: int, why: str) -> int:
    """The sub-steps per PWM period ``cfg`` needs; a :class:`ConfigError` when more than
    ``n_max`` (``why``: whose bound it is), naming the stiffness to lower and the largest
    value that fits (:func:`plant.substeps.refusal`)."""
    _, n_sub, omega_max, _ = _substep_choice(cfg)
    if n_sub > n_max:
        raise ConfigError(refusal(cfg, n_sub, n_max, why, omega_max,
                                  lambda c: _substep_choice(c)[1]))
    return n_sub


def build(cfg: MachineConfig) -> Built:
    """Fill the kernel's params vector from a checked machine file; refuses one that needs
    more than :data:`plant.substeps.MAX_SUB_PER_PWM` sub-steps per PWM period."""
    mo, cl, kind = cfg.motor, cfg.current_loop, cfg.machine.kind
    rot, ax = build_chains(cfg)
    dt, n_sub, omega_max, stops = _substep_choice(cfg)
    if n_sub > MAX_SUB_PER_PWM:
        check_substep_count(cfg, MAX_SUB_PER_PWM, PLANT_LIMIT)
    ratio = transmission_ratio(cfg)
    p = np.zeros(L.P_COUNT + params_size(rot.n) + (params_size(ax.n) if ax else 0))
    p[L.P_MOTOR_MODEL] = _MOTOR[mo.model]
    p[L.P_MECH_MODEL] = _MECH[cfg.mechanics.model]
    p[L.P_SOLVER] = _SOLVER[cfg.mechanics.solver]
    p[L.P_DT] = dt
    p[L.P_SUB_PER_PWM] = n_sub
    p[L.P_DIVERGE_LIMIT] = 1e12
    # electrical
    pole = mo.pole_pairs if kind != "linear" else math.pi / mo.pole_pitch_m
    kt = mo.force_constant_n_per_a if kind == "linear" else mo.torque_constant_nm_per_a
    p[L.P_POLE_PAIRS] = pole
    p[L.P_R] = mo.resistance_ohm
    p[L.P_LD] = mo.inductance_d_h
    p[L.P_LQ] = mo.inductance_q_h if mo.model == "dq" else mo.inductance_d_h
    p[L.P_KT] = kt
    p[L.P_PSI] = kt / (1.5 * pole)
    p[L.P_UDC] = mo.dc_link_v
    p[L.P_U_MAX] = voltage_limit(cfg)
    p[L.P_U_Q_ONLY] = 1.0 if mo.model == "dq" and mo.voltage_limit == "q" else 0.0
    p[L.P_I_MAX] = mo.current_max_a
    p[L.P_KP_I] = cl.kp_v_per_a
    p[L.P_KI_I] = cl.kp_v_per_a / cl.ti_s if cl.ti_s > 0 else 0.0
    p[L.P_T_CL] = cl.time_constant_s
    if mo.model == "first_order":
        p[L.P_EXP_Q] = math.exp(-dt / cl.time_constant_s)
        p[L.P_IQ_KICK_NOW], p[L.P_IQ_KICK_NEXT] = first_order_kick_weights(
            dt, cl.time_constant_s)
    else:
        if mo.resistance_ohm <= 0.0:
            raise ConfigError(f"{cfg.path}: [motor] resistance_ohm must be > 0 ohm for "
                              f"motor model '{mo.model}'")
        p[L.P_EXP_D] = math.exp(-mo.resistance_ohm * dt / p[L.P_LD])
        p[L.P_EXP_Q] = math.exp(-mo.resistance_ohm * dt / p[L.P_LQ])
    p[L.P_DECOUPLE] = 1.0 if cl.decoupling and mo.model == "dq" else 0.0
    p[L.P_FW_ENABLED] = 1.0 if cfg.field_weakening.enabled else 0.0
    p[L.P_FW_M_MAX] = cfg.field_weakening.max_torque_nm
    cog = cfg.cogging
    amps = cog.amplitudes_n if kind == "linear" else cog.amplitudes_nm
    p[L.P_COG_N] = len(amps)
    for k, a in enumerate(amps):
        p[L.P_COG_ORDER + k] = cog.orders[k]
        p[L.P_COG_AMP + k] = a
        p[L.P_COG_PHASE + k] = math.radians(cog.phases_deg[k]) if cog.phases_deg else 0.0
    # transmission, nut, table
    p[L.P_LEAD_RATIO] = ratio
    if cfg.screw is not None:
        sc = cfg.screw
        p[L.P_NUT_K] = sc.nut_stiffness_n_per_m
        p[L.P_NUT_C] = sc.nut_damping_ns_per_m
        p[L.P_NUT_GAP] = sc.backlash_m
        p[L.P_NUT_S0] = sc.nut_offset_m
        p[L.P_SEG_LEN] = sc.length_m / sc.segments
        _screw_friction(sc, p)
    p[L.P_BRAKE] = cfg.brake.holding_torque_nm or cfg.brake.holding_force_n
    if cfg.table is not None:
        p[L.P_TABLE_M] = cfg.table.mass_kg
        p[L.P_EXT_LOAD] = cfg.table.external_force_n
    else:
        p[L.P_EXT_LOAD] = cfg.mechanics.external_torque_nm
    _pitch_error(cfg, p)
    _friction(cfg, p)
    if stops is not None:
        p[L.P_STROKE] = 1.0
        p[L.P_STOP_NEG] = stops.stop_neg
        p[L.P_STOP_POS] = stops.stop_pos
        p[L.P_STOP_K] = stops.stiffness
        p[L.P_STOP_C] = stops.damping
        p[L.P_LIMIT_NEG] = stops.limit_neg
        p[L.P_LIMIT_POS] = stops.limit_pos
    # sensors
    se = cfg.sensors
    if kind == "linear":
        p[L.P_ENC_COUNTS_PER_RAD] = 1.0 / se.encoder_resolution_m
    else:
        p[L.P_ENC_COUNTS_PER_RAD] = se.encoder_counts_per_rev / (2.0 * math.pi)
    p[L.P_SCALE_RES] = se.scale_resolution_m
    p[L.P_I_NOISE] = se.current_noise_a
    p[L.P_I_LSB] = se.current_lsb_a
    p[L.P_I_FULL_SCALE] = se.current_full_scale_a
    p[L.P_ENC_ROUND] = 1.0 if se.encoder_rounding == "round" else 0.0
    p[L.P_ENC_ZERO] = 1.0 if se.encoder_zero_at_start else 0.0
    p[L.P_SEED] = se.seed
    n_delay = delay_periods(cfg)
    p[L.P_DELAY_N] = n_delay
    # chains
    p[L.P_N_ROT] = rot.n
    p[L.P_OFF_ROT] = L.P_COUNT
    p[L.P_SOFF_ROT] = L.S_COUNT
    p[L.P_COUNT:L.P_COUNT + params_size(rot.n)] = rot.packed()
    n_state = L.S_COUNT + state_size(rot.n)
    if ax is not None:
        p[L.P_N_AX] = ax.n
        p[L.P_OFF_AX] = L.P_COUNT + params_size(rot.n)
        p[L.P_SOFF_AX] = n_state
        p[int(p[L.P_OFF_AX]):] = ax.packed()
        n_state += state_size(ax.n)
    p[L.P_SOFF_DELAY] = n_state
    n_state += ring_size(n_delay)
    return Built(p, n_state, rot, ax, ratio, dt, n_sub, omega_max, stops)


def _pitch_error(cfg: MachineConfig, p: np.ndarray) -> None:
    pe = cfg.pitch_error
    p[L.P_PITCH_N] = len(pe.periods_m)
    for k, (period, amp) in enumerate(zip(pe.periods_m, pe.amplitudes_m)):
        p[L.P_PITCH_WAVENUMBER + k] = 2.0 * math.pi / period
        p[L.P_PITCH_AMP + k] = amp
        p[L.P_PITCH_PHASE + k] = math.radians(pe.phases_deg[k]) if pe.phases_deg else 0.0
    p[L.P_PITCH_LINEAR] = pe.linear_ppm * 1e-6


def _screw_friction(sc, p: np.ndarray) -> None:
    """The bearing and nut friction of [screw] (plant.effects.screw_friction)."""
    p[L.P_BRG_COULOMB] = sc.bearing_coulomb_nm
    p[L.P_NUT_COULOMB] = sc.nut_coulomb_nm
    p[L.P_NUT_VISCOUS] = sc.nut_viscous_nms_per_rad
    p[L.P_NUT_LOAD_FR] = sc.nut_load_friction
    p[L.P_SCREW_FRICTION] = 1.0 if (sc.bearing_coulomb_nm or sc.nut_coulomb_nm
                                    or sc.nut_viscous_nms_per_rad
                                    or sc.nut_load_friction) else 0.0


def _friction(cfg: MachineConfig, p: np.ndarray) -> None:
    fr, pre = cfg.friction, cfg.presliding
    if cfg.machine.kind == "rotary":
        vals = (fr.viscous_nms_per_rad, fr.coulomb_nm, fr.breakaway_nm,
                fr.stribeck_velocity_rad_s, fr.zero_velocity_band_rad_s,
                fr.viscous_asymmetry_nms_per_rad)
    else:
        vals = (fr.viscous_ns_per_m, fr.coulomb_n, fr.breakaway_n, fr.stribeck_velocity_m_s,
                fr.zero_velocity_band_m_s, fr.viscous_asymmetry_ns_per_m)
    viscous, coulomb, breakaway, v_s, dv, asym = vals
    p[L.P_FR_VISCOUS] = viscous
    p[L.P_FR_COULOMB] = coulomb
    p[L.P_FR_STATIC] = max(breakaway, coulomb)
    p[L.P_FR_STRIBECK_V] = v_s
    p[L.P_FR_DV] = dv
    p[L.P_FR_VISC_ASYM] = asym
    p[L.P_FR_REVERSAL_STOP] = 1.0 if fr.karnopp_reversal == "stop" else 0.0
    p[L.P_PRE_ENABLED] = 1.0 if pre.enabled else 0.0
    p[L.P_PRE_K1] = pre.stiffness_n_per_m
    p[L.P_PRE_X1] = pre.x1_m
    p[L.P_PRE_A] = pre.exponent
