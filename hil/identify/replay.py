"""Closed-loop replay: a machine file's answer to a record's setpoints.

The setpoints of a measured :class:`~hil.identify.record.Record` run through the same
closed loop that produced it, around the machine file's plant; what comes out is the
model's prediction of the measured position and effort, on the record's time grid.  The
replay runs with the current-measurement noise off (it is the prediction; noise belongs
to the measurement) and keeps every quantisation (encoder, scale, current LSB).

* **EMPS records** (``rec.emps`` set): the dSPACE PD loop of the EMPS benchmark
  (``/work/shared/data/EMPS/SOURCE.md``).  Per 1 ms sample k the loop reads the plant's
  encoder, q(k) = counts * lead / counts_per_rev; filters qf(k) = (q(k) + q(k-1)) / 2 and
  differentiates q'(k) = (qf(k) - qf(k-1)) / dt; computes
  nu(k) = sat_{v_max}(kp kv (qr(k) - q(k)) - kv q'(k)); and applies
  u(k) = nu(k-1) + pulse(k) over [k, k+1) as the plant's q-current setpoint (the machine
  file maps 1 A to the force gtau; ``configs/emps.toml``).  The unit delay is the
  reference model's; the pulse is not delayed because the measured vir(k) already holds
  pulse(k) at the sample where pulses_N switches.  The plant starts at rest at the record's
  first measured position (the reference model starts at 0; the EMPS records start within
  8 µm of it).  ``Replay.effort`` is gtau u(k), the measured one gtau vir(k).
* **CST runs** (``rec.applied == "current"``: a ``hil run`` recording of a controller
  that closed the position and speed loops itself): the q-current setpoint the drive
  applied in each tick, held inside the drive's 6072h limit (``[drive] max_current_a``,
  as :meth:`hil.drive.EmulatedDrive` holds it), is the plant's input over that tick's PWM
  periods; the plant's current loop and mechanics answer it, and the sensors are read after
  the tick, where the recording reads them.  No loop of the machine file's ``[controller]``
  runs (they ran in the controller, and the record holds their output), so the replay is
  open loop: the record's timing, late or missed setpoints included, is in the setpoints
  the drive applied.  The plant starts at rest at the record's first measured position.
* **NC records** (servo traces, CSP runs): the machine file's ``[controller]`` with the record's
  conventions (:mod:`hil.identify.conventions`: the header's keys override the machine
  file's; :class:`~hil.identify.trace_controller.TraceController`) and the emulated drive in
  lock step (:class:`hil.sim.LockStep`: the NC's and the drive's compiled steady states
  in compiled blocks, as ``hil sim`` runs them; no fault injected).  The position cycle
  and the record's sample time are whole multiples of one another: the record's
  position setpoints are fed once per position cycle (every m-th sample when the cycle is
  m samples) or, when a sample spans several cycles, linearly fine-interpolated between
  samples.  The drive is enabled at the first setpoint and, with a header
  ``preroll_s``, held there at rest that long before t = 0.  The speed feed-forward is the
  ``vel_set`` column (trace-format.md), taken per record row whatever the position cycle:
  every speed cycle gets the rows' value at its instant, linearly interpolated between the
  rows that bracket it or the last row held (``feedforward_interpolation``;
  :class:`~hil.identify.trace_controller.TraceController`).  Where the header says the
  column is the whole speed command, the feed-forward is recovered exactly, v_ff = (v_cmd -
  K_v e) / w_ff with e the record's own position-loop error; without the column, the
  central difference of the position setpoint stands in (a few µm of following error on
  jerk-limited moves).  The acceleration for the torque feed-forward is the central
  difference of v_ff over the rows.  The signals are taken where the
  trace takes them (:func:`hil.sim.servo_trace_columns`): the position and motor encoder
  the controller read and the current measured at the start of the sample's PWM period.
"""

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from hil.controller.config import ControllerSection, axis_limits, load_controller
from hil.controller.interpolator import ProfileSamples
from hil.controller.loops import PositionLoop
from hil.drive.config import current_limit_a
from hil.identify.conventions import (
    ConventionError,
    Conventions,
    apply_conventions,
    read_conventions,
)
from hil.identify.record import Record
from hil.identify.trace_controller import TraceController
from hil.sim import AxisRecording, LockStep
from plant import Plant
from plant import layout as L
from plant.config import ConfigError, MachineConfig
from plant.kernel import axis_step_nb

#: how far a record's sample time may be from a whole number of plant periods (relative)
PERIOD_TOLERANCE = 1e-3
#: relative margin below the velocity limit at which a recorded speed command counts as
#: clipped (the mm/min round trip of the trace file changes the last digits)
CLIP_TOLERANCE = 1e-9
#: default first sample of :func:`errors`: MATLAB's sample 50, the EMPS scripts' n_border
ERROR_START = 49


@dataclass(frozen=True)
class Replay:
    """The model's answer to the record's setpoints, on the record's time grid.

    Attributes (arrays of shape (n,); NaN after a fault):
        pos: m (rad), what the record's ``pos`` would be (same sensor: scale or encoder).
        effort: same kind and unit as ``Record.effort`` (A or N).
        motor_pos: motor encoder in table units (m or rad), read with ``pos``.
        vel: the model's table velocity, m/s (rad/s).
        status: 0, or what stopped it: the drive's error code 603Fh (an NC record;
            :mod:`hil.drive.faults`), the plant's status (an EMPS record;
            ``plant.layout.STATUS_*``).
    """
    pos: np.ndarray
    effort: np.ndarray
    motor_pos: np.ndarray | None
    vel: np.ndarray
    status: int


def replay(cfg: MachineConfig, rec: Record, progress=None, compiled: bool = True) -> Replay:
    """Run ``rec``'s setpoints through ``cfg``'s closed loop (see the module docstring).

    Args:
        cfg: the machine file (an EMPS record or a CST run needs no ``[controller]``, an NC
            record does).
        rec: the measured record.
        progress: optional callable(fraction done), called about 20 times.
        compiled: run an NC record's lock step on the NC's and the drive's compiled
            paths (False: the Python controller and drive throughout, the reference the
            compiled paths are tested against).
    Raises:
        ConventionError: the record's sample time is no whole number of PWM periods, a
            convention of the record's header the replay cannot honour
            (naming the key), or a sample time and position cycle of which neither is a
            whole multiple of the other.
        ConfigError: an NC record and a machine file without ``[controller]``.
    """
    quiet = dataclasses.replace(cfg, sensors=dataclasses.replace(cfg.sensors,
                                                                 current_noise_a=0.0))
    if rec.emps is not None:
        return _replay_emps(quiet, rec, progress)
    if rec.applied == "current":
        return _replay_current(quiet, rec, progress)
    return _replay_nc(quiet, rec, progress, compiled)


def errors(rec: Record, rep: Replay, start: int = ERROR_START) -> dict[str, float]:
    """Error of the replay against the record over samples ``start`` .. n-1.

    ``pos_rms_um`` (``pos_rms_urad`` on rotary tables) and ``pos_relerr_pct``, and
    ``iq_rms_a``/``iq_relerr_pct`` or ``force_rms_n``/``force_relerr_pct``;
    relerr = 100 ||y - y_hat|| / ||y||, the EMPS paper's measure (its scripts start at
    MATLAB sample 50, index 49 here).
    """
    if not 0 <= start < rec.n:
        raise ValueError(f"error start {start} outside the record's {rec.n} samples")
    pos_name = "pos_rms_urad" if rec.rotary else "pos_rms_um"
    effort_name, unit = ("iq", "a") if rec.effort_kind == "iq" else ("force", "n")
    out = {}
    for y, y_hat, rms_name, rel_name, scale in (
            (rec.pos, rep.pos, pos_name, "pos_relerr_pct", 1e6),
            (rec.effort, rep.effort, f"{effort_name}_rms_{unit}",
             f"{effort_name}_relerr_pct", 1.0)):
        e = y[start:] - y_hat[start:]
        out[rms_name] = float(np.sqrt(np.mean(e * e)) * scale)
        out[rel_name] = float(100.0 * np.linalg.norm(e) / np.linalg.norm(y[start:]))
    return out


def _periods(plant: Plant, rec: Record) -> int:
    """PWM periods per record sample; ConventionError when not whole."""
    dt = rec.dt
    n = round(dt / plant.pwm_period)
    if n < 1 or abs(n * plant.pwm_period - dt) > PERIOD_TOLERANCE * dt:
        raise ConventionError(f"{rec.source}: sample_time_s {dt:g} s is not a whole number "
                              f"of the plant's PWM periods ({plant.pwm_period:g} s, [motor] "
                              "pwm_frequency_hz): the replay samples the plant's basic clock")
    return n


def _replay_emps(cfg: MachineConfig, rec: Record, progress) -> Replay:
    """The EMPS dSPACE PD loop around the plant (:func:`_emps_loop`)."""
    loop = rec.emps
    plant = Plant(cfg, table_pos=float(rec.pos[0]))
    n_per = _periods(plant, rec)
    p = plant.params
    m_per_count = plant.built.ratio / p[L.P_ENC_COUNTS_PER_RAD]
    pulses = loop.pulses_v if loop.pulses_v is not None else np.zeros(rec.n)
    n = rec.n
    pos, vel, effort = np.full(n, math.nan), np.full(n, math.nan), np.full(n, math.nan)
    status = _emps_loop(p, plant.state, plant.inp, plant.out, n_per * plant.sub_per_pwm,
                        n_per * plant.pwm_period, m_per_count,
                        np.ascontiguousarray(rec.pos_set, dtype=np.float64),
                        np.ascontiguousarray(pulses, dtype=np.float64), loop.kp * loop.kv,
                        loop.kv, loop.v_max, loop.gtau, pos, vel, effort)
    if progress is not None:
        progress(1.0)
    return Replay(pos=pos, effort=effort, motor_pos=pos.copy(), vel=vel, status=int(status))


@njit(cache=True, error_model="numpy")
def _emps_loop(p, s, inp, out, n_sub, dt, m_per_count, qr, pulses, gain, kv, v_max, gtau,
               pos, vel, effort):
    """The EMPS loop, one kernel call per sample, compiled: a replay is called tens of
    times by the identification's refinement.  Fills pos, vel, effort (shape (n,));
    returns the plant's status (samples after a fault stay NaN)."""
    q1 = out[L.O_ENCODER] * m_per_count
    q2 = q1
    nu_prev = 0.0
    for k in range(qr.size):
        q = out[L.O_ENCODER] * m_per_count
        dq = 0.5 * (q - q2) / dt  # (qf(k) - qf(k-1)) / dt with qf(k) = (q(k) + q(k-1)) / 2
        q2 = q1
        q1 = q
        nu = gain * (qr[k] - q) - kv * dq
        nu = min(v_max, max(-v_max, nu))
        u = nu_prev + pulses[k]
        nu_prev = nu
        pos[k] = q
        vel[k] = out[L.O_TABLE_VEL]
        effort[k] = gtau * u
        inp[L.I_IQ_REF] = u
        status = axis_step_nb(p, s, inp, out, n_sub)
        if status != L.STATUS_OK:
            return status
    return L.STATUS_OK


def _replay_current(cfg: MachineConfig, rec: Record, progress) -> Replay:
    """A CST run's applied q-current setpoints into the plant (module docstring)."""
    plant = Plant(cfg, table_pos=float(rec.pos[0]))
    n_per = _periods(plant, rec)
    p = plant.params
    per_count = plant.built.ratio / p[L.P_ENC_COUNTS_PER_RAD]
    n = rec.n
    pos, motor_pos = np.full(n, math.nan), np.full(n, math.nan)
    vel, effort = np.full(n, math.nan), np.full(n, math.nan)
    status = _current_fed(p, plant.state, plant.inp, plant.out, n_per * plant.sub_per_pwm,
                          np.ascontiguousarray(rec.iq_set, dtype=np.float64),
                          current_limit_a(cfg), per_count, pos, motor_pos, vel, effort)
    if progress is not None:
        progress(1.0)
    return Replay(pos=pos, effort=effort, motor_pos=motor_pos, vel=vel, status=int(status))


@njit(cache=True, error_model="numpy")
def _current_fed(p, s, inp, out, n_sub, iq_set, limit, per_count, pos, motor_pos, vel,
                 effort):
    """The plant on ``iq_set`` (A, one per sample, within +-``limit``), compiled as
    :func:`_emps_loop` is.  Fills pos (the scale, else the motor encoder; m or rad),
    motor_pos, vel and effort (the measured q current, A) after each sample, shape (n,);
    returns the plant's status (samples after a fault stay NaN)."""
    scale = p[L.P_SCALE_RES]
    for k in range(iq_set.size):
        inp[L.I_IQ_REF] = min(limit, max(-limit, iq_set[k]))
        status = axis_step_nb(p, s, inp, out, n_sub)
        if status != L.STATUS_OK:
            return status
        motor_pos[k] = out[L.O_ENCODER] * per_count
        pos[k] = out[L.O_SCALE] * scale if scale > 0.0 else motor_pos[k]
        vel[k] = out[L.O_TABLE_VEL]
        effort[k] = out[L.O_IQ_MEAS]
    return L.STATUS_OK


@dataclass(frozen=True)
class _Grid:
    """How the record's samples meet the controller's cycles (all in PWM periods).

    Attributes:
        every: record sample time.
        ipo: spacing of the setpoints fed to the controller: the record's samples, or every
            ``step``-th of them when the position cycle is a multiple of the sample time.
        step: record samples per fed setpoint.
    """
    every: int
    ipo: int
    step: int


def _grid(rec: Record, plant: Plant, sec: ControllerSection, path: str) -> _Grid:
    """The record's sample time against the position cycle: either a whole multiple of the
    other (the trace-format convention), else a ConventionError naming the key."""
    ratio_pos = sec.position_cycle_ratio
    every = _periods(plant, rec)
    if ratio_pos % every == 0:
        return _Grid(every, ratio_pos, ratio_pos // every)
    if every % ratio_pos == 0:
        return _Grid(every, every, 1)
    raise ConventionError(
        f"{rec.source}: sample time {rec.dt:g} s is {every} PWM periods, the position cycle "
        f"is {ratio_pos} ([controller] position_cycle_ratio of {path}, or the header's "
        "position_loop_sample_time_s): neither is a whole multiple of the other")


def _feed_forward(rec: Record, conv: Conventions, loop: PositionLoop, step: int) -> np.ndarray:
    """The speed feed-forward (m/s, shape (n,)) the NC added to the P path.

    ``vel_set`` is that feed-forward (trace-format.md) unless the header says it is the
    whole speed command (``vel_set_column: speed_command``); then it is recovered exactly
    at every row where the command is below the velocity limit (a clipped command hides
    it), v_ff = (v_cmd - K_v e) / w_ff with e the record's own position-loop error of the
    last position cycle (every ``step``-th sample; the P part is held between them).
    Without the column, the setpoint's central difference stands in."""
    v_est = np.gradient(rec.pos_set, rec.dt)
    if rec.vel_set is None:
        return v_est
    if conv.vel_set_column == "feedforward":
        return rec.vel_set.copy()
    if loop.ff == 0.0:
        return v_est
    v_ff = v_est.copy()
    loop.reset(float(rec.pos[0]))
    for k in range(rec.n):
        if k % step == 0:
            loop.step(float(rec.pos_set[k]), 0.0, float(rec.pos[k]))
        v_ff[k] = (rec.vel_set[k] - loop.kv * loop.error) / loop.ff
    clipped = np.abs(rec.vel_set) >= loop.v_lim * (1.0 - CLIP_TOLERANCE)
    v_ff[clipped] = v_est[clipped]
    return v_ff


def _preroll_points(ctrl: TraceController, x0: float, ticks: int) -> ProfileSamples:
    """IPO points holding ``x0`` at rest for ``ticks`` PWM periods (and a little more)."""
    n_ipo = ticks // ctrl.sec.ipo_cycle_ratio + 2
    zero = np.zeros(n_ipo)
    return ProfileSamples(zero, np.full(n_ipo, x0), zero, zero)


def _replay_nc(cfg: MachineConfig, rec: Record, progress, compiled: bool = True) -> Replay:
    """The machine file's NC (with the record's conventions) and drive in lock step
    (:class:`hil.sim.LockStep`, no fault injected), the record's setpoints fed once per
    position cycle or once per sample, whichever is the longer."""
    conv = read_conventions(rec, cfg)
    cfg = apply_conventions(cfg, conv)
    try:
        sec = load_controller(cfg)
    except ConfigError as exc:
        if conv.overrides.get("controller"):
            raise ConventionError(f"{rec.source}: the header's conventions "
                                  f"{conv.given} make no valid [controller]: {exc}") from None
        raise
    x0 = float(rec.pos_set[0])
    plant = Plant(cfg, table_pos=x0)
    grid = _grid(rec, plant, sec, cfg.path)
    n_pos = sec.position_cycle_ratio
    period_pos = n_pos * plant.pwm_period
    section = dataclasses.replace(sec, ipo_cycle_ratio=grid.ipo)
    ctrl = TraceController(cfg, plant.pwm_period, x0, section, compiled=compiled)
    ls = LockStep(cfg, x0, inject=None, compiled=compiled, plant=plant, ctrl=ctrl)
    try:
        ls.enable(ctrl.enable_timeout_ticks * 2)
    except RuntimeError:
        raise RuntimeError(f"{cfg.path}: drive not enabled: {ctrl.enable.reason}") from None
    preroll_ticks = round(conv.preroll_s / ctrl.period)
    if preroll_ticks > 0:
        ctrl.follow_feed_forward(np.zeros(preroll_ticks // grid.every + 2), grid.every)
        ctrl.run_points(_preroll_points(ctrl, x0, preroll_ticks))
        ls.run_ticks(preroll_ticks)
    v_lim = axis_limits(cfg, sec).velocity
    v_set = _feed_forward(rec, conv, PositionLoop(sec, period_pos, v_lim), grid.step)
    # the speed loop takes the feed-forward of every row (trace-format.md); the position
    # loop only the setpoints of its cycles
    ctrl.follow_feed_forward(v_set, grid.every)
    fed = slice(0, rec.n, grid.step)
    ctrl.run_points(ProfileSamples(rec.t[fed], rec.pos_set[fed], v_set[fed],
                                   np.gradient(v_set, rec.dt)[fed]))
    # the record's t = 0 is the first position cycle
    first = -(-ctrl.tick_count // n_pos) * n_pos
    out = AxisRecording(rec.n, ctrl, plant)
    drive = ls.drive
    ls.record([out], rec.n, first, grid.every, progress, stop=lambda: drive.fault != 0)
    per_amp = _force_per_amp(cfg, ctrl.ratio) if rec.effort_kind == "force" else 1.0
    return Replay(out.rec["x_act"], out.rec["iq_meas"] * per_amp,
                  out.rec["motor_pos_meas"] * ctrl.ratio, out.rec["table_vel"],
                  int(drive.fault))


def _force_per_amp(cfg: MachineConfig, ratio: float) -> float:
    """Table force per q-current ampere, N/A (N·m/A on rotary tables)."""
    if cfg.machine.kind == "linear":
        return cfg.motor.force_constant_n_per_a
    return cfg.motor.torque_constant_nm_per_a / ratio
