"""The second generator's bench traces: a declared machine file, the truth (it plus one
undeclared effect of ``hil identify``'s library), the controller's and sensors'
conventions, and what should be found.

Together they cover every convention the replay takes from a trace header that differs
from the emulator's own: a position cycle (2 ms) slower than the 1 ms record with the
feed-forward interpolated per speed sample, a 0.5 ms speed cycle with a filter on the
measured speed, a PWM period of computation delay, rounding encoders, encoders zeroed at
the start (the axis then starts away from 0), an ADC that clips at full scale within the
program's peaks, and the rigid screw (every screw here).
"""

import math
from dataclasses import dataclass, field
from pathlib import Path

from plant.config import MachineConfig, load_machine

from .axis import axis_constants
from .controller import Conventions
from .program import bench_program
from .trace import SUBSTEPS, Trace, deviation, simulate

CONFIGS = Path(__file__).resolve().parents[3] / "configs" / "identify"
SCREW, LINEAR, ROTARY = (CONFIGS / f"bench_{n}.toml" for n in ("screw", "linear", "rotary"))
#: a Sinumerik-style cascade: 2 ms position cycle, 0.5 ms speed cycle, fine interpolation
SLOW_POSITION = {"position_cycle_s": 0.002, "speed_cycle_s": 0.0005, "feedforward": "linear",
                 "speed_filter_s": 0.0005, "current_delay_cycles": 1}
#: the traces' length when the bench asks for none, s (the issue's 16 s trace)
DURATION_S = 16.0
#: the default start, m: between two counts of every encoder of the bench's axes (on a
#: count's edge the reading would hang on the last bit of a float)
X0 = 0.050000037


@dataclass(frozen=True)
class Case:
    """One trace of the second generator.

    Attributes:
        name: short id (file names), ``g2_`` first.
        axis: the declared machine file.
        effects: the undeclared effects, as ``hil identify`` names them.
        truth: machine-file keys of the truth on top of ``axis``.
        start: machine-file keys of the file identification starts from, on top of
            ``axis`` (where the effect's absence is a key of the declared file).
        conventions: the trace's controller and sensors.
        x0: where the axis truly starts (m or rad).
        travel: the program's travel (m or rad); speed its top speed (per s).
        seed: of the current noise.
        tolerance: ``hil identify --tolerance`` of the case (effect -> relative
            tolerance of its declared coefficients): where a declared value is wrong on
            purpose by more than the 10 % default, as a user doubting it would say.
    """
    name: str
    axis: Path
    effects: tuple
    conventions: Conventions
    truth: dict = field(default_factory=dict)
    start: dict = field(default_factory=dict)
    x0: float = X0
    travel: float = 0.25
    speed: float = 0.15
    seed: int = 1
    tolerance: dict = field(default_factory=dict)


CASES = (
    Case("g2_screw_coulomb_slow_position", SCREW, ("coulomb_friction",),
         Conventions(**SLOW_POSITION), start={"friction": {"coulomb_n": 0.0}}, seed=41),
    Case("g2_screw_force_round", SCREW, ("gravity_offset",),
         Conventions(encoder_rounding="round"), truth={"table": {"external_force_n": -150.0}},
         seed=42),
    # the encoders count from a start 0.1037 m away from the cogging's zero
    Case("g2_screw_cogging_zeroed", SCREW, ("cogging",),
         Conventions(position_cycle_s=0.002, encoder_zero_at_start=True),
         truth={"cogging": {"orders": [2.0], "amplitudes_nm": [0.04], "phases_deg": [30.0]}},
         x0=0.1037, seed=43),
    # the ADC clips at 0.6 A, within the fastest moves' acceleration peaks (0.63 A declared,
    # 0.7 A true); the top speed 0.28 m/s within the axis's 0.3 m/s
    Case("g2_linear_inertia_clipping", LINEAR, ("inertia",),
         Conventions(position_cycle_s=0.002, adc_full_scale_a=0.6),
         truth={"table": {"mass_kg": 18.0}}, travel=0.4, speed=0.28, seed=44,
         tolerance={"inertia": 0.6}),
    Case("g2_rotary_viscous_round_zeroed", ROTARY, ("viscous_friction",),
         Conventions(**SLOW_POSITION, encoder_rounding="round", encoder_zero_at_start=True),
         start={"friction": {"viscous_nms_per_rad": 0.0}}, x0=1.0, travel=5.0, speed=1.5,
         seed=45),
    # every convention at once; 0.38 A of the force at rest, the ADC clipping at 0.9 A
    Case("g2_screw_force_every_convention", SCREW, ("gravity_offset",),
         Conventions(**SLOW_POSITION, encoder_rounding="round", encoder_zero_at_start=True,
                     adc_full_scale_a=0.9),
         truth={"table": {"external_force_n": -60.0}}, x0=0.12, seed=46),
)


def case(name: str) -> Case:
    """The case called ``name``; KeyError lists the names."""
    for c in CASES:
        if c.name == name:
            return c
    raise KeyError(f"no second-generator case {name!r}; cases: "
                   + ", ".join(c.name for c in CASES))


def generate(c: Case, truth: MachineConfig, duration_s: float | None = None
             ) -> tuple[Trace, dict]:
    """The case's trace on the truth's machine file ``truth`` (``duration_s``: at least this
    long, s; None: :data:`DURATION_S`) and the generator's repeat: its deviation from the
    same run at four times the integration steps, same noise (:func:`~.trace.deviation`)."""
    origin = 0.0 if c.conventions.encoder_zero_at_start else c.x0
    prog = bench_program(c.travel, c.speed, duration_s or DURATION_S, origin)
    trace, finer = (simulate(truth, c.conventions, prog, x0=c.x0, seed=c.seed, substeps=n)
                    for n in (SUBSTEPS, 4 * SUBSTEPS))
    return trace, deviation(trace, finer)


def truth_in_trace_frame(c: Case) -> dict:
    """The case's truth keys as the trace sees them: with encoders zeroed at the start the
    trace's positions are the travel since ``x0``, so a cogging harmonic
    A sin(n theta_e + phi) of the true position has the phase phi + n theta_e(x0) in the
    trace's frame (degrees, wrapped into [-180, 180]).  A replay of the truth in the trace's
    frame needs these; the generator runs on :attr:`Case.truth`."""
    cog = c.truth.get("cogging")
    if not (c.conventions.encoder_zero_at_start and cog):
        return c.truth
    ax, _ = axis_constants(load_machine(c.axis))
    phases = cog.get("phases_deg") or [0.0] * len(cog["orders"])
    shifted = [math.degrees(math.remainder(math.radians(ph) + n * ax.poles * c.x0,
                                           2 * math.pi))
               for n, ph in zip(cog["orders"], phases)]
    return {**c.truth, "cogging": {**cog, "phases_deg": shifted}}
