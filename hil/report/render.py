"""The latency report for people: a Markdown page, histograms of the wake-up latency and
of the lateness after the spin, each beside cyclictest's, and a plot of lateness and
compute time over the run (PNG).

The page and the histogram read only the dict :func:`hil.report.latency.build_report`
returns; the plot over time takes the per-tick arrays.  Every figure in the Markdown
carries its unit.
"""

from pathlib import Path

import numpy as np

from hil.report.wakeup import KEYS

NEGATIVE_WAIT = ("A negative wait: the setpoint arrived after its tick had started but "
                 "before the daemon polled for it inside the step (microseconds, more when "
                 "the step was preempted there); or the adapter has no arrival stamp "
                 "(serial, or UDP without the kernel's receive stamp), so its arrival is when "
                 "the adapter returned it and the time it waited for the tick counts as "
                 "transport.")
NO_PAIRING = ("Total and transport need the controller's receive stamps: "
              "`hil report RUN --controller DIR` pairs them from its controller.npz.")
QUANTILES = (("min", "min"), ("p50", "p50"), ("p99", "p99"), ("p999", "p99.9"),
             ("max", "max"))
WAKEUP_TEXT = ("The loop sleeps until {spin:.0f} µs before each deadline and spins from "
               "there.  Its wake-up latency (how late the sleep returned: what cyclictest "
               "measures) is known only where it passed the spin margin (spin + lateness); "
               "below, the spin hides it.  Its lateness after the spin is what the recording "
               "holds; cyclictest's equivalent is max(0, latency − spin), what this loop "
               "would have seen with cyclictest's wake-ups.")


def _cell(text) -> str:
    """``text`` safe inside a Markdown table cell."""
    return str(text).replace("|", "\\|")


def _us(value: float | None, decimals: int = 3) -> str:
    return "—" if value is None else f"{value:.{decimals}f} µs"


def _row(label: str, summary: dict | None, decimals: int = 3) -> str:
    cells = ["—"] * len(QUANTILES) if summary is None else [
        _us(summary[key], decimals) for key, _ in QUANTILES]
    return f"| {label} | " + " | ".join(cells) + " |"


def _table_head(first: str) -> list[str]:
    return [f"| {first} | " + " | ".join(name for _, name in QUANTILES) + " |",
            "|---|" + "--:|" * len(QUANTILES)]


def _timing(report: dict) -> list[str]:
    lines = ["## Tick timing", ""] + _table_head("quantity")
    lines.append(_row("tick lateness after the spin (wake-up − deadline)",
                      report["lateness_us"]))
    base = report["cyclictest"]
    lines.append(_row("compute time (end of step − wake-up)", report["compute_us"]))
    lines.append(_row("slack (period − compute − lateness; worst = min)", report["slack_us"]))
    lines.append("")
    if base is None:
        lines.append("No cyclictest baseline (`hil report RUN --cyclictest`; needs rt-tests).")
    else:
        lines.append(f"cyclictest: {base['samples']} wake-ups in 1 µs bins (whole µs, "
                     f"truncated), {base['overflows']} past the histogram's range; run when "
                     f"the report was made, on the same CPU and priority the loop asks for.")
    return lines + [""] + _wakeup(report)


def _wakeup_cells(q: dict, none: str) -> str:
    return " | ".join(none if q[k] is None else f"{q[k]:.1f} µs" for k in KEYS)


def _wakeup(report: dict) -> list[str]:
    """Wake-up latency and lateness after the spin, each beside cyclictest's."""
    w = report["wakeup"]
    spin, loop, cyc = w["spin_us"], w["loop"], w["cyclictest"]
    hidden = f"≤ {spin:.0f} µs"
    share = "—" if loop["beyond_spin"] is None else f"{100 * loop['beyond_spin']:.3f} %"
    lines = [f"## Wake-up latency and lateness after the {spin:.0f} µs spin", "",
             WAKEUP_TEXT.format(spin=spin), "",
             "| quantity | p50 | p99 | p99.9 | max | later than the spin |",
             "|---|--:|--:|--:|--:|--:|",
             f"| wake-up latency, loop | {_wakeup_cells(loop['wakeup_us'], hidden)} | {share} |"]
    if cyc is not None:
        cshare = "—" if cyc["beyond_spin"] is None else f"{100 * cyc['beyond_spin']:.3f} %"
        lines.append(f"| wake-up latency, cyclictest {cyc['interval_us']} µs | "
                     f"{_wakeup_cells(cyc['wakeup_us'], '—')} | {cshare} |")
    lines.append(f"| lateness after the spin, loop | {_wakeup_cells(loop['lateness_us'], '—')} "
                 f"| |")
    if cyc is not None:
        lines.append(f"| lateness after the spin, cyclictest (max(0, latency − spin)) | "
                     f"{_wakeup_cells(cyc['lateness_us'], '—')} | |")
    return lines + [""]


def _round_trip(report: dict) -> list[str]:
    rt = report["round_trip"]
    if rt is None:
        return ["## Round trip", "", "The run recorded no round-trip stamps.", ""]
    counts = (f"{rt['samples']} setpoints, {rt['with_transport']} with the controller's "
              f"receive stamp (total and transport need it).")
    pairing = rt["pairing"]
    if pairing is not None:
        counts += (f"  Paired with `{_cell(pairing['controller'])}`: {pairing['matched']} "
                   f"matched; {pairing['unmatched_ticks']} setpoints without a controller "
                   f"row (left out of total and transport); {pairing['unmatched_rows']} of "
                   f"its {pairing['rows']} feedback rows matched no setpoint (sent on a "
                   f"tick without a new one).")
    lines = [f"## Round trip setpoint → feedback, adapter `{rt['adapter']}`", "", counts, ""]
    lines += _table_head("part")
    lines += [_row("total (setpoint sent → feedback received)", rt["total_us"]),
              _row("transport (total − time the drive held the setpoint)", rt["transport_us"]),
              _row("wait for tick (arrival → start of the tick using it)", rt["wait_us"]),
              _row("compute (that tick's compute time)", rt["compute_us"]), ""]
    if pairing is None and rt["with_transport"] == 0:
        lines += [NO_PAIRING, ""]
    if rt["negative_waits"]:
        lines += [f"{rt['negative_waits']} of {rt['samples']} waits are negative.  "
                  + NEGATIVE_WAIT, ""]
    return lines


def _adapter(report: dict) -> list[str]:
    adapter = report["adapter"]
    if adapter is None:
        return []
    if adapter["stats"] is None:
        return [f"## Adapter `{adapter['name']}` counters", "",
                "Not known: the run wrote no report.json.", ""]
    lines = [f"## Adapter `{adapter['name']}` counters", "", "| counter | count |", "|---|--:|"]
    lines += [f"| {key} | {value} |" for key, value in adapter["stats"].items()]
    return lines + [""]


def _scheduling(report: dict) -> list[str]:
    if not report["scheduling"]:
        return ["## Scheduling granted", "", "Not known: the run wrote no report.json.", ""]
    lines = ["## Scheduling granted", "", "| request | granted | detail |", "|---|---|---|"]
    for name, grant in report["scheduling"].items():
        lines.append(f"| {_cell(name)} | {'yes' if grant.get('granted') else 'no'} | "
                     f"{_cell(grant.get('detail', ''))} |")
    return lines + [""]


def _governors(governors: dict) -> str:
    by_governor: dict[str, list[str]] = {}
    for cpu, governor in governors.items():
        by_governor.setdefault(governor, []).append(cpu)
    return "; ".join(f"{g} ({', '.join(cpus)})" for g, cpus in by_governor.items()) or "—"


def _host(report: dict) -> list[str]:
    h = report["host"]
    taken = ("recorded during the run" if report["host_source"] == "run"
             else "taken when the report was made (the run recorded none)")
    rt = (f"{'yes' if h['preempt_rt'] else 'no'} (from {h['preempt_rt_source']}); "
          f"uname says {h['preemption']}")
    rows = [("kernel", f"{h['kernel_release']} `{h['kernel_version']}` ({h['machine']})"),
            ("PREEMPT_RT", rt),
            ("CPU", f"{h['cpu_model']}, {h['cpu_count']} CPUs"),
            ("frequency governor", _governors(h["governors"])),
            ("virtualisation", h["virtualization"]),
            ("Python, numba", f"{h['python']}, {h['numba']}")]
    return (["## Host", "", f"Fingerprint {taken}.", "", "| | |", "|---|---|"]
            + [f"| {key} | {_cell(value)} |" for key, value in rows] + [""])


def markdown(report: dict, title: str, histogram_png: str,
             timeline_png: str | None = None) -> str:
    """The report as Markdown, linking the histogram image ``histogram_png`` and the plot
    over time ``timeline_png`` (None: none); the run's notes (cut short, corrupt) first."""
    period_us = report["period_us"]
    summary = (f"Period {period_us:.3f} µs ({1e6 / period_us:.0f} Hz); {report['ticks']} ticks "
               f"run; {report['overruns']} overruns; {report['missed_ticks']} missed ticks "
               f"(dropped by the skip policy, or after a stall).  Percentiles: "
               f"{report['percentiles']}, over the ticks that ran.")
    lines = [f"# Latency report: {title}", ""]
    lines += [line for note in report["notes"] for line in (f"> {note}", "")]
    lines += [summary, ""]
    lines += _timing(report) + _round_trip(report) + _adapter(report)
    lines += _scheduling(report) + _host(report)
    alt = "wake-up latency and lateness after the spin, beside cyclictest"
    lines += [f"![{alt}]({histogram_png})", ""]
    if timeline_png is not None:
        lines += [f"![lateness and compute time over the run]({timeline_png})", ""]
    return "\n".join(lines)


def _p999_text(value: float | None, hidden: str) -> str:
    return hidden if value is None else f"{value:.3g} µs"


def _hist_series(report: dict) -> list[tuple[str, list[tuple]]]:
    """The histogram's two panels, each (title, series), a series (label, counts, p99.9
    in µs or None, colour); each label names its panel's quantity and its side, its
    p99.9 the matching row of the report's ``wakeup`` table."""
    hist, w = report["histogram"], report["wakeup"]
    spin, loop, cyc = w["spin_us"], w["loop"], w["cyclictest"]
    hidden = f"≤ {spin:.0f} µs"
    loop_wakeup = (f"wake-up latency, loop: {sum(hist['wakeup_counts'])} known, "
                   f"{hist['wakeup_hidden']} {hidden} hidden by the spin; p99.9 "
                   f"{_p999_text(loop['wakeup_us']['p999'], hidden)}")
    loop_lateness = (f"lateness after the spin, loop: n = {sum(hist['lateness_counts'])}, "
                     f"p99.9 {_p999_text(loop['lateness_us']['p999'], '—')}")
    wakeup = [(loop_wakeup, hist["wakeup_counts"], loop["wakeup_us"]["p999"], "C0")]
    lateness = [(loop_lateness, hist["lateness_counts"], loop["lateness_us"]["p999"], "C0")]
    if cyc is not None and hist["cyclictest_wakeup_counts"] is not None:
        name = f"cyclictest {cyc['interval_us']} µs (whole µs)"
        cyc_wakeup = (f"wake-up latency, {name}: n = {sum(hist['cyclictest_wakeup_counts'])}, "
                      f"p99.9 {_p999_text(cyc['wakeup_us']['p999'], '—')}")
        cyc_lateness = (f"lateness after the spin, {name}: max(0, latency − {spin:.0f} µs); "
                        f"n = {sum(hist['cyclictest_lateness_counts'])}, p99.9 "
                        f"{_p999_text(cyc['lateness_us']['p999'], '—')}")
        wakeup.append((cyc_wakeup, hist["cyclictest_wakeup_counts"],
                       cyc["wakeup_us"]["p999"], "C1"))
        lateness.append((cyc_lateness, hist["cyclictest_lateness_counts"],
                         cyc["lateness_us"]["p999"], "C1"))
    lateness_title = (f"Lateness after the {spin:.0f} µs spin: wake-up − deadline (what the "
                      f"recording holds)")
    return [("Wake-up latency: how late the sleep returned (what cyclictest measures)", wakeup),
            (lateness_title, lateness)]


def histogram_figure(report: dict):
    """The loop's wake-up latency beside cyclictest's (top) and its lateness after the
    spin beside what cyclictest's wake-ups imply (bottom): counts on the report's shared
    log-spaced bins, log axes, each series' p99.9 dashed and quoted in its legend entry;
    the span the spin hides shaded.  Returns the matplotlib Figure."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    hist = report["histogram"]
    edges = hist["edges_us"]
    fig = Figure(figsize=(9, 7.5))
    axes = fig.subplots(2, 1, sharex=True)
    for ax, (title, series) in zip(axes, _hist_series(report)):
        for label, counts, p999, color in series:
            ax.stairs(counts, edges, color=color, label=label)
            if p999 is not None and p999 > edges[0]:
                ax.axvline(p999, color=color, linestyle="--", linewidth=1)
        top = max((c for _, counts, _, _ in series for c in counts), default=0)
        if top > 0:
            ax.set_yscale("log")
            # room above the bars for the legend: about 0.6 decades per entry
            ax.set_ylim(0.5, top * 10 ** (0.6 * (len(series) + 2)))
        ax.set_title(title, fontsize=10)
        ax.set_ylabel("wake-ups per bin")
        ax.grid(alpha=0.3, which="both")
    axes[0].axvspan(edges[0], hist["spin_us"], color="0.85", zorder=0,
                    label=f"the loop's spin: its wake-ups up to {hist['spin_us']:.0f} µs "
                          f"are not seen")
    for ax in axes:
        handles, labels = ax.get_legend_handles_labels()
        handles.append(Line2D([], [], color="0.3", linestyle="--", linewidth=1))
        labels.append("dashed: each series' p99.9")
        ax.legend(handles, labels, fontsize=7.5, loc="upper right")
    axes[0].set_xscale("log")
    axes[1].set_xlabel(f"µs (log; the first bin holds everything below {edges[1]:.2g} µs)")
    head = f"Tick timing, period {report['period_us']:.3f} µs"
    fig.suptitle(f"{head}: the loop (blue) beside cyclictest (orange)"
                 if report["cyclictest"] is not None else
                 f"{head} (no cyclictest baseline: hil report RUN --cyclictest)")
    fig.tight_layout()
    return fig


def plot_histogram(report: dict, path: Path) -> Path:
    """:func:`histogram_figure` of ``report`` as a PNG at ``path``."""
    histogram_figure(report).savefig(path, dpi=110)
    return path


#: the plot over time: linear below this, log above (µs), so a tick's sub-µs spin
#: precision, µs jitter and a stall of many ms are all readable
TIMELINE_LINEAR_US = 1.0


def timeline_figure(lateness_ns: np.ndarray, compute_ns: np.ndarray, period_ns: int):
    """Lateness and compute time of every tick over the run (µs, one slot per deadline,
    ``hil.report.latency.NO_VALUE`` where a tick did not run), on symmetric-log axes
    (linear below :data:`TIMELINE_LINEAR_US`), the period marked on the compute time
    and lateness + compute (an overrun above it).  Returns the matplotlib Figure."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter

    from hil.report.latency import NO_VALUE

    ran = np.flatnonzero(lateness_ns != NO_VALUE)
    t_s = ran * period_ns * 1e-9
    late, comp = lateness_ns[ran] / 1e3, compute_ns[ran] / 1e3
    fig = Figure(figsize=(9, 6))
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    dots = {"marker": ".", "markersize": 1.5, "linestyle": "none"}
    ax1.plot(t_s, late, color="C0", **dots)
    ax1.set_ylabel("lateness after the spin (µs)")
    ax1.set_title(f"Every tick of the run, period {period_ns / 1e3:.3f} µs (axes linear "
                  f"below {TIMELINE_LINEAR_US:g} µs, log above)", fontsize=10)
    ax2.plot(t_s, late + comp, color="C3", alpha=0.5, **dots)
    ax2.plot(t_s, comp, color="C2", **dots)
    ax2.axhline(period_ns / 1e3, color="k", linestyle="--")
    ax2.set_ylabel("µs")
    ax2.set_xlabel("time since the loop started (s)")
    for ax, values in ((ax1, late), (ax2, late + comp)):
        ax.set_yscale("symlog", linthresh=TIMELINE_LINEAR_US, linscale=0.5)
        ax.grid(alpha=0.3, which="both")
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        if values.size:  # the symlog's own margins reach far below 0 and cut the top
            ax.set_ylim(min(-0.2 * TIMELINE_LINEAR_US, 2.0 * float(values.min())),
                        2.0 * max(float(values.max()), period_ns / 1e3))
    # the legend's markers drawn large: the plotted dots are too small to show in it
    big = {"marker": "o", "markersize": 6, "linestyle": "none"}
    ax2.legend([Line2D([], [], color="C2", **big), Line2D([], [], color="C3", alpha=0.5, **big),
                Line2D([], [], color="k", linestyle="--")],
               ["compute time", "lateness + compute",
                f"period {period_ns / 1e3:g} µs (overrun above)"],
               fontsize=8, loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=3, frameon=False)
    fig.tight_layout()
    return fig


def plot_timeline(lateness_ns: np.ndarray, compute_ns: np.ndarray, period_ns: int,
                  path: Path) -> Path:
    """:func:`timeline_figure` of the run's arrays as a PNG at ``path``."""
    timeline_figure(lateness_ns, compute_ns, period_ns).savefig(path, dpi=110)
    return path
