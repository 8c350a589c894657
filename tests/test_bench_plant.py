"""``hil bench plant``: the JSON rows it prints, with the C baseline beside the kernel.

The figures themselves are wall-clock times and are not asserted; the rows' shape, the
ratio's definition and the null baseline where the C port does not run are.
"""

import json
import subprocess
import sys

import pytest

from hil.bench.csubstep import compiler
from hil.bench.plant import c_baseline
from plant import Plant
from tests.conftest import CONFIGS


@pytest.mark.skipif(compiler() is None, reason="no C compiler on PATH: no C baseline to "
                    "report (apt-get install gcc)")
def test_bench_plant_reports_the_c_step_and_the_ratio_to_it():
    """Arrow 500 X: C and numba figures, ratio_to_c = loop / C, the two timed runs ending
    in the same state; cold start and cold compile reported.  EMPS (first-order motor,
    rigid mechanics, not ported) is one the C port does not carry, so its C figures are
    null (bench_config times the C step only where ``supports`` is true; the CLI is run
    on the Arrow alone: each file costs a cold compile)."""
    res = subprocess.run([sys.executable, "-m", "hil.cli", "bench", "plant", "--json",
                          "--config", str(CONFIGS / "arrow500_x.toml"),
                          "--seconds", "0.05", "--ref-seconds", "0.05"],
                         capture_output=True, text=True, timeout=300, check=True)
    (arrow,) = json.loads(res.stdout)
    assert arrow["config"] == "arrow500_x"
    assert arrow["c_ns_per_step"] > 0.0 and arrow["loop_ns_per_step"] > 0.0
    assert arrow["ratio_to_c"] == arrow["loop_ns_per_step"] / arrow["c_ns_per_step"]
    assert arrow["c_same_state"] is True  # timed from the same state: still the same bits
    assert arrow["ns_per_step"] > 0.0
    assert arrow["cold_start_s"] > 0.0
    assert arrow["cold_compile_s"] > 0.0 and arrow["cold_compile_cpu_s"] > 0.0
    cstep, why = c_baseline()
    assert why is None
    assert cstep.supports(Plant.from_file(CONFIGS / "arrow500_x.toml").params)
    assert not cstep.supports(Plant.from_file(CONFIGS / "emps.toml").params)


def test_without_a_compiler_there_is_no_baseline_and_the_reason_is_given(tmp_path,
                                                                         monkeypatch):
    """PATH without a compiler (and no $CC): the baseline is None and the reason names
    the missing compiler."""
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CC", raising=False)
    cstep, why = c_baseline()
    assert cstep is None
    assert "no C compiler" in why and "ratio_to_c" in why

