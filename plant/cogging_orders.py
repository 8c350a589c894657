"""Cogging orders from a rotary motor's slot and pole numbers ([cogging] slots).

A rotor of 2 p magnet poles over Q stator slots lines up with the slots the same way
again after the smallest angle that is a whole number of slot pitches 2 pi / Q and of pole
pitches 2 pi / (2 p): the cogging torque repeats LCM(Q, 2 p) times per mechanical
revolution (the textbook result, e.g. Zhu and Howe 2000), LCM(Q, 2 p) / p times per
electrical revolution, and has harmonics at the multiples of that only.
"""

import math
from dataclasses import replace

from plant.errors import ConfigError
from plant.sections import CoggingSection, MotorSection


def cogging_fundamental(slots: int, pole_pairs: int) -> float:
    """Cycles per electrical revolution of the cogging's fundamental, LCM(slots, 2 p) / p
    (module docstring)."""
    return math.lcm(slots, 2 * pole_pairs) / pole_pairs


def slot_orders(cog: CoggingSection, motor: MotorSection, where: str) -> CoggingSection:
    """``cog`` with its orders checked against, or taken from, its slots and the motor's pole
    pairs (``where``: the file, for the messages): given orders must be whole multiples of
    :func:`cogging_fundamental`; none given are its first len(amplitudes) multiples."""
    if not cog.slots or not motor.pole_pairs:  # no pole pairs: refused by the loader
        return cog
    pairs = round(motor.pole_pairs)
    if pairs != motor.pole_pairs:
        raise ConfigError(f"{where}: [cogging] slots needs a whole number of [motor] pole_pairs "
                          f"(got {motor.pole_pairs:g})")
    base = cogging_fundamental(cog.slots, pairs)
    if not cog.orders:
        return replace(cog, orders=tuple(base * (k + 1) for k in range(len(cog.amplitudes_nm))))
    for order in cog.orders:
        if not math.isclose(order / base, round(order / base)) or order < base:
            raise ConfigError(
                f"{where}: [cogging] orders = {list(cog.orders)}: {order:g} is no cogging "
                f"harmonic of {cog.slots} slots and {2 * pairs} poles, whose fundamental is "
                f"LCM({cog.slots}, {2 * pairs}) / {pairs} = {base:g} cycles per electrical "
                "revolution (give its multiples, or leave orders empty)")
    return cog
