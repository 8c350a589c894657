"""How well a run kept its time, one side at a time: what ``hil run`` and ``hil
controller`` print when they end, what their JSON keeps (``timing_quality``), and what
``hil report``'s verdict judges when no lock-step reference can price the timing
(:mod:`hil.report.run_verdict`).

Counted per side, from the figures each already writes:

* **overruns**: ticks whose work ended after their period (the loop's count after its
  grace period, ``report.json``/``summary.json`` ``loop.overruns``), with the worst
  lateness;
* **stalls**: ticks that ended ``resume_after`` or more deadlines late (``loop.stalls``:
  the process was not running), and the ticks the loop skipped (``loop.skipped``);
* **the other side's messages**: for the emulator the controller's setpoints, *late* when
  one came after its tick and was taken together with the next (the endpoint's
  ``drained``), *missed* when its sequence number never arrived (``lost``); for the
  controller the drive's feedback, *late* when it answered an older setpoint than the one
  before last (``feedback.lag_ticks`` 2 and more), *missed* when a tick read none
  (``feedback.ticks_without_new``).

**The limits** (:data:`MAX_SHARE`, no stall): a run is within them when overruns, late and
missed messages each stay at or under one tick in a thousand and no tick stalled.  They
are not a physical tolerance (a lock-step reference prices the timing in micrometres,
:mod:`hil.replay.timing`): they say when a run's timing is worth a look before its
results are trusted.
"""

from dataclasses import asdict, dataclass

from hil.rt.causes import Cause

#: overruns, late and missed messages each at most this share of the ticks
MAX_SHARE = 1e-3


@dataclass(frozen=True)
class TimingQuality:
    """One side's timing over a run (module docstring).

    Attributes:
        side: ``"emulator"`` or ``"controller"``.
        ticks: ticks run.
        overruns: ticks that overran their period.
        worst_lateness_us: the latest a tick's deadline was met, µs.
        stalls: ticks that ended several deadlines late.
        skipped: ticks skipped.
        messages: what ``late`` and ``missed`` count (``"setpoints"``, ``"feedback"``).
        late: messages that came after their tick.
        missed: messages that never came (or ticks without one).
        worst_overrun: the loop's overrun that ended latest, and what kept it
            (:attr:`hil.rt.loop.LoopStats.worst_overrun`); None: none.
        period_s: the loop's period, s (the worst overrun's time).
    """
    side: str
    ticks: int
    overruns: int
    worst_lateness_us: float
    stalls: int
    skipped: int
    messages: str
    late: int
    missed: int
    worst_overrun: dict | None = None
    period_s: float = 0.0

    @classmethod
    def of_emulator(cls, report: dict) -> "TimingQuality":
        """From ``hil run``'s ``report.json`` (or the dict it is written from)."""
        loop, stats = report["loop"], report["adapter"]["stats"]
        return cls("emulator", loop["ticks"], loop["overruns"], loop["lateness_us"]["max"],
                   loop["stalls"], loop["skipped"], "setpoints", stats.get("drained", 0),
                   stats.get("lost", 0), loop.get("worst_overrun"),
                   loop.get("period_ns", 0) * 1e-9)

    @classmethod
    def of_controller(cls, summary: dict) -> "TimingQuality":
        """From ``hil controller``'s ``summary.json`` (or the dict it is written from)."""
        loop, fb = summary["loop"], summary["feedback"]
        return cls("controller", loop["ticks"], loop["overruns"], loop["lateness_us"]["max"],
                   loop["stalls"], loop["skipped"], "feedback", fb["lag_ticks"]["2+"],
                   fb["ticks_without_new"], loop.get("worst_overrun"),
                   loop.get("period_ns", 0) * 1e-9)

    def _share(self, n: int) -> str:
        return f"{100 * n / max(1, self.ticks):.3g} %"

    def reasons(self, counts: bool = True) -> list[str]:
        """What exceeds the limits, one phrase each (empty: within them); without
        ``counts`` the stalls alone (a lock-step reference prices the rest)."""
        out, limit = [], f"limit {100 * MAX_SHARE:g} %"
        if counts and self.overruns > MAX_SHARE * self.ticks:
            out.append(f"{self.side}: {self.overruns} overruns in {self.ticks} ticks "
                       f"({self._share(self.overruns)}, {limit}), the worst "
                       f"{self.worst_lateness_us:.1f} µs late")
        if self.stalls:
            out.append(f"{self.side}: {self.stalls} stall(s) (ticks several periods late; "
                       f"the worst {self.worst_lateness_us:.1f} µs): the process was not "
                       "running")
        for what, n in (("late", self.late), ("missed", self.missed)):
            if counts and n > MAX_SHARE * self.ticks:
                out.append(f"{self.side}: {n} {self.messages} {what} in {self.ticks} ticks "
                           f"({self._share(n)}, {limit})")
        return out

    @property
    def within(self) -> bool:
        return not self.reasons()

    def line(self) -> str:
        """One line: the counts and whether they are within the limits."""
        counts = (f"{self.overruns} overruns ({self._share(self.overruns)}, worst "
                  f"{self.worst_lateness_us:.1f} µs late), {self.stalls} stalls, "
                  f"{self.skipped} skipped; {self.messages} late {self.late}, missed "
                  f"{self.missed} of {self.ticks} ticks")
        verdict = ("within the limits" if self.within else "BEYOND the limits ("
                   + f"{100 * MAX_SHARE:g} % of ticks each, no stall): the results may "
                   "show the timing, not the machine")
        return f"timing: {counts}: {verdict}"

    def worst_text(self) -> str:
        """The worst overrun: when, how far behind, where it ran and what kept it (empty
        when the loop had none)."""
        w = self.worst_overrun
        if not w:
            return ""
        return (f"{self.side}'s worst overrun: tick {w['tick']} (t = "
                f"{w['tick'] * self.period_s:.4f} s), {w['behind_us']:.1f} µs after the next "
                f"deadline, in a {w['where']} tick; since the overrun before it: "
                f"{Cause.from_dict(w['cause']).text()}")

    def window_ns(self) -> tuple[int, int] | None:
        """The worst overrun's tick from its deadline to its end, on the machine's
        monotonic clock, ns (None: no worst overrun, or one of a report that kept no
        deadline)."""
        w = self.worst_overrun
        if not w or "deadline_ns" not in w:
            return None
        start = w["deadline_ns"]
        return start, start + round(self.period_s * 1e9 + w["behind_us"] * 1e3)

    def header(self) -> dict[str, str]:
        """The trace header's ``# key: value`` lines for this side's timing (a trace's
        reader, ``hil identify``, warns on ``timing_within_limits: no``)."""
        return {"timing_side": self.side, "timing_ticks": str(self.ticks),
                "timing_overruns": str(self.overruns), "timing_stalls": str(self.stalls),
                f"timing_{self.messages}_late": str(self.late),
                f"timing_{self.messages}_missed": str(self.missed),
                "timing_within_limits": "yes" if self.within else "no"}

    def as_dict(self) -> dict:
        return {**asdict(self), "max_share": MAX_SHARE, "within": self.within,
                "reasons": self.reasons()}


def same_moment(a: TimingQuality, b: TimingQuality) -> str:
    """A line when the worst overruns of two loops (the emulator's and the controller's,
    each on a CPU of its own) overlap in time: the machine stopped both, which neither
    program's counters see (a virtual machine's host running something else, a firmware
    interrupt); empty otherwise."""
    wa, wb = a.window_ns(), b.window_ns()
    if wa is None or wb is None or wa[1] <= wb[0] or wb[1] <= wa[0]:
        return ""
    return (f"both loops' worst overruns happened at the same moment ({a.side} "
            f"{a.worst_overrun['behind_us']:.1f} µs, {b.side} "
            f"{b.worst_overrun['behind_us']:.1f} µs behind, {abs(wa[0] - wb[0]) * 1e-3:.0f} µs "
            "apart): the whole machine stopped them (on a virtual machine, its host), not "
            "either program")
