"""The emulated drive: the device side of the wire, around one plant.

Every cycle (one PWM period of the plant) it takes a :class:`~io_adapters.messages.Setpoint`,
runs the CiA 402 state machine on its controlword, passes the setpoints to the
plant only while the state machine has the power stage on, steps the plant
and fills a :class:`~io_adapters.messages.Feedback`.  A plant fault status latches a
drive fault (CiA 402 FAULT, torque off) until the state is reset and a fault
reset is commanded.  Torque is on only in OPERATION ENABLED; a quick stop
removes it and the axis coasts to rest against its friction (this drive has
no braking ramp of its own), after which transition 12 disables it.  The same
object serves the lock-step simulator and the real-time loop.
"""

from hil.cia402 import DriveStateMachine, State
from io_adapters.messages import MODE_VOLTAGE, Feedback, Setpoint
from plant import Plant
from plant import layout as L

#: motor speed (rad/s, or m/s) below which a quick-stopped axis counts as stopped
STOPPED_SPEED = 1e-3


class EmulatedDrive:
    """A plant behind a CiA 402 drive interface."""

    def __init__(self, plant: Plant):
        self.plant = plant
        self.sm = DriveStateMachine()
        self.fault = 0

    def cycle(self, sp: Setpoint, fb: Feedback) -> None:
        """Apply ``sp``, advance the plant one PWM period, write ``fb`` (no allocation)."""
        plant = self.plant
        stopped = abs(plant.out[L.O_MOTOR_VEL]) < STOPPED_SPEED
        statusword = self.sm.update(sp.controlword, self.fault != 0, stopped=stopped)
        inp = plant.inp
        on = self.sm.state == State.OPERATION_ENABLED
        inp[L.I_ENABLE] = 1.0 if on else 0.0
        inp[L.I_MODE] = L.INPUT_VOLTAGE if sp.mode == MODE_VOLTAGE else L.INPUT_CURRENT
        inp[L.I_IQ_REF] = sp.iq_ref_a if on else 0.0
        inp[L.I_ID_REF] = sp.id_ref_a if on else 0.0
        inp[L.I_UD] = sp.ud_v if on else 0.0
        inp[L.I_UQ] = sp.uq_v if on else 0.0
        status = plant.step(plant.sub_per_pwm)
        if status != L.STATUS_OK:
            self.fault = status
        out = plant.out
        fb.seq = sp.seq
        fb.statusword = statusword
        fb.time_s = out[L.O_TIME]
        fb.encoder_counts = out[L.O_ENCODER]
        fb.scale_counts = out[L.O_SCALE]
        fb.iq_a = out[L.O_IQ_MEAS]
        fb.id_a = out[L.O_ID_MEAS]
        fb.fault = self.fault

    def clear_fault(self, table_pos: float = 0.0) -> None:
        """Reset the plant after a fault so that a fault reset can succeed."""
        self.plant.reset(table_pos)
        self.fault = 0
