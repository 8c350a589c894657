"""The latency report for people: a Markdown page, a lateness histogram and a plot of
lateness and compute time over the run (PNG).

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
    lines += [f"![tick lateness histogram]({histogram_png})", ""]
    if timeline_png is not None:
        lines += [f"![lateness and compute time over the run]({timeline_png})", ""]
    return "\n".join(lines)


def plot_histogram(report: dict, path: Path) -> Path:
    """Tick lateness counts on log-spaced bins, log count axis, with cyclictest's wake-ups
    on the same bins when the report has them, each p99.9 marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hist = report["histogram"]
    edges = hist["edges_us"]
    fig, ax = plt.subplots(figsize=(8, 4.5))
    series = [("tick lateness", hist["lateness_counts"], report["lateness_us"], "C0")]
    base = report["cyclictest"]
    if base is not None and hist["cyclictest_counts"] is not None:
        series.append((f"cyclictest, {base['interval_us']} µs", hist["cyclictest_counts"],
                       base["latency_us"], "C1"))
    for label, counts, summary, color in series:
        ax.stairs(counts, edges, color=color, label=f"{label} (n = {sum(counts)})")
        if summary is not None:
            ax.axvline(summary["p999"], color=color, linestyle="--",
                       label=f"{label} p99.9 = {summary['p999']:.3g} µs")
    ax.set_xscale("log")
    if any(c > 0 for _, counts, _, _ in series for c in counts):
        ax.set_yscale("log")
    ax.set_xlabel(f"lateness (µs; the first bin holds everything below {edges[1]:.2g} µs)")
    ax.set_ylabel("wake-ups per bin")
    ax.set_title(f"Tick lateness, period {report['period_us']:.3f} µs")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_timeline(lateness_ns: np.ndarray, compute_ns: np.ndarray, period_ns: int,
                  path: Path) -> Path:
    """Lateness and compute time of every tick over the run (µs, one slot per deadline,
    ``hil.report.latency.NO_VALUE`` where a tick did not run), the period marked on the
    compute time and lateness + compute (an overrun above it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hil.report.latency import NO_VALUE

    ran = np.flatnonzero(lateness_ns != NO_VALUE)
    t_s = ran * period_ns * 1e-9
    late, comp = lateness_ns[ran] / 1e3, compute_ns[ran] / 1e3
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    ax1.plot(t_s, late, ",", color="C0")
    ax1.set_ylabel("lateness after the spin (µs)")
    ax1.set_title(f"Every tick of the run, period {period_ns / 1e3:.3f} µs")
    ax2.plot(t_s, comp, ",", color="C2", label="compute time")
    ax2.plot(t_s, late + comp, ",", color="C3", alpha=0.4, label="lateness + compute")
    ax2.axhline(period_ns / 1e3, color="k", linestyle="--", label="period (overrun above)")
    ax2.set_ylabel("µs")
    ax2.set_xlabel("time since the loop started (s)")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
    ax2.legend(fontsize=8, markerscale=20, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
