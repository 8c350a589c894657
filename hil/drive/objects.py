"""The drive's parameter objects as a CANopen master reads and writes them by SDO.

:class:`DriveObjects` is the :class:`io_adapters.cia402_objects.ObjectAccess` that
``hil run`` gives a ``can://`` endpoint: each object of
:data:`~io_adapters.cia402_objects.PARAMETER_OBJECTS` maps onto a field of the axis's
:class:`~hil.drive.config.DriveParameters` (or, read-only, onto what the drive measures),
converted between the wire's units and the drive's motor coordinate:

=======  ===========================  ==============================  ======================
object   meaning                      wire unit                       refused (abort code)
=======  ===========================  ==============================  ======================
6007h    abort connection option      code 0-3                        other (0609 0030)
605Ah    quick stop option            code 1-8                        other (0609 0030)
605Eh    fault reaction option        code 0-4                        other (0609 0030)
6065h    following error window       increments, FFFFFFFFh: off
6066h    following error time out     ms
6067h    position window              increments
6068h    position window time         ms
6072h    max torque, as the current   per mille of 6075h (the torque  0 (0609 0032), above
         limit                        objects' unit on this wire)     the peak (0609 0031)
607Dh    software position limits     increments (sub 1 min,          min > max (0609 0036)
                                      sub 2 max; -2^31 and 2^31-1:
                                      that side off)
6080h    max motor speed              increments/s (velocity unit),
                                      0: off (device-specific)
6084h    profile deceleration         increments/s²                   0 (0609 0032)
6085h    quick stop deceleration      increments/s²                   0 (0609 0032)
60F4h    following error actual       increments (read only)
60FDh    digital inputs               bit 0 negative, bit 1 positive
                                      limit switch (read only)
=======  ===========================  ==============================  ======================

Reads and writes hold the drive's lock, so a write lands between two cycles and takes
effect from the next.  An NMT reset node puts every object back to the machine file's
values.
"""

import math
from dataclasses import fields, replace

from hil.cia402 import AbortConnectionOption, FaultReactionOption, QuickStopOption
from hil.drive.core import EmulatedDrive
from io_adapters.cia402_objects import (
    DI_NEGATIVE_LIMIT,
    DI_POSITIVE_LIMIT,
    SDO_ABORT_MAX_BELOW_MIN,
    SDO_ABORT_NO_OBJECT,
    SDO_ABORT_VALUE_HIGH,
    SDO_ABORT_VALUE_LOW,
    SDO_ABORT_VALUE_RANGE,
    ObjectAccessError,
)
from plant import layout as L

U32_OFF = 0xFFFFFFFF
I32_MIN, I32_MAX = -2**31, 2**31 - 1
#: option objects: index -> (parameter field, the option codes offered)
OPTIONS = {0x6007: ("abort_connection_option", AbortConnectionOption),
           0x605A: ("quick_stop_option", QuickStopOption),
           0x605E: ("fault_reaction_option", FaultReactionOption)}
#: position objects in increments: index -> field
POSITIONS = {0x6065: "fe_window", 0x6067: "position_window"}
#: times in ms: index -> field (s)
TIMES = {0x6066: "fe_time_s", 0x6068: "position_window_time_s"}
#: decelerations in increments/s²: index -> field
DECELERATIONS = {0x6084: "profile_decel", 0x6085: "quick_stop_decel"}


class DriveObjects:
    """The parameter objects of every axis's drive (see the module docstring).

    Args:
        drives: the drives in axis order.
        rated_current_a: 6075h, the reference of 6072h's per mille, A.
    """

    def __init__(self, drives: list[EmulatedDrive], rated_current_a: float):
        self.drives = drives
        self.rated_current_a = rated_current_a
        self._initial = [replace(d.params) for d in drives]

    def read(self, axis: int, index: int, subindex: int) -> int:
        d = self.drives[axis]
        with d.lock:
            return self._read(d, index, subindex)

    def _read(self, d: EmulatedDrive, index: int, subindex: int) -> int:
        p, rpc = d.params, d.rad_per_count
        if index in OPTIONS:
            return getattr(p, OPTIONS[index][0])
        if index in POSITIONS:
            value = getattr(p, POSITIONS[index])
            return U32_OFF if math.isinf(value) else min(round(value / rpc), U32_OFF - 1)
        if index in TIMES:
            return round(getattr(p, TIMES[index]) * 1e3)
        if index in DECELERATIONS:
            return min(round(getattr(p, DECELERATIONS[index]) / rpc), U32_OFF)
        if index == 0x6072:
            return min(round(p.max_current_a / self.rated_current_a * 1e3), 0xFFFF)
        if index == 0x607D:
            limit = p.limit_min if subindex == 1 else p.limit_max
            return min(max(round(limit / rpc), I32_MIN), I32_MAX) if math.isfinite(limit) \
                else (I32_MIN if limit < 0 else I32_MAX)
        if index == 0x6080:
            return 0 if math.isinf(p.max_speed) else min(round(p.max_speed / rpc), U32_OFF)
        if index == 0x60F4:
            return min(max(round(d.monitor.following_error / rpc), I32_MIN), I32_MAX)
        if index == 0x60FD:
            out = d.plant.out
            return ((DI_NEGATIVE_LIMIT if out[L.O_LIMIT_NEG] > 0.0 else 0)
                    | (DI_POSITIVE_LIMIT if out[L.O_LIMIT_POS] > 0.0 else 0))
        raise ObjectAccessError(SDO_ABORT_NO_OBJECT, f"{index:04X}h is not a drive parameter")

    def write(self, axis: int, index: int, subindex: int, value: int) -> None:
        d = self.drives[axis]
        with d.lock:
            self._write(d, index, subindex, value)

    def _write(self, d: EmulatedDrive, index: int, subindex: int, value: int) -> None:
        p, rpc = d.params, d.rad_per_count
        if index in OPTIONS:
            name, codes = OPTIONS[index]
            if value not in {int(c) for c in codes}:
                raise ObjectAccessError(SDO_ABORT_VALUE_RANGE, f"{index:04X}h = {value}: "
                                        f"not one of {[int(c) for c in codes]}")
            if index == 0x605A:
                d.set_quick_stop_option(value)
            else:
                setattr(p, name, value)
        elif index in POSITIONS:
            setattr(p, POSITIONS[index], math.inf if value == U32_OFF else value * rpc)
        elif index in TIMES:
            setattr(p, TIMES[index], value * 1e-3)
        elif index in DECELERATIONS:
            _positive(index, value)
            setattr(p, DECELERATIONS[index], value * rpc)
        elif index == 0x6072:
            _positive(index, value)
            current = value * self.rated_current_a * 1e-3
            if current > p.current_max_a:
                raise ObjectAccessError(SDO_ABORT_VALUE_HIGH, f"6072h = {value} per mille "
                                        f"= {current:g} A is above the drive's peak "
                                        f"{p.current_max_a:g} A")
            p.max_current_a = current
        elif index == 0x607D:
            self._limit(p, subindex, value, rpc)
        elif index == 0x6080:
            p.max_speed = math.inf if value == 0 else value * rpc

    @staticmethod
    def _limit(p, subindex: int, value: int, rpc: float) -> None:
        off = value == (I32_MIN if subindex == 1 else I32_MAX)
        limit = (-math.inf if subindex == 1 else math.inf) if off else value * rpc
        lo, hi = (limit, p.limit_max) if subindex == 1 else (p.limit_min, limit)
        if lo > hi:
            raise ObjectAccessError(SDO_ABORT_MAX_BELOW_MIN, f"607Dh: min {lo / rpc:.0f} > "
                                    f"max {hi / rpc:.0f} increments")
        p.limit_min, p.limit_max = lo, hi

    def reset_application(self, axis: int) -> None:
        d, initial = self.drives[axis], self._initial[axis]
        with d.lock:
            for f in fields(initial):
                setattr(d.params, f.name, getattr(initial, f.name))
            d.set_quick_stop_option(initial.quick_stop_option)


def _positive(index: int, value: int) -> None:
    if value <= 0:
        raise ObjectAccessError(SDO_ABORT_VALUE_LOW, f"{index:04X}h = {value}: must be > 0")
