"""One trace of the second generator: the program run through :mod:`.loop` on a machine
file's values with a case's conventions, the noise floor, and the servo-trace file.

The floor is what no model can explain: per channel the rms (about its mean) of measured
minus true, the current's noise and ADC step (not its clipping, which the header declares)
and the encoders' quantisation.  The repeat is the same run at a finer integration step
with the same noise: where the trace changes with the step, no model follows it closer.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.trace_file import write_trace
from plant.config import MachineConfig

from . import loop
from .axis import axis_constants
from .controller import Conventions, header, loop_constants
from .program import Program

#: integration steps per PWM period (the repeat: four times as many)
SUBSTEPS = 16
RECORD_S = 0.001
PREROLL_S = 0.5


@dataclass(frozen=True)
class Trace:
    """A generated trace.

    Attributes:
        columns: the trace's columns in the file's units (mm, mm/min, A; deg on a rotary
            table), shape (n,) each.
        meta: the header's convention keys.
        floor: measured minus true per channel (``iq_rms_a``, ``pos_rms_um`` or
            ``pos_rms_urad``, ``motor_pos_rms_um`` with a scale), in A, um, urad.
        measured: those channels as measured, same units, shape (n,).
    """
    columns: dict
    meta: dict
    floor: dict
    measured: dict


def simulate(cfg: MachineConfig, conv: Conventions, prog: Program, *, x0: float, seed: int,
             substeps: int = SUBSTEPS) -> Trace:
    """Run ``prog`` (its positions in the encoders' frame) on ``cfg`` with ``conv``.

    Args:
        cfg: the truth's machine file (its physics and its ``[controller]`` gains).
        conv: the controller's and sensors' conventions.
        prog: the setpoint, m or rad.
        x0: where the axis truly starts, m or rad: the program's start, or anywhere when
            the encoders are zeroed at the start (the program then starts at 0).
        seed: of the current noise.
        substeps: integration steps per PWM period.
    Raises:
        UnsupportedFeature: a machine-file key outside the generator's equations.
        ValueError: a program whose start contradicts ``x0`` and the encoders' zero.
    """
    start = float(prog.position(0.0))
    if start != (0.0 if conv.encoder_zero_at_start else x0):
        raise ValueError(f"the program starts at {start:g}, the axis at {x0:g}: zeroed "
                         "encoders need a program from 0, others one from x0")
    ax, cog = axis_constants(cfg)
    lc = loop_constants(cfg, conv, RECORD_S, PREROLL_S, substeps)
    n_rows = int(prog.duration_s / RECORD_S) + 1
    n_ticks = lc.pre_ticks + n_rows * lc.n_rec
    t_pos = (np.arange(n_ticks // lc.n_pos + 1) * lc.n_pos - lc.pre_ticks) * lc.pwm_s
    x_set = prog.position(np.maximum(t_pos, 0.0))
    t_rows = np.arange(n_rows + 1) * RECORD_S
    v_rows = prog.velocity(t_rows)
    noise = np.random.default_rng(seed).standard_normal(n_ticks) * cfg.sensors.current_noise_a
    out = np.empty((n_rows, loop.N_COLUMNS))
    loop.run_loop_compiled(ax, lc, *cog, x_set, v_rows, noise, x0, out)
    return _trace(cfg, conv, t_rows[:-1], prog.position(t_rows[:-1]), v_rows[:-1], out,
                  lc.scale_step > 0.0)


def _trace(cfg: MachineConfig, conv: Conventions, t: np.ndarray, x_set: np.ndarray,
           v_ff: np.ndarray, out: np.ndarray, scale: bool) -> Trace:
    rotary = cfg.machine.kind == "rotary"
    k, u = (180.0 / math.pi, "deg") if rotary else (1e3, "mm")
    cols = {"t_s": t, f"pos_set_{u}": x_set * k, f"pos_{u}": out[:, loop.FB] * k,
            f"vel_set_{u}_min": v_ff * k * 60.0, f"vel_{u}_min": out[:, loop.SPEED] * k * 60.0,
            "iq_set_a": out[:, loop.IQ_SET], "iq_a": out[:, loop.IQ]}
    pos_key = "pos_rms_urad" if rotary else "pos_rms_um"
    measured = {"iq_rms_a": out[:, loop.IQ], pos_key: out[:, loop.FB] * 1e6}
    true = {"iq_rms_a": out[:, loop.IQ_TRUE], pos_key: out[:, loop.POS_TRUE] * 1e6}
    if scale:
        cols[f"motor_pos_{u}"] = out[:, loop.MOTOR] * k
        measured["motor_pos_rms_um"] = out[:, loop.MOTOR] * 1e6
        true["motor_pos_rms_um"] = out[:, loop.POS_TRUE] * 1e6
    return Trace(cols, header(cfg, conv, RECORD_S, PREROLL_S), _rms(measured, true), measured)


def _rms(a: dict, b: dict) -> dict:
    """Per channel the rms of a - b about its mean (an encoder's zero is no model error)."""
    return {key: float(np.std(a[key] - b[key])) for key in a}


def deviation(a: Trace, b: Trace) -> dict:
    """How far two runs of one program differ through the sensors, per floor channel, in
    the floor's units (rms about the mean)."""
    return _rms(a.measured, b.measured)


def write(tr: Trace, path: Path, source: str) -> Path:
    """The trace as a servo-trace CSV, its conventions in the header."""
    return write_trace(path, tr.columns, {**tr.meta, "source": source})
