"""The controller's side of run-time injection: ``hil controller --inject`` sends each
fault as an INJECT message (:class:`~io_adapters.messages.InjectRequest`) once its
program has run ``at_s`` seconds, so a test bench can break the axis it is driving at a
chosen point of the part program.  The emulator checks the request again and starts the
fault when it arrives (its ramp included); the flags are checked here before start too, so
a typing error does not wait until the middle of the run."""

from dataclasses import dataclass

from hil.inject.schedule import check, flag_target
from io_adapters.messages import InjectRequest
from plant.machines import MachineSet


@dataclass(frozen=True)
class Planned:
    """One request and the program time it is due at, s."""
    at_s: float
    request: InjectRequest


class InjectionSender:
    """The ``--inject`` flags of a controller, due by program time.

    Args:
        flags: ``[AXIS/]FAULT:KEY=VALUE,...``; ``at_s`` is the program time to send it at
            (default 0: as the program starts).
        machine: the machine the flags are checked against (its axes' machine files).
    """

    def __init__(self, flags: tuple[str, ...], machine: MachineSet):
        planned = []
        for text in flags:
            axis, fault, table = flag_target(text, machine.names)
            check(fault, table, machine.configs[axis], f"--inject {text}", "--inject")
            at_s = table.pop("at_s", 0.0)
            planned.append(Planned(at_s, InjectRequest(axis, fault, table)))
        self.planned = sorted(planned, key=lambda p: p.at_s)
        self.sent: list[Planned] = []

    def due(self, t_s: float) -> list[InjectRequest]:
        """The requests due at program time ``t_s`` not sent yet (they count as sent)."""
        out = []
        while self.planned and self.planned[0].at_s <= t_s:
            p = self.planned.pop(0)
            self.sent.append(p)
            out.append(p.request)
        return out
