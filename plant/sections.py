"""The sections of a machine file, each key declared with its unit, range and meaning.

:mod:`plant.config` reads and checks a file against these declarations; ``hil
config-keys`` prints them.  Every number has a physical range (:func:`plant.schema.key`):
what real feed drives span -- from a micro-positioning stage to a large machine tool's
axis -- with a margin of about ten on each side; where 0 means "automatic" or "not used
by this model" it says so.  A value outside is refused with the range and the unit.
Stiffness ranges alone do not bound the sub-steps (a stiff spring on a light mass): the
sub-step count is bounded by :mod:`plant.substeps`.
"""

from dataclasses import dataclass

from plant.schema import key

KINDS = ("screw", "linear", "rotary")
#: which of the screw's diameters a property is computed with ([screw] inertia_diameter,
#: stiffness_diameter)
DIAMETERS = ("root", "nominal")
#: [motor] modulation: space-vector or sine PWM (plant.assemble.voltage_limit)
MODULATIONS = ("svpwm", "spwm")
#: [motor] voltage_limit: the d-q vector's length, or u_q alone (plant.effects.pmsm)
VOLTAGE_LIMITS = ("vector", "q")
#: [sensors] encoder_rounding: the count below the position, or the nearest one
ROUNDINGS = ("floor", "round")
#: [friction] karnopp_reversal: what a sub-step that would reverse the velocity does
REVERSALS = ("breakaway", "stop")


@dataclass(frozen=True, kw_only=True)
class MachineSection:
    """What the machine is."""
    name: str = key("-", "Human-readable name of the axis.")
    source: str = key("-", "Where the values come from (paper, data sheet).")
    kind: str = key("-", "screw: rotary motor and ball screw, table in m; linear: linear "
                    "motor, table in m; rotary: direct-drive rotary axis, table in rad.",
                    choices=KINDS)


@dataclass(frozen=True, kw_only=True)
class MotorSection:
    """Motor and power stage."""
    model: str = key("-", "dq: PMSM in d-q with FOC current PI loops; first_order: current "
                     "loop as a first-order lag; commutation: torque motor with "
                     "commutation-angle field weakening (seed 001).",
                     choices=("dq", "first_order", "commutation"))
    pole_pairs: float = key("1", "Pole pairs of a rotary motor.", 0.0, ge=1.0, le=200.0,
                            zero="not used", only="kind=screw|rotary")
    pole_pitch_m: float = key("m", "Pole pitch of a linear motor (north to south).", 0.0, ge=1e-3,
                              le=0.5, zero="not used", only="kind=linear")
    resistance_ohm: float = key("ohm", "Phase resistance.", 0.0, ge=1e-4, le=1e3, zero="not used")
    inductance_d_h: float = key("H", "d-axis inductance (commutation model: coil inductance).",
                                0.0, ge=1e-7, le=10.0, zero="not used")
    inductance_q_h: float = key("H", "q-axis inductance.", 0.0, ge=1e-7, le=10.0, zero="not used",
                                only="model=dq")
    torque_constant_nm_per_a: float = key("N*m/A", "Torque constant K_t = 1.5 p psi "
                                          "(commutation model: K_M at beta = 90 deg).", 0.0,
                                          ge=1e-3, le=1e3, zero="not used",
                                          only="kind=screw|rotary")
    force_constant_n_per_a: float = key("N/A", "Force constant of a linear motor.", 0.0, ge=0.1,
                                        le=1e4, zero="not used", only="kind=linear")
    inertia_kgm2: float = key("kg*m^2", "Rotor inertia (up to 1e6: a rotor held still).", 0.0,
                              ge=1e-8, le=1e6, zero="not used", only="kind=screw|rotary")
    mass_kg: float = key("kg", "Moving mass of a linear motor's thrust block.", 0.0, ge=0.01,
                         le=1e4, zero="not used", only="kind=linear")
    viscous_nms_per_rad: float = key("N*m*s/rad", "Viscous friction of the motor bearings.",
                                     0.0, ge=0.0, le=1e3, only="kind=screw|rotary")
    current_max_a: float = key("A", "Current limit I_max (peak).", ge=0.01, le=5000.0)
    dc_link_v: float = key("V", "DC-link voltage; the d-q voltage vector is limited by "
                           "[motor] modulation (commutation model: |U| <= U_dc, seed 001 "
                           "eq. 2).", 0.0, ge=1.0, le=2000.0, zero="not used")
    modulation: str = key("-", "The inverter's modulation, which sets the largest d-q voltage "
                          "vector: svpwm (space-vector PWM, or sine PWM with third-harmonic "
                          "injection, as most drives have): U_dc/sqrt(3); spwm (sine PWM): "
                          "U_dc/2.", "svpwm", choices=MODULATIONS, only="model=dq")
    voltage_limit: str = key("-", "What the current controller limits to that voltage: "
                             "vector (|(u_d, u_q)|, u_d served first, as drives do) or q "
                             "(|u_q| alone, u_d not limited: a simulator's q-voltage clamp); "
                             "a voltage set in voltage mode is limited as a vector either way.",
                             "vector", choices=VOLTAGE_LIMITS, only="model=dq")
    pwm_frequency_hz: float = key("Hz", "PWM and current-controller frequency; the "
                                  "inverter applies each voltage one period late.", ge=500.0,
                                  le=1e5)


@dataclass(frozen=True, kw_only=True)
class CurrentLoopSection:
    """Current controller held by the drive (the plant)."""
    kp_v_per_a: float = key("V/A", "PI proportional gain.", 0.0, ge=1e-3, le=1e4, zero="not used",
                            only="model=dq|commutation")
    ti_s: float = key("s", "PI integral time.", 0.0, ge=1e-6, le=10.0, zero="not used",
                      only="model=dq|commutation")
    time_constant_s: float = key("s", "First-order current-loop time constant T_cl.", 0.0,
                                 ge=1e-7, le=1.0, zero="not used", only="model=first_order")
    decoupling: bool = key("-", "EMF and cross-coupling precontrol (u_d -= w_e L_q i_q, "
                           "u_q += w_e (psi + L_d i_d)), as drives have by default.", True,
                           only="model=dq")


@dataclass(frozen=True, kw_only=True)
class FieldWeakeningSection:
    """Commutation-angle field weakening (seed 001 eq. 6-10), commutation model only."""
    enabled: bool = key("-", "Reduce the commutation angle above omega_Mmax.", False)
    max_torque_nm: float = key("N*m", "M_max of seed 001 eq. 8.", 0.0, ge=0.0, le=1e5)


@dataclass(frozen=True, kw_only=True)
class CoggingSection:
    """Cogging / reluctance torque as harmonics of the electrical angle."""
    slots: int = key("1", "Stator slots of a rotary motor: the cogging's fundamental is then "
                     "LCM(slots, 2 pole_pairs) cycles per mechanical revolution, and the "
                     "orders (empty: the first len(amplitudes) multiples of it) must be its "
                     "multiples.", 0, ge=3, le=1000, zero="not given",
                     only="kind=screw|rotary")
    orders: tuple = key("1", "Harmonic orders in cycles per electrical revolution.", (), gt=0.0,
                        le=1000.0)
    amplitudes_nm: tuple = key("N*m", "Amplitudes (rotary motors).", (), ge=-1e4, le=1e4,
                               only="kind=screw|rotary")
    amplitudes_n: tuple = key("N", "Amplitudes (linear motors).", (), ge=-1e5, le=1e5,
                              only="kind=linear")
    phases_deg: tuple = key("deg", "Phases; empty means all zero.", (), ge=-360.0, le=360.0)


@dataclass(frozen=True, kw_only=True)
class MechanicsSection:
    """Which mechanical model and solver."""
    model: str = key("-", "rigid: one inertia (on a screw axis a rigid screw, the table at "
                     "lead theta / 2pi); two_mass: motor-coupling-load; screw: "
                     "distributed ball screw with moving nut and table.",
                     choices=("rigid", "two_mass", "screw"))
    solver: str = key("-", "Solver of the screw chains.", "lumped", choices=("lumped", "tlm"))
    lead_m: float = key("m", "Ball-screw lead (table travel per screw revolution).", 0.0, ge=1e-4,
                        le=0.2, zero="not used", only="kind=screw")
    load_inertia_kgm2: float = key("kg*m^2", "Load-side inertia besides the table (screw "
                                   "and coupling in rigid/two_mass models; the rotary "
                                   "table of a direct drive).", 0.0, ge=0.0, le=1e4)
    external_torque_nm: float = key("N*m", "Constant external torque on the rotary table, "
                                    "+ toward +angle (an unbalanced load); added to the "
                                    "plant input 'load'.", 0.0, ge=-1e6, le=1e6,
                                    only="kind=rotary")


@dataclass(frozen=True, kw_only=True)
class CouplingSection:
    """Elastic coupling between motor and screw (two_mass and screw models)."""
    stiffness_nm_per_rad: float = key("N*m/rad", "Torsional stiffness.", ge=1.0, le=1e9)
    damping_nms_per_rad: float = key("N*m*s/rad", "Torsional damping.", 0.0, ge=0.0, le=1e5)
    inertia_kgm2: float = key("kg*m^2", "Coupling inertia, split between its two sides.",
                              0.0, ge=0.0, le=10.0)
    backlash_rad: float = key("rad", "Backlash in the coupling (two_mass only).", 0.0, ge=0.0,
                              le=0.1)


@dataclass(frozen=True, kw_only=True)
class ScrewSection:
    """Distributed ball screw (screw model)."""
    length_m: float = key("m", "Screw length between the bearings.", ge=0.01, le=20.0)
    diameter_m: float = key("m", "Root (core) diameter d_r of the thread, the screw's "
                            "smallest cross-section.", ge=1e-3, le=0.3)
    nominal_diameter_m: float = key("m", "Nominal (outer) diameter d_0, the catalogue's size "
                                    "(40 mm for a 40x10 screw), >= diameter_m.", 0.0,
                                    ge=1e-3, le=0.3, zero="not given: d_r stands for it")
    inertia_diameter: str = key("-", "Diameter of the screw's polar inertia rho J_p l and "
                                "axial mass rho A l: root (d_r, a solid core) or nominal (d_0, "
                                "what screw catalogues compute the inertia with).", "root",
                                choices=DIAMETERS)
    stiffness_diameter: str = key("-", "Diameter of the screw's torsional G J_p / l and axial "
                                  "E A / l stiffness: root (d_r, what screw catalogues compute "
                                  "the stiffness with) or nominal (d_0).", "root",
                                  choices=DIAMETERS)
    segments: int = key("1", "Number of screw segments N (N+1 nodes).", ge=1, le=64)
    density_kg_m3: float = key("kg/m^3", "Screw material density.", 7850.0, ge=1000.0, le=25000.0)
    youngs_modulus_pa: float = key("Pa", "Young's modulus E.", 2.1e11, ge=1e9, le=1e12)
    shear_modulus_pa: float = key("Pa", "Shear modulus G.", 8.1e10, ge=1e9, le=5e11)
    torsional_damping_nms_per_rad: float = key("N*m*s/rad", "Damper across each segment.",
                                               0.0, ge=0.0, le=1e4)
    axial_damping_ns_per_m: float = key("N*s/m", "Axial damper across each segment.", 0.0, ge=0.0,
                                        le=1e8)
    bearing_viscous_nms_per_rad: float = key("N*m*s/rad", "Rotational friction of each "
                                             "support bearing.", 0.0, ge=0.0, le=1e3)
    bearing_coulomb_nm: float = key("N*m", "Coulomb friction torque of each support bearing "
                                    "on the screw's rotation (stiction at the same level; "
                                    "lumped solver only).", 0.0, ge=0.0, le=1e3)
    nut_coulomb_nm: float = key("N*m", "Coulomb friction torque of the nut on the screw's "
                                "rotation at no load: the catalogue's preload (dynamic) "
                                "torque (lumped solver only).", 0.0, ge=0.0, le=1e3)
    nut_viscous_nms_per_rad: float = key("N*m*s/rad", "Viscous friction torque of the nut on "
                                         "the screw's rotation (lumped solver only).", 0.0,
                                         ge=0.0, le=1e3)
    nut_load_friction: float = key("1", "Growth of the nut's Coulomb torque with its axial "
                                   "force F: + this times F lead/2pi (about 1/eta - 1 for a "
                                   "screw of efficiency eta; lumped solver only).", 0.0, ge=0.0,
                                   le=1.0)
    thrust_bearing_stiffness_n_per_m: float = key("N/m", "Axial stiffness of the fixed "
                                                  "(thrust) bearing.", ge=1e5, le=1e11)
    thrust_bearing_damping_ns_per_m: float = key("N*s/m", "Axial damping of the thrust "
                                                 "bearing.", 0.0, ge=0.0, le=1e8)
    support: str = key("-", "Axial support: the thrust bearing at the motor end only, or "
                       "at both ends.", "fixed-supported",
                       choices=("fixed-supported", "fixed-fixed"))
    nut_stiffness_n_per_m: float = key("N/m", "Axial stiffness of the nut.", ge=1e5, le=1e11)
    nut_damping_ns_per_m: float = key("N*s/m", "Axial damping of the nut.", 0.0, ge=0.0, le=1e8)
    nut_offset_m: float = key("m", "Nut distance from the motor-end bearing at table "
                              "position 0.", ge=0.0, le=20.0)
    backlash_m: float = key("m", "Backlash between screw and nut (total lost motion).", 0.0,
                            ge=0.0, le=1e-3)

    def diameter(self, which: str) -> float:
        """m: the root diameter for ``which`` = "root", the nominal one for "nominal" (the
        loader refuses "nominal" without it); ``which`` is :attr:`inertia_diameter` or
        :attr:`stiffness_diameter`."""
        return self.nominal_diameter_m if which == "nominal" else self.diameter_m


@dataclass(frozen=True, kw_only=True)
class TableSection:
    """The moving table (screw and linear axes)."""
    mass_kg: float = key("kg", "Table mass with workpiece (linear: payload besides the "
                         "thrust block).", ge=1e-3, le=1e5, zero="none")
    travel_m: float = key("m", "Usable travel from position 0.", ge=1e-4, le=50.0)
    external_force_n: float = key("N", "Constant external force on the table, + pushing "
                                  "toward +x (a vertical axis: -m g; a weight-compensation "
                                  "offset); added to the plant input 'load'.", 0.0, ge=-1e6,
                                  le=1e6)
    end_stop_overtravel_m: float = key("m", "Mechanical end stops at -x and travel_m + x: a "
                                       "stiff, damped contact that only pushes the table "
                                       "back (output end_stop_force_n).  Default: 15 mm "
                                       "beyond the limit switches, what a table at 30 "
                                       "m/min needs to brake at 10 m/s^2.", 0.025, ge=1e-4, le=1.0)
    limit_switch_overtravel_m: float = key("m", "Limit switches on beyond -x and travel_m + "
                                           "x (outputs limit_neg, limit_pos); < "
                                           "end_stop_overtravel_m.  Default: 10 mm, just "
                                           "beyond the usable travel.", 0.01, ge=0.0, le=1.0)
    end_stop_stiffness_n_per_m: float = key("N/m", "End-stop contact stiffness, on the "
                                            "table's mass; 0: automatic, a contact frequency "
                                            "of omega dt = max_omega_dt/4 on the chains' "
                                            "sub-step, which it leaves as it is "
                                            "(plant.end_stops).", 0.0, ge=1e3, le=1e13,
                                            zero="automatic")
    end_stop_damping_ns_per_m: float = key("N*s/m", "End-stop contact damping; 0: "
                                           "automatic, damping ratio 0.5 on the table's "
                                           "mass (rebound at 30 % of the impact speed).", 0.0,
                                           ge=1e-3, le=1e9, zero="automatic")


@dataclass(frozen=True, kw_only=True)
class PitchErrorSection:
    """Ball-screw pitch (lead) error: the table stands at x = u + e(u), u = lead/2pi times
    the screw angle at the nut, e(u) = sum A_k sin(2 pi u / P_k + phi_k) + c u."""
    periods_m: tuple = key("m", "Periods P_k of the harmonics along the travel (> 0, at most "
                           "4).", (), gt=0.0, le=10.0, only="kind=screw")
    amplitudes_m: tuple = key("m", "Amplitudes A_k, one per period.", (), ge=-1e-3, le=1e-3,
                              only="kind=screw")
    phases_deg: tuple = key("deg", "Phases phi_k; empty means all zero.", (), ge=-360.0, le=360.0,
                            only="kind=screw")
    linear_ppm: float = key("um/m", "Cumulative lead error c (table travel per nominal "
                            "travel - 1, in 1e-6).", 0.0, ge=-1e4, le=1e4, only="kind=screw")


@dataclass(frozen=True, kw_only=True)
class FrictionSection:
    """Table friction: viscous, Coulomb, Stribeck and Karnopp stick-slip."""
    viscous_ns_per_m: float = key("N*s/m", "Viscous coefficient.", 0.0, ge=0.0, le=1e6,
                                  only="kind=screw|linear")
    viscous_asymmetry_ns_per_m: float = key("N*s/m", "Viscous coefficient's difference by "
                                            "direction dB: B + dB moving +, B - dB moving -; "
                                            "|dB| <= B.", 0.0, ge=-1e6, le=1e6,
                                            only="kind=screw|linear")
    coulomb_n: float = key("N", "Coulomb (sliding) force F_C.", 0.0, ge=0.0, le=1e7,
                           only="kind=screw|linear")
    breakaway_n: float = key("N", "Breakaway force F_H >= F_C (0: equal to F_C).", 0.0, ge=0.0,
                             le=1e7, only="kind=screw|linear")
    stribeck_velocity_m_s: float = key("m/s", "Stribeck velocity (0: no Stribeck dip).",
                                       0.0, ge=0.0, le=1.0, only="kind=screw|linear")
    zero_velocity_band_m_s: float = key("m/s", "Karnopp zero-velocity band DV.", 0.0, ge=0.0,
                                        le=0.1, only="kind=screw|linear")
    karnopp_reversal: str = key("-", "A sub-step that would reverse the table's velocity: "
                                "breakaway (it sticks while the applied force is <= F_H, "
                                "else it reverses within the step) or stop (it ends at rest "
                                "whatever the force; the next step breaks away above F_H).",
                                "breakaway", choices=REVERSALS)
    viscous_nms_per_rad: float = key("N*m*s/rad", "Viscous coefficient.", 0.0, ge=0.0, le=1e5,
                                     only="kind=rotary")
    viscous_asymmetry_nms_per_rad: float = key("N*m*s/rad", "Viscous coefficient's "
                                               "difference by direction (see the linear key).",
                                               0.0, ge=-1e5, le=1e5, only="kind=rotary")
    coulomb_nm: float = key("N*m", "Coulomb torque.", 0.0, ge=0.0, le=1e7, only="kind=rotary")
    breakaway_nm: float = key("N*m", "Breakaway torque (0: equal to Coulomb).", 0.0, ge=0.0,
                              le=1e7, only="kind=rotary")
    stribeck_velocity_rad_s: float = key("rad/s", "Stribeck velocity.", 0.0, ge=0.0, le=10.0,
                                         only="kind=rotary")
    zero_velocity_band_rad_s: float = key("rad/s", "Karnopp zero-velocity band.", 0.0, ge=0.0,
                                          le=1.0, only="kind=rotary")


@dataclass(frozen=True, kw_only=True)
class PreslidingSection:
    """Presliding nonlinear spring dF/dx = k1 / (|x/x1|^a + 1), reset at reversals (seed 004)."""
    enabled: bool = key("-", "Use the presliding spring instead of Karnopp stiction.", False)
    stiffness_n_per_m: float = key("N/m", "Initial stiffness k1 (T1 / (lead/2pi)^2 for a "
                                   "torque law).", 0.0, ge=0.0, le=1e10)
    x1_m: float = key("m", "Displacement scale x1.", 0.0, ge=0.0, le=1e-3)
    exponent: float = key("1", "Shape exponent a.", 1.0, ge=0.1, le=10.0)


@dataclass(frozen=True, kw_only=True)
class SensorsSection:
    """Encoders and current measurement."""
    encoder_counts_per_rev: int = key("1", "Motor encoder counts per revolution "
                                      "(17 bit: 131072).", 0, ge=256, le=2 ** 32, zero="not used",
                                      only="kind=screw|rotary")
    encoder_resolution_m: float = key("m", "Linear-motor encoder resolution.", 0.0, ge=1e-10,
                                      le=1e-3, zero="not used", only="kind=linear")
    scale_resolution_m: float = key("m", "Linear scale on the table (0: none).", 0.0, ge=1e-10,
                                    le=1e-3, zero="no scale", only="kind=screw|linear")
    current_noise_a: float = key("A", "Standard deviation of current-measurement noise.",
                                 0.0, ge=0.0, le=100.0)
    current_lsb_a: float = key("A", "Current ADC quantization step (0: none).", 0.0, ge=0.0,
                               le=10.0)
    current_full_scale_a: float = key("A", "Current ADC full scale: the measured currents "
                                      "clip at +- this, after noise and quantization.", 0.0,
                                      ge=0.01, le=1e4, zero="no clipping")
    encoder_rounding: str = key("-", "Count shown at a position of x counts (encoder and "
                                "scale): floor (floor(x), an edge counter) or round "
                                "(floor(x + 1/2), the nearest count).", "floor",
                                choices=ROUNDINGS)
    encoder_zero_at_start: bool = key("-", "Every encoder (motor encoder, scale) counts from "
                                      "the position at reset, 0 there: count = q((x - x_0) "
                                      "per unit); false: from position 0.", False)
    seed: int = key("1", "Seed of the measurement-noise generator.", 1, ge=0, le=2 ** 32 - 1)
    delay_s: float = key("s", "Measurement delay of the encoder and scale counts and the "
                         "measured currents (the true states are not delayed); a whole "
                         "number of PWM periods, at most 32.", 0.0, ge=0.0, le=0.1)


@dataclass(frozen=True, kw_only=True)
class BrakeSection:
    """The motor's holding brake: a friction brake on the rotor (on the mover of a linear
    motor), closed by the drive (:mod:`hil.drive.core`) when the pulses are off."""
    holding_torque_nm: float = key("N*m", "Holding (static and sliding) torque of the closed "
                                   "brake; 0: no brake.", 0.0, ge=0.0, le=1e5,
                                   only="kind=screw|rotary")
    holding_force_n: float = key("N", "Holding force of a linear motor's closed brake; 0: no "
                                 "brake.", 0.0, ge=0.0, le=1e6, only="kind=linear")
    closing_time_s: float = key("s", "From the drive's command to the brake holding (its "
                                "coil's decay and air gap); it opens at once.", 0.03, ge=0.0,
                                le=2.0)


@dataclass(frozen=True, kw_only=True)
class SimulationSection:
    """Integration settings."""
    substep_s: float = key("s", "Integration sub-step; 0 picks the largest divisor of the "
                           "PWM period with omega_max*dt <= max_omega_dt.", 0.0, ge=1e-8, le=1e-2,
                           zero="automatic")
    max_omega_dt: float = key("1", "Bound on omega_max*dt for the automatic sub-step "
                              "(relative frequency error (omega*dt)^2/24).", 0.5, ge=0.01, le=1.9)


SECTIONS = {
    "machine": MachineSection, "motor": MotorSection, "current_loop": CurrentLoopSection,
    "field_weakening": FieldWeakeningSection, "cogging": CoggingSection,
    "mechanics": MechanicsSection, "coupling": CouplingSection, "screw": ScrewSection,
    "table": TableSection, "pitch_error": PitchErrorSection, "friction": FrictionSection,
    "presliding": PreslidingSection, "sensors": SensorsSection, "simulation": SimulationSection,
    "brake": BrakeSection,
}
# sections read by other packages (hil's controller, drive, fault injection and
# identification): the plant keeps them as raw tables
FOREIGN_SECTIONS = ("controller", "drive", "inject", "identify")
# sections that may be absent: they then take every default
OPTIONAL_SECTIONS = {"field_weakening", "cogging", "friction", "presliding", "sensors",
                     "simulation", "current_loop", "pitch_error", "brake"}
