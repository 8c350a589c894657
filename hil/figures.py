"""Plots a commissioning engineer looks at: a run's setpoint, actual value, following error
and current; a step response.  Axes are labelled in the units a CNC shows (mm, mm/min,
A; deg on rotary tables)."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (backend must be chosen first)

from hil.measure.runs import StepResponse  # noqa: E402
from hil.sim import SimResult  # noqa: E402


def _units(kind: str) -> tuple[float, str]:
    """Factor from SI table units to display units, and the display unit."""
    return (57.29577951308232, "deg") if kind == "rotary" else (1e3, "mm")


def plot_sim(res: SimResult, path: Path, title: str) -> Path:
    """Four panels over time: position setpoint and actual, velocity, following error,
    current setpoint and measured current."""
    k, unit = _units(res.kind)
    t = res["t_s"] - res["t_s"][0]
    fig, ax = plt.subplots(4, 1, figsize=(9, 9), sharex=True)
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
    ax[3].plot(t, res["iq_set"], label="i_q setpoint")
    ax[3].plot(t, res["iq_meas"], alpha=0.7, label="i_q measured")
    ax[3].set_ylabel("current (A)")
    ax[3].set_xlabel("time (s)")
    ax[3].legend()
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
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
