"""``hil bench plant``: kernel speed per machine file against an uncompiled reference and
against the same sub-step in C.

For each config the compiled kernel is warmed, then called once per PWM
period (as a real-time loop calls it) for ``seconds`` of wall time; the
result is ns per sub-step and the real-time factor (simulated / wall time).
The reference is the *same kernel source* run uncompiled by CPython on NumPy
arrays (``NUMBA_DISABLE_JIT=1`` in a child process, same machine file, same
inputs) — the plain NumPy step of the same equations — measured in the same
call; ``speedup_vs_reference`` is the ratio.

The C baseline (issue 12 part 7) is :mod:`hil.bench.csubstep`, the sub-step ported to C
with the same equations in the same floating-point order (bit-identical results), built
``-O2 -ffp-contract=off``.  Both are timed the same way, in the same run, for ``seconds``:
one call per PWM period from a compiled loop (a C loop for C, a numba loop for the
kernel), so neither pays Python's call overhead, in alternating batches from the same
state (they stay bit-identical: ``c_same_state``); each figure is its fastest batch.
``ratio_to_c`` is ``loop_ns_per_step / c_ns_per_step`` (the goal: <= 1.3).  These are
null for the models the port does not carry (everything but the d-q motor on a screw
with the lumped solver) or when no C compiler is installed (the reason goes to stderr).

``cold_start_s`` is the time a fresh process needs to import, load the machine file and
make its first kernel call with numba's on-disk cache warm (the goal is <= 5 s);
``cold_compile_s`` the same with an empty cache (the cache on: what the first run after a
change of the plant's source costs; the goal is < 20 s), and ``cold_compile_cpu_s`` the
CPU time it took, which the machine's other load inflates far less than the wall time.
"""

import itertools
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from numba import njit

from hil.bench.csubstep import CCompilerMissing, CStep
from plant.kernel import axis_step_nb

_PROBE = """
import json, sys, time
t0, cpu0 = time.perf_counter(), time.process_time()
from hil.bench.plant import time_kernel
from plant import Plant
plant = Plant.from_file(sys.argv[1])
plant.set_input(iq_ref_a=0.1 * plant.config.motor.current_max_a)
plant.step(plant.sub_per_pwm)
cold, cold_cpu = time.perf_counter() - t0, time.process_time() - cpu0
ns = time_kernel(plant, float(sys.argv[2])) if float(sys.argv[2]) > 0 else None
print(json.dumps({"cold_start_s": cold, "cold_start_cpu_s": cold_cpu, "ns_per_step": ns}))
"""


#: kernel calls per timed batch of the compiled loops (C and numba)
_BATCH = 2000


@dataclass(frozen=True)
class PlantBench:
    """One config's figures (the JSON object ``hil bench plant --json`` prints).

    Times are ns per sub-step; ``c_ns_per_step``, ``loop_ns_per_step``, ``ratio_to_c``
    and ``c_same_state`` (the C port and the kernel ended the timing with the same state,
    bit for bit) are None where the C port does not run (see the module's doc)."""
    config: str
    ns_per_step: float
    substep_s: float
    realtime_factor: float
    reference_ns_per_step: float
    speedup_vs_reference: float
    sub_per_pwm: int
    cold_start_s: float
    cold_compile_s: float
    cold_compile_cpu_s: float
    c_ns_per_step: float | None
    loop_ns_per_step: float | None
    ratio_to_c: float | None
    c_same_state: bool | None


@njit(cache=True, error_model="numpy", _nrt=False)
def kernel_calls(p, s, inp, out, n_sub, calls):
    """``calls`` kernel calls of ``n_sub`` sub-steps from compiled code (no Python)."""
    for _ in range(calls):
        axis_step_nb(p, s, inp, out, n_sub)


@dataclass(frozen=True)
class CompiledLoopTimes:
    """ns per sub-step of the numba kernel and of the C port, each called once per PWM
    period from a compiled loop; ``same_state``: both ended with the same bits."""
    numba_ns: float
    c_ns: float
    same_state: bool


def time_compiled_loops(plant, cstep: CStep, seconds: float) -> CompiledLoopTimes:
    """Time the numba kernel and the C port on copies of ``plant``'s arrays (its inputs
    held) for ~``seconds``: batches of :data:`_BATCH` calls, alternating, so that both see
    the same load and the same stretch of trajectory; each figure is its fastest batch (the
    machine's other load only ever adds time)."""
    n = plant.sub_per_pwm
    k_arrays = (plant.params.copy(), plant.state.copy(), plant.inp.copy(), plant.out.copy())
    c_arrays = (plant.params.copy(), plant.state.copy(), plant.inp.copy(), plant.out.copy())
    best_k = best_c = float("inf")
    t_end = time.perf_counter() + seconds
    for batch in itertools.count():
        t0 = time.perf_counter_ns()
        kernel_calls(*k_arrays, n, _BATCH)
        k_ns = time.perf_counter_ns() - t0
        c_ns = cstep.time_calls(*c_arrays, n, _BATCH)
        if batch > 0:  # the first batch warms caches and branch predictors
            best_k, best_c = min(best_k, k_ns), min(best_c, c_ns)
            if time.perf_counter() >= t_end:
                break
    per_step = _BATCH * n
    return CompiledLoopTimes(numba_ns=best_k / per_step, c_ns=best_c / per_step,
                             same_state=bool((k_arrays[1] == c_arrays[1]).all()))


def time_kernel(plant, seconds: float) -> float:
    """ns per sub-step of ``plant``'s kernel called once per PWM period for ~``seconds``."""
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


def _child(config: Path, seconds: float, jit: bool, cache_dir: str | None = None) -> dict:
    env = dict(os.environ)
    if not jit:
        env["NUMBA_DISABLE_JIT"] = "1"
    if cache_dir is not None:
        env["NUMBA_CACHE_DIR"] = cache_dir
    res = subprocess.run([sys.executable, "-c", _PROBE, str(config), str(seconds)],
                         capture_output=True, text=True, env=env, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"benchmark child for {config} failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def cold_compile(config: Path) -> dict:
    """The probe's answer for a fresh process with an empty numba cache (the cache on,
    written as it compiles; a temporary folder): ``cold_start_s`` and ``cold_start_cpu_s``
    are then the cold compile's wall and CPU seconds up to the first kernel call."""
    with tempfile.TemporaryDirectory(prefix="hil-bench-cold-") as empty:
        return _child(config, 0.0, jit=True, cache_dir=empty)


def c_baseline() -> tuple[CStep | None, str | None]:
    """The C port, built and loaded; or (None, why not)."""
    try:
        return CStep(), None
    except (CCompilerMissing, RuntimeError, OSError) as err:
        return None, f"no C baseline, c_ns_per_step and ratio_to_c are null: {err}"


def bench_config(config: Path, seconds: float, ref_seconds: float,
                 cstep: CStep | None = None) -> PlantBench:
    """Measure one machine file (compiled, reference, cold start and compile; against
    ``cstep`` when given and it carries the config's models)."""
    from plant import Plant

    plant = Plant.from_file(config)
    plant.set_input(iq_ref_a=0.1 * plant.config.motor.current_max_a)
    loops = None
    if cstep is not None and cstep.supports(plant.params):
        loops = time_compiled_loops(plant, cstep, seconds)
    ns = time_kernel(plant, seconds)
    cold = _child(config, 0.0, jit=True)["cold_start_s"]
    ref = _child(config, ref_seconds, jit=False)["ns_per_step"]
    compiled = cold_compile(config)
    return PlantBench(config=config.stem, ns_per_step=ns, substep_s=plant.dt,
                      realtime_factor=plant.dt / (ns * 1e-9), reference_ns_per_step=ref,
                      speedup_vs_reference=ref / ns, sub_per_pwm=plant.sub_per_pwm,
                      cold_start_s=cold, cold_compile_s=compiled["cold_start_s"],
                      cold_compile_cpu_s=compiled["cold_start_cpu_s"],
                      c_ns_per_step=None if loops is None else loops.c_ns,
                      loop_ns_per_step=None if loops is None else loops.numba_ns,
                      ratio_to_c=None if loops is None else loops.numba_ns / loops.c_ns,
                      c_same_state=None if loops is None else loops.same_state)


def run(configs: list[Path], seconds: float, ref_seconds: float, progress=None,
        note: Callable[[str], None] = lambda message: print(message, file=sys.stderr)
        ) -> list[dict]:
    """Benchmark every config; returns the JSON-ready rows.

    Args:
        progress: receives each :class:`PlantBench` as it is done.
        note: receives the reason when there is no C baseline.
    """
    cstep, why_not = c_baseline()
    if why_not is not None:
        note(why_not)
    rows = []
    for cfg in configs:
        row = bench_config(cfg, seconds, ref_seconds, cstep)
        rows.append(asdict(row))
        if progress is not None:
            progress(row)
    return rows
