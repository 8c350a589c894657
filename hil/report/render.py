"""The latency report for people: a Markdown page and a lateness histogram (PNG).

Both read only the dict :func:`hil.report.latency.build_report` returns.  Every figure
in the Markdown carries its unit.
"""

from pathlib import Path

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
    lines.append(_row("tick lateness (wake-up − deadline)", report["lateness_us"]))
    base = report["cyclictest"]
    if base is not None:
        lines.append(_row(f"cyclictest wake-up latency, {base['interval_us']} µs interval "
                          f"(baseline)", base["latency_us"], decimals=0))
    lines.append(_row("compute time (end of step − wake-up)", report["compute_us"]))
    lines.append(_row("slack (period − compute − lateness; worst = min)", report["slack_us"]))
    lines.append("")
    if base is None:
        lines.append("No cyclictest baseline (`hil report RUN --cyclictest`; needs rt-tests).")
    else:
        lines.append(f"cyclictest: {base['samples']} wake-ups in 1 µs bins (whole µs, "
                     f"truncated), {base['overflows']} past the histogram's range; run when "
                     f"the report was made, on the same CPU and priority the loop asks for.")
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
    lines = [f"## Adapter `{adapter['name']}` counters", "", "| counter | count |", "|---|--:|"]
    lines += [f"| {key} | {value} |" for key, value in adapter["stats"].items()]
    return lines + [""]


def _scheduling(report: dict) -> list[str]:
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


def markdown(report: dict, title: str, histogram_png: str) -> str:
    """The report as Markdown, linking the histogram image ``histogram_png``."""
    period_us = report["period_us"]
    summary = (f"Period {period_us:.3f} µs ({1e6 / period_us:.0f} Hz); {report['ticks']} ticks "
               f"run; {report['overruns']} overruns; {report['missed_ticks']} missed ticks "
               f"(dropped by the skip policy).  Percentiles: {report['percentiles']}, over the "
               f"ticks that ran.")
    lines = [f"# Latency report: {title}", "", summary, ""]
    lines += _timing(report) + _round_trip(report) + _adapter(report)
    lines += _scheduling(report) + _host(report)
    lines += [f"![tick lateness histogram]({histogram_png})", ""]
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
