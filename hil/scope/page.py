"""The scope's page: a Bokeh document per browser tab, fed by a :class:`~hil.scope.view.
ScopeView` every :data:`UPDATE_S`.

The page, top to bottom: the status panel (the run's time and state, the controller's link,
a row per axis) beside the events list; the injection panel on a run with an injection port
(:mod:`hil.scope.inject_panel`); the scope's controls (channels, time window, pause,
trigger); the plot, one line per channel on a shared time axis, one y axis per unit.  A live
run shows the last window (free running) or the captures of the trigger; a finished run (or
one cut short) shows its whole length, and a zoom reads the zoomed span again at the
screen's resolution.

Models a test (or a user's script) can find by name in the page's document:
``scope_data`` (the plotted curve: ``t_s`` and a column per channel), ``scope_trigger``
(``t_s``: the last capture's trigger time, ``armed_after_s``: the run time it was
armed at; empty before one), ``scope_status`` and
``scope_events`` (the panels' HTML), ``scope_state`` (live, ended or stopped); the
injection panel's (``scope_inject_*``, :mod:`hil.scope.inject_panel`).
"""

import html
import math
from pathlib import Path

import numpy as np
from bokeh.document import Document
from bokeh.layouts import column, row
from bokeh.models import (
    Button,
    ColumnDataSource,
    DataRange1d,
    Div,
    LinearAxis,
    MultiChoice,
    RadioButtonGroup,
    Range1d,
    Select,
    Slider,
    Span,
    Spinner,
    Toggle,
)
from bokeh.palettes import Category10_10
from bokeh.plotting import figure

from hil.cia402 import STATUSWORD_BITS
from hil.drive.faults import fault_text
from hil.runtime.run_status import mode_text, state_text
from hil.scope.inject_panel import InjectPanel
from hil.scope.trigger import MODES, SLOPES, Trigger
from hil.scope.view import WINDOW_MAX_S, WINDOW_MIN_S, ScopeView

#: the page's update period, s: a recording flushed every 0.25 s is on the page within
#: about a second, at a bounded cost a second
UPDATE_S = 1.0
#: the plot's size, pixels (its width is the curve's bins)
WIDTH, HEIGHT = 1200, 420
#: the trigger channel's choice that means "free running"
FREE = "(free running)"


def _statusword_text(word: int) -> str:
    """The set bits of statusword ``word`` by their CiA 402 names (the first clause)."""
    if word < 0:
        return "-"
    return ", ".join(name.split(" (")[0] for mask, name in STATUSWORD_BITS.items()
                     if word & mask) or "none"


def status_html(view: ScopeView) -> str:
    """The status panel's HTML."""
    p = view.status.panel()
    link = p["link"]
    if not link["started"]:
        said = "<b>waiting for the controller</b> (no setpoint yet)"
    elif link["silent"]:
        said = f"<b style='color:#c00'>SILENT</b> for {link['since_setpoint_s']:.2f} s"
    else:
        said = (f"<b style='color:#070'>connected</b>: last setpoint "
                f"{link['since_setpoint_s'] * 1e3:.1f} ms ago")
    state = view.state()
    where = {"live": "live", "ended": "ended (the recording is closed)",
             "stopped": "not growing (the run stopped or was cut short)"}[state]
    if view.catching_up:
        where = "reading the recording so far"
    lines = [f"<div><b>run</b> {html.escape(str(view.rec.folder))}: t = {p['t_s']:.2f} s, "
             f"{where}</div>",
             f"<div><b>controller</b>: {said}; {link['ticks_without']} ticks without a new "
             f"setpoint, {link['skipped_setpoints']} setpoints never applied (late or "
             f"lost)</div>",
             f"<div><b>loop</b>: overruns {p['overruns']}, lateness max "
             f"{p['lateness_max_us']:.0f} µs</div>",
             "<table style='border-collapse:collapse'><tr>" + "".join(
                 f"<th style='text-align:left;padding:2px 8px'>{h}</th>" for h in (
                     "axis", "state", "mode", "statusword 6041h", "fault 603Fh",
                     "following error now / max", "position")) + "</tr>"]
    for label, (now, position, unit) in p["axes"].items():
        fault = ("none" if now.fault == 0 else f"<b style='color:#c00'>0x{now.fault:04X}</b> "
                 f"{html.escape(fault_text(now.fault))}")
        if not math.isfinite(now.following_error):
            fe = "-"
        elif unit == "deg":
            fe = f"{now.following_error:.4f} / {now.following_error_max:.4f} deg"
        else:  # the trace's mm, shown in µm
            fe = f"{now.following_error * 1e3:.1f} / {now.following_error_max * 1e3:.1f} µm"
        cells = (label, state_text(now.state).upper(), mode_text(now.mode),
                 html.escape(_statusword_text(now.statusword)), fault, fe,
                 f"{position:.3f} {unit}")
        lines.append("<tr>" + "".join(f"<td style='padding:2px 8px'>{c}</td>" for c in cells)
                     + "</tr>")
    return "\n".join(lines) + "</table>"


def events_html(view: ScopeView) -> str:
    """The events list's HTML, the newest first."""
    if not view.events:
        return "<div><b>events</b>: none yet</div>"
    rows = []
    for e in reversed(view.events):
        when = "after the loop" if not math.isfinite(e.t_s) else f"{e.t_s:9.3f} s"
        code = f" 0x{e.code:04X}" if e.code else ""
        rows.append(f"<div>{when} {html.escape(e.axis)} <b>{html.escape(e.source)} "
                    f"{html.escape(e.kind)}</b>{code}: {html.escape(e.reason)}</div>")
    return ("<div><b>events</b> (newest first)</div><div style='max-height:160px;"
            "overflow-y:auto;font-family:monospace;font-size:12px'>" + "".join(rows)
            + "</div>")


class ScopePage:
    """One tab's page (module docstring) on ``folder``."""

    def __init__(self, doc: Document, folder: Path):
        self.doc = doc
        self.view = ScopeView(folder, pixels=WIDTH)
        rec = self.view.rec
        self.label = {n: f"{n} [{rec.units[n] or '-'}]" for n in rec.names if n != "tick"}
        prefix = rec.meta["axes"][0]["prefix"] if rec.meta.get("axes") else ""
        default = [n for n in (f"{prefix}plant_table_pos", f"{prefix}plant_iq_meas_a")
                   if n in rec.names]
        options = [(n, label) for n, label in self.label.items()]
        self.channels = MultiChoice(name="scope_channels", title="channels", value=default,
                                    options=options, width=520)
        self.window = Spinner(name="scope_window", title="time window, s", low=WINDOW_MIN_S,
                              high=WINDOW_MAX_S, step=0.1, value=5.0, width=120)
        self.pause = Toggle(name="scope_pause", label="pause", width=90)
        self.trig_channel = Select(name="scope_trig_channel", title="trigger on", value=FREE,
                                   options=[FREE, *[(n, lab) for n, lab in options]],
                                   width=260)
        self.trig_level = Spinner(name="scope_trig_level", title="level (channel's unit)",
                                  value=0.0, step=0.001, width=150)
        self.trig_slope = Select(name="scope_trig_slope", title="slope", value=SLOPES[0],
                                 options=list(SLOPES), width=100)
        self.trig_pre = Slider(name="scope_trig_pre", title="pre-trigger, % of the window",
                               start=0, end=100, step=5, value=20, width=200)
        self.trig_mode = RadioButtonGroup(name="scope_trig_mode", labels=list(MODES), active=0)
        self.arm = Button(name="scope_arm", label="arm", width=80)
        self.trig_info = Div(name="scope_trig_info", text="", width=700)
        self.status_div = Div(name="scope_status", width=760)
        self.events_div = Div(name="scope_events", width=560)
        self.state_div = Div(name="scope_state", text="", visible=False)
        self.inject = InjectPanel(self.view)
        self.source = ColumnDataSource(name="scope_data", data={"t_s": []})
        self.trigger_source = ColumnDataSource(name="scope_trigger",
                                                data={"t_s": [], "armed_after_s": []})
        self.armed_after = -np.inf
        self.capture: tuple[float, float] | None = None
        self.view_span: tuple[float, float] | None = None  # a zoom of a finished run
        self.shown_whole_at = -1.0
        self.setting_range = False
        self.plot_box = column()
        self.channels.on_change("value", lambda attr, old, new: self.choose(rebuild=True))
        for widget in (self.trig_channel, self.trig_level, self.trig_slope, self.trig_pre):
            widget.on_change("value", lambda attr, old, new: self.choose())
        self.trig_mode.on_change("active", lambda attr, old, new: self.choose())
        self.arm.on_click(self.rearm)
        self.choose(rebuild=True)
        doc.title = f"hil scope: {folder}"
        doc.add_root(column(
            row(self.status_div, self.events_div),
            self.inject.layout,
            row(self.channels, self.window, self.pause),
            row(self.trig_channel, self.trig_level, self.trig_slope, self.trig_pre,
                column(Div(text="mode"), self.trig_mode), self.arm),
            self.trig_info, self.plot_box, self.state_div))
        doc.add_root(self.trigger_source)  # no glyph draws it: a root, so the page has it
        self.update()
        doc.add_periodic_callback(self.update, int(UPDATE_S * 1000))

    # -- the controls -------------------------------------------------------------------

    def _trigger(self) -> Trigger | None:
        if self.trig_channel.value == FREE:
            return None
        return Trigger(self.trig_channel.value, float(self.trig_level.value or 0.0),
                       self.trig_slope.value, self.trig_pre.value / 100.0,
                       MODES[self.trig_mode.active])

    def choose(self, rebuild: bool = False) -> None:
        """The channels or the trigger changed: keep what they need, arm the trigger
        again, and (``rebuild``: the channels changed) make the plot anew."""
        self.view.choose(list(self.channels.value), self._trigger())
        self.rearm()
        self.shown_whole_at = -1.0
        if rebuild:
            self._build_plot()

    def rearm(self) -> None:
        """Wait for the next trigger from the present on."""
        self.armed_after = self.view.end_s if self.view.trigger is not None else -np.inf
        self.capture = None
        self.trigger_source.data = {"t_s": [], "armed_after_s": []}
        if hasattr(self, "trigger_mark"):
            self.trigger_mark.visible = False

    def _build_plot(self) -> None:
        """A figure for the chosen channels: one y range per unit, the first on the left."""
        units: dict[str, list[str]] = {}
        for n in self.view.channels:
            units.setdefault(self.view.rec.units[n] or "-", []).append(n)
        self.source.data = {"t_s": [], **{n: [] for n in self.view.channels}}
        fig = figure(width=WIDTH, height=HEIGHT, x_range=Range1d(0, 1),
                     x_axis_label="run time, s",
                     tools="xpan,xwheel_zoom,box_zoom,reset,save",
                     active_scroll="xwheel_zoom")
        fig.x_range.on_change("start", self._zoomed)
        fig.x_range.on_change("end", self._zoomed)
        self.x_range = fig.x_range
        colours = iter(Category10_10 * 4)
        for i, (unit, names) in enumerate(units.items()):
            if i == 0:
                range_name, y_range = "default", fig.y_range
                fig.yaxis.axis_label = unit
            else:
                range_name, y_range = f"unit{i}", DataRange1d()
                fig.extra_y_ranges[range_name] = y_range
                fig.add_layout(LinearAxis(y_range_name=range_name, axis_label=unit),
                               "right" if i % 2 else "left")
            renderers = [fig.line("t_s", n, source=self.source, color=next(colours),
                                  legend_label=self.label[n], y_range_name=range_name)
                         for n in names]
            y_range.renderers = renderers
        if not self.view.channels:
            fig.title.text = "choose a channel"
        fig.legend.location = "top_left"
        fig.legend.click_policy = "hide"
        self.trigger_mark = Span(location=np.nan, dimension="height", line_dash="dashed",
                                 line_color="#c00", visible=False)
        fig.add_layout(self.trigger_mark)
        self.plot_box.children = [fig]

    def _zoomed(self, attr, old, new) -> None:
        """A zoom or pan by the user: the span read again at full resolution (paused or
        finished), at the next update."""
        if self.setting_range:
            return
        if self.pause.active or self.view.state() != "live":
            self.view_span = (self.x_range.start, self.x_range.end)

    def _set_range(self, t0_s: float, t1_s: float) -> None:
        self.setting_range = True
        try:
            self.x_range.start, self.x_range.end = t0_s, t1_s
            # the reset tool goes back to what the page last showed, not to the first range
            self.x_range.reset_start, self.x_range.reset_end = t0_s, t1_s
        finally:
            self.setting_range = False

    # -- every update -------------------------------------------------------------------

    def update(self) -> None:
        """Read what is new, refresh the panels, draw (unless paused)."""
        view = self.view
        view.update()
        self.status_div.text = status_html(view)
        self.events_div.text = events_html(view)
        state = view.state()
        self.state_div.text = state
        self.inject.update()
        if self.pause.active and self.view_span is None:
            return
        if self.view_span is not None:
            self._draw(*self.view_span, keep_range=True)
            self.view_span = None
        elif state != "live" and not view.catching_up:
            if self.shown_whole_at != view.end_s:  # the whole run, once per length
                self.shown_whole_at = view.end_s
                self.trig_info.text = (f"the whole run: {view.end_s:.2f} s; zoom with the "
                                       f"mouse wheel or the box")
                whole = view.whole()
                self._show(whole.t_s, whole.values, whole.t0_s, whole.t1_s)
        elif view.trigger is None:
            window = float(self.window.value)
            self.trig_info.text = "free running"
            self._draw(max(view.end_s - window, 0.0), max(view.end_s, window))
        else:
            self._triggered()

    def _triggered(self) -> None:
        view, window = self.view, float(self.window.value)
        trig = view.trigger
        at = None
        if not (trig.mode == "single" and self.capture is not None):
            at = view.trigger_at(self.armed_after, window)
        if at is not None:
            self.trigger_source.data = {"t_s": [at], "armed_after_s": [self.armed_after]}
            self.capture = trig.window(at, window)
            # normal: the next trigger after this capture; single: none until armed again
            self.armed_after = self.capture[1] if trig.mode == "normal" else np.inf
            self.trigger_mark.location, self.trigger_mark.visible = at, True
            self._draw(*self.capture)
        if self.capture is None:
            self.trig_info.text = (f"armed ({trig.mode}): waiting for {trig.channel} to cross "
                                   f"{trig.level:g} {trig.slope}")
        else:
            t = self.trigger_source.data["t_s"][0]
            more = ": press arm for the next" if trig.mode == "single" else ""
            self.trig_info.text = f"triggered at t = {t:.4f} s ({trig.mode}{more})"

    def _draw(self, t0_s: float, t1_s: float, keep_range: bool = False) -> None:
        if not self.view.channels or not t1_s > t0_s:
            return
        curve = self.view.curve(t0_s, t1_s)
        self._show(curve.t_s, curve.values, t0_s, t1_s, keep_range)

    def _show(self, t_s, values, t0_s, t1_s, keep_range: bool = False) -> None:
        self.source.data = {"t_s": t_s, **values}
        if not keep_range:
            self._set_range(t0_s, t1_s)


def make_app(folder: Path):
    """The Bokeh application's document maker for ``folder``."""
    def modify(doc: Document) -> None:
        ScopePage(doc, folder)
    return modify
