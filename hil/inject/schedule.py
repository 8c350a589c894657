"""When the faults of :mod:`hil.inject.catalog` act: the machine file's ``[inject]``
tables, ``--inject`` flags and requests arriving over the adapter, applied to one axis's
plant between drive cycles by its :class:`Injector`, the one owner of the plant's fault
parameters.

A request is checked like a machine-file table (unknown fault or key, a value out of its
range, a fault this machine cannot have): from the machine file or a flag it is refused
before start with a :class:`~plant.errors.ConfigError`; from the adapter it is dropped and
logged as a ``refused`` event, the run going on.  Each injection starts from the fault's
level at its ``at_s`` (the present level for a request without one) and reaches its own
level ``ramp_s`` later; a later injection of the same fault takes over from where the
earlier one stands, so a fault can also be ramped back to 0.
"""

import json
import math
from collections import deque
from dataclasses import asdict, dataclass, fields

import numpy as np

from hil.inject.catalog import FAULTS, Fault
from plant import layout as L
from plant.config import MachineConfig, build_section
from plant.effects.faults import faults_active
from plant.errors import ConfigError

#: the machine file's section of injections
SECTION = "inject"


@dataclass(frozen=True)
class Injection:
    """One checked injection.

    Attributes:
        fault: the fault's name (a key of :data:`~hil.inject.catalog.FAULTS`).
        settings: its table, checked (the fault's section dataclass).
        source: where it came from ("machine file", "--inject", "adapter", ...).
        timed: it acts at ``at_s`` (a run-time request without one acts when it arrives).
    """
    fault: str
    settings: object
    source: str
    timed: bool = True

    @property
    def level(self) -> float:
        return float(getattr(self.settings, FAULTS[self.fault].level_key))

    @property
    def at_s(self) -> float:
        return self.settings.at_s

    @property
    def ramp_s(self) -> float:
        return self.settings.ramp_s

    def describe(self) -> str:
        """The injection in one line: ``friction_growth growth_pct=50 at 2 s, ramp 10 s``."""
        f = FAULTS[self.fault]
        extra = "".join(f" {x.name}={getattr(self.settings, x.name):g}"
                        for x in fields(self.settings)
                        if x.name not in (f.level_key, "at_s", "ramp_s"))
        when = f"at {self.at_s:g} s" if self.timed else "on arrival"
        ramp = f", ramp {self.ramp_s:g} s" if self.ramp_s > 0.0 else ""
        return f"{self.fault} {f.level_key}={self.level:g}{extra} {when}{ramp} ({self.source})"

    def as_dict(self) -> dict:
        """For the recording's metadata and report.json."""
        return {"fault": self.fault, **asdict(self.settings), "timed": self.timed,
                "source": self.source}


def check(fault: str, table: dict, cfg: MachineConfig, where: str, source: str,
          runtime: bool = False) -> Injection:
    """One ``[inject.FAULT]`` table checked against the catalog and ``cfg``; a
    :class:`ConfigError` naming ``where``, the table and the key otherwise.  ``runtime``:
    a request made while running, which acts on arrival unless it gives ``at_s``."""
    f = FAULTS.get(fault)
    if f is None:
        raise ConfigError(f"{where}: unknown fault [{SECTION}.{fault}]; faults: "
                          f"{', '.join(FAULTS)}")
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: [{SECTION}.{fault}] must be a table of keys")
    settings = build_section(f.section, table, where, f"{SECTION}.{fault}")
    why = f.why_not(cfg)
    if why:
        raise ConfigError(f"{where}: [{SECTION}.{fault}] {why}")
    return Injection(fault, settings, source, "at_s" in table or not runtime)


def from_machine(cfg: MachineConfig) -> list[Injection]:
    """The injections of ``cfg``'s ``[inject]`` section (checked)."""
    raw = cfg.section(SECTION)
    return [check(name, table, cfg, cfg.path, "machine file") for name, table in raw.items()]


def parse_flag(text: str) -> tuple[str, dict]:
    """``FAULT:KEY=VALUE[,KEY=VALUE...]`` (the ``--inject`` flag) as (fault, table);
    ValueError saying what is wrong."""
    fault, sep, rest = text.partition(":")
    if not sep or not fault or not rest:
        raise ValueError(f"--inject {text!r}: expected FAULT:KEY=VALUE[,KEY=VALUE...], e.g. "
                         f"friction_growth:growth_pct=50,at_s=2,ramp_s=10")
    table = {}
    for item in rest.split(","):
        name, eq, value = item.partition("=")
        try:
            table[name.strip()] = float(value)
        except ValueError:
            raise ValueError(f"--inject {text!r}: {item!r} is not KEY=NUMBER") from None
        if not eq:
            raise ValueError(f"--inject {text!r}: {item!r} is not KEY=NUMBER")
    return fault.strip(), table


def flag_target(text: str, names: tuple[str, ...] = ("",)) -> tuple[int, str, dict]:
    """(axis index, fault, table) of an ``--inject`` flag on a machine of the axes
    ``names`` (("",): one unnamed axis): ``AXIS/FAULT:...`` names the axis, which only a
    machine of one axis may leave out; ConfigError saying what is wrong."""
    target, slash, rest = text.partition("/")
    if not slash:
        if len(names) > 1:
            raise ConfigError(f"--inject {text}: this machine has axes {', '.join(names)}; "
                              f"name one: AXIS/FAULT:KEY=VALUE,...")
        axis, rest = 0, text
    elif target in names:
        axis = names.index(target)
    else:
        raise ConfigError(f"--inject {text}: no axis {target!r} (axes: "
                          f"{', '.join(names) if any(names) else 'one, unnamed'})")
    try:
        fault, table = parse_flag(rest)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    return axis, fault, table


def from_flags(flags: list[str] | tuple[str, ...], cfg: MachineConfig, axis: int = 0,
               names: tuple[str, ...] = ("",)) -> list[Injection]:
    """The ``--inject`` flags of axis ``axis`` (of ``names``, :func:`flag_target`) checked
    against its machine file ``cfg``; ConfigError naming the flag.  Flags of other axes are
    skipped."""
    out = []
    for text in flags:
        target, fault, table = flag_target(text, names)
        if target == axis:
            out.append(check(fault, table, cfg, f"--inject {text}", "--inject"))
    return out


@dataclass(frozen=True)
class InjectEvent:
    """What an injector did: ``kind`` is "request" (a run-time request as it came, its
    ``reason`` the JSON object ``{"fault", "settings", "source"}``: what ``hil replay``
    feeds the replayed run), "injected" (a ramp or step began), "reached" (a ramp ended
    at its level) or "refused" (a run-time request that did not check)."""
    t_s: float
    kind: str
    reason: str


@dataclass
class _Ramp:
    fault: Fault
    settings: object
    start: float
    target: float
    t0: float
    ramp_s: float


class Injector:
    """The fault parameters of one axis's plant, written between drive cycles.

    Args:
        params: the plant's params array (written in place; the kernel reads it).
        cfg: the machine file (for the checks of run-time requests).
        injections: those known before start (machine file, flags), in any order.

    Attributes:
        events: what happened, in order (:class:`InjectEvent`).
        injections: every injection taken, in order of arrival.
        requests: run-time requests ``(fault, table, source)`` waiting for the next
            :meth:`update`; appended by :meth:`request` from any thread.
    """

    def __init__(self, params: np.ndarray, cfg: MachineConfig,
                 injections: list[Injection] | tuple = ()):
        self.params = params
        self.base = params.copy()
        self.cfg = cfg
        self.levels = {name: 0.0 for name in FAULTS}
        self.pending = sorted(injections, key=lambda i: i.at_s)
        self.injections: list[Injection] = list(injections)
        self.ramps: dict[str, _Ramp] = {}
        self.requests: deque = deque()
        self.events: list[InjectEvent] = []
        self.counts_lost = False
        # compiled (or loaded from numba's cache) now, before any clock starts: its first
        # call at an injection's start compiled it in the loop on a cold cache (a stall of
        # seconds)
        faults_active(params)

    @property
    def busy(self) -> bool:
        """Whether :meth:`update` has anything to do (the loop skips it otherwise)."""
        return bool(self.pending or self.ramps or self.requests)

    def request(self, fault: str, table: dict, source: str) -> None:
        """A run-time request (thread-safe; checked at the next :meth:`update`)."""
        self.requests.append((fault, dict(table), source))

    def update(self, t_s: float) -> None:
        """Bring the fault parameters to drive time ``t_s`` (s)."""
        while self.requests:
            fault, table, source = self.requests.popleft()
            self.events.append(InjectEvent(t_s, "request", json.dumps(
                {"fault": fault, "settings": table, "source": source})))
            try:
                inj = check(fault, table, self.cfg, source, source, runtime=True)
            except ConfigError as e:
                self.events.append(InjectEvent(t_s, "refused", str(e)))
                continue
            self.injections.append(inj)
            if inj.timed and inj.at_s > t_s:
                self.pending.append(inj)
                self.pending.sort(key=lambda i: i.at_s)
            else:
                self._start(inj, t_s)
        while self.pending and self.pending[0].at_s <= t_s:
            inj = self.pending.pop(0)
            self._start(inj, inj.at_s)
        for name in list(self.ramps):
            self._advance(self.ramps[name], t_s)

    def _start(self, inj: Injection, t0: float) -> None:
        f = FAULTS[inj.fault]
        self.ramps[inj.fault] = _Ramp(f, inj.settings, self.levels[inj.fault], inj.level, t0,
                                      inj.ramp_s)
        self.events.append(InjectEvent(t0, "injected", inj.describe()))

    def _advance(self, r: _Ramp, t_s: float) -> None:
        share = 1.0 if r.ramp_s <= 0.0 else min(1.0, max(0.0, (t_s - r.t0) / r.ramp_s))
        level = r.start + (r.target - r.start) * share
        self.levels[r.fault.name] = level
        r.fault.write(self.params, self.base, level, r.settings)
        # counts an encoder lost stay lost when the fault heals (until it is referenced
        # again): the kernel shows them only while its fault terms are on
        self.counts_lost |= r.fault.name == "encoder_lost_counts" and level != 0.0
        self.params[L.P_FAULTS] = max(faults_active(self.params), float(self.counts_lost))
        if share >= 1.0:
            del self.ramps[r.fault.name]
            if r.ramp_s > 0.0:
                self.events.append(InjectEvent(r.t0 + r.ramp_s, "reached",
                                               f"{r.fault.name} {r.fault.level_key}="
                                               f"{level:g}"))

    def state(self) -> dict:
        """The present level of every fault not at 0, in its level key's unit."""
        return {name: level for name, level in self.levels.items()
                if level != 0.0 and math.isfinite(level)}


def injectors_for(plants, configs, names: tuple[str, ...],
                  flags: list[str] | tuple[str, ...] = ()) -> tuple[Injector, ...]:
    """One :class:`Injector` per axis (the plants' params, in axis order) with its machine
    file's ``[inject]`` tables and its ``--inject`` flags; ConfigError before anything
    runs."""
    return tuple(Injector(p.params, c, from_machine(c) + from_flags(flags, c, i, names))
                 for i, (p, c) in enumerate(zip(plants, configs)))
