"""What the machine files' comments claim, checked against what their values give.

- ``modal_damping``: each comment that says how much modal damping a damper gives
  ("~5 % damping at that mode") against the damping ratio of that mode, from the complex
  eigenvalues of the linearised mechanics (:func:`plant.assemble.mechanics_matrices`).
  "That mode" is the lowest whose strain energy lies mostly in the damper's part: the
  coupling, the screw's torsion, or the axial path (screw, thrust bearing, nut).
- ``cogging_orders``: the Arrow's cogging orders against its [cogging] slots and its pole
  number: cogging repeats LCM(slots, poles) times per revolution, so its orders in cycles
  per electrical revolution are multiples of LCM(slots, poles) / pole pairs.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.linalg

from hil.validate.core import CONFIGS, VERIFICATION, Result, SeedRef, experiment
from hil.validate.experiments.mechanics import screw_geometry
from plant.assemble import build_chains, mechanics_matrices
from plant.config import MachineConfig, load_machine

#: a comment's "~N %": one unit of its last digit
COMMENT_PM_PCT = 1.0
#: the share of a mode's strain energy that makes it a part's mode
PART_SHARE = 0.5
PART_NAMES = {"coupling": "coupling", "torsion": "screw torsion", "axial": "axial path"}


@dataclass(frozen=True)
class DampingClaim:
    """A machine-file comment about modal damping.

    Attributes:
        file: machine file name in configs/.
        key: "[section] key" the comment stands beside.
        part: "coupling", "torsion" or "axial".
        percent: the damping ratio the comment claims, %.
        comment: the comment's words, verbatim.
        table_pos: m, where the mechanics are linearised.
    """
    file: str
    key: str
    part: str
    percent: float
    comment: str
    table_pos: float


CLAIMS = (
    DampingClaim("arrow500_x.toml", "[coupling] damping_nms_per_rad", "coupling", 5.0,
                 "elastomer spider, ~5 % damping at that mode", 0.25),
    DampingClaim("arrow500_x.toml", "[screw] torsional_damping_nms_per_rad", "torsion", 2.0,
                 "explicit damping giving ~2 % modal damping", 0.25),
    DampingClaim("arrow500_x.toml", "[screw] axial_damping_ns_per_m", "axial", 2.0,
                 "as above for the axial modes", 0.25),
    DampingClaim("tlm_rig.toml", "[coupling] damping_nms_per_rad", "coupling", 5.0,
                 "~5 % damping at the coupling mode", 0.3),
    DampingClaim("tlm_rig.toml", "[screw] torsional_damping_nms_per_rad", "torsion", 2.0,
                 "explicit damping giving ~2 % modal damping", 0.3),
    DampingClaim("tlm_rig.toml", "[screw] axial_damping_ns_per_m", "axial", 2.0,
                 "as above for the axial modes", 0.3),
)


@dataclass(frozen=True)
class Mode:
    """A mode of the linearised screw mechanics.

    Attributes:
        freq_hz: undamped natural frequency, Hz.
        damping: damping ratio of the matching complex eigenvalue pair, 1.
        shares: part -> share of the mode's strain energy ("coupling", "torsion",
            "axial"; the nut's counts as axial).
    """
    freq_hz: float
    damping: float
    shares: dict


def screw_modes(cfg: MachineConfig, table_pos: float) -> list[Mode]:
    """The elastic modes of a screw machine file at ``table_pos`` (m), ascending."""
    m_mat, c_mat, k_mat = mechanics_matrices(cfg, table_pos)
    rot, _ = build_chains(cfg)
    n = m_mat.shape[0]
    state = np.block([[np.zeros((n, n)), np.eye(n)],
                      [-np.linalg.solve(m_mat, k_mat), -np.linalg.solve(m_mat, c_mat)]])
    lam = np.linalg.eigvals(state)
    lam = lam[lam.imag > 0.0]
    w2, phi = scipy.linalg.eigh(k_mat, m_mat)
    modes = []
    for w_sq, q in zip(w2, phi.T):
        if w_sq <= 1e-6 * w2[-1]:
            continue  # rigid-body motion
        th = q[:rot.n]
        twist = np.diff(th)
        total = 0.5 * q @ k_mat @ q
        coupling = 0.5 * rot.k_link[0] * twist[0] ** 2
        torsion = 0.5 * float(np.sum(rot.k_link[1:] * twist[1:] ** 2))
        pair = lam[np.argmin(np.abs(np.abs(lam) - math.sqrt(w_sq)))]
        modes.append(Mode(math.sqrt(w_sq) / (2.0 * math.pi), -pair.real / abs(pair),
                          {"coupling": coupling / total, "torsion": torsion / total,
                           "axial": 1.0 - (coupling + torsion) / total}))
    return modes


def claim_row(claim: DampingClaim) -> Result:
    """The damping of the lowest mode of the claim's part against the claim."""
    cfg = load_machine(CONFIGS / claim.file)
    mode = next(m for m in screw_modes(cfg, claim.table_pos)
                if m.shares[claim.part] > PART_SHARE)
    model = 100.0 * mode.damping
    agrees = abs(model - claim.percent) <= COMMENT_PM_PCT
    part = PART_NAMES[claim.part]
    return Result(f"{claim.file}: damping of the {part} mode ({mode.freq_hz:.0f} Hz)",
                  claim.percent, model, "%", agrees,
                  f"configuration: {claim.key}, whose comment claims ~{claim.percent:g} %: "
                  f'"{claim.comment}"',
                  f"±{COMMENT_PM_PCT:g} %-point ('~'); the mode: the lowest with over "
                  f"{PART_SHARE * 100:g} % of its strain energy in the {part}; screw "
                  f"{screw_geometry(cfg)}", VERIFICATION,
                  note="" if agrees else
                  f"disagrees: the configured dampers give {model:.2f} % (complex eigenvalues "
                  f"of mechanics_matrices at {claim.table_pos * 1e3:.0f} mm); the comment or "
                  "the damper is wrong", uncertainty=COMMENT_PM_PCT)


@experiment("modal_damping", "000")
def modal_damping(out_dir: Path | None) -> list[Result]:
    """The modal damping the Arrow's and the TLM rig's comments claim, against their
    dampers (no plot)."""
    return [claim_row(claim) for claim in CLAIMS]


ARROW = CONFIGS / "arrow500_x.toml"
POLES_SOURCE = SeedRef("000", "§3", None, "The three-phase permanent magnet synchronous AC "
                       "motors of the feed drives contain a six-pole stator")


@experiment("cogging_orders", "000")
def cogging_orders(out_dir: Path | None) -> list[Result]:
    """Each configured cogging order of the Arrow against the harmonics its [cogging] slots
    and six poles allow (no plot): LCM(slots, poles) per revolution, recomputed here as the
    smallest number of cycles that is a whole number of slot and of pole pitches."""
    cfg = load_machine(ARROW)
    pairs = round(cfg.motor.pole_pairs)
    slots = cfg.cogging.slots
    per_rev = next(n for n in range(1, slots * 2 * pairs + 1)
                   if n % slots == 0 and n % (2 * pairs) == 0)
    base = per_rev / pairs
    rows = []
    for order in cfg.cogging.orders:
        agrees = math.isclose(order / base, round(order / base)) and order >= base
        rows.append(Result(
            f"arrow500_x.toml: cogging order {order:g} (cycles per electrical revolution)",
            f"multiples of {base:g}", order, "1", agrees,
            f"analytic: LCM({slots} slots, {2 * pairs} poles) / {pairs} pole pairs; the slots "
            "from [cogging] slots (assumed), the poles from seed 000", "exact", VERIFICATION,
            POLES_SOURCE, "" if agrees else
            f"disagrees: {slots} slots and six poles cog {base:g} times per electrical "
            f"revolution, so order {order:g} is no cogging harmonic (a 6th-order ripple of a "
            "PMSM is the back-EMF's 5th and 7th harmonics under current, not cogging)"))
    return rows
