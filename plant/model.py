"""The typed Python face of one axis: load a machine file, set inputs, step, read outputs.

>>> from plant import Plant
>>> axis = Plant.from_file("configs/arrow500_x.toml")
>>> axis.set_input(iq_ref_a=0.84)
>>> status = axis.step(axis.sub_per_pwm)       # one PWM period
>>> axis.output("iq_a")                         # doctest: +SKIP

All values are SI (rad, m, A, V, N, N·m).  The kernel (:func:`plant.kernel.
axis_step_nb`) works on the arrays this object owns; callers in real time pass
``plant.params``, ``plant.state``, ``plant.inp`` and ``plant.out`` to the
kernel themselves and never allocate.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plant import layout as L
from plant.assemble import Built, build
from plant.config import MachineConfig, load_machine
from plant.effects.delay import delay_fill
from plant.effects.pitch import nominal_position
from plant.effects.reference import counts_per_mark
from plant.effects.tlm import tlm_init
from plant.kernel import axis_step_nb

#: output names -> index in the out vector (units in plant.layout)
OUTPUTS = {
    "status": L.O_STATUS, "time_s": L.O_TIME, "motor_pos": L.O_MOTOR_POS,
    "motor_vel": L.O_MOTOR_VEL, "table_pos": L.O_TABLE_POS, "table_vel": L.O_TABLE_VEL,
    "encoder_counts": L.O_ENCODER, "scale_counts": L.O_SCALE, "id_a": L.O_ID, "iq_a": L.O_IQ,
    "id_meas_a": L.O_ID_MEAS, "iq_meas_a": L.O_IQ_MEAS, "torque": L.O_TORQUE, "ud_v": L.O_UD,
    "uq_v": L.O_UQ, "nut_force_n": L.O_NUT_FORCE, "friction": L.O_FRICTION,
    "limit_neg": L.O_LIMIT_NEG, "limit_pos": L.O_LIMIT_POS, "end_stop_force_n": L.O_END_STOP_F,
    "home_switch": L.O_HOME_SWITCH, "index_marks": L.O_INDEX,
}
INPUTS = {
    "mode": L.I_MODE, "enable": L.I_ENABLE, "id_ref_a": L.I_ID_REF, "iq_ref_a": L.I_IQ_REF,
    "ud_v": L.I_UD, "uq_v": L.I_UQ, "load": L.I_LOAD,
}


@dataclass(frozen=True)
class Trace:
    """Outputs recorded at the end of every kernel call.

    Attributes:
        signals: name -> array of shape (n_calls,), names as in ``OUTPUTS``.
    """
    signals: dict

    def __getitem__(self, name: str) -> np.ndarray:
        return self.signals[name]


class Plant:
    """One axis: its machine file, the kernel arrays and a small stepping API."""

    def __init__(self, config: MachineConfig, table_pos: float = 0.0):
        self.config = config
        self.built: Built = build(config)
        self.params = self.built.params
        p = self.params
        if config.machine.kind == "linear":  # a mark per electrical period (two pole pitches)
            p[L.P_INDEX_PERIOD] = 2.0 * config.motor.pole_pitch_m
        # the home switch's edge halfway between two index marks above the start of the
        # travel (table m, rad on a rotary table), as a machine builder sets the cam, so
        # that no homing meets the edge and a mark at once
        p[L.P_HOME_SWITCH] = (0.5 * counts_per_mark(p) / p[L.P_ENC_COUNTS_PER_RAD]
                              * self.built.ratio)
        self.state = np.zeros(self.built.state_size)
        self.inp = np.zeros(L.I_COUNT)
        self.out = np.zeros(L.O_COUNT)
        self.reset(table_pos)

    @classmethod
    def from_file(cls, path: str | Path, table_pos: float = 0.0,
                  overrides: dict | None = None) -> "Plant":
        """Load, check and build a machine file (see :func:`plant.config.load_machine`)."""
        return cls(load_machine(path, overrides), table_pos)

    @property
    def dt(self) -> float:
        """Integration sub-step in s."""
        return self.built.dt

    @property
    def sub_per_pwm(self) -> int:
        """Sub-steps per PWM (current-controller) period."""
        return self.built.sub_per_pwm

    @property
    def pwm_period(self) -> float:
        """PWM period in s."""
        return self.built.dt * self.built.sub_per_pwm

    @property
    def counts_per_mark(self) -> int:
        """Motor-encoder counts between two index marks (one motor revolution, or one
        electrical period of a linear motor; :mod:`plant.effects.reference`)."""
        return int(counts_per_mark(self.params))

    def reset(self, table_pos: float = 0.0) -> None:
        """Rest state with the table at ``table_pos`` (m, or rad for rotary tables),
        springs relaxed, inputs cleared and the power stage enabled.  With a pitch error
        the screw turns to the angle that puts the table there; the measurement-delay
        ring holds the rest state's measured signals.  With [sensors]
        encoder_zero_at_start every encoder counts from here (its count 0)."""
        s = self.state
        s[:] = 0.0
        p = self.params
        ratio = self.built.ratio
        ro, nr = int(p[L.P_SOFF_ROT]), int(p[L.P_N_ROT])
        s[ro:ro + nr] = nominal_position(p, table_pos) / ratio
        s[L.S_TABLE_X] = table_pos
        s[L.S_PRE_XREV] = table_pos
        s[L.S_PRE_DIR] = 1.0
        s[L.S_KM] = p[L.P_KT]
        if p[L.P_ENC_ZERO] > 0.0:  # [sensors] encoder_zero_at_start: count 0 here
            p[L.P_ENC_ORIGIN] = s[ro]
            p[L.P_SCALE_ORIGIN] = table_pos
        if p[L.P_SOLVER] == L.SOLVER_TLM:
            tlm_init(p, int(p[L.P_OFF_ROT]), s, ro, nr, self.dt)
            tlm_init(p, int(p[L.P_OFF_AX]), s, int(p[L.P_SOFF_AX]), int(p[L.P_N_AX]), self.dt)
        if p[L.P_DELAY_N] > 0:
            delay_fill(p, s)
        self.inp[:] = 0.0
        self.inp[L.I_ENABLE] = 1.0
        self.step(0)

    def set_input(self, **values: float) -> None:
        """Set inputs by name: mode, enable, id_ref_a, iq_ref_a, ud_v, uq_v, load
        (N, or N·m for rotary tables; the machine file's constant external force or torque
        adds to it).  Unknown names raise KeyError."""
        for name, value in values.items():
            if name not in INPUTS:
                raise KeyError(f"unknown plant input {name!r}; known: {', '.join(INPUTS)}")
            self.inp[INPUTS[name]] = value

    def step(self, n_sub: int) -> int:
        """Advance ``n_sub`` sub-steps; returns the kernel status (0 = ok)."""
        return int(axis_step_nb(self.params, self.state, self.inp, self.out, n_sub))

    def output(self, name: str) -> float:
        """One output of the last step by name (see ``OUTPUTS``)."""
        return float(self.out[OUTPUTS[name]])

    def run(self, n_calls: int, n_sub: int, inputs=None) -> Trace:
        """Step ``n_calls`` times by ``n_sub`` sub-steps, recording every output.

        Args:
            inputs: optional callable ``(k, plant) -> None`` run before call k to
                change the inputs (a test stimulus, a controller).
        """
        rec = np.empty((n_calls, L.O_COUNT))
        for k in range(n_calls):
            if inputs is not None:
                inputs(k, self)
            self.step(n_sub)
            rec[k] = self.out
        return Trace({name: rec[:, i].copy() for name, i in OUTPUTS.items()})
