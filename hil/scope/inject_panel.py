"""The scope page's injection panel: a fault or wear sent from the page to a live run's
injection port (``hil run --inject-port N``, :mod:`io_adapters.inject_port`), as a bench's
experiment software inserts a fault into the simulator, not through the controller.

The panel offers the run's axes, the faults of :mod:`hil.inject.catalog` the chosen
axis's machine file can have (a nut fault not on a linear motor), and the fault's
settings as ``hil controller --inject`` writes them after the colon
(``growth_pct=50,ramp_s=2``; ``at_s``, if given, is the run's time at which it starts,
else it starts on arrival).  A request is checked as the emulator will check it
(:func:`hil.inject.schedule.check`, against the machine file recorded in the run's
metadata) before it is sent: a typing error, an unknown key or a level out of its range
is shown on the page and never sent.  What became of a request sent -- taken, started,
refused by the run (a machine file changed since, say) -- is read back from the run's
events (source ``inject``, the request's source ``bench``), which the page lists too.
A finished run's panel is disabled; a run without an injection port shows a line saying
how to open one.

Models a test (or a user's script) can find by name in the page's document:
``scope_inject_axis``, ``scope_inject_fault`` (Select), ``scope_inject_settings``
(TextInput), ``scope_inject_send`` (Button), ``scope_inject_keys`` (the fault's keys) and
``scope_inject_answer`` (what became of the last request).
"""

import html
import json
from collections.abc import Sequence
from dataclasses import fields

from bokeh.layouts import column, row
from bokeh.models import Button, Div, Select, TextInput

from hil.inject.catalog import FAULTS
from hil.inject.schedule import check, parse_flag
from hil.replay.machine_files import ReplayError, machine_files
from hil.scope.view import EventRow
from io_adapters.base import AdapterConfigError, AdapterError, FrameError
from io_adapters.inject_port import InjectClient, parse_address
from io_adapters.messages import InjectRequest
from plant.errors import ConfigError
from plant.machines import MachineSet, load_machine_set
from plant.schema import is_required

#: the source the emulator records for the injection port's requests
SOURCE = "bench"


class InjectTarget:
    """A run's injection port and machine, from its recording's metadata: what the panel
    may send and the checks before it sends.

    Args:
        meta: the recording's metadata (``inject_port``, ``machine_files``).
        where: names the run in errors (its folder).

    Attributes:
        address: the port's (host, port).
        machine: the run's machine, rebuilt from the machine files' recorded text.

    Raises:
        ValueError: the run has no injection port, its address or machine files do not
            load (the message says which and why).
    """

    def __init__(self, meta: dict, where: str):
        port = meta.get("inject_port")
        if not port:
            raise ValueError(f"{where}: the run has no injection port (hil run "
                             f"--inject-port N)")
        try:
            self.address = parse_address(str(port))
            with machine_files(meta, where) as path:
                self.machine: MachineSet = load_machine_set(path)
        except (AdapterConfigError, ReplayError, ConfigError, OSError) as e:
            raise ValueError(f"{where}: no injection from the page: {e}") from e

    @property
    def axes(self) -> tuple[str, ...]:
        return self.machine.names

    def faults(self, axis: str) -> list[str]:
        """The faults axis ``axis``'s machine file can have, in the catalog's order."""
        cfg = self.machine.configs[self.axes.index(axis)]
        return [name for name, f in FAULTS.items() if not f.why_not(cfg)]

    def request(self, axis: str, fault: str, settings: str) -> InjectRequest:
        """The request of fault ``fault`` with ``settings`` (``KEY=VALUE,...``) on axis
        ``axis``, checked as the emulator checks it; :class:`ConfigError` saying what is
        wrong."""
        if axis not in self.axes:
            raise ConfigError(f"no axis {axis!r} (axes: {', '.join(self.axes)})")
        try:
            name, table = parse_flag(f"{fault}:{settings.strip()}")
        except ValueError as e:
            raise ConfigError(f"{e}".replace("--inject ", "settings ", 1)) from None
        check(name, table, self.machine.configs[self.axes.index(axis)], SOURCE, SOURCE,
              runtime=True)
        return InjectRequest(self.axes.index(axis), name, table)

    def send(self, request: InjectRequest) -> None:
        """Send ``request`` to the port; :class:`~io_adapters.base.AdapterError` or
        :class:`~io_adapters.base.FrameError` when it cannot go."""
        with InjectClient(self.address) as client:
            client.send(request)


def keys_html(fault: str) -> str:
    """The keys of ``fault``'s table, its level's first, each with its unit, range and
    meaning."""
    f = FAULTS.get(fault)
    if f is None:
        return ""
    order = {f.level_key: 0, "ramp_s": 2, "at_s": 3}
    items = []
    for x in sorted(fields(f.section), key=lambda x: order.get(x.name, 1)):
        m = x.metadata
        lo = m["ge"] if m["ge"] is not None else m["gt"]
        span = f" {lo:g}..{m['le']:g}" if lo is not None and m["le"] is not None else ""
        if x.name == "at_s":
            need, doc = "optional", "the run's time it starts at (left out: on arrival)"
        else:
            need = "required" if is_required(x) else f"default {x.default:g}"
            doc = m["doc"]
        items.append(f"<b>{x.name}</b> [{m['unit']}]{span}, {need}: "
                     f"{html.escape(doc, quote=False)}")
    return "<div style='font-size:12px'>" + "<br>".join(items) + "</div>"


def _from_bench(e: EventRow) -> bool:
    """An injector's event of a request from the injection port."""
    if e.source != "inject":
        return False
    if e.kind == "request":
        try:
            return json.loads(e.reason).get("source") == SOURCE
        except ValueError:
            return False
    return e.reason.startswith(f"{SOURCE}:") or e.reason.endswith(f"({SOURCE})")


def outcome(events: Sequence[EventRow]) -> str | None:
    """What the run made of the last request sent, from the events read since it was
    sent (oldest first); None while none has come."""
    mine = [e for e in events if _from_bench(e)]
    if not mine:
        return None
    e = mine[-1]
    when = f"t = {e.t_s:.3f} s"
    reason = html.escape(e.reason, quote=False)
    if e.kind == "refused":
        return f"<b style='color:#c00'>refused by the run</b> at {when}: {reason}"
    if e.kind == "request":
        return f"taken by the run at {when}; it starts at its at_s"
    return f"<b style='color:#070'>{html.escape(e.kind)}</b> at {when}: {reason}"


class InjectPanel:
    """The panel's widgets on a page of ``view``'s run (module docstring); ``layout`` is
    what the page adds, :meth:`update` follows the run every page update."""

    def __init__(self, view):
        self.view = view
        self.answer = Div(name="scope_inject_answer", width=900)
        try:
            self.target: InjectTarget | None = InjectTarget(view.rec.meta, str(view.rec.folder))
        except ValueError as e:
            self.target = None
            self.answer.text = f"<b>fault injection</b>: {html.escape(str(e))}"
            self.layout = self.answer
            return
        axes = list(self.target.axes)
        self.axis = Select(name="scope_inject_axis", title="inject on axis", value=axes[0],
                           options=axes, width=110)
        faults = self.target.faults(axes[0])
        self.fault = Select(name="scope_inject_fault", title="fault", value=faults[0],
                            options=faults, width=200)
        self.settings = TextInput(name="scope_inject_settings", title="settings: "
                                  "KEY=VALUE,... (as hil controller --inject)",
                                  value="", width=380)
        self.send_button = Button(name="scope_inject_send", label="inject",
                                  button_type="warning", width=90)
        self.keys = Div(name="scope_inject_keys", width=900)
        self.waiting_from: int | None = None  # events read when the last request went
        self.axis.on_change("value", lambda attr, old, new: self._axis_chosen())
        self.fault.on_change("value", lambda attr, old, new: self._fault_chosen())
        self.send_button.on_click(self.send)
        self._fault_chosen()
        host, port = self.target.address
        self.answer.text = (f"<b>fault injection</b> into the run through its injection port "
                            f"{host}:{port}")
        self.layout = column(row(self.axis, self.fault, self.settings,
                                 column(Div(text="&nbsp;"), self.send_button)),
                             self.keys, self.answer)

    def _axis_chosen(self) -> None:
        faults = self.target.faults(self.axis.value)
        self.fault.options = faults
        if self.fault.value not in faults:
            self.fault.value = faults[0]

    def _fault_chosen(self) -> None:
        f = FAULTS[self.fault.value]
        self.settings.placeholder = f"{f.level_key}=LEVEL[,ramp_s=S][,at_s=S]"
        self.keys.text = keys_html(self.fault.value)

    def send(self) -> None:
        """The button: check the request, then send it; the answer says which."""
        if self.view.state() != "live":
            self.answer.text = "<b>not sent</b>: the run has ended"
            return
        try:
            request = self.target.request(self.axis.value, self.fault.value,
                                          self.settings.value or "")
        except ConfigError as e:
            self.answer.text = (f"<b style='color:#c00'>not sent</b>, refused on the page: "
                                f"{html.escape(str(e), quote=False)}")
            return
        try:
            self.target.send(request)
        except (AdapterError, FrameError) as e:
            self.answer.text = (f"<b style='color:#c00'>not sent</b>: "
                                f"{html.escape(str(e), quote=False)}")
            return
        self.waiting_from = self.view.events_read
        settings = ",".join(f"{k}={v:g}" for k, v in request.settings.items())
        self.answer.text = (f"<b>sent</b> at about t = {self.view.end_s:.2f} s: "
                            f"{html.escape(self.axis.value)} {html.escape(request.fault)}:"
                            f"{html.escape(settings)}; waiting for the run's events")

    def update(self) -> None:
        """Every page update: disabled once the run is no longer live; the answer from the
        events that came since the last request was sent."""
        if self.target is None:
            return
        live = self.view.state() == "live"
        for widget in (self.axis, self.fault, self.settings, self.send_button):
            widget.disabled = not live
        if not live:
            self.answer.text = ("<b>fault injection</b>: the run is no longer live; nothing "
                                "to inject into")
            return
        if self.waiting_from is None:
            return
        since = self.view.events_read - self.waiting_from
        if since <= 0:
            return
        recent = list(self.view.events)[-min(since, len(self.view.events)):]
        said = outcome(recent)
        if said is not None:
            self.answer.text = said
