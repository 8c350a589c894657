/* The plant kernel's sub-step in C: the baseline of `hil bench plant` (issue 12, part 7).
 *
 * A port of plant/kernel.py for the models the Arrow 500 X uses -- d-q PMSM with its
 * discrete current loop, screw mechanics on the lumped (symplectic Euler) solver, Karnopp
 * friction with the Stribeck curve, the screw's bearing and nut friction, end stops,
 * cogging, pitch error, current noise and quantization, the measurement delay ring --
 * with the same equations in the same floating-point order, built with -ffp-contract=off
 * (no fused multiply-add) so that its state is bit-identical to the numba kernel's.  It
 * reads and writes the same flat arrays (plant/layout.py); the indices (and
 * STRIBECK_CUTOFF) come from layout.h, which hil.bench.csubstep writes from plant.layout
 * at build time.  Other models (first-order and commutation motors, rigid and two-mass
 * mechanics, the TLM solver, presliding friction, the fault terms of
 * plant/effects/faults.py) are not ported: c_supports() says whether a params vector is
 * one this file runs.
 */
#include <math.h>
#include <stdint.h>
#include <time.h>

#include "layout.h"

static inline double clamp(double x, double lo, double hi) {
    return x < lo ? lo : (x > hi ? hi : x);
}

/* ---- plant/effects/rng.py ---------------------------------------------------------- */
static const uint64_t GOLDEN = 0x9E3779B97F4A7C15ULL;

static uint64_t splitmix64(uint64_t x) {
    uint64_t z = x + GOLDEN;
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
    return z ^ (z >> 31);
}

static double uniform01(double seed, double counter) {
    uint64_t z = splitmix64((uint64_t)seed * GOLDEN + (uint64_t)counter);
    return ((double)(z >> 11) + 0.5) * (1.0 / 9007199254740992.0);
}

static double gaussian(double seed, double counter) {
    double u1 = uniform01(seed, counter);
    double u2 = uniform01(seed, counter + 1.0);
    return sqrt(-2.0 * log(u1)) * cos(2.0 * M_PI * u2);
}

/* ---- plant/effects/sensors.py, delay.py, reference.py, end_stop.py ----------------- */
static double counts(double position, double per_unit) {
    if (per_unit <= 0.0) return 0.0;
    return floor(position * per_unit);
}

static double measure_current(const double *p, double *s, double current) {
    double i = current;
    if (p[P_I_NOISE] > 0.0) {
        i += p[P_I_NOISE] * gaussian(p[P_SEED], s[S_RNG_COUNTER]);
        s[S_RNG_COUNTER] += 2.0;
    }
    double lsb = p[P_I_LSB];
    if (lsb > 0.0) i = lsb * floor(i / lsb + 0.5);
    return i;
}

static void measured_now(const double *p, const double *s, double m[4]) {
    m[0] = counts(s[(long)p[P_SOFF_ROT]], p[P_ENC_COUNTS_PER_RAD]);
    double res = p[P_SCALE_RES];
    m[1] = res > 0.0 ? counts(s[S_TABLE_X], 1.0 / res) : 0.0;
    m[2] = s[S_ID_MEAS];
    m[3] = s[S_IQ_MEAS];
}

static void delay_push(const double *p, double *s) {
    long n1 = (long)p[P_DELAY_N] + 1;
    long head = (long)s[S_DELAY_HEAD] + 1;
    head = head >= n1 ? 0 : head;
    s[S_DELAY_HEAD] = (double)head;
    long so = (long)p[P_SOFF_DELAY];
    double m[4];
    measured_now(p, s, m);
    for (long c = 0; c < 4; c++) s[so + c * n1 + head] = m[c];
}

static void measured_delayed(const double *p, const double *s, double m[4]) {
    if (p[P_DELAY_N] <= 0.0) {
        measured_now(p, s, m);
        return;
    }
    long n1 = (long)p[P_DELAY_N] + 1;
    long oldest = (long)s[S_DELAY_HEAD] + 1;
    oldest = oldest >= n1 ? 0 : oldest;
    long so = (long)p[P_SOFF_DELAY];
    for (long c = 0; c < 4; c++) m[c] = s[so + c * n1 + oldest];
}

static double end_stop_force(const double *p, double x, double v) {
    if (p[P_STROKE] <= 0.0) return 0.0;
    if (x > p[P_STOP_POS]) {
        double f = -p[P_STOP_K] * (x - p[P_STOP_POS]) - p[P_STOP_C] * v;
        return f < 0.0 ? f : 0.0;
    }
    if (x < p[P_STOP_NEG]) {
        double f = p[P_STOP_K] * (p[P_STOP_NEG] - x) - p[P_STOP_C] * v;
        return f > 0.0 ? f : 0.0;
    }
    return 0.0;
}

static double home_switch(const double *p, double x) {
    double below = x - p[P_HOME_SWITCH];
    if (p[P_STROKE] <= 0.0)
        return below - 2.0 * M_PI * floor(below / (2.0 * M_PI)) >= M_PI ? 1.0 : 0.0;
    return below < 0.0 ? 1.0 : 0.0;
}

static double index_marks(const double *p, double cnt) {
    double period = p[P_INDEX_PERIOD] > 0.0 ? p[P_INDEX_PERIOD] : 2.0 * M_PI;
    double per_mark = (double)(int64_t)round(period * p[P_ENC_COUNTS_PER_RAD]);
    if (per_mark <= 0.0) return 0.0;
    return floor(cnt / per_mark);
}

/* ---- plant/effects/pmsm.py, cogging.py, pitch.py ------------------------------------ */
static double dq_torque(const double *p, double i_d, double i_q) {
    return 1.5 * p[P_POLE_PAIRS] * (p[P_PSI] * i_q + (p[P_LD] - p[P_LQ]) * i_d * i_q);
}

static double pi_step(double err, double *integ, double kp, double ki, double period,
                      double ff, double umax) {
    double u = ff + kp * err + *integ;
    if (u > umax) {
        if (err < 0.0) *integ += ki * period * err;
        return umax;
    }
    if (u < -umax) {
        if (err > 0.0) *integ += ki * period * err;
        return -umax;
    }
    *integ = *integ + ki * period * err;
    return u;
}

static void dq_current_control(const double *p, double *s, double id_ref, double iq_ref,
                               double omega_m) {
    double period = p[P_DT] * p[P_SUB_PER_PWM];
    double imax = p[P_I_MAX];
    double umax = p[P_U_MAX];
    iq_ref = clamp(iq_ref, -imax, imax);
    id_ref = clamp(id_ref, -imax, imax);
    double ff_d = 0.0, ff_q = 0.0;
    if (p[P_DECOUPLE] > 0.0) {
        double we = p[P_POLE_PAIRS] * omega_m;
        ff_d = -we * p[P_LQ] * s[S_IQ_MEAS];
        ff_q = we * (p[P_PSI] + p[P_LD] * s[S_ID_MEAS]);
    }
    double ud = pi_step(id_ref - s[S_ID_MEAS], &s[S_INT_D], p[P_KP_I], p[P_KI_I], period,
                        ff_d, umax);
    double rest = umax * umax - ud * ud;
    double uq_max = sqrt(rest > 0.0 ? rest : 0.0);
    double uq = pi_step(iq_ref - s[S_IQ_MEAS], &s[S_INT_Q], p[P_KP_I], p[P_KI_I], period,
                        ff_q, uq_max);
    s[S_UD_NEXT] = ud;
    s[S_UQ_NEXT] = uq;
}

static double freewheel(double i, double u_link, double inductance, double dt) {
    double step = u_link / inductance * dt;
    if (i > 0.0) return fmax(0.0, i - step);
    if (i < 0.0) return fmin(0.0, i + step);
    return 0.0;
}

static double cogging_torque(const double *p, double theta_e) {
    double t = 0.0;
    for (long k = 0; k < (long)p[P_COG_N]; k++)
        t += p[P_COG_AMP + k] * sin(p[P_COG_ORDER + k] * theta_e + p[P_COG_PHASE + k]);
    return t;
}

static void pitch_error(const double *p, double u, double *e, double *e1, double *e2) {
    *e = p[P_PITCH_LINEAR] * u;
    *e1 = p[P_PITCH_LINEAR];
    *e2 = 0.0;
    for (long k = 0; k < (long)p[P_PITCH_N]; k++) {
        double a = p[P_PITCH_AMP + k];
        double kw = p[P_PITCH_WAVENUMBER + k];
        double arg = kw * u + p[P_PITCH_PHASE + k];
        double sn = sin(arg);
        *e += a * sn;
        *e1 += a * kw * cos(arg);
        *e2 -= a * kw * kw * sn;
    }
}

/* ---- plant/kernel.py: pwm_event, motor_substep -------------------------------------- */
static void pwm_event(const double *p, double *s, const double *inp, double omega_m) {
    s[S_UD_APPLIED] = s[S_UD_NEXT];
    s[S_UQ_APPLIED] = s[S_UQ_NEXT];
    s[S_ID_MEAS] = measure_current(p, s, s[S_ID]);
    s[S_IQ_MEAS] = measure_current(p, s, s[S_IQ]);
    if (inp[I_ENABLE] <= 0.0) {
        s[S_UD_APPLIED] = s[S_UQ_APPLIED] = s[S_UD_NEXT] = s[S_UQ_NEXT] = 0.0;
        s[S_INT_D] = s[S_INT_Q] = 0.0;
        return;
    }
    if (inp[I_MODE] == INPUT_VOLTAGE) {
        double umax = p[P_U_MAX];
        double ud = inp[I_UD], uq = inp[I_UQ];
        double mag = sqrt(ud * ud + uq * uq);
        if (mag > umax) {
            double k = umax / mag;
            ud = ud * k;
            uq = uq * k;
        }
        s[S_UD_NEXT] = ud;
        s[S_UQ_NEXT] = uq;
    } else {
        dq_current_control(p, s, inp[I_ID_REF], inp[I_IQ_REF], omega_m);
    }
}

static double motor_substep(const double *p, double *s, const double *inp, double omega_m) {
    if (inp[I_ENABLE] <= 0.0) {
        double dt = p[P_DT];
        double torque = dq_torque(p, s[S_ID], s[S_IQ]);
        double u_link = 0.5 * p[P_UDC];
        s[S_ID] = freewheel(s[S_ID], u_link, p[P_LD], dt);
        s[S_IQ] = freewheel(s[S_IQ], u_link, p[P_LQ], dt);
        return torque;
    }
    double r = p[P_R];
    double we = p[P_POLE_PAIRS] * omega_m;
    double i_d = s[S_ID], i_q = s[S_IQ];
    double torque = dq_torque(p, i_d, i_q);
    double d_inf = (s[S_UD_APPLIED] + we * p[P_LQ] * i_q) / r;
    double q_inf = (s[S_UQ_APPLIED] - we * p[P_LD] * i_d - we * p[P_PSI]) / r;
    s[S_ID] = d_inf + (i_d - d_inf) * p[P_EXP_D];
    s[S_IQ] = q_inf + (i_q - q_inf) * p[P_EXP_Q];
    return torque;
}

/* ---- plant/effects/chain.py, friction.py ------------------------------------------- */
static inline double dead_zone(double delta, double gap) {
    if (gap <= 0.0) return delta;
    double half = 0.5 * gap;
    if (delta > half) return delta - half;
    if (delta < -half) return delta + half;
    return 0.0;
}

static void chain_internal_forces(const double *p, long po, double *s, long so, long n) {
    long xo = so, vo = so + n, fo = so + 2 * n;
    double carry = 0.0, x = s[xo], v = s[vo];
    for (long i = 0; i < n - 1; i++) {
        double x_next = s[xo + i + 1], v_next = s[vo + i + 1];
        double gap = p[po + 5 * n - 2 + i];
        double de = dead_zone(x_next - x, gap);
        double fl = p[po + 3 * n + i] * de;
        if (de != 0.0 || gap <= 0.0) fl += p[po + 4 * n - 1 + i] * (v_next - v);
        s[fo + i] = carry + fl - p[po + 2 * n + i] * x - p[po + n + i] * v;
        carry = -fl;
        x = x_next;
        v = v_next;
    }
    s[fo + n - 1] = carry - p[po + 3 * n - 1] * x - p[po + 2 * n - 1] * v;
}

static void chain_step(const double *p, long po, double *s, long so, long n, double dt) {
    long vo = so + n, fo = so + 2 * n;
    for (long i = 0; i < n; i++) {
        double v = s[vo + i] + dt * s[fo + i] / p[po + i];
        s[vo + i] = v;
        s[so + i] += dt * v;
    }
}

static double viscous_friction(const double *p, double v) {
    return -p[P_FR_VISCOUS] * v - p[P_FR_VISC_ASYM] * fabs(v);
}

static double sliding_friction(const double *p, double v) {
    double level = p[P_FR_COULOMB];
    double vs = p[P_FR_STRIBECK_V];
    if (vs > 0.0) {
        double r = v / vs;
        double x = r * r;
        if (x < STRIBECK_CUTOFF) level += (p[P_FR_STATIC] - p[P_FR_COULOMB]) * exp(-x);
    }
    if (v > 0.0) return viscous_friction(p, v) - level;
    if (v < 0.0) return viscous_friction(p, v) + level;
    return 0.0;
}

/* Karnopp stick-slip (friction.karnopp_friction); *stuck set, the force returned. */
static double table_friction(const double *p, double v, double f_app, double mass, double dt,
                             int *stuck) {
    *stuck = 0;
    if (p[P_FR_STATIC] <= 0.0) return viscous_friction(p, v);
    double f_h = p[P_FR_STATIC];
    if (fabs(v) <= p[P_FR_DV]) {
        if (fabs(f_app) <= f_h) {
            *stuck = 1;
            return -f_app;
        }
        return f_app > 0.0 ? -f_h : f_h;
    }
    double ff = sliding_friction(p, v);
    double v_new = v + dt * (f_app + ff) / mass;
    if (v_new * v <= 0.0 && fabs(f_app) <= f_h) {
        *stuck = 1;
        return -f_app;
    }
    return ff;
}

/* ---- plant/effects/screw_friction.py ------------------------------------------------ */
static double coulomb_projection(const double *p, long po, double *s, long so, long n, long i,
                                 double w, double level, double dt) {
    long vo = so + n, fo = so + 2 * n;
    double m0 = p[po + i], m1 = p[po + i + 1];
    double v = (1.0 - w) * s[vo + i] + w * s[vo + i + 1];
    double acc = (1.0 - w) * s[fo + i] / m0 + w * s[fo + i + 1] / m1;
    double inv_mass = (1.0 - w) * (1.0 - w) / m0 + w * w / m1;
    double t = -(v / dt + acc) / inv_mass;
    t = t > level ? level : (t < -level ? -level : t);
    s[fo + i] += (1.0 - w) * t;
    s[fo + i + 1] += w * t;
    return t;
}

static void screw_friction(const double *p, long po, double *s, long so, long n, long j,
                           double w, double f_nut, double dt) {
    double brg = p[P_BRG_COULOMB];
    if (brg > 0.0) {
        coulomb_projection(p, po, s, so, n, 1, 0.0, brg, dt);
        coulomb_projection(p, po, s, so, n, n - 2, 1.0, brg, dt);
    }
    double c = p[P_NUT_VISCOUS];
    if (c > 0.0) {
        long vo = so + n;
        double t = -c * ((1.0 - w) * s[vo + 1 + j] + w * s[vo + 2 + j]);
        s[so + 2 * n + 1 + j] += (1.0 - w) * t;
        s[so + 2 * n + 2 + j] += w * t;
    }
    double level = p[P_NUT_COULOMB] + p[P_NUT_LOAD_FR] * p[P_LEAD_RATIO] * fabs(f_nut);
    if (level > 0.0) coulomb_projection(p, po, s, so, n, 1 + j, w, level, dt);
}

/* ---- plant/kernel.py: nut_place, nut_coupling, screw_mechanics, substep ------------- */
static void nut_place(const double *p, const double *s, long na, long *j_out, double *w_out) {
    double pos = (p[P_NUT_S0] + s[S_TABLE_X]) / p[P_SEG_LEN];
    long j = (long)pos;
    j = j < 0 ? 0 : (j > na - 2 ? na - 2 : j);
    double w = pos - (double)j;
    *j_out = j;
    *w_out = w < 0.0 ? 0.0 : (w > 1.0 ? 1.0 : w);
}

static double nut_coupling(const double *p, double *s, long ro, long nr, long ao, long na,
                           long j, double w) {
    double theta = (1.0 - w) * s[ro + 1 + j] + w * s[ro + 2 + j];
    double omega = (1.0 - w) * s[ro + nr + 1 + j] + w * s[ro + nr + 2 + j];
    double u = (1.0 - w) * s[ao + j] + w * s[ao + j + 1];
    double du = (1.0 - w) * s[ao + na + j] + w * s[ao + na + j + 1];
    double u_nom = p[P_LEAD_RATIO] * theta;
    double e, e1, e2;
    pitch_error(p, u_nom, &e, &e1, &e2);
    double lead = p[P_LEAD_RATIO] * (1.0 + e1);
    double delta = u + u_nom + e - s[S_TABLE_X];
    double rate = du + lead * omega - s[S_TABLE_V];
    double gap = p[P_NUT_GAP];
    double de = dead_zone(delta, gap);
    double f = p[P_NUT_K] * de;
    if (de != 0.0 || gap <= 0.0) f += p[P_NUT_C] * rate;
    long fr = ro + 2 * nr, fa = ao + 2 * na;
    s[fr + 1 + j] -= (1.0 - w) * f * lead;
    s[fr + 2 + j] -= w * f * lead;
    s[fa + j] -= (1.0 - w) * f;
    s[fa + j + 1] -= w * f;
    return f;
}

static void screw_mechanics(const double *p, double *s, double load, double dt) {
    long ro = (long)p[P_SOFF_ROT], nr = (long)p[P_N_ROT];
    long ao = (long)p[P_SOFF_AX], na = (long)p[P_N_AX];
    long j;
    double w;
    nut_place(p, s, na, &j, &w);
    double f_nut = nut_coupling(p, s, ro, nr, ao, na, j, w);
    s[S_NUT_F] = f_nut;
    double v = s[S_TABLE_V];
    double m = p[P_TABLE_M];
    double f_stop = end_stop_force(p, s[S_TABLE_X], v);
    s[S_STOP_F] = f_stop;
    double f_app = f_nut + load + f_stop;
    int stuck;
    double ff = table_friction(p, v, f_app, m, dt, &stuck);
    s[S_FRICTION] = ff;
    s[S_STUCK] = stuck ? 1.0 : 0.0;
    if (p[P_SCREW_FRICTION] > 0.0)
        screw_friction(p, (long)p[P_OFF_ROT], s, ro, nr, j, w, f_nut, dt);
    chain_step(p, (long)p[P_OFF_ROT], s, ro, nr, dt);
    chain_step(p, (long)p[P_OFF_AX], s, ao, na, dt);
    v = stuck ? 0.0 : v + dt * (f_app + ff) / m;
    double x_old = s[S_TABLE_X];
    s[S_TABLE_V] = v;
    s[S_TABLE_X] = x_old + dt * v;
}

static void substep(const double *p, double *s, const double *inp) {
    double dt = p[P_DT];
    long ro = (long)p[P_SOFF_ROT], nr = (long)p[P_N_ROT];
    double omega_m = s[ro + nr];
    if (s[S_SUB_COUNT] == 0.0) pwm_event(p, s, inp, omega_m);
    s[S_SUB_COUNT] += 1.0;
    if (s[S_SUB_COUNT] >= p[P_SUB_PER_PWM]) s[S_SUB_COUNT] = 0.0;
    double torque = motor_substep(p, s, inp, omega_m)
                    + cogging_torque(p, p[P_POLE_PAIRS] * s[ro]);
    s[S_TORQUE] = torque;
    chain_internal_forces(p, (long)p[P_OFF_ROT], s, ro, nr);
    chain_internal_forces(p, (long)p[P_OFF_AX], s, (long)p[P_SOFF_AX], (long)p[P_N_AX]);
    s[ro + 2 * nr] += torque;
    double load = inp[I_LOAD] + p[P_EXT_LOAD];
    screw_mechanics(p, s, load, dt);
    s[S_TIME] += dt;
    if (s[S_SUB_COUNT] == 0.0 && p[P_DELAY_N] > 0.0) delay_push(p, s);
}

static int check_state(const double *p, const double *s, long n_s) {
    double limit = p[P_DIVERGE_LIMIT];
    for (long i = 0; i < n_s; i++) {
        double x = s[i];
        if (x != x || x - x != 0.0) return STATUS_NONFINITE;
        if (fabs(x) > limit) return STATUS_DIVERGED;
    }
    return STATUS_OK;
}

static void write_outputs(const double *p, const double *s, double *out, int status) {
    long ro = (long)p[P_SOFF_ROT], nr = (long)p[P_N_ROT];
    out[O_STATUS] = (double)status;
    out[O_TIME] = s[S_TIME];
    out[O_MOTOR_POS] = s[ro];
    out[O_MOTOR_VEL] = s[ro + nr];
    out[O_TABLE_POS] = s[S_TABLE_X];
    out[O_TABLE_VEL] = s[S_TABLE_V];
    double m[4];
    measured_delayed(p, s, m);
    out[O_ENCODER] = m[0];
    out[O_SCALE] = m[1];
    out[O_ID] = s[S_ID];
    out[O_IQ] = s[S_IQ];
    out[O_ID_MEAS] = m[2];
    out[O_IQ_MEAS] = m[3];
    out[O_TORQUE] = s[S_TORQUE];
    out[O_UD] = s[S_UD_APPLIED];
    out[O_UQ] = s[S_UQ_APPLIED];
    out[O_NUT_FORCE] = s[S_NUT_F];
    out[O_FRICTION] = s[S_FRICTION];
    double x = s[S_TABLE_X];
    int stroke = p[P_STROKE] > 0.0;
    out[O_LIMIT_NEG] = stroke && x < p[P_LIMIT_NEG] ? 1.0 : 0.0;
    out[O_LIMIT_POS] = stroke && x > p[P_LIMIT_POS] ? 1.0 : 0.0;
    out[O_END_STOP_F] = s[S_STOP_F];
    out[O_HOME_SWITCH] = home_switch(p, x);
    out[O_INDEX] = index_marks(p, m[0]);
}

/* ---- the exported API ---------------------------------------------------------------- */

/* 1 when this file runs the axis `p` describes (d-q motor, screw, lumped solver, no
 * presliding, no fault terms: the healthy machine's baseline), else 0. */
int c_supports(const double *p) {
    return p[P_MOTOR_MODEL] == MOTOR_DQ && p[P_MECH_MODEL] == MECH_SCREW
           && p[P_SOLVER] == SOLVER_LUMPED && !(p[P_PRE_ENABLED] > 0.0)
           && !(p[P_FAULTS] > 0.0);
}

/* plant.kernel.axis_step_nb: n_sub sub-steps with inp held, then the state check (n_s
 * state values) and the outputs; returns the status code. */
int c_axis_step(const double *p, double *s, const double *inp, double *out, long n_sub,
                long n_s) {
    for (long k = 0; k < n_sub; k++) substep(p, s, inp);
    int status = check_state(p, s, n_s);
    write_outputs(p, s, out, status);
    return status;
}

/* `calls` calls of c_axis_step (as a real-time loop makes them, one per PWM period);
 * returns the wall time they took, ns (CLOCK_MONOTONIC). */
double c_time_calls(const double *p, double *s, const double *inp, double *out, long n_sub,
                    long n_s, long calls) {
    struct timespec t0, t1;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (long c = 0; c < calls; c++) c_axis_step(p, s, inp, out, n_sub, n_s);
    clock_gettime(CLOCK_MONOTONIC, &t1);
    return (double)(t1.tv_sec - t0.tv_sec) * 1e9 + (double)(t1.tv_nsec - t0.tv_nsec);
}
