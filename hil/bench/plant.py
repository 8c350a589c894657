"""``hil bench plant``: kernel speed per machine file against an uncompiled reference.

For each config the compiled kernel is warmed, then called once per PWM
period (as a real-time loop calls it) for ``seconds`` of wall time; the
result is ns per sub-step and the real-time factor (simulated / wall time).
The reference is the *same kernel source* run uncompiled by CPython on NumPy
arrays (``NUMBA_DISABLE_JIT=1`` in a child process, same machine file, same
inputs) — the plain NumPy step of the same equations — measured in the same
call; ``speedup_vs_reference`` is the ratio.  ``cold_start_s`` is the time a
fresh process needs to import, load the machine file and make its first
kernel call with numba's on-disk cache warm (the goal is <= 5 s).
"""

import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

_PROBE = """
import json, sys, time
t0 = time.perf_counter()
from hil.bench.plant import time_kernel
from plant import Plant
plant = Plant.from_file(sys.argv[1])
plant.set_input(iq_ref_a=0.1 * plant.config.motor.current_max_a)
plant.step(plant.sub_per_pwm)
cold = time.perf_counter() - t0
ns = time_kernel(plant, float(sys.argv[2])) if float(sys.argv[2]) > 0 else None
print(json.dumps({"cold_start_s": cold, "ns_per_step": ns}))
"""


@dataclass(frozen=True)
class PlantBench:
    """One config's figures (the JSON object ``hil bench plant --json`` prints)."""
    config: str
    ns_per_step: float
    substep_s: float
    realtime_factor: float
    reference_ns_per_step: float
    speedup_vs_reference: float
    sub_per_pwm: int
    cold_start_s: float


def time_kernel(plant, seconds: float) -> float:
    """ns per sub-step of ``plant``'s kernel called once per PWM period for ~``seconds``."""
    from plant.kernel import axis_step_nb

    p, s, inp, out, n = plant.params, plant.state, plant.inp, plant.out, plant.sub_per_pwm
    axis_step_nb(p, s, inp, out, n)
    calls = 0
    t0 = time.perf_counter()
    t_end = t0 + seconds
    while True:
        for _ in range(50):
            axis_step_nb(p, s, inp, out, n)
        calls += 50
        now = time.perf_counter()
        if now >= t_end:
            break
    return (now - t0) / (calls * n) * 1e9


def _child(config: Path, seconds: float, jit: bool) -> dict:
    env = dict(os.environ)
    if not jit:
        env["NUMBA_DISABLE_JIT"] = "1"
    res = subprocess.run([sys.executable, "-c", _PROBE, str(config), str(seconds)],
                         capture_output=True, text=True, env=env, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"benchmark child for {config} failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def bench_config(config: Path, seconds: float, ref_seconds: float) -> PlantBench:
    """Measure one machine file (compiled, reference, cold start)."""
    from plant import Plant

    plant = Plant.from_file(config)
    plant.set_input(iq_ref_a=0.1 * plant.config.motor.current_max_a)
    ns = time_kernel(plant, seconds)
    cold = _child(config, 0.0, jit=True)["cold_start_s"]
    ref = _child(config, ref_seconds, jit=False)["ns_per_step"]
    return PlantBench(config=config.stem, ns_per_step=ns, substep_s=plant.dt,
                      realtime_factor=plant.dt / (ns * 1e-9), reference_ns_per_step=ref,
                      speedup_vs_reference=ref / ns, sub_per_pwm=plant.sub_per_pwm,
                      cold_start_s=cold)


def run(configs: list[Path], seconds: float, ref_seconds: float, progress=None) -> list[dict]:
    """Benchmark every config; returns the JSON-ready rows."""
    rows = []
    for cfg in configs:
        row = bench_config(cfg, seconds, ref_seconds)
        rows.append(asdict(row))
        if progress is not None:
            progress(row)
    return rows
