"""One bench trace: a Sinumerik-style cascade around :class:`~.axis.Axis`, written from the
``[controller]`` keys' documented meaning (not with :mod:`hil.controller`'s classes), the
measurements with their noise and quantisation, and the servo-trace CSV with every
convention in its header.

Per PWM period (the basic clock) k, in this order:

* the measurements of the period's start, delayed by ``[sensors] delay_s``: encoder and
  scale counts (floor, or the nearest count with ``[sensors] encoder_rounding = "round"``;
  of the travel since the start with ``encoder_zero_at_start``), the current with Gaussian
  noise, rounded to the ADC's step and clipped at its full scale (``adc_bits`` steps);
* every position cycle: e = x_set' - x_meas with x_set' the setpoint through a first-order
  lag of ``speedctrl_equiv_time_s``; v_P = K_v e;
* every speed cycle: the speed from the encoder's difference over the cycle, through the
  first-order filter of ``speed_actual_filter_s``; the feed-forward v_ff as trace-format.md
  defines it, per record row whatever the position cycle: the row's ``vel_set`` (the
  setpoint's velocity at the row plus any excitation given for it) held until the next
  row or, with ``feedforward_interpolation = "linear"``, interpolated linearly between the
  two rows that bracket the speed sample; w_set = clip(v_P + w_ff v_ff) / r; the PI
  (``speed_antiwindup``) gives the torque, / K_t the current setpoint, limited;
* the setpoint applied ``current_delay_cycles`` periods later, held over the period while
  the axis is integrated.

The run stands ``preroll_s`` at rest with the loops closed before its first sample.
"""

import collections
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.bench.identify_gen.axis import RTOL, Axis, AxisParams, UnsupportedModel, axis_params
from hil.bench.identify_gen.trajectory import Trajectory
from hil.controller.config import ControllerSection, axis_limits, kv_si, load_controller
from hil.trace_file import write_trace
from plant.config import MachineConfig, load_machine


@dataclass(frozen=True)
class Recording:
    """The sampled signals (SI table units, shape (n,)) and the noise floor per channel.

    Attributes:
        columns: the trace's columns in the file's units (mm, mm/min, A or deg).
        floor: deviation of measured minus true per channel: ``iq_rms_a``, ``pos_rms_um`` (or
            ``_urad``), ``motor_pos_rms_um``: what no model can explain.
        meta: the header's conventions.
        measured: the floor's channels as measured, in the floor's units (A, um, urad).
    """
    columns: dict
    floor: dict
    meta: dict
    measured: dict


class _PI:
    """Speed PI with the anti-windup modes of ``speed_antiwindup``."""

    def __init__(self, kp: float, ki_t: float, limit: float, mode: str):
        self.kp, self.ki_t, self.limit, self.mode = kp, ki_t, limit, mode
        self.integ = 0.0

    def __call__(self, e: float) -> float:
        u = self.kp * e + self.integ
        lim = self.limit
        # the generator has no D part and no torque feed-forward (_check_supported): the
        # whole torque setpoint is the PI's output, so 'torque_setpoint' is 'conditional'
        if self.mode in ("conditional", "torque_setpoint"):
            if (u > lim and e > 0) or (u < -lim and e < 0):
                return max(-lim, min(lim, u))
            self.integ += self.ki_t * e
        elif self.mode == "clamp":
            self.integ = max(-lim, min(lim, self.integ + self.ki_t * e))
        else:
            self.integ += self.ki_t * e
        return max(-lim, min(lim, u))


def _check_supported(cfg: MachineConfig, sec: ControllerSection) -> None:
    """UnsupportedModel naming the first [controller] key the generator does not model."""
    unsupported = {"plant_input": sec.plant_input != "current", "torque_ff": sec.torque_ff,
                   "speed_setpoint_lowpass_hz": sec.speed_setpoint_lowpass_hz > 0,
                   "current_setpoint_lowpass_hz": sec.current_setpoint_lowpass_hz > 0,
                   "notch_hz": sec.notch_hz > 0, "encoder_feedback_polarity":
                   sec.encoder_feedback_polarity < 0,
                   "speed_kd_nms2_per_rad": sec.speed_kd_nms2_per_rad > 0,
                   "speed_kd_ns2_per_m": sec.speed_kd_ns2_per_m > 0}
    for key, used in unsupported.items():
        if used:
            raise UnsupportedModel(f"{cfg.path}: [controller] {key} = {getattr(sec, key)!r}: "
                                   "not modelled by the bench's generator")


def _conventions(cfg: MachineConfig, sec: ControllerSection, dt_rec: float,
                 preroll_s: float, adc: tuple[int, float]) -> dict:
    """The header's convention keys (trace-format.md) of this run."""
    pwm = 1.0 / cfg.motor.pwm_frequency_hz
    sen = cfg.sensors
    meta = {
        "sample_time_s": repr(dt_rec),
        "position_loop_sample_time_s": repr(sec.position_cycle_ratio * pwm),
        "speed_loop_sample_time_s": repr(sec.speed_cycle_ratio * pwm),
        "current_loop_sample_time_s": repr(pwm),
        "feedforward_interpolation": sec.feedforward_interpolation,
        "velocity_feedforward_factor": repr(sec.speed_ff_weight if sec.speed_ff else 0.0),
        "speed_actual_filter_s": repr(sec.speed_actual_filter_s),
        "speed_antiwindup": sec.speed_antiwindup,
        "current_delay_cycles": str(sec.current_delay_cycles),
        "current_adc_bits": str(adc[0]), "current_adc_full_scale_a": repr(adc[1]),
        "preroll_s": repr(preroll_s), "vel_set_column": "feedforward",
        "encoder_rounding": sen.encoder_rounding,
        "encoder_zero_at_start": "true" if sen.encoder_zero_at_start else "false",
    }
    if cfg.machine.kind == "linear":
        meta["encoder_resolution_m"] = repr(sen.encoder_resolution_m)
    else:
        meta["encoder_counts_per_rev"] = str(sen.encoder_counts_per_rev)
    if sen.scale_resolution_m > 0:
        meta["scale_resolution_m"] = repr(sen.scale_resolution_m)
    return meta


def simulate(truth: str | Path, traj: Trajectory, *, record_every: int, preroll_s: float,
             adc_bits: int, seed: int, rtol: float = RTOL, progress=None,
             excitation: np.ndarray | None = None,
             start_m: float | None = None) -> Recording:
    """Run ``traj`` on the machine file ``truth`` (its ``[controller]`` with the
    conventions of the module docstring) and record every ``record_every`` PWM periods.

    Args:
        truth: machine file of the truth (first_order current loop, rigid or two_mass).
        traj: the setpoint (table units), starting at rest.
        record_every: PWM periods per record sample.
        preroll_s: s at rest before the first sample (a whole number of position cycles).
        adc_bits: the current ADC's bits; its full scale, where the measured current
            clips, is 2^(bits-1) times ``[sensors] current_lsb_a`` (the truth's
            ``current_full_scale_a`` must be 0 or that).
        seed: of the measurement noise.
        rtol: the integration's relative tolerance (the bench's repeat uses ten times
            RTOL: a trace that changes with it cannot be followed closer by any model).
        progress: optional callable(fraction).
        excitation: added to the speed feed-forward of each record row (m/s or rad/s),
            shape (n,) with n at least the number of rows (traj.duration_s over the sample
            time, plus one); the trace's ``vel_set`` holds it.
        start_m: where the table truly stands at the start (m or rad; default the
            trajectory's start).  Only with ``[sensors] encoder_zero_at_start``, whose
            encoders read the travel since the start, may it differ from it: the trace's
            frame is then the encoders', and the trajectory must start at 0.
    Raises:
        UnsupportedModel: a key of ``truth`` the generator does not model.
        ValueError: an excitation of the wrong shape, or a start the trajectory's frame
            contradicts.
    """
    cfg = load_machine(truth)
    sec = load_controller(cfg)
    _check_supported(cfg, sec)
    kind = cfg.machine.kind
    pwm = 1.0 / cfg.motor.pwm_frequency_hz
    lim = axis_limits(cfg, sec)
    p: AxisParams = axis_params(cfg)
    x_start, _ = traj.at(0.0)
    sen = cfg.sensors
    table0 = _start(cfg, float(x_start[0]), start_m)
    axis = Axis(p, table0, rtol)
    rng = np.random.default_rng(seed)
    lsb = sen.current_lsb_a
    full_scale = lsb * 2 ** (adc_bits - 1) if lsb > 0 else math.inf
    if sen.current_full_scale_a and sen.current_full_scale_a != full_scale:
        raise UnsupportedModel(f"{cfg.path}: [sensors] current_full_scale_a = "
                               f"{sen.current_full_scale_a:g} A: the generator's ADC clips at "
                               f"2^(adc_bits-1) current_lsb_a = {full_scale:g} A")
    rounding = 0.5 if sen.encoder_rounding == "round" else 0.0
    linear = kind == "linear"
    enc_step = sen.encoder_resolution_m if linear else 2 * math.pi / sen.encoder_counts_per_rev
    enc_step_table = enc_step * p.ratio  # one count in table units
    scale = sen.scale_resolution_m if kind != "rotary" else 0.0
    # the encoders' zeros: the axis's start, or position 0
    zero_motor, zero_table = ((axis.motor_position, axis.table_position)
                              if sen.encoder_zero_at_start else (0.0, 0.0))
    feedback_scale = sec.feedback == "scale"
    kt = p.kf * p.ratio  # torque (force) per ampere on the motor side
    n_pos, n_spd = sec.position_cycle_ratio, sec.speed_cycle_ratio
    t_pos = n_pos * pwm
    kv = kv_si(sec)
    w_ff = sec.speed_ff_weight if sec.speed_ff else 0.0
    linear_ff = sec.feedforward_interpolation == "linear"
    a_sym = math.exp(-t_pos / sec.speedctrl_equiv_time_s) if sec.speed_ff and \
        sec.speedctrl_equiv_time_s > 0 else 0.0
    a_filt = math.exp(-n_spd * pwm / sec.speed_actual_filter_s) if sec.speed_actual_filter_s \
        > 0 else 0.0
    kp = sec.speed_kp_ns_per_m if linear else sec.speed_kp_nms_per_rad
    pi = _PI(kp, kp * n_spd * pwm / sec.speed_tn_s if sec.speed_tn_s > 0 else 0.0,
             kt * p.i_max, sec.speed_antiwindup)
    delay_q = collections.deque([0.0] * sec.current_delay_cycles)
    meas_delay = round(sen.delay_s / pwm)
    meas_q: collections.deque = collections.deque(maxlen=meas_delay + 1)

    pre_ticks = round(preroll_s / t_pos) * n_pos
    n_rec = int(traj.duration_s / (record_every * pwm)) + 1
    # each row's feed-forward (one row past the last, for the interpolation toward it)
    v_rows = traj.at(np.arange(n_rec + 1) * record_every * pwm)[1]
    if excitation is not None:
        if np.ndim(excitation) != 1 or len(excitation) < n_rec:
            raise ValueError(f"excitation has shape {np.shape(excitation)}; the trace has "
                             f"{n_rec} rows")
        v_rows[:n_rec] += np.asarray(excitation[:n_rec], dtype=float)
        v_rows[n_rec] = v_rows[n_rec - 1]
    n_ticks = pre_ticks + n_rec * record_every
    rec = {k: np.empty(n_rec) for k in ("t", "x_set", "v_ff", "x", "v", "iq_set", "iq",
                                        "motor", "x_true", "motor_true", "iq_true")}
    x_sym = float(x_start[0])
    v_p = 0.0
    theta_prev = None
    w_act = 0.0
    i_set = 0.0
    x_set = float(x_start[0])
    row = 0
    for k in range(n_ticks):
        t = (k - pre_ticks) * pwm  # trace time; negative during the pre-roll
        true_motor, true_table, true_i = axis.motor_position, axis.table_position, axis.current
        counts = math.floor((true_motor - zero_motor) / enc_step_table + rounding + 1e-9)
        x_scale = math.floor((true_table - zero_table) / scale + rounding + 1e-9) * scale \
            if scale > 0 else math.nan
        i_meas = true_i + sen.current_noise_a * rng.standard_normal()
        if lsb > 0:
            i_meas = max(-full_scale, min(full_scale, round(i_meas / lsb) * lsb))
        meas_q.append((counts, x_scale, i_meas, true_motor, true_table, true_i))
        counts, x_scale, i_meas, true_motor, true_table, true_i = meas_q[0]
        motor_meas = counts * enc_step_table
        x_meas = x_scale if feedback_scale else motor_meas
        if k % n_pos == 0:
            x_set = float(traj.at(max(t, 0.0))[0][0])
            x_sym = x_set + (x_sym - x_set) * a_sym
            v_p = kv * (x_sym - x_meas)
        if k % n_spd == 0:
            theta = counts * enc_step
            if theta_prev is not None:
                w_raw = (theta - theta_prev) / (n_spd * pwm)
                w_act = w_raw + (w_act - w_raw) * a_filt
            theta_prev = theta
            v_ff = 0.0  # at rest before the first row
            if t >= 0:
                r, within = divmod(k - pre_ticks, record_every)
                r = min(r, n_rec)
                v_ff = v_rows[r]
                if linear_ff and r < n_rec:
                    v_ff += (v_rows[r + 1] - v_ff) * (within / record_every)
            v_cmd = v_p + w_ff * v_ff
            v_cmd = max(-lim.velocity, min(lim.velocity, v_cmd))
            i_set = max(-p.i_max, min(p.i_max, pi(v_cmd / p.ratio - w_act) / kt))
        delay_q.append(i_set)
        applied = delay_q.popleft()
        if t >= 0 and (k - pre_ticks) % record_every == 0 and row < n_rec:
            rec["t"][row] = t
            rec["x_set"][row] = float(traj.at(t)[0][0])
            rec["v_ff"][row] = v_rows[row]
            rec["x"][row] = x_meas
            rec["v"][row] = w_act * p.ratio
            rec["iq_set"][row] = i_set
            rec["iq"][row] = i_meas
            rec["motor"][row] = motor_meas
            rec["x_true"][row] = true_table
            rec["motor_true"][row] = true_motor
            # what no model can explain: the noise and the step, not the clipping
            rec["iq_true"][row] = max(-full_scale, min(full_scale, true_i))
            row += 1
            if progress is not None and row % max(1, n_rec // 20) == 0:
                progress(row / n_rec)
        axis.step(pwm, applied)
    return _recording(cfg, sec, rec, record_every * pwm, preroll_s, adc_bits, feedback_scale)


def _start(cfg: MachineConfig, traj_start: float, start_m: float | None) -> float:
    """The table's true start position (see :func:`simulate`'s ``start_m``)."""
    if cfg.sensors.encoder_zero_at_start:
        if traj_start != 0.0:
            raise ValueError(f"the trajectory starts at {traj_start:g}: with encoders zeroed "
                             "at the start ([sensors] encoder_zero_at_start) it is in their "
                             "frame and starts at 0")
        return traj_start if start_m is None else start_m
    if start_m is not None and start_m != traj_start:
        raise ValueError(f"start_m = {start_m:g} differs from the trajectory's start "
                         f"{traj_start:g}: only encoders zeroed at the start "
                         "([sensors] encoder_zero_at_start) read another frame")
    return traj_start


def _recording(cfg, sec, rec: dict, dt: float, preroll_s: float, adc_bits: int,
               feedback_scale: bool) -> Recording:
    """The trace's columns in the file's units, its header and the noise floor."""
    rotary = cfg.machine.kind == "rotary"
    k, u = (180.0 / math.pi, "deg") if rotary else (1e3, "mm")
    cols = {"t_s": rec["t"], f"pos_set_{u}": rec["x_set"] * k, f"pos_{u}": rec["x"] * k,
            f"vel_set_{u}_min": rec["v_ff"] * k * 60, f"vel_{u}_min": rec["v"] * k * 60,
            "iq_set_a": rec["iq_set"], "iq_a": rec["iq"]}
    if feedback_scale:
        cols[f"motor_pos_{u}"] = rec["motor"] * k
    full_scale = cfg.sensors.current_lsb_a * 2 ** (adc_bits - 1)
    meta = _conventions(cfg, sec, dt, preroll_s, (adc_bits, full_scale))

    pos_key = "pos_rms_urad" if rotary else "pos_rms_um"
    true_pos = rec["x_true"] if feedback_scale else rec["motor_true"]
    measured = {"iq_rms_a": rec["iq"], pos_key: rec["x"] * 1e6}
    true = {"iq_rms_a": rec["iq_true"], pos_key: true_pos * 1e6}
    if feedback_scale:
        measured["motor_pos_rms_um"] = rec["motor"] * 1e6
        true["motor_pos_rms_um"] = rec["motor_true"] * 1e6
    return Recording(cols, _rms_about_mean(measured, true), meta, measured)


def _rms_about_mean(a: dict, b: dict) -> dict:
    """Per channel of ``a`` the rms of a - b about its mean: a sensor's zero (a floor's half
    step) is no error a model can make."""
    return {k: float(np.std(a[k] - b[k])) for k in a}


def deviation(a: Recording, b: Recording) -> dict:
    """The rms deviation (about its mean, as the floor) of two recordings of one program
    per floor channel, in the floor's units: with ``b`` the same truth integrated at another
    tolerance, how closely the generator repeats itself through the sensors."""
    return _rms_about_mean(a.measured, b.measured)


def write(recording: Recording, path: Path, source: str) -> Path:
    """The recording as a servo-trace CSV with its conventions in the header."""
    return write_trace(path, recording.columns, {**recording.meta, "source": source})
