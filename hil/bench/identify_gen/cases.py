"""The bench's traces: an axis as declared, the truth (the declared file plus one or two
undeclared effects and a Sinumerik-style controller's conventions), and what should be found.

Every effect of ``hil identify``'s library is undeclared in at least one trace, across a
ball screw, a linear motor and a rotary table.  The truths' controllers differ from the
declared files' (the emulator's own conventions) in everything the trace header can say:
a 2 ms position cycle against the 1 ms record, 0.5 ms speed cycle, the feed-forward
finely interpolated, a 0.5 ms filter on the actual speed, the integrator clamped at the
current limit, one PWM period of computation delay, 0.5 s at rest before the trace.
"""

import math
from dataclasses import dataclass, field
from pathlib import Path

CONFIGS = Path(__file__).resolve().parents[3] / "configs" / "identify"
SCREW, LINEAR, ROTARY = (CONFIGS / f"bench_{n}.toml" for n in ("screw", "linear", "rotary"))
#: the truths' controller conventions (4 kHz PWM: 2 ms position, 0.5 ms speed cycle)
SINUMERIK_STYLE = {"controller": {
    "position_cycle_ratio": 8, "ipo_cycle_ratio": 8, "speed_cycle_ratio": 2,
    "feedforward_interpolation": "linear", "speed_actual_filter_s": 0.0005,
    "speed_antiwindup": "clamp", "current_delay_cycles": 1}}
#: record sample time in PWM periods (1 ms at 4 kHz)
RECORD_EVERY = 4
PREROLL_S = 0.5
ADC_BITS = 12
LEAD = 0.01
TWO_MASS = {"mechanics": {"model": "two_mass"},
            "coupling": {"stiffness_nm_per_rad": 1000.0, "damping_nms_per_rad": 0.03}}


@dataclass(frozen=True)
class Case:
    """One bench trace.

    Attributes:
        name: short id (file names).
        axis: the declared machine file.
        effects: the undeclared effects, as ``hil identify`` names them.
        truth: machine-file keys of the truth on top of ``axis`` (besides SINUMERIK_STYLE).
        start: machine-file keys of the file identification starts from, on top of ``axis``
            (where the effect's absence is a key of the declared file).
        travel: the program's travel (m or rad); speed its top speed (per s).
        seed: of the measurement noise.
        tolerance: ``hil identify --tolerance`` of the case (effect -> relative
            tolerance of its declared coefficients): where a declared value is wrong on
            purpose by more than the 10 % default, as a user doubting it would say.
    """
    name: str
    axis: Path
    effects: tuple
    truth: dict = field(default_factory=dict)
    start: dict = field(default_factory=dict)
    travel: float = 0.3
    speed: float = 0.15
    seed: int = 1
    tolerance: dict = field(default_factory=dict)


def merged(*tables: dict) -> dict:
    """``{"section": {"key": value}}`` tables merged, later ones winning."""
    out: dict = {}
    for t in tables:
        for sec, values in t.items():
            out.setdefault(sec, {}).update(values)
    return out


_LIN = {"axis": LINEAR, "travel": 0.4, "speed": 0.25}
_ROT = {"axis": ROTARY, "travel": 2 * math.pi, "speed": 1.5}

CASES = (
    Case("screw_coulomb", SCREW, ("coulomb_friction",), start={"friction": {"coulomb_n": 0.0}},
         seed=11),
    Case("screw_stribeck", SCREW, ("stribeck",),
         truth={"friction": {"breakaway_n": 60.0, "stribeck_velocity_m_s": 0.008}}, seed=12),
    Case("screw_viscous_asymmetry", SCREW, ("viscous_asymmetry",),
         truth={"friction": {"viscous_asymmetry_ns_per_m": -60.0}}, seed=13),
    # seed 004 §3.2's law and values (T1, theta1 and a in table units, as
    # configs/xy_table_004.toml has them)
    Case("screw_presliding", SCREW, ("presliding_hysteresis",),
         truth={"presliding": {"enabled": True, "stiffness_n_per_m": 1.8002e6, "x1_m": 4e-6,
                               "exponent": 1.2}}, seed=14),
    # a spring 17 times stiffer, saturating within 1.7 um: a 74 Hz mode damped 0.2 % under
    # the 50 nm scale's quantised loop, where the trace changes with the generator's own
    # tolerance (its repeat / floor is 1.7): no model can reach the floor goal there
    Case("screw_presliding_stiff", SCREW, ("presliding_hysteresis",),
         truth={"presliding": {"enabled": True, "stiffness_n_per_m": 3e7, "x1_m": 1e-6,
                               "exponent": 1.0}}, seed=19),
    Case("screw_pitch", SCREW, ("pitch_error",),
         truth={"pitch_error": {"periods_m": [0.025], "amplitudes_m": [4e-6]}}, seed=15),
    Case("screw_backlash", SCREW, ("backlash",),
         truth=merged(TWO_MASS, {"coupling": {"backlash_rad": 1e-5 / (LEAD / (2 * math.pi))}}),
         start=TWO_MASS, seed=16),
    Case("screw_compliance", SCREW, ("compliance",), truth=TWO_MASS, seed=17),
    Case("screw_force_coulomb", SCREW, ("gravity_offset", "coulomb_friction"),
         truth={"table": {"external_force_n": -150.0}},
         start={"friction": {"coulomb_n": 0.0}}, seed=18),
    Case("linear_cogging", effects=("cogging",),
         truth={"cogging": {"orders": [1.0, 2.0], "amplitudes_n": [3.0, 1.5],
                            "phases_deg": [0.0, 40.0]}}, seed=21, **_LIN),
    # the table 50 % heavier than declared (+41 % of the moved mass): beyond the 10 %
    # default tolerance, declared as doubted
    Case("linear_inertia", effects=("inertia",), truth={"table": {"mass_kg": 18.0}}, seed=22,
         tolerance={"inertia": 0.6},
         **_LIN),
    Case("linear_force", effects=("gravity_offset",),
         truth={"table": {"external_force_n": 40.0}}, seed=23, **_LIN),
    Case("rotary_cogging_viscous", effects=("cogging", "viscous_friction"),
         truth={"cogging": {"orders": [1.0], "amplitudes_nm": [3.0]}},
         start={"friction": {"viscous_nms_per_rad": 0.0}}, seed=31, **_ROT),
    Case("rotary_delay", effects=("time_delay",), truth={"sensors": {"delay_s": 0.001}},
         seed=32, **_ROT),
)
#: the reduced set CI runs (tests/test_bench_identify.py)
CI_CASES = ("screw_coulomb", "linear_force")


def case(name: str) -> Case:
    """The case called ``name``; KeyError lists the names."""
    for c in CASES:
        if c.name == name:
            return c
    raise KeyError(f"no bench case {name!r}; cases: {', '.join(c.name for c in CASES)}")
