"""The axis kernel: every effect composed into one allocation-free step function.

``axis_step_nb(p, s, inp, out, n_sub)`` advances one axis by ``n_sub``
sub-steps of ``p[P_DT]`` seconds with the setpoints ``inp`` held, writes the
output signals into ``out`` and returns a status code (``STATUS_*`` in
:mod:`plant.layout`).  It never raises and never allocates; the model
selectors in ``p`` (motor, mechanics, solver, friction switches) pick the
effects a machine file asked for.

One sub-step, in order:

1. once per PWM period: the inverter takes the voltage computed last period,
   the drive samples the currents (with the current sensors' faults) and runs its
   current controller (or takes the voltage setpoint in voltage mode);
2. the motor's currents advance with the applied voltage; torque = motor
   torque (times the fault's ripple) + cogging;
3. mechanics: chain forces (springs, dampers, bearings), the nut coupling the
   torsional and axial screw chains to the table at the nut's present
   location, the end stops' contact on the table, table friction with stiction,
   then a symplectic Euler (or TLM) update;
4. at the end of a PWM period: the encoder's fault terms are drawn (if any) and the
   measured signals enter the delay ring (if any).

The fault terms (:mod:`plant.effects.faults`) cost one test of ``P_FAULTS`` per sub-step
while it is 0, and change no bit then.

The outputs give the true states (positions, velocities, currents, forces) as they are
and the measured ones (encoder and scale counts, measured currents) through the delay.

Speed (issue 12 part 7; about 1.1x the same sub-step in C, hil.bench.csubstep, measured):
the effects of every sub-step are inlined into it (``inline="always"``; the once-per-PWM
and once-per-call parts stay calls), the flat offsets are taken as non-negative
(:func:`plant.effects.index.offset`) so numba does not wrap the indices, and the kernel
is compiled without reference counting (see :func:`axis_step_nb`).  None of it changes a
bit of the results (``tests/test_kernel_speed.py``).
"""

from numba import njit

from plant.effects.brake import holding_brake
from plant.effects.chain import (
    chain_clear_forces,
    chain_internal_forces,
    chain_step,
    dead_zone,
)
from plant.effects.cogging import cogging_torque
from plant.effects.commutation import commutation_control, commutation_substep
from plant.effects.delay import delay_push, measured_delayed
from plant.effects.end_stop import end_stop_force, limit_switches
from plant.effects.faults import (
    electrical_angle,
    encoder_mark,
    encoder_sample,
    first_order_target,
    ripple_factor,
    sensed_current,
)
from plant.effects.friction import presliding_update, table_friction
from plant.effects.index import offset
from plant.effects.pitch import pitch_error
from plant.effects.pmsm import (
    dq_current_control,
    dq_substep,
    dq_torque,
    first_order_substep,
    freewheel,
    limit_voltage,
)
from plant.effects.reference import home_switch, index_marks
from plant.effects.screw_friction import screw_friction
from plant.effects.sensors import measure_current
from plant.effects.tlm import tlm_step
from plant.layout import (
    I_BRAKE,
    I_ENABLE,
    I_ID_REF,
    I_IQ_REF,
    I_LOAD,
    I_MODE,
    I_UD,
    I_UQ,
    INPUT_VOLTAGE,
    MECH_SCREW,
    MOTOR_COMMUTATION,
    MOTOR_DQ,
    MOTOR_FIRST_ORDER,
    O_ENCODER,
    O_END_STOP_F,
    O_FRICTION,
    O_HOME_SWITCH,
    O_ID,
    O_ID_MEAS,
    O_INDEX,
    O_IQ,
    O_IQ_MEAS,
    O_LIMIT_NEG,
    O_LIMIT_POS,
    O_MOTOR_POS,
    O_MOTOR_VEL,
    O_NUT_FORCE,
    O_SCALE,
    O_STATUS,
    O_TABLE_POS,
    O_TABLE_VEL,
    O_TIME,
    O_TORQUE,
    O_UD,
    O_UQ,
    P_BRAKE,
    P_DELAY_N,
    P_DIVERGE_LIMIT,
    P_DT,
    P_EXT_LOAD,
    P_FAULTS,
    P_LD,
    P_LEAD_RATIO,
    P_LQ,
    P_MECH_MODEL,
    P_MOTOR_MODEL,
    P_N_AX,
    P_N_ROT,
    P_NUT_C,
    P_NUT_GAP,
    P_NUT_K,
    P_NUT_S0,
    P_OFF_AX,
    P_OFF_ROT,
    P_POLE_PAIRS,
    P_PRE_ENABLED,
    P_SCREW_FRICTION,
    P_SEG_LEN,
    P_SOFF_AX,
    P_SOFF_ROT,
    P_SOLVER,
    P_SUB_PER_PWM,
    P_TABLE_M,
    P_U_MAX,
    P_UDC,
    S_FRICTION,
    S_ID,
    S_ID_MEAS,
    S_INT_D,
    S_INT_Q,
    S_IQ,
    S_IQ_MEAS,
    S_KM,
    S_NUT_F,
    S_STOP_F,
    S_STUCK,
    S_SUB_COUNT,
    S_TABLE_V,
    S_TABLE_X,
    S_TIME,
    S_TORQUE,
    S_UD_APPLIED,
    S_UD_NEXT,
    S_UQ_APPLIED,
    S_UQ_NEXT,
    SOLVER_LUMPED,
    STATUS_DIVERGED,
    STATUS_NONFINITE,
    STATUS_OK,
)


@njit(cache=True, error_model="numpy")
def pwm_event(p, s, inp, omega_m):
    """Start of a PWM period: apply last period's voltage, sample, compute the next one."""
    model = int(p[P_MOTOR_MODEL])
    s[S_UD_APPLIED] = s[S_UD_NEXT]
    s[S_UQ_APPLIED] = s[S_UQ_NEXT]
    i_d = s[S_ID]
    i_q = s[S_IQ]
    if p[P_FAULTS] > 0.0:
        encoder_mark(p, s)
        i_d, i_q = sensed_current(p, s)
    if model == MOTOR_DQ:
        s[S_ID_MEAS] = measure_current(p, s, i_d)
    s[S_IQ_MEAS] = measure_current(p, s, i_q)
    if inp[I_ENABLE] <= 0.0:
        # pulses blocked: no voltage now or next period, controller reset
        s[S_UD_APPLIED] = 0.0
        s[S_UQ_APPLIED] = 0.0
        s[S_UD_NEXT] = 0.0
        s[S_UQ_NEXT] = 0.0
        s[S_INT_D] = 0.0
        s[S_INT_Q] = 0.0
        return
    if model == MOTOR_FIRST_ORDER:
        return
    if inp[I_MODE] == INPUT_VOLTAGE:
        s[S_UD_NEXT], s[S_UQ_NEXT] = limit_voltage(inp[I_UD], inp[I_UQ], p[P_U_MAX])
    elif model == MOTOR_DQ:
        dq_current_control(p, s, inp[I_ID_REF], inp[I_IQ_REF], omega_m)
    else:
        commutation_control(p, s, inp[I_IQ_REF], omega_m)


@njit(cache=True, error_model="numpy", inline="always")
def motor_substep(p, s, inp, omega_m):
    """Advance the motor's electrical state one sub-step; return its torque (N·m or N).

    The torque returned is the kick of a kick-drift (symplectic Euler) step, which belongs
    to the start of the step: that of the currents there (the d-q and commutation models),
    or for the first-order model the lag's exact current averaged around the start
    (:func:`plant.effects.pmsm.first_order_substep`).  A current taken at the end would act
    one sub-step early: on the trace of a coarse plant (one sub-step per PWM period) that
    lead biased an inverse-model fit of viscous friction and cogging by several per cent.

    With the power stage off the currents of the voltage-fed models freewheel to zero
    (pulses blocked: the windings are open, not shorted; back-EMF above the link
    voltage, which would rectify into the link, is not modelled)."""
    model = int(p[P_MOTOR_MODEL])
    if inp[I_ENABLE] <= 0.0 and model != MOTOR_FIRST_ORDER:
        dt = p[P_DT]
        if model == MOTOR_DQ:
            torque = dq_torque(p, s[S_ID], s[S_IQ])
            u_link = 0.5 * p[P_UDC]
            s[S_ID] = freewheel(s[S_ID], u_link, p[P_LD], dt)
            s[S_IQ] = freewheel(s[S_IQ], u_link, p[P_LQ], dt)
            return torque
        torque = s[S_KM] * s[S_IQ]
        s[S_IQ] = freewheel(s[S_IQ], p[P_UDC], p[P_LD], dt)
        return torque
    if model == MOTOR_DQ:
        return dq_substep(p, s, s[S_UD_APPLIED], s[S_UQ_APPLIED], omega_m)
    if model == MOTOR_COMMUTATION:
        return commutation_substep(p, s, s[S_UQ_APPLIED], omega_m)
    iq_ref = inp[I_IQ_REF] if inp[I_ENABLE] > 0.0 else 0.0
    return dq_torque(p, 0.0, first_order_substep(p, s, iq_ref))


@njit(cache=True, error_model="numpy")
def faulty_motor_substep(p, s, inp, omega_m):
    """:func:`motor_substep` with the fault terms (:mod:`plant.effects.faults`): the torque
    ripple on the motor's torque and, for the first-order model, the lag's target moved to
    the true current whose measurement equals the reference (the lag stands for a closed
    current loop, which regulates its measurement)."""
    theta_e = electrical_angle(p, s)
    if int(p[P_MOTOR_MODEL]) == MOTOR_FIRST_ORDER and inp[I_ENABLE] > 0.0:
        torque = dq_torque(p, 0.0, first_order_substep(
            p, s, first_order_target(p, inp[I_IQ_REF], theta_e)))
    else:
        torque = motor_substep(p, s, inp, omega_m)
    return torque * ripple_factor(p, theta_e)


@njit(cache=True, error_model="numpy", inline="always")
def nut_place(p, s, na):
    """(j, w): the nut sits between screw nodes j and j+1 (of ``na``) with weight w."""
    pos = (p[P_NUT_S0] + s[S_TABLE_X]) / p[P_SEG_LEN]
    j = int(pos)
    j = offset(0 if j < 0 else (na - 2 if j > na - 2 else j))
    w = pos - j
    w = 0.0 if w < 0.0 else (1.0 if w > 1.0 else w)
    return j, w


@njit(cache=True, error_model="numpy", inline="always")
def nut_coupling(p, s, ro, nr, ao, na, j, w):
    """Nut force (N, pushing the table forward) at the nut's present place on the screw.

    The nut sits between screw nodes j and j+1 with weight w (:func:`nut_place`); its
    angle and axial displacement are interpolated there and its reaction is spread back
    with the same weights, which keeps the coupling energy-consistent while the place
    moves with the table (seed 003's moving nut).
    """
    ro, nr, ao, na = offset(ro), offset(nr), offset(ao), offset(na)
    theta = (1.0 - w) * s[ro + 1 + j] + w * s[ro + 2 + j]
    omega = (1.0 - w) * s[ro + nr + 1 + j] + w * s[ro + nr + 2 + j]
    u = (1.0 - w) * s[ao + j] + w * s[ao + j + 1]
    du = (1.0 - w) * s[ao + na + j] + w * s[ao + na + j + 1]
    # pitch error: the thread carries the nut to lead*theta + e(lead*theta); the local
    # ratio lead (1 + e') moves the nut and takes its reaction back to the screw
    u_nom = p[P_LEAD_RATIO] * theta
    e, e1, _ = pitch_error(p, u_nom)
    lead = p[P_LEAD_RATIO] * (1.0 + e1)
    delta = u + u_nom + e - s[S_TABLE_X]
    rate = du + lead * omega - s[S_TABLE_V]
    gap = p[P_NUT_GAP]
    de = dead_zone(delta, gap)
    f = p[P_NUT_K] * de
    if de != 0.0 or gap <= 0.0:
        f += p[P_NUT_C] * rate
    fr = ro + 2 * nr
    fa = ao + 2 * na
    s[fr + 1 + j] -= (1.0 - w) * f * lead
    s[fr + 2 + j] -= w * f * lead
    s[fa + j] -= (1.0 - w) * f
    s[fa + j + 1] -= w * f
    return f


@njit(cache=True, error_model="numpy", inline="always")
def screw_mechanics(p, s, load, dt, lumped, brake):
    """One sub-step of motor - coupling - screw - nut - table (torque already in scratch);
    ``brake``: the holding brake's torque on the motor while closed, N·m (0: open)."""
    ro = offset(p[P_SOFF_ROT])
    nr = offset(p[P_N_ROT])
    ao = offset(p[P_SOFF_AX])
    na = offset(p[P_N_AX])
    por = offset(p[P_OFF_ROT])
    poa = offset(p[P_OFF_AX])
    j, w = nut_place(p, s, na)
    f_nut = nut_coupling(p, s, ro, nr, ao, na, j, w)
    s[S_NUT_F] = f_nut
    v = s[S_TABLE_V]
    m = p[P_TABLE_M]
    # the stop's reaction reaches the screw through the nut: a table held by the wall
    # loads the nut, the screw and its thrust bearing with the motor's force
    f_stop = end_stop_force(p, s[S_TABLE_X], v)
    s[S_STOP_F] = f_stop
    f_app = f_nut + load + f_stop
    ff, stuck = table_friction(p, s, v, f_app, m, dt)
    s[S_FRICTION] = ff
    s[S_STUCK] = 1.0 if stuck else 0.0
    if lumped:
        if p[P_SCREW_FRICTION] > 0.0:
            screw_friction(p, por, s, ro, nr, j, w, f_nut, dt)
        if brake > 0.0:
            holding_brake(p, por, s, ro, nr, brake, dt)
        chain_step(p, por, s, ro, nr, dt, -1)
        chain_step(p, poa, s, ao, na, dt, -1)
    else:
        tlm_step(p, por, s, ro, nr, dt)
        tlm_step(p, poa, s, ao, na, dt)
    v = 0.0 if stuck else v + dt * (f_app + ff) / m
    x_old = s[S_TABLE_X]
    s[S_TABLE_V] = v
    s[S_TABLE_X] = x_old + dt * v
    if p[P_PRE_ENABLED] > 0.0:
        presliding_update(p, s, x_old, s[S_TABLE_X])


@njit(cache=True, error_model="numpy", inline="always")
def lumped_mechanics(p, s, load, dt, brake):
    """One sub-step of the rigid or two-mass chain; the table moves with the last node;
    ``brake``: the holding brake's torque (force) on the motor while closed (0: open).

    With a pitch error the table stands at x = u + e(u), u = ratio * theta_last: forces on
    the table reach the node through the local ratio g = ratio (1 + e'(u)) (virtual work),
    and the table's share of the kinematic acceleration, m e''(u) u_dot^2, is taken from
    the node as a force -m e'' u_dot^2 on the table.  The table's reflected inertia stays
    m ratio^2 (the node's constant inertia) instead of m g^2: a relative error of 2 e' in
    the table's share, below 1e-1 by the loader's slope bound and ~1e-3 for real screws.
    The end stops act on the table like the load does.
    """
    ro = offset(p[P_SOFF_ROT])
    nr = offset(p[P_N_ROT])
    por = offset(p[P_OFF_ROT])
    last = offset(nr - 1)
    ratio = p[P_LEAD_RATIO]
    fr = ro + 2 * nr
    u_dot = ratio * s[ro + nr + last]
    _, e1, e2 = pitch_error(p, ratio * s[ro + last])
    g = ratio * (1.0 + e1)
    v = (1.0 + e1) * u_dot
    f_stop = end_stop_force(p, s[S_TABLE_X], v)
    s[S_STOP_F] = f_stop
    f_tab = load + f_stop - p[P_TABLE_M] * e2 * u_dot * u_dot
    f_app = s[fr + last] / g + f_tab
    m_eff = p[por + last] / (g * g)
    ff, stuck = table_friction(p, s, v, f_app, m_eff, dt)
    s[S_FRICTION] = ff
    s[S_STUCK] = 1.0 if stuck else 0.0
    s[fr + last] += (ff + f_tab) * g
    if brake > 0.0:  # after the table's forces: a rigid chain's one node carries them
        holding_brake(p, por, s, ro, nr, brake, dt)
    chain_step(p, por, s, ro, nr, dt, last if stuck else -1)
    x_old = s[S_TABLE_X]
    u = ratio * s[ro + last]
    e, e1, _ = pitch_error(p, u)
    s[S_TABLE_X] = u + e
    s[S_TABLE_V] = (1.0 + e1) * ratio * s[ro + nr + last]
    if p[P_PRE_ENABLED] > 0.0:
        presliding_update(p, s, x_old, s[S_TABLE_X])


@njit(cache=True, error_model="numpy", inline="always")
def substep(p, s, inp):
    """Advance the axis by one sub-step of p[P_DT]."""
    dt = p[P_DT]
    ro = offset(p[P_SOFF_ROT])
    nr = offset(p[P_N_ROT])
    omega_m = s[ro + nr]
    if s[S_SUB_COUNT] == 0.0:
        pwm_event(p, s, inp, omega_m)
    s[S_SUB_COUNT] += 1.0
    if s[S_SUB_COUNT] >= p[P_SUB_PER_PWM]:
        s[S_SUB_COUNT] = 0.0
    if p[P_FAULTS] > 0.0:
        torque = faulty_motor_substep(p, s, inp, omega_m)
    else:
        torque = motor_substep(p, s, inp, omega_m)
    torque += cogging_torque(p, p[P_POLE_PAIRS] * s[ro])
    s[S_TORQUE] = torque
    lumped = p[P_SOLVER] == SOLVER_LUMPED
    screw = p[P_MECH_MODEL] == MECH_SCREW
    if lumped:
        chain_internal_forces(p, offset(p[P_OFF_ROT]), s, ro, nr)
        if screw:
            chain_internal_forces(p, offset(p[P_OFF_AX]), s, offset(p[P_SOFF_AX]),
                                  offset(p[P_N_AX]))
    else:
        chain_clear_forces(s, ro, nr)
        chain_clear_forces(s, offset(p[P_SOFF_AX]), offset(p[P_N_AX]))
    s[ro + 2 * nr] += torque
    load = inp[I_LOAD] + p[P_EXT_LOAD]
    brake = p[P_BRAKE] if inp[I_BRAKE] > 0.0 else 0.0
    if screw:
        screw_mechanics(p, s, load, dt, lumped, brake)
    else:
        lumped_mechanics(p, s, load, dt, brake)
    s[S_TIME] += dt
    if s[S_SUB_COUNT] == 0.0:
        # this sub-step closed a PWM period: the encoder is sampled (its fault terms drawn)
        # and the measured signals enter the delay ring
        if p[P_FAULTS] > 0.0:
            encoder_sample(p, s)
        if p[P_DELAY_N] > 0.0:
            delay_push(p, s)


@njit(cache=True, error_model="numpy")
def check_state(p, s):
    """STATUS_OK, or the fault a non-finite or runaway state value shows."""
    limit = p[P_DIVERGE_LIMIT]
    for i in range(s.size):
        x = s[i]
        if x != x or x - x != 0.0:
            return STATUS_NONFINITE
        if abs(x) > limit:
            return STATUS_DIVERGED
    return STATUS_OK


@njit(cache=True, error_model="numpy")
def write_outputs(p, s, out, status):
    """Fill ``out`` (layout O_*) from the state."""
    ro = offset(p[P_SOFF_ROT])
    nr = offset(p[P_N_ROT])
    out[O_STATUS] = status
    out[O_TIME] = s[S_TIME]
    out[O_MOTOR_POS] = s[ro]
    out[O_MOTOR_VEL] = s[ro + nr]
    out[O_TABLE_POS] = s[S_TABLE_X]
    out[O_TABLE_VEL] = s[S_TABLE_V]
    enc, scale, i_d, i_q = measured_delayed(p, s)
    out[O_ENCODER] = enc
    out[O_SCALE] = scale
    out[O_ID] = s[S_ID]
    out[O_IQ] = s[S_IQ]
    out[O_ID_MEAS] = i_d
    out[O_IQ_MEAS] = i_q
    out[O_TORQUE] = s[S_TORQUE]
    out[O_UD] = s[S_UD_APPLIED]
    out[O_UQ] = s[S_UQ_APPLIED]
    out[O_NUT_FORCE] = s[S_NUT_F]
    out[O_FRICTION] = s[S_FRICTION]
    out[O_LIMIT_NEG], out[O_LIMIT_POS] = limit_switches(p, s[S_TABLE_X])
    out[O_END_STOP_F] = s[S_STOP_F]
    out[O_HOME_SWITCH] = home_switch(p, s[S_TABLE_X])
    out[O_INDEX] = index_marks(p, enc)


# _nrt=False: compiled without numba's reference counting, inherited by every function
# it calls.  The kernel never allocates, and with counting on, each array passed into an
# inlined or called effect was an atomic increment and decrement per sub-step: about half
# the step's time (issue 12 part 7).  An allocation anywhere in the kernel now fails to
# compile, which the real-time path wants anyway.
@njit(cache=True, error_model="numpy", _nrt=False)
def axis_step_nb(p, s, inp, out, n_sub):
    """Advance ``n_sub`` sub-steps with ``inp`` held; fill ``out``; return a status code.

    The state is checked once per call (a NaN or a runaway value persists, so
    nothing is missed); after a fault status the caller must reset the state.
    """
    for _ in range(n_sub):
        substep(p, s, inp)
    status = check_state(p, s)
    write_outputs(p, s, out, status)
    return status
