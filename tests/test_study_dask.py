"""``hil study`` on real Dask clusters: a two-worker LocalCluster, a ``dask scheduler`` and
``dask worker`` started as separate processes (as docs/study.md says), a study killed
halfway and resumed, the Ishigami function's Sobol indices (analytic) and tuning studies
with known optima through the same pipeline, and a tuned machine file that loads.

Every study runs as its own process (``python3 -m hil.study``, the same code as ``hil
study``); waits are bounded and every process started here is reaped.
"""

import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import dask
import numpy as np
import pyarrow.parquet as pq
import pytest
from distributed import Client
from scipy.stats import qmc

from hil.controller.config import load_controller
from hil.measure.runs import position_step
from hil.study.analytic import ishigami_indices
from hil.study.outputs import step_metrics
from hil.study.run import dask_client
from hil.study.spec import load_study
from hil.study.tuning import robust_values
from plant.config import load_machine

ROOT = Path(__file__).resolve().parents[1]
STUDIES = ROOT / "configs" / "studies"
CI_SMALL = STUDIES / "ci_small.toml"
ARROW = ROOT / "configs" / "arrow500_x.toml"
STUDY_TIMEOUT_S = 600


def hil_study(*args: str, timeout: float = STUDY_TIMEOUT_S) -> subprocess.CompletedProcess:
    """``python3 -m hil.study ARGS`` to its end (bounded)."""
    return subprocess.run([sys.executable, "-m", "hil.study", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT, check=False)


def run_json(*args: str) -> dict:
    res = hil_study(*args, "--json")
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout)


def table(out: Path):
    return pq.read_table(out / "results").sort_by("sample_id")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop(proc: subprocess.Popen) -> None:
    """SIGTERM the process group, SIGKILL after 30 s; reap."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)


@pytest.fixture(scope="module")
def dask_cluster():
    """``dask scheduler`` and ``dask worker`` (two worker processes, one thread each) on
    127.0.0.1, started as separate processes; yields the scheduler address.  The module's
    pipeline and tuning studies share it (an existing cluster, as a user's would be); the
    LocalCluster path has its own tests (the small study, resume, SIGTERM, the bench)."""
    address = f"tcp://127.0.0.1:{free_port()}"
    port = address.rsplit(":", 1)[1]
    procs = [subprocess.Popen(["dask", "scheduler", "--host", "127.0.0.1", "--port", port,
                               "--no-dashboard"], start_new_session=True,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        procs.append(subprocess.Popen(["dask", "worker", address, "--nworkers", "2",
                                       "--nthreads", "1", "--no-dashboard"],
                                      start_new_session=True, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL))
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)
        yield address
    finally:
        for proc in reversed(procs):
            stop(proc)


def test_small_study_same_numbers_on_local_cluster_and_separate_dask_processes(tmp_path,
                                                                             dask_cluster):
    # one local worker against a separately started two-worker cluster: other worker
    # counts and other processes, the same numbers (the resume test runs two local workers);
    # tasks of 2 samples, so that both remote workers get some whatever the sizing does
    runs = {"one local worker": ["--workers", "1"],
            "dask scheduler + dask worker": ["--scheduler", dask_cluster, "--task-size", "2"]}
    tables = {}
    for name, args in runs.items():
        out = tmp_path / name.replace(" ", "_")
        summary = run_json(str(CI_SMALL), "--out", str(out), *args)
        assert (summary["samples"], summary["failed"]) == (16, 0), name
        tables[name] = table(out)
    workers = {name: set(t["worker"].to_pylist()) for name, t in tables.items()}
    assert len(workers["one local worker"]) == 1
    assert len(workers["dask scheduler + dask worker"]) == 2
    columns = ["sample_id", "table.mass_kg", "motor.torque_constant_nm_per_a", "rise_time_s",
               "lag_50pct_s", "overshoot_pct", "settling_time_s", "curve_0"]
    reference = tables["one local worker"].select(columns)
    for name, t in tables.items():
        assert t.select(columns).equals(reference), f"{name} gave other numbers"
    # the parameters: scrambled Sobol' points of seed 7 through the +-10 % tolerances
    u = qmc.Sobol(2, scramble=True, seed=7).random(16)
    assert reference["table.mass_kg"].to_numpy() == pytest.approx(315.0 + 70.0 * u[:, 0])
    assert reference["motor.torque_constant_nm_per_a"].to_numpy() == pytest.approx(
        1.215 + 0.27 * u[:, 1])
    # one sample again, here, through the machine-file loader's own overrides
    k = 5
    cfg = load_machine(ARROW, {"table": {"mass_kg": reference["table.mass_kg"][k].as_py()},
                               "motor": {"torque_constant_nm_per_a": reference[
                                   "motor.torque_constant_nm_per_a"][k].as_py()}})
    window_s = load_study(CI_SMALL).experiments[0].opts.duration_s
    res = position_step(cfg, 0.25, 0.0005, window_s)
    post = res.t_s >= 0.0
    m = step_metrics(res.t_s[post], res.response[post], 0.25, 0.0005, 2.0)
    assert reference["lag_50pct_s"][k].as_py() == m.lag_50pct_s
    assert reference["rise_time_s"][k].as_py() == m.rise_time_s


def _event_loop_module(dask_worker) -> str:
    return type(dask_worker.loop.asyncio_loop).__module__


# the module's separately started cluster may hold the dashboard's port: Dask then takes
# another one, and the note gives that link
@pytest.mark.filterwarnings("ignore:Port 8787 is already in use")
def test_the_local_cluster_a_study_starts_has_quiet_workers_on_uvloop():
    """The LocalCluster a study starts (hil.study.run.dask_client): its workers' profiler
    is off and their event loop is uvloop's, the settings that cut the loop's work per
    task; the dashboard's link is given."""
    notes = []
    with dask_client(None, 1, notes.append) as client:
        (loop_module,) = client.run(_event_loop_module).values()
        (profile,) = client.run(dask.config.get, "distributed.worker.profile.enabled").values()
    assert loop_module.startswith("uvloop"), loop_module
    assert profile is False
    assert "dashboard http://127.0.0.1:" in notes[0]


def test_study_killed_halfway_resumes_without_recomputing(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "hil.study", str(CI_SMALL), "--out",
                             str(out), "--workers", "2", "--task-size", "1"], cwd=ROOT,
                            start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + STUDY_TIMEOUT_S
        while len(list((out / "results").glob("part-*.parquet"))) < 3:
            assert proc.poll() is None, "the study ended before it could be killed"
            assert time.monotonic() < deadline, "no results within the time limit"
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGKILL)  # the study, its cluster and its workers
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)
    first = {f.name: (f.stat().st_mtime_ns, hashlib.sha256(f.read_bytes()).hexdigest())
             for f in (out / "results").glob("part-*.parquet")}
    done = set(table(out)["sample_id"].to_pylist())
    assert 3 <= len(done) < 16, "kill the study halfway"
    restart = time.time()
    summary = run_json(str(CI_SMALL), "--out", str(out), "--workers", "2")
    assert summary["run"]["ran"] == 16 - len(done)
    rows = table(out)
    assert rows["sample_id"].to_pylist() == list(range(16))  # every sample once
    for name, stamp in first.items():  # the first run's files untouched
        f = out / "results" / name
        assert (f.stat().st_mtime_ns, hashlib.sha256(f.read_bytes()).hexdigest()) == stamp
    started = [t.timestamp() for t in rows["started_utc"].to_pylist()]
    for sample_id, t in zip(rows["sample_id"].to_pylist(), started):
        assert (t < restart) == (sample_id in done), f"sample {sample_id}"


def test_sigterm_stops_the_study_and_its_workers(tmp_path):
    """SIGTERM to the study process alone: it exits 130 with what finished kept, and its
    LocalCluster's worker processes end with it (none is left in its process group)."""
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "hil.study", str(CI_SMALL), "--out",
                             str(out), "--workers", "2", "--task-size", "1"], cwd=ROOT,
                            start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + STUDY_TIMEOUT_S
        while not list((out / "results").glob("part-*.parquet")):
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=60)
    assert proc.returncode == 130
    assert "run the same command again to resume" in err
    deadline = time.monotonic() + 30
    while True:
        try:
            os.killpg(proc.pid, 0)  # is any process of the group left?
        except ProcessLookupError:
            break
        if time.monotonic() > deadline:
            os.killpg(proc.pid, signal.SIGKILL)
            pytest.fail("worker processes outlived the study")
        time.sleep(0.1)
    assert table(out).num_rows >= 1


def test_ishigami_sobol_indices_through_the_pipeline(tmp_path, dask_cluster):
    """A pipeline check (analytic function, no physics): spec, Saltelli design, Dask
    tasks, Parquet store and SALib give the closed-form indices."""
    out = tmp_path / "out"
    summary = run_json(str(STUDIES / "pipeline_ishigami.toml"), "--out", str(out),
                       "--scheduler", dask_cluster)
    assert summary["samples"] == 1024 * 5
    got = summary["indices"]["y"]["parameters"]
    first, total = ishigami_indices()
    for i, name in enumerate(("analytic.x1", "analytic.x2", "analytic.x3")):
        assert got[name]["S1"] == pytest.approx(first[i], abs=0.04), name
        assert got[name]["ST"] == pytest.approx(total[i], abs=0.04), name
        # and the 95 % intervals SALib reports are of a size that says so
        assert got[name]["S1_conf"] < 0.1 and got[name]["ST_conf"] < 0.1
    assert (out / "sensitivity.png").stat().st_size > 0


def test_morris_indices_of_a_linear_function_through_the_pipeline(tmp_path, dask_cluster):
    """A pipeline check: Morris elementary effects of y = x1 + 2 x2 + 0 x3, x_i uniform on
    [-1, 1], are the coefficients times the range (2): mu* = 2, 4, 0 and sigma 0."""
    spec = tmp_path / "morris.toml"
    spec.write_text("""
[study]
name = "Morris, linear"
method = "sensitivity"
design = "morris"
seed = 2
samples = 12
[experiment]
kind = "analytic"
function = "linear"
[vary.analytic]
x1 = { uniform = [-1.0, 1.0] }
x2 = { uniform = [-1.0, 1.0] }
x3 = { uniform = [-1.0, 1.0] }
""")
    summary = run_json(str(spec), "--out", str(tmp_path / "out"), "--scheduler", dask_cluster)
    assert summary["samples"] == 12 * 4
    got = summary["indices"]["y"]["parameters"]
    for name, mu in (("analytic.x1", 2.0), ("analytic.x2", 4.0), ("analytic.x3", 0.0)):
        assert got[name]["mu_star"] == pytest.approx(mu, abs=1e-9)
        assert got[name]["sigma"] == pytest.approx(0.0, abs=1e-9)
    assert summary["outputs"] == {}  # a Morris grid is not a sample of the distributions


def test_tuning_finds_the_constrained_optimum(tmp_path, dask_cluster):
    out = tmp_path / "out"
    summary = run_json(str(STUDIES / "pipeline_tuning.toml"), "--out", str(out),
                       "--scheduler", dask_cluster)
    best = summary["tuning"]["best"]
    x1, x2 = best["params"]["analytic.x1"], best["params"]["analytic.x2"]
    assert x1 + x2 <= 2.0  # feasible
    assert np.hypot(x1 - 0.5, x2 - 1.5) < 0.25  # the projection of (1, 2) onto x1 + x2 = 2
    assert 0.5 <= best["values"]["y"] < 0.6
    assert summary["tuning"]["trials"] == 200 and table(out).num_rows == 200
    assert (out / "pareto.png").stat().st_size > 0


def test_robust_tuning_finds_the_worst_case_optimum(tmp_path, dask_cluster):
    spec = STUDIES / "pipeline_tuning_robust.toml"
    x3 = robust_values(load_study(spec))[:, 0]
    out = tmp_path / "out"
    summary = run_json(str(spec), "--out", str(out), "--scheduler", dask_cluster)
    best = summary["tuning"]["best"]
    # worst over the 8 machines of (x1 - 1 - x3)^2 is least at the middle of x3's values
    assert best["params"]["analytic.x1"] == pytest.approx(1.0 + (x3.max() + x3.min()) / 2,
                                                          abs=0.05)
    assert best["params"]["analytic.x2"] == pytest.approx(2.0, abs=0.1)
    assert best["values"]["y"] == pytest.approx(((x3.max() - x3.min()) / 2) ** 2, abs=0.02)
    assert table(out).num_rows == 200 * 8


def test_tuned_machine_file_loads_and_holds_the_best_trial(tmp_path, dask_cluster):
    """K_v of the Arrow 500 X tuned for the shortest lag with the overshoot bounded: the
    lag falls as K_v rises (linear theory: the P loop's time constant is 1/K_v), so the
    best trial is the largest feasible K_v; its machine file loads and says so."""
    spec = tmp_path / "kv.toml"
    spec.write_text(f"""
[study]
name = "K_v for the shortest lag"
machine = "{ARROW}"
method = "tuning"
seed = 1
[experiment]
kind = "step"
at_mm = 250.0
duration_s = 0.12
outputs = ["lag_50pct_s", "overshoot_pct"]
[tune.controller]
kv_m_min_per_mm = {{ uniform = [1.0, 4.0] }}
[tuning]
trials = 8
sampler = "random"
minimize = ["lag_50pct_s"]
[tuning.constraints]
overshoot_pct = {{ max = 5.0 }}
""")
    out = tmp_path / "out"
    summary = run_json(str(spec), "--out", str(out), "--scheduler", dask_cluster)
    trials = summary["tuning"]["trial_rows"]
    kv = np.array([t["params"]["controller.kv_m_min_per_mm"] for t in trials])
    lag = np.array([t["values"]["lag_50pct_s"] for t in trials])
    assert np.all(np.diff(lag[np.argsort(kv)]) < 0)
    feasible = [t for t in trials if t["feasible"]]
    best = max(feasible, key=lambda t: t["params"]["controller.kv_m_min_per_mm"])
    assert summary["tuning"]["best"]["trial"] == best["trial"]
    path = out / "best.toml"
    text = path.read_text()
    assert "tuned by hil study kv.toml" in text and "(was 2.0)" in text
    assert "# seed 000: 8 kHz IGBT carrier" in text  # the file's other comments kept
    cfg = load_machine(path)
    assert load_controller(cfg).kv_m_min_per_mm == pytest.approx(
        best["params"]["controller.kv_m_min_per_mm"], rel=1e-6)


def test_bench_study_reports_both_cluster_sizes():
    """``hil bench study`` on a small load: every sample ran in every round, on one and on
    two workers, and in hil study's own task size; its ratios are the ones its figures
    give (no timing is asserted)."""
    res = subprocess.run([sys.executable, "-m", "hil.bench.study", "--samples", "8",
                          "--seconds", "0.1", "--rounds", "2", "--json"], capture_output=True,
                         text=True, timeout=STUDY_TIMEOUT_S, cwd=ROOT, check=False)
    assert res.returncode == 0, res.stderr[-3000:]
    r = json.loads(res.stdout)
    one, two = r["one_worker"], r["two_workers"]
    assert len(one["rounds"]) == len(two["rounds"]) == 2
    assert all((x["samples"], x["failed"], x["distinct_workers"], x["tasks"]) == (8, 0, 1, 8)
               for x in one["rounds"])
    assert all((x["samples"], x["failed"], x["distinct_workers"]) == (8, 0, 2)
               for x in two["rounds"])
    # hil study's size on one worker: samples of 0.1 s (a few ms each) so many that Dask's
    # 10 ms per task stays within 5 % of theirs, but no fewer tasks than workers: one task
    assert r["study_task_size"] == 8
    assert all((x["samples"], x["failed"], x["task_size"], x["tasks"]) == (8, 0, 8, 1)
               for x in one["study_task_size_rounds"])
    assert r["bare_over_plant"] == pytest.approx(r["bare_s_per_sample"]
                                                 / r["plant_kernel_s_per_sample"])
    assert 0.0 < r["plant_kernel_s_per_sample"] < r["bare_s_per_sample"]
    assert r["task_vs_bare_pct"] == pytest.approx(
        100 * (r["bare_in_task_s_per_sample"] / r["bare_s_per_sample"] - 1))
    assert one["wall_s"] == sorted(x["wall_s"] for x in one["rounds"])[1]
    assert r["scaling_ratio"] == pytest.approx(two["samples_per_s"] / (2 * one["samples_per_s"]))
    # on two workers too, in hil study's size there (no fewer tasks than workers: two)
    assert r["study_task_size_two_workers"] == 4
    assert all((x["samples"], x["failed"], x["task_size"], x["tasks"]) == (8, 0, 4, 2)
               for x in two["study_task_size_rounds"])
    own = [[x["samples_per_s"] for x in c["study_task_size_rounds"]] for c in (one, two)]
    assert r["scaling_ratio_study_task_size"] == pytest.approx(
        np.median(own[1]) / (2 * np.median(own[0])))
    # the first bare run, then one after each round; each round against its neighbours
    bares = [None, *one["bare_s_after_rounds"]]
    assert len(bares) == 3 and len(r["overhead_pct_per_round"]) == 2
    last = 0.5 * (bares[1] + bares[2])
    assert r["overhead_pct_per_round"][1] == pytest.approx(
        100 * (one["rounds"][1]["wall_s"] / 8 - last) / last)
    assert r["overhead_pct"] == pytest.approx(np.median(r["overhead_pct_per_round"]))
    assert 0.0 < one["worker_compute_s"] < one["wall_s"]
    # the event loop's CPU is read on its own thread: some per task, less than the task
    assert all(0.0 < x["worker_loop_cpu_s"] < x["wall_s"] for x in one["rounds"])
    floors = one["dask_floor_rounds"]
    assert len(floors) == 2 and all(f["worker_loop_cpu_s"] > 0.0 for f in floors)
    assert 0.0 < r["machine_build_s_per_sample"] < r["bare_s_per_sample"]
    assert r["dask_floor_pct"] == pytest.approx(
        100 * np.median([f["worker_loop_cpu_s"] for f in floors]) / r["bare_s_per_sample"])
