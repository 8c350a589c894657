"""Plots a commissioning engineer looks at: a run's setpoint, actual value, following error
and current; a step response.  Axes are labelled in the units a CNC shows (mm, mm/min,
A; deg on rotary tables)."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (backend must be chosen first)
from matplotlib.figure import Figure  # noqa: E402

from hil.measure.runs import StepResponse  # noqa: E402
from hil.sim import SimResult, position_cycle_mean, ripple_hz  # noqa: E402


def _units(kind: str) -> tuple[float, str]:
    """Factor from SI table units to display units, and the display unit."""
    return (57.29577951308232, "deg") if kind == "rotary" else (1e3, "mm")


def _current_panel(ax, res: SimResult, t) -> None:
    """i_q setpoint and measured: every tick, light, and their mean over the position
    cycle on top, with what the ripple between the two is."""
    ticks = res.position_cycle_ticks
    cycle_ms = ticks * res.period_s * 1e3
    for sig, name, colour in (("iq_set", "setpoint", "tab:blue"),
                              ("iq_meas", "measured", "tab:orange")):
        ax.plot(t, res[sig], color=colour, alpha=0.35, lw=0.6,
                label=f"{name}, each {res.period_s * 1e6:g} µs tick")
    for sig, name, colour, style in (("iq_set", "setpoint", "tab:blue", "-"),
                                     ("iq_meas", "measured", "tab:orange", "--")):
        ax.plot(t, position_cycle_mean(res[sig], ticks), color=colour, ls=style, lw=1.2,
                label=f"{name}, {cycle_ms:g} ms position-cycle mean")
    ax.set_ylabel("current i_q (A)")
    ax.legend(fontsize=7, loc="lower center", ncols=2)
    ax.set_title(f"light: each tick, with a {ripple_hz(res):g} Hz ripple while the axis "
                 f"accelerates (the speed command changes once per {cycle_ms:g} ms position "
                 "cycle); bold: its mean", fontsize=8)


def sim_figure(res: SimResult, title: str) -> Figure:
    """Four panels over time (s): position setpoint and actual, velocity, following error,
    current setpoint and measured current (:func:`_current_panel`).  ``res`` must know
    its position cycle (``position_cycle_ticks``, as :class:`hil.sim.LockStep` records)."""
    if res.position_cycle_ticks is None:
        raise ValueError("sim_figure: the recording does not know its position-control "
                         "cycle (position_cycle_ticks)")
    k, unit = _units(res.kind)
    t = res["t_s"] - res["t_s"][0]
    fig = Figure(figsize=(9, 9.5))
    ax = fig.subplots(4, 1, sharex=True)
    fig.suptitle(title)
    ax[0].plot(t, res["x_set"] * k, label="setpoint")
    ax[0].plot(t, res["x_act"] * k, "--", label="actual")
    ax[0].set_ylabel(f"position ({unit})")
    ax[0].legend()
    ax[1].plot(t, res["v_set"] * k * 60, label="interpolator")
    ax[1].plot(t, res["v_act"] * k * 60, label="actual")
    ax[1].set_ylabel(f"velocity ({unit}/min)")
    ax[1].legend()
    ax[2].plot(t, res["following_error"] * k * 1e3)
    ax[2].set_ylabel("following error (mdeg)" if res.kind == "rotary"
                     else "following error (µm)")
    _current_panel(ax[3], res, t)
    ax[3].set_xlabel("time (s)")
    for a in ax:
        a.grid(alpha=0.3)
        # an offset ("+2.5e2") would hide the values a commissioning engineer reads off
        a.ticklabel_format(useOffset=False)
    fig.tight_layout()
    return fig


def plot_sim(res: SimResult, path: Path, title: str) -> Path:
    """:func:`sim_figure` as a PNG at ``path``."""
    sim_figure(res, title).savefig(path, dpi=110)
    return path


def plot_step(res: StepResponse, path: Path, title: str, scale: float = 1.0,
              unit: str | None = None) -> Path:
    """Setpoint and response of a step measurement, with rise time and overshoot."""
    fig, ax = plt.subplots(figsize=(8, 4))
    t_ms = res.t_s * 1e3
    ax.plot(t_ms, res.setpoint * scale, label="setpoint")
    ax.plot(t_ms, res.response * scale, label="actual")
    ax.set_xlabel("time from the step (ms)")
    ax.set_ylabel(unit or res.unit)
    ax.set_title(f"{title}\nrise time 10-90 % {res.rise_time_s * 1e3:.2f} ms, overshoot "
                 f"{res.overshoot_pct:.1f} %")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
