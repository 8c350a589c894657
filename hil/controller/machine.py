"""The NC of a whole machine: one :class:`~hil.controller.nc.Controller` per axis, one
message pair per tick.

Every axis keeps its own interpolation output, position, speed (and current) loop and its
own CiA 402 enable sequence on its own drive; they share the basic clock, so one tick
steps them all.  On one axis the messages are the plain records and the tick is exactly
``Controller.tick`` (single-axis behaviour unchanged); on several they are a
:class:`~io_adapters.messages.SetpointGroup` and
:class:`~io_adapters.messages.FeedbackGroup`, whose ``seq`` the tick advances.  A
multi-axis program runs as one profile per axis on common knots
(:func:`hil.controller.path.plan_path`), started on the same tick.

An alarm on one axis stops every axis (as an alarm stops a SINUMERIK channel): from the
next tick the other axes brake too and their drives are disabled, without alarms of their
own.  A block beyond an axis's software limits (alarm 10720, :mod:`hil.controller.limits`)
ends the program on every axis before that block.
"""

import math
from collections.abc import Sequence

from hil.controller.alarms import Alarm
from hil.controller.config import axis_limits, clamp_codes, load_controller
from hil.controller.interpolator import Profile
from hil.controller.nc import Controller
from hil.controller.path import PathProgram, plan_path
from hil.controller.program import ClampCodes
from hil.controller.stop import Phase
from io_adapters.messages import SetpointGroup, axis_records
from plant.machines import MachineSet

U32 = 0xFFFFFFFF


class MachineController:
    """The controllers of every axis of ``machine``.

    Args:
        machine: the machine (one or more axes), each axis with a ``[controller]`` section.
        period_s: the basic clock (the common PWM period), s.
        x0: each axis's table position at start (SI; default all 0).
        compiled: each axis's compiled path (:class:`~hil.controller.nc.Controller`).
    """

    def __init__(self, machine: MachineSet, period_s: float,
                 x0: Sequence[float] | None = None, compiled: bool = True):
        self.machine = machine
        x0 = tuple(x0) if x0 is not None else (0.0,) * len(machine.axes)
        if len(x0) != len(machine.axes):
            raise ValueError(f"{len(x0)} start positions for {len(machine.axes)} axes")
        self.names = machine.names
        self.ctrls = tuple(Controller(a.config, period_s, x, load_controller(a.config), a.name,
                                      compiled) for a, x in zip(machine.axes, x0))
        self.period = period_s
        self.enable_timeout_ticks = max(c.enable_timeout_ticks for c in self.ctrls)

    def __len__(self) -> int:
        return len(self.ctrls)

    @property
    def limits(self):
        """Each axis's interpolator limits (SI)."""
        return tuple(axis_limits(c.cfg, c.sec) for c in self.ctrls)

    @property
    def enabled(self) -> bool:
        """Every drive reported OPERATION ENABLED."""
        return all(c.enabled for c in self.ctrls)

    @property
    def enable_failed(self) -> bool:
        return any(c.enable.failed for c in self.ctrls)

    @property
    def clamp_codes(self) -> tuple[ClampCodes, ...]:
        """Each axis's clamp and unclamp M functions, for the program parser."""
        return tuple(clamp_codes(c.sec) for c in self.ctrls)

    @property
    def alarms(self) -> list[Alarm]:
        """Every axis's alarms (first raise of each number per axis) in the order raised."""
        return sorted((a for c in self.ctrls for a in c.alarms.alarms), key=lambda a: a.tick)

    def alarm_dicts(self) -> list[dict]:
        """:attr:`alarms` JSON-ready, each with how often it was raised (``count``)."""
        rows = [row for c in self.ctrls for row in c.alarms.as_dicts()]
        return sorted(rows, key=lambda row: row["tick"])

    @property
    def alarmed(self) -> bool:
        """Some axis raised an alarm."""
        return any(c.alarms for c in self.ctrls)

    @property
    def stopped(self) -> bool:
        """Every axis's stop reaction is complete (:attr:`Controller.stopped`)."""
        return all(c.stopped for c in self.ctrls)

    def reset_alarms(self) -> None:
        """The NC's RESET of every axis (:meth:`Controller.reset_alarms`)."""
        for c in self.ctrls:
            c.reset_alarms()

    def enable_reason(self) -> str:
        """The enable sequences' reasons, per axis."""
        return "; ".join(f"{n}: {c.enable.reason}" for n, c in zip(self.names, self.ctrls))

    def plan(self, program: PathProgram) -> tuple[Profile, ...]:
        """The program's per-axis profiles with these axes' limits; the program's axes must
        be this machine's, in its order."""
        if program.axes != self.names:
            raise ValueError(f"program for axes {program.axes}, machine has {self.names}")
        return plan_path(program, self.limits)

    def run_profiles(self, profiles: Sequence[Profile]) -> tuple[Profile, ...]:
        """Start every axis's profile on the next tick, up to the first block beyond some
        axis's software limits (alarm 10720 on each axis that block takes beyond them).
        Returns the profiles run."""
        found = [c.limit_violation(p) for c, p in zip(self.ctrls, profiles, strict=True)]
        stop = min((v.t_s for v in found if v is not None), default=math.inf)
        return tuple(c.start_program(p, stop, v if v is not None and v.t_s == stop else None)
                     for c, p, v in zip(self.ctrls, profiles, found))

    def tick(self, fb, sp) -> None:
        """One basic-clock cycle of every axis: read ``fb``, write ``sp`` (plain records on
        one axis, groups on several)."""
        for c, f, s in zip(self.ctrls, axis_records(fb), axis_records(sp)):
            c.tick(f, s)
        if any(c.phase is not Phase.RUN for c in self.ctrls):
            for c in self.ctrls:
                c.stop()
        if isinstance(sp, SetpointGroup):
            sp.seq = seq = (sp.seq + 1) & U32
            for s in sp.axes:
                s.seq = seq
