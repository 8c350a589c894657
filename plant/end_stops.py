"""End stops and limit switches of a table with a stroke: where they sit, how stiff they
are, and what they ask of the integration sub-step.

A screw or linear axis travels over [0, [table] travel_m]; its limit switches trip at
``-limit_switch_overtravel_m`` and ``travel_m + limit_switch_overtravel_m``, its hard stops
sit at ``-end_stop_overtravel_m`` and ``travel_m + end_stop_overtravel_m``
(:mod:`plant.effects.end_stop` has the contact law).  A rotary table turns endlessly and
has neither.

The contact acts on the table: in the screw model on the table's own degree of freedom
(mass ``[table] mass_kg``), in the rigid and two-mass models (and on a linear motor)
through the table's kinematic link to the last node, whose whole inertia moves with the
table (mass: that inertia over ``(lead/2pi)^2``).  That mass ``m`` and the contact's
stiffness ``k`` and damping ``c`` give the contact's rate ``sqrt(k/m) + c/m`` (rad/s):
semi-implicit Euler on ``m x'' = -k x - c x'`` is stable iff ``k dt^2/m + 2 c dt/m < 4``,
which a rate times ``dt`` below 2 implies.  The sub-step choice (:mod:`plant.assemble`)
bounds that rate like the chains' highest natural frequency, and the chains' modes with a
stop in contact as well.

Automatic values (a key at 0): the damping ratio is :data:`AUTO_DAMPING_RATIO`; the
stiffness gives the contact with that damping the rate :data:`AUTO_RATE_SHARE` times the
rate the sub-step of the chains alone carries (``max_omega_dt / dt``), so automatic stops
add no sub-steps: with the defaults the contact frequency ``sqrt(k/m)`` is a quarter of
the carried rate (``omega dt = 0.125``, a frequency error of 0.07 %) and a contact lasts
about 20 sub-steps.  An explicit damping with an automatic stiffness keeps that stiffness.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

from plant.errors import ConfigError
from plant.sections import TableSection

#: damping ratio of an automatic end-stop damper: the unilateral contact then returns a
#: table with 30 % of its impact speed (bilateral Kelvin-Voigt would say 16 %), of the
#: order of a polymer buffer, and a table pushed into it settles within one oscillation
AUTO_DAMPING_RATIO = 0.5
#: share of the rate the chains' sub-step carries given to an automatic contact; the rest
#: leaves room for the contact mode's coupling to the nut and screw
AUTO_RATE_SHARE = 0.5


@dataclass(frozen=True)
class EndStops:
    """The end stops and limit switches of one table.

    Attributes:
        stop_neg, stop_pos: m, positions of the hard stops.
        limit_neg, limit_pos: m, positions of the limit switches.
        stiffness: N/m, contact stiffness (an automatic value filled in).
        damping: N·s/m, contact damping (an automatic value filled in).
        mass: kg, the table's effective mass at the contact (see the module).
    """
    stop_neg: float
    stop_pos: float
    limit_neg: float
    limit_pos: float
    stiffness: float
    damping: float
    mass: float

    @property
    def rate(self) -> float:
        """rad/s, the contact's rate sqrt(k/m) + c/m (see the module)."""
        return contact_rate(self.stiffness, self.damping, self.mass)


def contact_rate(stiffness: float, damping: float, mass: float) -> float:
    """rad/s: sqrt(k/m) + c/m of a contact of ``stiffness`` (N/m) and ``damping``
    (N·s/m) on ``mass`` (kg)."""
    return math.sqrt(stiffness / mass) + damping / mass


def damping_for(stiffness: float, mass: float, table: TableSection) -> float:
    """N·s/m: the file's damping, or the automatic one (ratio :data:`AUTO_DAMPING_RATIO`)
    for a contact of ``stiffness`` (N/m) on ``mass`` (kg)."""
    if table.end_stop_damping_ns_per_m > 0.0:
        return table.end_stop_damping_ns_per_m
    return 2.0 * AUTO_DAMPING_RATIO * math.sqrt(stiffness * mass)


def end_stops(table: TableSection, mass: float, carried_rate: float) -> EndStops:
    """The table's end stops; automatic values for a sub-step that carries
    ``carried_rate`` (rad/s, max_omega_dt / dt of the chains alone) on ``mass`` (kg)."""
    k = table.end_stop_stiffness_n_per_m
    if k <= 0.0:
        # with the automatic damping, sqrt(k/m) + c/m = (1 + 2 zeta) sqrt(k/m)
        omega = AUTO_RATE_SHARE * carried_rate / (1.0 + 2.0 * AUTO_DAMPING_RATIO)
        k = mass * omega * omega
    travel, stop, limit = (table.travel_m, table.end_stop_overtravel_m,
                           table.limit_switch_overtravel_m)
    return EndStops(-stop, travel + stop, -limit, travel + limit, k,
                    damping_for(k, mass, table), mass)


def check_substep(where: str, table: TableSection, stops: EndStops, dt: float,
                  omega_of: Callable[[EndStops], float]) -> None:
    """Refuse end stops that make the sub-step ``dt`` (s) unstable, ``omega_of(stops) * dt
    >= 2`` with ``omega_of`` their highest rate in rad/s, by a ConfigError naming ``where``
    and the largest stiffness that fits."""
    def fits(k: float) -> bool:
        trial = replace(stops, stiffness=k, damping=damping_for(k, stops.mass, table))
        return omega_of(trial) * dt < 2.0

    if fits(stops.stiffness):
        return
    given = "automatic" if table.end_stop_stiffness_n_per_m <= 0.0 else "given"
    label = (f"{where}: [table] end_stop_stiffness_n_per_m = {stops.stiffness:.4g} N/m "
             f"({given}) with end_stop_damping_ns_per_m = {stops.damping:.4g} N*s/m is "
             f"unstable at [simulation] substep_s = {dt:g} s: the contact on "
             f"{stops.mass:.4g} kg needs (sqrt(k/m) + c/m) dt < 2 and every mode in contact "
             "omega dt < 2")
    k_max = _largest(fits, stops.stiffness)
    if k_max <= 0.0:
        raise ConfigError(f"{label}; the damping alone is too much: end_stop_damping_ns_per_m "
                          f"must be < 2 m / dt = {2.0 * stops.mass / dt:.4g} N*s/m")
    raise ConfigError(f"{label}; too stiff: at most {k_max:.4g} N/m fits")


def _largest(fits: Callable[[float], bool], start: float) -> float:
    """The largest stiffness (N/m) with ``fits(k)``, to 0.1 %, by bisection in log k below
    ``start`` (which does not fit); 0 when none above 1e-6 N/m does."""
    lo, hi = 0.0, start
    while lo == 0.0:
        hi *= 0.5
        if hi < 1e-6:
            return 0.0
        if fits(hi):
            lo = hi
    hi *= 2.0
    while hi / lo > 1.001:
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return lo
