"""The generator's axis: the equations of motion written from a machine file's keys as the
schema documents them (``hil config-keys``), solved with ``scipy.integrate.solve_ivp``.

Nothing here runs or imports the plant's kernel: the machine file is only read for its
values (``plant.config``), and every law is written again from its documented definition,
in another formulation where the kernel's is a numerical choice:

* coordinates in table units (m; rad on rotary tables), inertias reflected through
  r = lead / 2pi (screws) or 1;
* ``first_order`` current loop: di/dt = (i_set - i) / T_cl, a continuous state;
* ``rigid`` mechanics: one mass; ``two_mass``: motor and load coupled by a spring of
  stiffness k / r^2 with its damper acting in contact only and a dead zone of the backlash;
* friction on the table: -(B v + dB |v|) - sign(v) (F_C + (F_H - F_C) exp(-(v/v_s)^2))
  while sliding; stuck (v = 0 exactly) while the force on it stays within F_H, as a hybrid
  system -- solve_ivp stops at each zero of the velocity (an event), and the axis sticks or
  slides on by the force there, and a stuck axis breaks away where the force on it reaches
  F_H (another event) -- instead of Karnopp's band around v = 0; or, with
  ``[presliding]``, the spring dF/dx = k1 / (|(x - x_rev)/x1|^a + 1) as a state, limited to
  +-F_C, restarted where the velocity reverses (an event);
* cogging: sum A_k sin(n_k theta_e + phi_k) on the motor (theta_e = pole pairs x motor angle,
  or pi x / pole pitch);
* pitch error: the table stands at x = u + e(u), e(u) = sum A_k sin(2 pi u / P_k + phi_k)
  + c u, u the nut's nominal travel; the linear scale reads x, the motor encoder reads u.
  The table (its mass m_t) moves with x: its velocity is g u', g = 1 + e'(u), its
  friction, viscous and external forces act at that velocity and reach u's equation
  times g (virtual work), and its inertia adds m_t (g^2 u'' + g e''(u) u'^2) to u's
  (Lagrange's equation of the constraint x(u), written exactly);
* the constant external force (torque) on the table.
"""

import math
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

from plant.config import MachineConfig

#: solve_ivp tolerances, absolute per state (positions m, velocities m/s, current A,
#: presliding force N): two orders below the finest sensor step of the bench's axes.  The
#: relative one keeps rtol |x| below the positions' absolute one over the whole travel
#: (0.4 m, 2 pi rad): at 1e-7 it allowed 10-40 nm per step, and the gap between motor and
#: load, a difference of two positions, strayed by up to 0.25 um from the converged solution
RTOL = 1e-11
ATOL = np.array([1e-10, 1e-8, 1e-10, 1e-8, 1e-6, 1e-4])


class UnsupportedModel(ValueError):
    """A machine-file feature the generator does not model (the message names the key)."""


@dataclass(frozen=True)
class AxisParams:
    """Every parameter of the equations, SI in table units (see the module docstring)."""
    kind: str
    ratio: float
    kf: float
    t_cl: float
    i_max: float
    m_motor: float
    m_load: float
    m_table: float
    two_mass: bool
    k_c: float
    c_c: float
    backlash: float
    b_motor: float
    b: float
    db: float
    fc: float
    fh: float
    vs: float
    presliding: tuple | None
    cog: tuple
    poles: float
    pitch: tuple
    pitch_linear: float
    f_ext: float

    @property
    def mass(self) -> float:
        """Total moved inertia at the table (kg, kg m^2)."""
        return self.m_motor + self.m_load


def axis_params(cfg: MachineConfig) -> AxisParams:
    """The equations' parameters from ``cfg``.  UnsupportedModel names a key the generator
    does not model."""
    kind, mo, me = cfg.machine.kind, cfg.motor, cfg.mechanics
    if mo.model != "first_order":
        raise UnsupportedModel(f"{cfg.path}: [motor] model = {mo.model!r}: the generator "
                               "models 'first_order' only")
    if me.model not in ("rigid", "two_mass"):
        raise UnsupportedModel(f"{cfg.path}: [mechanics] model = {me.model!r}: the generator "
                               "models 'rigid' and 'two_mass'")
    r = me.lead_m / (2 * math.pi) if kind == "screw" else 1.0
    linear = kind == "linear"
    kf = mo.force_constant_n_per_a if linear else mo.torque_constant_nm_per_a / r
    motor = (mo.mass_kg if linear else mo.inertia_kgm2) / r ** 2
    table = cfg.table.mass_kg if cfg.table is not None else 0.0
    fr = cfg.friction
    if kind == "rotary":
        b, db, fc = fr.viscous_nms_per_rad, fr.viscous_asymmetry_nms_per_rad, fr.coulomb_nm
        fh, vs, f_ext = fr.breakaway_nm, fr.stribeck_velocity_rad_s, me.external_torque_nm
    else:
        b, db, fc = fr.viscous_ns_per_m, fr.viscous_asymmetry_ns_per_m, fr.coulomb_n
        fh, vs, f_ext = fr.breakaway_n, fr.stribeck_velocity_m_s, cfg.table.external_force_n
    two = me.model == "two_mass"
    cp = cfg.coupling
    half_c = 0.5 * cp.inertia_kgm2 / r ** 2 if two else 0.0
    pre = cfg.presliding
    cg = cfg.cogging
    amps = cg.amplitudes_n if linear else cg.amplitudes_nm
    phases = cg.phases_deg or (0.0,) * len(cg.orders)
    cog = tuple((n, a / r, math.radians(ph)) for n, a, ph in zip(cg.orders, amps, phases))
    pe = cfg.pitch_error
    pitch = ()
    pitch_linear = 0.0
    if pe is not None and kind == "screw":
        ph = pe.phases_deg or (0.0,) * len(pe.periods_m)
        pitch = tuple((p, a, math.radians(f)) for p, a, f in zip(pe.periods_m, pe.amplitudes_m, ph))
        pitch_linear = pe.linear_ppm * 1e-6
    return AxisParams(
        kind=kind, ratio=r, kf=kf, t_cl=cfg.current_loop.time_constant_s,
        i_max=mo.current_max_a, m_motor=motor + half_c,
        m_load=half_c + me.load_inertia_kgm2 / r ** 2 + table, m_table=table, two_mass=two,
        k_c=cp.stiffness_nm_per_rad / r ** 2 if two else 0.0,
        c_c=cp.damping_nms_per_rad / r ** 2 if two else 0.0,
        backlash=cp.backlash_rad * r if two else 0.0,
        b_motor=mo.viscous_nms_per_rad / r ** 2, b=b, db=db, fc=fc,
        fh=fh if fh > 0.0 else fc, vs=vs,
        presliding=(pre.stiffness_n_per_m, pre.x1_m, pre.exponent) if pre is not None
        and pre.enabled else None,
        cog=cog, poles=math.pi / mo.pole_pitch_m if linear else mo.pole_pairs,
        pitch=pitch, pitch_linear=pitch_linear, f_ext=f_ext)


def pitch_position(p: AxisParams, u: float) -> float:
    """Where the table stands when the nut's nominal travel is ``u`` (m)."""
    e = sum(a * math.sin(2 * math.pi * u / per + ph) for per, a, ph in p.pitch)
    return u + e + p.pitch_linear * u


def pitch_slope(p: AxisParams, u: float) -> tuple[float, float]:
    """(g, e'') at the nut's nominal travel ``u`` (m): g = dx/du = 1 + e'(u) and the
    error's curvature e''(u) (1/m)."""
    g, curv = 1.0 + p.pitch_linear, 0.0
    for per, a, ph in p.pitch:
        k = 2 * math.pi / per
        g += a * k * math.cos(k * u + ph)
        curv -= a * k * k * math.sin(k * u + ph)
    return g, curv


def nut_travel(p: AxisParams, x: float) -> float:
    """The nut's nominal travel u that puts the table at ``x`` (the inverse of
    :func:`pitch_position`, by fixed-point iteration: |e'| << 1)."""
    u = x
    for _ in range(50):
        u_next = x - (pitch_position(p, u) - u)
        if abs(u_next - u) < 1e-15:
            break
        u = u_next
    return u


class Axis:
    """The axis's state and its integration over one interval at a held current setpoint.

    State y: [u_m, v_m, u_l, v_l, i, f_pre] (motor side and load side in table units; a
    rigid axis keeps u_l = u_m).  ``stuck``: the load sticks (v_l = 0); ``x_rev`` and
    ``direction`` hold the presliding spring's last reversal.
    """

    def __init__(self, p: AxisParams, x0: float, rtol: float = RTOL):
        """At rest with the table at ``x0`` (m or rad); ``rtol``: solve_ivp's relative
        tolerance (the absolute ones are ATOL)."""
        self.p = p
        self.rtol = rtol
        u0 = nut_travel(p, x0) if p.pitch else x0
        self.y = np.array([u0, 0.0, u0, 0.0, 0.0, 0.0])
        self.x_rev = u0
        self.direction = 0.0
        self.stuck = p.presliding is None and p.fh > 0.0

    def _level(self, v: float) -> float:
        p = self.p
        return p.fc + ((p.fh - p.fc) * math.exp(-(v / p.vs) ** 2) if p.vs > 0 else 0.0)

    def _drive(self, y: np.ndarray) -> tuple[float, float, float]:
        """(force of the motor on the motor side, coupling force on the load, external and
        viscous force on the table, at the table's velocity) at state ``y``, friction of
        the contact left out."""
        p = self.p
        u_m, v_m, u_l, v_l, i, _ = y
        theta_e = p.poles * u_m / p.ratio
        f_motor = p.kf * i + sum(a * math.sin(n * theta_e + ph) for n, a, ph in p.cog)
        f_motor -= p.b_motor * v_m
        f_c = 0.0
        if p.two_mass:
            delta = u_m - u_l
            half = 0.5 * p.backlash
            de = delta - half if delta > half else (delta + half if delta < -half else 0.0)
            f_c = p.k_c * de + (p.c_c * (v_m - v_l) if de != 0.0 or half == 0.0 else 0.0)
        v_t = self._table_velocity(y)
        return f_motor, f_c, p.f_ext - p.b * v_t - p.db * abs(v_t)

    def _table_velocity(self, y: np.ndarray) -> float:
        """The table's velocity g u_l' (m/s; rad/s) at state ``y``."""
        return pitch_slope(self.p, y[2])[0] * y[3] if self.p.pitch else y[3]

    def _rhs(self, _t: float, y: np.ndarray, i_set: float, slide: float) -> list[float]:
        """d/dt y; ``slide``: the direction of sliding (0 while stuck)."""
        p = self.p
        u_m, v_m, u_l, v_l, i, f_pre = y
        f_motor, f_c, f_load = self._drive(y)
        g, curv = pitch_slope(p, u_l) if p.pitch else (1.0, 0.0)
        v_t = g * v_l
        di = (i_set - i) / p.t_cl
        df = 0.0
        if p.presliding is not None:
            k1, x1, a = p.presliding
            df = k1 / (abs((u_l - self.x_rev) / x1) ** a + 1.0) * v_t if x1 > 0 else k1 * v_t
            if (f_pre >= p.fc and df > 0) or (f_pre <= -p.fc and df < 0):
                df = 0.0
            friction = -f_pre
        else:
            friction = -slide * self._level(v_t)
        # the table's forces reach u_l times g; its inertia is m_t g^2 and its share of the
        # curved kinematics m_t g e'' u_l'^2 (module docstring)
        m_extra = p.m_table * (g * g - 1.0)
        f_table = g * (f_load + friction) - p.m_table * g * curv * v_l * v_l
        if not p.two_mass:
            if slide == 0.0 and p.presliding is None:
                return [0.0, 0.0, 0.0, 0.0, di, 0.0]
            acc = (f_motor + f_table) / (p.mass + m_extra)
            return [v_m, acc, v_m, acc, di, df]
        acc_l = 0.0 if slide == 0.0 and p.presliding is None else \
            (f_c + f_table) / (p.m_load + m_extra)
        return [v_m, (f_motor - f_c) / p.m_motor, v_l if acc_l or slide else 0.0, acc_l, di, df]

    def _applied(self, y: np.ndarray) -> float:
        """The force on the table besides its sliding friction (N or N·m): the drive's
        reaches it divided by g."""
        f_motor, f_c, f_load = self._drive(y)
        g = pitch_slope(self.p, y[2])[0] if self.p.pitch else 1.0
        return (f_c if self.p.two_mass else f_motor) / g + f_load

    def _release(self, _t: float, y: np.ndarray, *_) -> float:
        """Zero where the force on the stuck load reaches F_H: the load breaks away there
        (a gap closing within an interval loads the flank in microseconds, long before the
        interval ends)."""
        return abs(self._applied(y)) - self.p.fh

    _release.terminal = True
    _release.direction = 1.0

    def step(self, dt: float, i_set: float) -> None:
        """Integrate over ``dt`` seconds with the current setpoint ``i_set`` (A) held."""
        p = self.p
        i_set = max(-p.i_max, min(p.i_max, i_set))
        if p.presliding is not None:
            self.y = self._presliding_step(dt, i_set)
            return
        t = 0.0
        y = self.y
        for _ in range(8):  # a few stick/slip switches per interval at most
            if self.stuck:
                f = self._applied(y)
                if abs(f) > p.fh:
                    self.stuck = False
                    slide = math.copysign(1.0, f)
                else:
                    sol = solve_ivp(self._rhs, (t, dt), y, args=(i_set, 0.0),
                                    rtol=self.rtol, atol=ATOL, max_step=dt,
                                    events=self._release)
                    y = sol.y[:, -1].copy()
                    y[3] = 0.0
                    if not p.two_mass:
                        y[1] = 0.0
                    if sol.status != 1:
                        break
                    # released within the interval: slide on from there
                    t = float(sol.t[-1])
                    self.stuck = False
                    continue
            else:
                slide = math.copysign(1.0, y[3]) if y[3] != 0.0 else \
                    math.copysign(1.0, self._applied(y))

            def zero(_t, yy, *_):
                return yy[3]
            zero.terminal = True
            zero.direction = -slide
            sol = solve_ivp(self._rhs, (t, dt), y, args=(i_set, slide), rtol=self.rtol,
                            atol=ATOL, max_step=dt, events=zero)
            y = sol.y[:, -1].copy()
            if sol.status != 1:
                break
            if sol.t[-1] <= t + 1e-9 * dt:
                # a zero at the interval's start (the load just released): slide through it
                sol = solve_ivp(self._rhs, (t, dt), y, args=(i_set, slide), rtol=self.rtol,
                                atol=ATOL, max_step=dt)
                y = sol.y[:, -1].copy()
                break
            t = float(sol.t[-1])
            y[3] = 0.0
            if not p.two_mass:
                y[1] = 0.0
            self.stuck = abs(self._applied(y)) <= p.fh
            if t >= dt:
                break
        self.y = y

    def _presliding_step(self, dt: float, i_set: float) -> np.ndarray:
        """The state after ``dt`` seconds with the presliding spring: solve_ivp stops where
        the load's velocity reverses (an event) and the spring restarts from that position."""
        p = self.p
        t = 0.0
        y = self.y
        for _ in range(8):  # a few reversals per interval at most

            def reversal(_t, yy, *_):
                return yy[3]
            reversal.terminal = True
            reversal.direction = -self.direction
            sol = solve_ivp(self._rhs, (t, dt), y, args=(i_set, 1.0), rtol=self.rtol,
                            atol=ATOL, max_step=dt,
                            events=reversal if self.direction else None)
            y = sol.y[:, -1].copy()
            y[5] = max(-p.fc, min(p.fc, y[5]))
            if sol.status != 1:
                break
            t = float(sol.t[-1])
            y[3] = 0.0
            # a velocity that only touches zero and goes on the same way is no reversal
            if self._rhs(t, y, i_set, 1.0)[3] * self.direction <= 0.0:
                self.x_rev = float(y[2])
                self.direction = -self.direction
        if self.direction == 0.0 and y[3] != 0.0:
            # the first motion: the spring starts relaxed where the axis stood (x_rev)
            self.direction = math.copysign(1.0, y[3])
        return y

    @property
    def motor_position(self) -> float:
        """The motor-side position in table units (m or rad)."""
        return float(self.y[0])

    @property
    def table_position(self) -> float:
        """Where the table stands (pitch error included), m or rad."""
        return pitch_position(self.p, float(self.y[2])) if self.p.pitch else float(self.y[2])

    @property
    def current(self) -> float:
        return float(self.y[4])
