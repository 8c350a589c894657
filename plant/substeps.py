"""How many sub-steps a PWM period may take, and what to change when a machine file asks
for more.

The automatic sub-step (:func:`plant.assemble.choose_substep`) divides the PWM period
into ``ceil(T_pwm omega_max / max_omega_dt)`` parts: a stiff spring on a light mass asks
for as many as it likes (a coupling of 1e15 N*m/rad: millions per PWM period, a kernel
call that never ends in practice).  So the count is bounded twice:

* by the plant, for every use (:data:`MAX_SUB_PER_PWM`): beyond it even an offline
  simulation runs far slower than real time;
* by ``hil run``, for real time (:func:`realtime_limit`): a sub-step costs the compiled
  kernel at most :data:`SUBSTEP_COST_S` (the plant benchmark's goal; about 0.08 µs
  measured on the Arrow 500 X since issue 12 part 7, docs/benchmarks.md), and the kernel gets
  :data:`KERNEL_SHARE` of each period, the rest being the drive's, the adapter's and the
  recording's.

A machine file over a bound is refused before anything runs (:func:`refusal`), naming the
stiffness and damping keys that, lowered alone, would fit and the largest value of each
that does -- found by bisection on the same sub-step rule, so the value given is one the
plant takes.
"""

import math
from collections.abc import Callable
from dataclasses import fields, replace

from plant.config import MachineConfig

#: the most sub-steps per PWM period the plant takes (a thousand sub-steps of the
#: kernel's 0.1-1 µs: a PWM period of 125 µs simulated in 0.1-1 ms)
MAX_SUB_PER_PWM = 1000
#: why :data:`MAX_SUB_PER_PWM` holds, for :func:`refusal`
PLANT_LIMIT = f"the plant takes at most {MAX_SUB_PER_PWM}"
#: the compiled kernel's cost per sub-step assumed for real time, s
SUBSTEP_COST_S = 1e-6
#: the share of real time the kernel may take in ``hil run``
KERNEL_SHARE = 0.5
#: the stiffnesses and dampers that set the mechanics' fastest rate: (section, key)
RATE_KEYS = (("coupling", "stiffness_nm_per_rad"), ("screw", "nut_stiffness_n_per_m"),
             ("screw", "thrust_bearing_stiffness_n_per_m"),
             ("screw", "youngs_modulus_pa"), ("screw", "shear_modulus_pa"),
             ("table", "end_stop_stiffness_n_per_m"),
             # heavy dampers add their own rate c/m (plant.assemble.mechanics_rate)
             ("coupling", "damping_nms_per_rad"), ("screw", "nut_damping_ns_per_m"),
             ("screw", "axial_damping_ns_per_m"), ("screw", "torsional_damping_nms_per_rad"),
             ("screw", "thrust_bearing_damping_ns_per_m"), ("screw", "nut_viscous_nms_per_rad"))
#: where a key's range starts at 0, the bisection's bottom relative to its value
_FLOOR = 1e-9
#: the bisection stops when the bracket is this narrow (relative)
_RELATIVE_TOLERANCE = 1e-3


def realtime_limit(pwm_frequency_hz: float) -> int:
    """The sub-steps per PWM period a real-time tick allows at ``pwm_frequency_hz`` (Hz):
    those whose assumed cost fits in :data:`KERNEL_SHARE` of the period (62 at 8 kHz)."""
    return max(1, math.floor(KERNEL_SHARE / (pwm_frequency_hz * SUBSTEP_COST_S)))


def realtime_limit_text(cfg: MachineConfig) -> str:
    """Why :func:`realtime_limit` holds, for :func:`refusal`."""
    f_pwm = cfg.motor.pwm_frequency_hz
    return (f"a real-time tick allows {realtime_limit(f_pwm)} at {f_pwm:g} Hz PWM (a sub-step "
            f"costs up to {SUBSTEP_COST_S * 1e6:g} µs of compute, the kernel gets "
            f"{KERNEL_SHARE:.0%} of the period)")


def _with(cfg: MachineConfig, section: str, key: str, value: float) -> MachineConfig:
    return replace(cfg, **{section: replace(getattr(cfg, section), **{key: value})})


def _field(cfg: MachineConfig, section: str, key: str):
    return {f.name: f for f in fields(getattr(cfg, section))}[key]


def largest_fitting(cfg: MachineConfig, section: str, key: str, n_max: int,
                    substeps_of: Callable[[MachineConfig], int]) -> float | None:
    """The largest value of ``[section] key`` (the others as they are) for which
    ``substeps_of`` gives at most ``n_max``, to 0.1 %; None when even the bottom of the
    key's range needs more.  ``substeps_of`` must grow with the key's value."""
    hi = getattr(getattr(cfg, section), key)
    lo = _field(cfg, section, key).metadata["ge"] or _FLOOR * hi
    if substeps_of(_with(cfg, section, key, lo)) > n_max:
        return None
    while hi / lo > 1.0 + _RELATIVE_TOLERANCE:
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if substeps_of(_with(cfg, section, key, mid)) <= n_max else (lo, mid)
    return lo


def refusal(cfg: MachineConfig, n: int, n_max: int, why: str, omega_max: float,
            substeps_of: Callable[[MachineConfig], int]) -> str:
    """The one-line message refusing ``cfg``, whose sub-step rule asks for ``n`` > ``n_max``
    sub-steps per PWM period (``why``: whose bound ``n_max`` is; ``omega_max``: the fastest
    rate found, rad/s (plant.assemble._omega_max); ``substeps_of``: the sub-step rule)."""
    sim = cfg.simulation
    head = f"{cfg.path}: {n} sub-steps per PWM period"
    if sim.substep_s > 0.0:
        least = 1.0 / (cfg.motor.pwm_frequency_hz * n_max)
        return (f"{head} at [simulation] substep_s = {sim.substep_s:g} s, and {why}: "
                f"substep_s must be >= {least:.4g} s (or 0: automatic)")
    head += (f": the fastest rate of the mechanics (stiffest mode or heaviest damper), "
             f"{omega_max / (2 * math.pi):.4g} Hz, at "
             f"[simulation] max_omega_dt = {sim.max_omega_dt:g}, and {why}")
    fixes = []
    for section, key in RATE_KEYS:
        part = getattr(cfg, section)
        if part is None or getattr(part, key) <= 0.0:  # absent, or automatic
            continue
        k_max = largest_fitting(cfg, section, key, n_max, substeps_of)
        if k_max is not None:
            unit = _field(cfg, section, key).metadata["unit"]
            fixes.append(f"[{section}] {key} = {getattr(part, key):.4g} {unit}: at most "
                         f"{k_max:.4g} {unit} fits")
    if not fixes:
        return (f"{head}; no stiffness or damping lowered alone fits: the masses and inertias "
                "are too light for these springs and dampers")
    return f"{head}; too stiff or too heavily damped: {'; or '.join(fixes)}"
