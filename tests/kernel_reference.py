"""A fixed stimulus for every machine file in configs/ and the kernel's answer to it, kept
bit for bit in ``tests/data/kernel_reference.json``.

The file was written by the kernel as it was before the speed work of issue 12 part 7
(unsigned indexing, inlined effects, the Stribeck cut-off); ``tests/test_kernel_speed.py``
checks that the kernel of today gives the very same bits.  Rewrite it only for a
deliberate change of the physics::

    PYTHONPATH=. python3 -m tests.kernel_reference      # rewrites the JSON

The stimulus visits every branch the configs reach: current steps of random height
(seeded), an external load, the power stage off (freewheeling, controller reset),
voltage mode, and a long push toward the negative end of the travel from a start 3 mm
inside it (into the end stop on axes with a stroke, sliding far into the Stribeck tail).
Beside the files as they are, the Arrow 500 X runs once more with the effects its file
leaves off (:data:`VARIANTS`: pitch error, measurement delay, nut backlash, asymmetric
viscous friction; the screw's bearing and nut friction).
"""

import json
from pathlib import Path

import numpy as np

from plant import Plant
from plant import layout as L

ROOT = Path(__file__).resolve().parent.parent
REFERENCE = Path(__file__).resolve().parent / "data" / "kernel_reference.json"
#: kernel calls of one PWM period each, and a snapshot every SNAPSHOT_EVERY calls
CALLS = 600
SNAPSHOT_EVERY = 50
#: where every run starts: 3 mm (rad on the rotary table) inside the negative end stop
START_POS_M = -0.022
#: extra cases: name -> (machine file, overrides)
VARIANTS = {
    "arrow500_x_effects": ("arrow500_x.toml", {
        "pitch_error": {"periods_m": [0.01, 0.0023], "amplitudes_m": [4e-6, 1e-6],
                        "phases_deg": [10.0, -40.0], "linear_ppm": 20.0},
        "sensors": {"delay_s": 2.0 / 8000.0},
        "screw": {"backlash_m": 2e-6},
        "friction": {"viscous_asymmetry_ns_per_m": 150.0}}),
    # issue 14 part 4: the screw's bearing and nut friction (stiction in the push's stops)
    "arrow500_x_screw_friction": ("arrow500_x.toml", {
        "screw": {"bearing_coulomb_nm": 0.05, "nut_coulomb_nm": 0.15,
                  "nut_viscous_nms_per_rad": 2e-4, "nut_load_friction": 0.05}}),
}


#: the stroke the reference was written with, the plant's defaults: issue 27 moved the
#: limit switches and end stops of these files out (room for the drive to brake), and the
#: push toward the end stop is laid out for the stroke as it was
REFERENCE_STROKE = {"limit_switch_overtravel_m": 0.01, "end_stop_overtravel_m": 0.025}
STROKE_MOVED = ("arrow500_x.toml", "ld386_linear.toml")


def _as_written(file: Path, overrides: dict | None) -> tuple[Path, dict | None]:
    """``file`` with ``overrides``, and the reference's stroke where the file moved it."""
    if file.name not in STROKE_MOVED:
        return file, overrides
    return file, {**(overrides or {}), "table": REFERENCE_STROKE}


def cases() -> dict[str, tuple[Path, dict | None]]:
    """The runs the reference covers: every file in configs/ as it is (the stroke as the
    reference was written: :data:`REFERENCE_STROKE`), and VARIANTS."""
    runs = {cfg.stem: _as_written(cfg, None)
            for cfg in sorted((ROOT / "configs").glob("*.toml"))}
    for name, (file, overrides) in VARIANTS.items():
        runs[name] = _as_written(ROOT / "configs" / file, overrides)
    return runs


def set_inputs(k: int, plant: Plant, rng: np.random.Generator) -> None:
    """The stimulus before call ``k`` (A, V and N scaled to the machine's ratings)."""
    i_max = plant.config.motor.current_max_a
    u_max = 0.2 * plant.config.motor.dc_link_v
    if k < 200:
        if k % 20 == 0:
            plant.set_input(iq_ref_a=0.3 * i_max * rng.uniform(-1.0, 1.0),
                            id_ref_a=0.05 * i_max * rng.uniform(-1.0, 1.0))
    elif k < 300:
        if k % 25 == 0:
            plant.set_input(load=rng.uniform(-50.0, 50.0))
    elif k < 350:
        plant.set_input(enable=0.0, load=0.0)
    elif k < 450:
        if k % 20 == 0:
            plant.set_input(enable=1.0, mode=float(L.INPUT_VOLTAGE),
                            ud_v=u_max * rng.uniform(-1.0, 1.0),
                            uq_v=u_max * rng.uniform(-1.0, 1.0))
    elif k == 450:
        plant.set_input(mode=float(L.INPUT_CURRENT), id_ref_a=0.0, iq_ref_a=-0.5 * i_max)


def trajectory(config: Path, overrides: dict | None = None) -> dict:
    """The snapshots of ``config``'s plant under the stimulus: {"sub_per_pwm", "state":
    [[hex float, ...], ...], "out": [...]}, a snapshot after every SNAPSHOT_EVERY-th call."""
    plant = Plant.from_file(config, table_pos=START_POS_M, overrides=overrides)
    rng = np.random.default_rng(12)
    states, outs = [], []
    for k in range(CALLS):
        set_inputs(k, plant, rng)
        plant.step(plant.sub_per_pwm)
        if (k + 1) % SNAPSHOT_EVERY == 0:
            states.append([float(x).hex() for x in plant.state])
            outs.append([float(x).hex() for x in plant.out])
    return {"sub_per_pwm": plant.sub_per_pwm, "state": states, "out": outs}


def main() -> None:
    data = {name: trajectory(*case) for name, case in cases().items()}
    REFERENCE.write_text(json.dumps(data, indent=0) + "\n")
    print(f"wrote {REFERENCE} ({len(data)} configs)")


if __name__ == "__main__":
    main()
