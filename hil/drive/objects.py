"""The drive's objects as a CANopen master reads and writes them by SDO.

:class:`DriveObjects` is the :class:`io_adapters.cia402_objects.ObjectAccess` that
``hil run`` gives a ``can://`` endpoint: each object of
:data:`~io_adapters.cia402_objects.PARAMETERS` maps onto a field of the axis's
:class:`~hil.drive.config.DriveParameters` (or, read-only, onto what the drive measures),
converted between the drive's motor coordinate and increments (the node scales those to
the master's position unit, :mod:`io_adapters.can_dictionary`):

=======  ===========================  ==============================  ======================
object   meaning                      unit here                       refused (abort code)
=======  ===========================  ==============================  ======================
1006h    communication cycle period   µs                              not whole PWM periods
                                                                      (0609 0030)
6007h    abort connection option      code 0-3                        other (0609 0030)
605Ah    quick stop option            code 1-8                        other (0609 0030)
605Eh    fault reaction option        code 0-4                        other (0609 0030)
6062h    position demand value        increments (read only)
6065h    following error window       increments, FFFFFFFFh: off
6066h    following error time out     ms
6067h    position window              increments
6068h    position window time         ms
6072h    max torque, as the current   per mille of 6075h (the torque  0 (0609 0032), above
         limit                        objects' unit on this wire)     the peak (0609 0031)
607Ch    home offset                  increments
607Dh    software position limits     increments (sub 1 min,          min > max (0609 0036)
                                      sub 2 max; -2^31 and 2^31-1:
                                      that side off)
6080h    max motor speed              increments/s, 0: off            so high that 6084h or
                                                                      6085h would stop it
                                                                      in more than 2 s
                                                                      (0609 0031)
6081h    profile velocity             increments/s
6083h    profile acceleration         increments/s²                   0 (0609 0032)
6084h    profile deceleration         increments/s²                   below a stop from
                                                                      1.1 x 6080h in 2 s
                                                                      (0609 0032)
6085h    quick stop deceleration      increments/s²                   as 6084h (0609 0032)
608Fh    encoder increments per       :01 increments, :02 1 (read
         motor revolution             only; a linear motor's
                                      revolution: 2 pole pitches)
6098h    homing method                :mod:`hil.drive.homing`'s       other (0609 0030)
6099h    homing speeds                increments/s (:01 switch,       0 (0609 0032)
                                      :02 zero)
609Ah    homing acceleration          increments/s²                   0 (0609 0032)
60C2h    interpolation time period    :01 value, :02 index (10^index
                                      s); 0: none
60F4h    following error actual       increments (read only)
60FDh    digital inputs               bit 0 negative, bit 1 positive
                                      limit switch, bit 2 home switch
                                      (read only)
2F00h    fault injection (the test    :01-:09 each fault's level in   a fault this machine
         bench's object,              its integer unit                cannot have, a level
         :mod:`hil.inject`)           (``wire_per_unit``, in the      out of range
                                      order of :data:`~hil.inject.    (0609 0030)
                                      catalog.BY_SUBINDEX`); :0A
                                      ramp time of the next writes,
                                      ms
=======  ===========================  ==============================  ======================

A write of 2F00h:01-09 is checked at once (an abort refuses it) and acts from the next
tick, ramped over 2F00h:0A; the torque ripple takes its order and phase from the machine
file's ``[inject.torque_ripple]`` table where there is one.  Reading gives the present
level.  An NMT reset node does not heal the axis: a fault is the machine's, not a
setting.

Positions (6062h, 607Dh) are those of the position actual value: shifted by the home
offset once a homing has ended.  Reads and writes hold the drive's lock, so a write lands
between two cycles and takes effect from the next.  An NMT reset node puts every object
back to the machine file's values and forgets the home (the position offset back to 0).
"""

import math
from dataclasses import fields, replace

from hil.cia402 import AbortConnectionOption, FaultReactionOption, QuickStopOption
from hil.drive.braking import RAMP_TIME_LIMIT_S, min_deceleration
from hil.drive.core import EmulatedDrive
from hil.drive.homing import METHODS
from hil.inject.catalog import BY_SUBINDEX
from hil.inject.schedule import Injector, check
from io_adapters.can_catalog import (
    FAULT_INJECTION,
    INJECT_RAMP_SUB,
    SDO_ABORT_MAX_BELOW_MIN,
    SDO_ABORT_NO_OBJECT,
    SDO_ABORT_VALUE_HIGH,
    SDO_ABORT_VALUE_LOW,
    SDO_ABORT_VALUE_RANGE,
)
from io_adapters.cia402_objects import ObjectAccessError
from plant.errors import ConfigError

U32_OFF = 0xFFFFFFFF
I32_MIN, I32_MAX = -2**31, 2**31 - 1
#: option objects: index -> (parameter field, the option codes offered)
OPTIONS = {0x6007: ("abort_connection_option", AbortConnectionOption),
           0x605A: ("quick_stop_option", QuickStopOption),
           0x605E: ("fault_reaction_option", FaultReactionOption)}
#: distances in increments: index -> field (6065h's FFFFFFFFh is "off")
POSITIONS = {0x6065: "fe_window", 0x6067: "position_window", 0x607C: "home_offset"}
#: times in ms: index -> field (s)
TIMES = {0x6066: "fe_time_s", 0x6068: "position_window_time_s"}
#: speeds (increments/s) and accelerations (increments/s²) that must be > 0 (6081h may be
#: 0: a move that never starts): (index, sub-index) -> field
POSITIVE = {(0x6083, 0): "profile_acceleration", (0x6084, 0): "profile_decel",
            (0x6085, 0): "quick_stop_decel", (0x6099, 1): "homing_speed_switch",
            (0x6099, 2): "homing_speed_zero", (0x609A, 0): "homing_acceleration"}
#: whole numbers stored as they come: (index, sub-index) -> field
CODES = {(0x60C2, 1): "interpolation_value", (0x60C2, 2): "interpolation_index"}


def _i32(value: float) -> int:
    return min(max(round(value), I32_MIN), I32_MAX)


class DriveObjects:
    """The objects of every axis's drive (see the module docstring).

    Args:
        drives: the drives in axis order.
        rated_current_a: 6075h, the reference of 6072h's per mille, A.
        injectors: every axis's fault injector (2F00h); none: 2F00h does not exist.
    """

    def __init__(self, drives: list[EmulatedDrive], rated_current_a: float,
                 injectors: tuple[Injector, ...] = ()):
        self.drives = drives
        self.rated_current_a = rated_current_a
        self.injectors = injectors
        self._ramp_ms = [0] * len(drives)
        self._initial = [replace(d.params) for d in drives]

    def cycle_s(self, axis: int) -> float:
        return self.drives[axis].plant.pwm_period

    def read(self, axis: int, index: int, subindex: int) -> int:
        if index == FAULT_INJECTION:
            return self._injection_read(axis, subindex)
        d = self.drives[axis]
        with d.lock:
            d.settle()
            return self._read(d, index, subindex)

    def _read(self, d: EmulatedDrive, index: int, subindex: int) -> int:
        p, rpc, shift = d.params, d.rad_per_count, d.modes.shift_counts
        key = (index, subindex)
        if index in OPTIONS:
            return getattr(p, OPTIONS[index][0])
        if index in POSITIONS:
            value = getattr(p, POSITIONS[index])
            if math.isinf(value):
                return U32_OFF
            return _i32(value / rpc) if index == 0x607C else min(round(value / rpc),
                                                                  U32_OFF - 1)
        if index in TIMES:
            return round(getattr(p, TIMES[index]) * 1e3)
        if key in POSITIVE or index == 0x6081:
            value = getattr(p, POSITIVE.get(key, "profile_velocity"))
            return min(round(value / rpc), U32_OFF)
        if key in CODES:
            return getattr(p, CODES[key])
        if index == 0x1006:
            return round(p.communication_cycle_s * 1e6)
        if index == 0x6062:
            return _i32(d.modes.demand / rpc + shift)
        if index == 0x6072:
            return min(round(p.max_current_a / self.rated_current_a * 1e3), 0xFFFF)
        if index == 0x607D:
            limit = p.limit_min if subindex == 1 else p.limit_max
            return _i32(limit / rpc + shift) if math.isfinite(limit) \
                else (I32_MIN if limit < 0 else I32_MAX)
        if index == 0x6080:
            return 0 if math.isinf(p.max_speed) else min(round(p.max_speed / rpc), U32_OFF)
        if index == 0x608F:
            return d.plant.counts_per_mark if subindex == 1 else 1
        if index == 0x6098:
            return p.homing_method
        if index == 0x60F4:
            return _i32(d.monitor.following_error / rpc)
        if index == 0x60FD:
            return d.digital_inputs()
        raise ObjectAccessError(SDO_ABORT_NO_OBJECT, f"{index:04X}h is not a drive parameter")

    def write(self, axis: int, index: int, subindex: int, value: float) -> None:
        if index == FAULT_INJECTION:
            self._inject(axis, subindex, value)
            return
        d = self.drives[axis]
        with d.lock:
            d.settle()
            self._write(d, index, subindex, value)

    def _write(self, d: EmulatedDrive, index: int, subindex: int, value: float) -> None:
        p, rpc = d.params, d.rad_per_count
        key = (index, subindex)
        if index in OPTIONS:
            name, codes = OPTIONS[index]
            if value not in {int(c) for c in codes}:
                raise ObjectAccessError(SDO_ABORT_VALUE_RANGE, f"{index:04X}h = {value}: "
                                        f"not one of {[int(c) for c in codes]}")
            if index == 0x605A:
                d.set_quick_stop_option(int(value))
            else:
                setattr(p, name, int(value))
        elif index in POSITIONS:
            off = index == 0x6065 and value == U32_OFF
            setattr(p, POSITIONS[index], math.inf if off else value * rpc)
        elif index in TIMES:
            setattr(p, TIMES[index], value * 1e-3)
        elif key in POSITIVE:
            _positive(index, value)
            if index in (0x6084, 0x6085):
                _ramp_bound(index, value * rpc, p.max_speed, rpc)
            setattr(p, POSITIVE[key], value * rpc)
        elif key in CODES:
            setattr(p, CODES[key], int(value))
        elif index == 0x1006:
            periods = value * 1e-6 / d.plant.pwm_period
            if abs(periods - round(periods)) > 1e-6:
                raise ObjectAccessError(SDO_ABORT_VALUE_RANGE, f"1006h = {value} µs is not a "
                                        f"whole number of drive cycles "
                                        f"({d.plant.pwm_period * 1e6:g} µs)")
            p.communication_cycle_s = value * 1e-6
        elif index == 0x6072:
            self._max_current(p, value)
        elif index == 0x607D:
            self._limit(p, subindex, value, rpc, d.modes.shift_counts)
        elif index == 0x6080:
            speed = math.inf if value == 0 else value * rpc
            if min(p.profile_decel, p.quick_stop_decel) < min_deceleration(speed):
                raise ObjectAccessError(SDO_ABORT_VALUE_HIGH, f"6080h = {value:g} increments/s: "
                                        "6084h or 6085h would take longer than "
                                        f"{RAMP_TIME_LIMIT_S:g} s to stop the axis from it")
            p.max_speed = speed
        elif index == 0x6081:
            p.profile_velocity = value * rpc
        elif index == 0x6098:
            if value not in METHODS:
                raise ObjectAccessError(SDO_ABORT_VALUE_RANGE, f"6098h = {value}: homing "
                                        f"methods offered: {sorted(METHODS)}")
            p.homing_method = int(value)

    def _injector(self, axis: int) -> Injector:
        if not self.injectors:
            raise ObjectAccessError(SDO_ABORT_NO_OBJECT, "2F00h: no fault injection here")
        return self.injectors[axis]

    def _injection_read(self, axis: int, subindex: int) -> int:
        if not self.injectors:  # a drive nobody injects into is healthy
            return 0
        inj = self.injectors[axis]
        if subindex == INJECT_RAMP_SUB:
            return self._ramp_ms[axis]
        fault = BY_SUBINDEX[subindex - 1]
        return round(inj.levels[fault.name] * fault.wire_per_unit)

    def _inject(self, axis: int, subindex: int, value: float) -> None:
        """Check a 2F00h write as the machine file's table would be, then hand it to the
        axis's injector (it acts at the next tick)."""
        inj = self._injector(axis)
        if subindex == INJECT_RAMP_SUB:
            self._ramp_ms[axis] = int(value)
            return
        fault = BY_SUBINDEX[subindex - 1]
        table = {**inj.cfg.section("inject").get(fault.name, {}),
                 fault.level_key: value / fault.wire_per_unit,
                 "ramp_s": self._ramp_ms[axis] * 1e-3}
        table.pop("at_s", None)
        try:
            check(fault.name, table, inj.cfg, f"2F00h:{subindex:02X}", "SDO 2F00h")
        except ConfigError as e:
            raise ObjectAccessError(SDO_ABORT_VALUE_RANGE, str(e)) from None
        inj.request(fault.name, table, "SDO 2F00h")

    def _max_current(self, p, value: float) -> None:
        _positive(0x6072, value)
        current = value * self.rated_current_a * 1e-3
        if current > p.current_max_a:
            raise ObjectAccessError(SDO_ABORT_VALUE_HIGH, f"6072h = {value} per mille "
                                    f"= {current:g} A is above the drive's peak "
                                    f"{p.current_max_a:g} A")
        p.max_current_a = current

    @staticmethod
    def _limit(p, subindex: int, value: float, rpc: float, shift: float) -> None:
        off = value == (I32_MIN if subindex == 1 else I32_MAX)
        limit = (-math.inf if subindex == 1 else math.inf) if off else (value - shift) * rpc
        lo, hi = (limit, p.limit_max) if subindex == 1 else (p.limit_min, limit)
        if lo > hi:
            raise ObjectAccessError(SDO_ABORT_MAX_BELOW_MIN, f"607Dh: min {lo / rpc:.0f} > "
                                    f"max {hi / rpc:.0f} increments")
        p.limit_min, p.limit_max = lo, hi

    def reset_application(self, axis: int) -> None:
        d, initial = self.drives[axis], self._initial[axis]
        with d.lock:
            d.settle()
            for f in fields(initial):
                setattr(d.params, f.name, getattr(initial, f.name))
            d.set_quick_stop_option(initial.quick_stop_option)
            d.modes.homing.reset()


def _ramp_bound(index: int, decel: float, max_speed: float, rpc: float) -> None:
    """A reaction ramp (6084h, 6085h) must stop the axis from its top speed within
    :data:`~hil.drive.braking.RAMP_TIME_LIMIT_S` (motor units/s², rad per increment)."""
    bound = min_deceleration(max_speed)
    if decel < bound:
        raise ObjectAccessError(SDO_ABORT_VALUE_LOW, f"{index:04X}h = {decel / rpc:.0f} "
                                f"increments/s^2: below {bound / rpc:.0f}, the least that "
                                f"stops the axis from 1.1 x 6080h within "
                                f"{RAMP_TIME_LIMIT_S:g} s")


def _positive(index: int, value: float) -> None:
    if value <= 0:
        raise ObjectAccessError(SDO_ABORT_VALUE_LOW, f"{index:04X}h = {value}: must be > 0")
