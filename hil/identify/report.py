"""What ``hil identify`` writes: report.json, report.md, the plots and the fitted config."""

import json
import math
from pathlib import Path

import numpy as np

from hil.identify.changes import asked_text, change_text, finding_text
from hil.identify.config_out import write_config
from hil.identify.diagnosis import as_json, diagnose, faults_markdown
from hil.identify.effects import FORCE
from hil.identify.fit import Identification
from hil.identify.spectrum import position_spectrum

#: EMPS reference model, closed-loop simulation vs measurement (SOURCE.md, Janot et al.
#: 2019 §4.2): relative errors in % over samples 50..N
EMPS_PUBLISHED = {
    "DATA_EMPS": {"pos_relerr_pct": 0.013752, "force_relerr_pct": 5.848},
    "DATA_EMPS_PULSES": {"pos_relerr_pct": 0.0080248, "force_relerr_pct": 8.9409},
}
#: the reference model's IDIM-LS parameters (SOURCE.md) as machine-file keys on top of
#: configs/emps.toml, which holds its M and Fv: tau = M q'' + Fv q' + Fc sign(q') + offset,
#: the offset -3.1648 N being a constant force of +3.1648 N on the table
EMPS_REFERENCE_KEYS = {"friction": {"coulomb_n": 20.3935},
                       "table": {"external_force_n": 3.1648}}
EMPS_NOTE = ("The published position errors come from the reference scripts, which simulate "
             "at the sample time t(10) - t(9) = 0.999984 ms (DATA_EMPS) and 1.000008 ms "
             "(PULSES) instead of the data's 1 ms; their time drifts up to 0.4 ms against "
             "the data, which is most of their position error "
             "(tests/test_identify_replay.py reproduces it).  The row 'reference "
             "parameters, replayed here' runs the reference model's parameters through the "
             "same replay as ours, on the data's own time grid: the like-for-like comparison.")
METHOD = ("Inverse model on the measured motion (zero-phase low-pass, parallel filtering of "
          "the force) to find and fit the effects, because it is linear in most parameters "
          "and needs no simulation; errors before and after by closed-loop replay of the "
          "recorded setpoints through the machine file's model and controller (the EMPS "
          "records: the benchmark's PD loop), because that is how the emulator will be used.")


def _clean(obj):
    """JSON-ready: numpy scalars and arrays to Python, non-finite floats to None."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def over_floor(err: dict, floor: dict) -> dict:
    """Each replay error over its channel's noise floor."""
    return {k: err[k] / f for k, f in floor.items() if isinstance(err.get(k), float) and f > 0}


def summary(ident: Identification, validation: dict | None, elapsed_s: float,
            reference: dict | None = None) -> dict:
    """The content of report.json."""
    rec = ident.rec
    out = {
        "trace": rec.source, "config": str(ident.config), "method": METHOD,
        "samples": rec.n, "sample_time_s": rec.dt, "filter_cutoff_hz": ident.motion.cutoff_hz,
        "effects_added": [s.effect for s in ident.steps],
        "steps": [{"effect": s.effect, "params": s.params, "evidence": s.evidence,
                   "error": s.error} for s in ident.steps],
        "error_before": ident.error_before, "error_after": ident.error_after,
        "validation": validation or {},
        "noise_floor": {d: ident.noise_floor(d) for d in ident.domains()},
        "replay_noise_floor": ident.floor,
        "replay_noise_floor_origin": ident.floor_origins,
        "error_before_over_floor": over_floor(ident.error_before, ident.floor),
        "error_after_over_floor": over_floor(ident.error_after, ident.floor),
        "proposals": ident.proposals, "rounds": ident.rounds,
        "declared_changes": ident.declared_changes,
        "faults": as_json(diagnose(ident)),
        "refinement": ident.refinement, "rejected": ident.rejected,
        "unexplained": ident.unexplained, "not_looked_for": ident.skipped,
        "thresholds": {"min_explained": ident.min_explained,
                       "floor_factor": ident.floor_factor},
        "elapsed_s": elapsed_s,
    }
    published = EMPS_PUBLISHED.get(Path(rec.source).stem)
    if published is not None:
        out["published_reference"] = {Path(rec.source).stem: published}
        if validation:
            stem = Path(validation["trace"]).stem
            if stem in EMPS_PUBLISHED:
                out["published_reference"][stem] = EMPS_PUBLISHED[stem]
        out["reference_replayed"] = reference or {}
    return _clean(out)


def _row(err: dict, keys) -> list[str]:
    return [_fmt(err[k]) if k in err else "-" for k in keys]


def markdown(rep: dict) -> str:
    """report.md from report.json's content."""
    eff = "force" if "force_relerr_pct" in rep["error_before"] else "iq"
    unit = "n" if eff == "force" else "a"
    keys = ["pos_rms_um", "pos_relerr_pct", f"{eff}_rms_{unit}", f"{eff}_relerr_pct"]
    if "motor_pos_rms_um" in rep["error_before"]:
        keys.append("motor_pos_rms_um")
    lines = [f"# Identification of `{Path(rep['trace']).name}`", "",
             f"Start config: `{rep['config']}`; {rep['samples']} samples at "
             f"{rep['sample_time_s'] * 1e3:.4g} ms; inverse-model low-pass "
             f"{rep['filter_cutoff_hz']:.4g} Hz; {rep['elapsed_s']:.1f} s.", "",
             f"Method: {rep['method']}", "",
             "Effects added, in order: " + (", ".join(f"`{e}`" for e in rep["effects_added"])
                                            or "none"), "",
             *faults_markdown(rep.get("faults", []), rep["effects_added"]),
             "## Errors (closed-loop replay, from sample 50; relerr = 100 ||y - y^|| / ||y||)",
             "", "| record | model | " + " | ".join(keys) + " |",
             "|---" * (len(keys) + 2) + "|"]
    name = Path(rep["trace"]).stem
    lines.append(f"| {name} | config as given | " + " | ".join(_row(rep["error_before"], keys))
                 + " |")
    lines.append(f"| {name} | identified | " + " | ".join(_row(rep["error_after"], keys))
                 + " |")
    val = rep.get("validation") or {}
    if val:
        vname = Path(val["trace"]).stem
        lines.append(f"| {vname} (validation) | config as given | "
                     + " | ".join(_row(val["error_before"], keys)) + " |")
        lines.append(f"| {vname} (validation) | identified | "
                     + " | ".join(_row(val["error_after"], keys)) + " |")
    for rname, err in (rep.get("reference_replayed") or {}).items():
        lines.append(f"| {rname} | reference parameters (Janot et al. 2019), replayed here | "
                     + " | ".join(_row(err, keys)) + " |")
    for rname, pub in (rep.get("published_reference") or {}).items():
        lines.append(f"| {rname} | published reference model (Janot et al. 2019) | - | "
                     f"{pub['pos_relerr_pct']} | - | {pub['force_relerr_pct']} |"
                     + (" - |" if len(keys) > 4 else ""))
    if rep.get("published_reference"):
        lines += ["", EMPS_NOTE]
    lines += ["", "## Steps", ""]
    for i, s in enumerate(rep["steps"], 1):
        params = ", ".join(f"{k} = {_fmt(v)}" for k, v in s["params"].items())
        lines += [f"{i}. **{s['effect']}** — {params}",
                  f"   - evidence: {s['evidence'].get('text', '')} (explains "
                  f"{100 * s['evidence'].get('explained', 0):.1f} % of its residual)",
                  "   - error after this step: " + ", ".join(
                      f"{k} {_fmt(v)}" for k, v in s["error"].items())]
    ref = rep.get("refinement") or {}
    if ref:
        lines += ["", f"Closed-loop refinement ({ref['replays']} replays, least squares on the "
                  f"replay's errors over their floors, J {_fmt(ref['cost_before'])} -> "
                  f"{_fmt(ref['cost_after'])}): " + ", ".join(
                      f"{k} {_fmt(ref['before'][k])} -> {_fmt(v)} ± "
                      f"{_fmt(ref['sigma'][k])}" for k, v in ref["after"].items())]
    changes = rep.get("declared_changes") or []
    if changes:
        lines += ["", "## Declared parameters (refitted with a prior at the declared value, "
                  "within their tolerance)", "",
                  "| parameter | declared | identified | change | ± (1 sigma) | tolerance | "
                  "asked for | |", "|---|---|---|---|---|---|---|---|"]
        for c in changes:
            flag = "**finding**" if c["beyond_tolerance"] else ""
            if c["significant"] is False:
                flag = (flag + " " if flag else "") + "within its uncertainty"
            asked = (f"{_fmt(c['wanted'])} ({asked_text(c)})" if c.get("wanted") is not None
                     else "-")
            lines.append(f"| {c['parameter']} | {_fmt(c['declared'])} | "
                         f"{_fmt(c['identified'])} | {change_text(c)} | "
                         f"{_fmt(c['sigma'])} | {c['tolerance_pct']:g} % | {asked} | {flag} |")
        found = [c for c in changes if c["beyond_tolerance"]]
        if found:
            lines += ["", "### Findings", "",
                      "What the data ask of a declared value (a coefficient or a shape) "
                      "beyond its tolerance is not taken: the model lacks something, or the "
                      "machine file is wrong there.", ""] + [f"- {finding_text(c)}" for c in found]
    origin = rep.get("replay_noise_floor_origin", {})
    lines += ["", "Noise floor of the replay channels: " + ", ".join(
        f"{k} {_fmt(v)}" + (f" ({origin[k]})" if k in origin else "")
        for k, v in rep["replay_noise_floor"].items())
        + "; error over it before: " + ", ".join(
        f"{k} {v:.3g}" for k, v in rep["error_before_over_floor"].items())
        + "; after: " + ", ".join(f"{k} {v:.3g}" for k, v in rep["error_after_over_floor"].items())]
    for i, rnd in enumerate(rep.get("rounds") or [], 1):
        if i == 1:
            lines += ["", "## Every candidate of each round, ranked by its held-out gain", "",
                      "Fitted on alternate 0.5 s blocks, scored by the replay on the others: "
                      "J = sum of (error / floor)², BIC = n ln(J / J0) + k ln n.", ""]
        lines += [f"Round {i} (held-out J before {_fmt(rnd['heldout_cost_before'])}):", ""]
        for c in rnd["ranking"]:
            params = ", ".join(f"{k} = {_fmt(v)}" for k, v in c["params"].items())
            score = (f"J {_fmt(c['heldout_cost'])}, BIC {_fmt(c['heldout_delta_bic'])}"
                     if c["heldout_cost"] is not None else "no score")
            lines.append(f"- `{c['effect']}`: {score}" + (f" — {params}" if params else "")
                         + (f" ({c['note']})" if c["note"] else ""))
        lines.append("")
    if rep.get("proposals"):
        lines += ["", "## Every proposal, kept or not", ""]
        for i, prop in enumerate(rep["proposals"], 1):
            params = ", ".join(f"{k} = {_fmt(v)}" for k, v in prop["params"].items())
            lines += [f"{i}. `{prop['effect']}` {'kept' if prop['accepted'] else 'rejected'}"
                      f" — {params}", f"   - {prop['reason']}"]
    lines += ["", "## What is left", ""]
    for domain, info in rep["unexplained"].items():
        unit_d = "N" if domain == FORCE else "m"
        text = (f"- {domain} residual: rms {_fmt(info['rms'])} {unit_d} (noise floor "
                f"{_fmt(info['noise_floor'])} {unit_d}); correlation with sign(v) "
                f"{info['corr_sign_v']:.2f}, v {info['corr_v']:.2f}, a {info['corr_a']:.2f}")
        peaks = info.get("periodic_in_table_position") or []
        if peaks:
            p = peaks[0]
            text += (f"; strongest periodic part: period {p['period_m'] * 1e3:.4g} mm in table "
                     f"position, amplitude {_fmt(p['amplitude'])} {unit_d}")
        lines.append(text)
    if rep["not_looked_for"]:
        lines += ["", "Not looked for: " + "; ".join(f"`{k}`: {v}" for k, v in
                                                    rep["not_looked_for"].items())]
    lines += ["", "Plots: `residual_time.png`, `residual_position.png`, `spectrum.png`, "
              "`friction_map.png`, `reversals.png`; fitted "
              "machine file: `config.toml`.", ""]
    return "\n".join(lines)


def _fmt(v) -> str:
    """A number of the report in 4 digits; -0 as 0 (a sign that says nothing); None (a
    value report.json could not hold, or none) as n/a."""
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v + 0.0:.4g}"  # + 0.0: -0.0 becomes 0.0
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


def plots(ident: Identification, out: Path) -> None:
    """residual_time.png, residual_position.png, spectrum.png, friction_map.png and
    reversals.png."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rec, m, ctx = ident.rec, ident.motion, ident.ctx
    domains = ident.domains()
    fig, axes = plt.subplots(len(domains) + 1, 1, figsize=(10, 3 * (len(domains) + 1)),
                             sharex=True)
    # the filter's edges are no residual: leave them out
    edge = np.where(m.use, 1.0, np.nan)
    for ax, d in zip(axes, domains):
        scale, unit = (1.0, "N") if d == FORCE else (1e6, "um")
        ax.plot(rec.t, ident.residual_before[d] * scale * edge, lw=0.6, label="before")
        ax.plot(rec.t, ident.residual_after[d] * scale * edge, lw=0.6, label="after")
        ax.set_ylabel(f"{'force' if d == FORCE else 'table - motor'} residual ({unit})")
        ax.legend(loc="upper right")
    ax = axes[-1]
    for name, rp in (("before", ident.replay_before), ("after", ident.replay_after)):
        if rp is not None and rp.status == 0:
            ax.plot(rec.t, rec.effort - rp.effort, lw=0.6, label=f"replay error {name}")
    ax.set_ylabel("effort error (" + ("N" if rec.effort_kind == "force" else "A") + ")")
    ax.set_xlabel("t (s)")
    ax.legend(loc="upper right")
    fig.suptitle("Residuals: inverse model (top), closed-loop replay (bottom)")
    fig.tight_layout()
    fig.savefig(out / "residual_time.png", dpi=110)
    plt.close(fig)

    # the same residuals over the table position: what repeats with position lines up
    fig, axes = plt.subplots(len(domains), 1, figsize=(10, 3 * len(domains)), squeeze=False)
    unit_x = (1.0, "rad") if ident.drive.kind == "rotary" else (1e3, "mm")
    for ax, d in zip(axes[:, 0], domains):
        scale, unit = (1.0, "N") if d == FORCE else (1e6, "um")
        for name in ("before", "after"):
            r = getattr(ident, f"residual_{name}")[d]
            ax.plot(m.x[ctx.moving] * unit_x[0], r[ctx.moving] * scale, ".", ms=1,
                    alpha=0.5, label=name)
        ax.set_ylabel(f"{'force' if d == FORCE else 'table - motor'} residual ({unit})")
        ax.set_xlabel(f"table position ({unit_x[1]})")
        ax.legend(loc="upper right", markerscale=8)
    fig.suptitle("Residuals over the table position (moving samples)")
    fig.tight_layout()
    fig.savefig(out / "residual_position.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(len(domains), 1, figsize=(10, 3.5 * len(domains)), squeeze=False)
    travel = float(np.ptp(m.x[ctx.moving])) if ctx.moving.any() else 0.0
    for ax, d in zip(axes[:, 0], domains):
        if travel <= 0:
            break
        for name, r in (("before", ident.residual_before[d]), ("after", ident.residual_after[d])):
            s = position_spectrum(r, m.x, ctx.moving, travel / 4000)
            ax.semilogy(s.cycles_per_unit[1:] * 1e-3, s.amplitude[1:], lw=0.8, label=name)
        if ident.drive.kind == "screw":
            lead_mm = 2e3 * math.pi * ident.drive.ratio
            ax.axvline(1.0 / lead_mm, color="k", ls=":", lw=0.8, label="once per motor rev")
            # the same lines counted per motor revolution: where cogging and runout sit
            top = ax.secondary_xaxis("top", functions=(lambda f: f * lead_mm,
                                                       lambda k: k / lead_mm))
            top.set_xlabel("cycles per motor revolution")
        # above half the binning's Nyquist frequency the bins' averaging distorts the lines
        ax.set_xlim(0.0, 0.25 / (travel / 4000) * 1e-3)
        ax.set_xlabel("spatial frequency (cycles per mm of table travel)")
        ax.set_ylabel(f"{d} residual amplitude ({'N' if d == FORCE else 'm'})")
        ax.legend()
    fig.suptitle("Position-domain spectrum of the residuals")
    fig.tight_layout()
    fig.savefig(out / "spectrum.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 5))
    inertia_before = ident.model_before_inertia
    inertia_after = ident.model.term("inertia").coef[0]
    sel = ctx.m.use
    ax.plot(m.v[sel], (m.force - inertia_after * m.a)[sel], ",", alpha=0.4,
            label="measured F - M a")
    v = np.linspace(float(m.v[sel].min()), float(m.v[sel].max()), 400)
    for name, fr in (("before", ident.friction_before), ("after", ident.friction_after)):
        ax.plot(v, fr(v), lw=1.5, label=f"model friction {name}")
    ax.set_xlabel("table velocity (m/s)" if ident.drive.kind != "rotary" else "rad/s")
    ax.set_ylabel("force (N)" if ident.drive.kind != "rotary" else "torque (N m)")
    ax.set_title(f"Friction map (M before {inertia_before:.4g}, after {inertia_after:.4g})")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "friction_map.png", dpi=110)
    plt.close(fig)
    _reversals_plot(ident, out / "reversals.png", plt)


#: displacement after a reversal the reversal plot shows (m, or rad on rotary tables)
REVERSAL_SPAN = 50e-6


def _reversals_plot(ident: Identification, path: Path, plt) -> None:
    """Friction against the displacement since each reversal, every reversal overlaid
    (signed by the new direction): presliding builds up over micrometres there, Coulomb
    jumps, backlash and compliance shift it."""
    m, ctx = ident.motion, ident.ctx
    flips = np.flatnonzero(np.diff(ctx.direction) != 0) + 1
    fig, ax = plt.subplots(figsize=(8, 5))
    inertia = ident.model.term("inertia").coef[0]
    measured = m.force - inertia * m.a
    model = measured - ident.residual_after[FORCE]
    for i, k in enumerate(flips):
        d = ctx.direction[k]
        dx = d * (m.x[k:] - m.x[k - 1])
        end = k + int(np.argmax(dx > REVERSAL_SPAN)) if np.any(dx > REVERSAL_SPAN) else m.x.size
        sl = slice(k - 1, end)
        span = d * (m.x[sl] - m.x[k - 1]) * 1e6
        ax.plot(span, d * measured[sl], ".", ms=2, color="C0",
                label="measured F - M a" if i == 0 else None)
        ax.plot(span, d * model[sl], lw=1, color="C1", label="model after" if i == 0 else None)
    unit = "urad" if ident.drive.kind == "rotary" else "um"
    ax.set_xlabel(f"displacement since the reversal ({unit}), in the new direction")
    ax.set_ylabel("friction in the new direction (" +
                  ("N m" if ident.drive.kind == "rotary" else "N") + ")")
    ax.set_title(f"The {flips.size} reversals of motion overlaid")
    if flips.size:
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(ident: Identification, out: str | Path, validation: dict | None,
          elapsed_s: float, reference: dict | None = None) -> dict:
    """Write every output into ``out``; returns report.json's content.  ``reference``:
    record name -> errors of a reference model replayed on it (EMPS)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rep = summary(ident, validation, elapsed_s, reference)
    (out / "report.json").write_text(json.dumps(rep, indent=2) + "\n")
    (out / "report.md").write_text(markdown(rep))
    write_config(ident.config, out / "config.toml", ident.model.overrides(),
                 "identified by hil identify from " + Path(ident.rec.source).name)
    plots(ident, out)
    return rep
