"""``hil bench can``: the same CSP program at a 1 kHz cycle over CAN, over UDP and in the
lock-step simulation, on the Arrow 500 X at 2 kHz PWM (two drive cycles per SYNC).

References: the lock-step run is its own reference (difference 0); the three runs carry
the same targets, so their following errors are of one size -- v / K_v at the move's top
speed (50 mm/s, 1/K_v = 30 ms: 1.5 mm) -- and the links' differ from the lock-step's by
what the timing of a link adds: a cycle late is 25 µm at that speed, and a loop that
overruns (a tick skipped: the plant falls behind the master) adds more; bounded here by
half the size, as a check that the bench compares like with like, not of the link.  With
the master's velocity offset (60B1h) as speed feed-forward the v / K_v part is gone: what
is left is the speed loop's lag while the axis accelerates, under a tenth of it in the
lock-step and under a quarter over CAN.
"""

import argparse
import json

import pytest

from hil.bench.can import add_arguments, program_targets, run_from_args
from tests.runtime_helpers import SLOW_2KHZ, machine_variant

MOVE = "N10 G90 G71\nN20 G1 X5 F3000\nN30 M30\n"


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    return machine_variant(tmp_path_factory.mktemp("cfg") / "arrow_2khz.toml", SLOW_2KHZ)


def test_program_is_sampled_once_per_sync(config, tmp_path):
    program = tmp_path / "move.nc"
    program.write_text(MOVE)
    prog = program_targets(config, program, 1000.0)
    assert prog.ticks_per_sync == 2 and prog.sync_s == 1e-3
    assert prog.deltas[-1] == 5 / 10 * 4194304  # 5 mm of a 10 mm lead
    assert (prog.deltas[1:] >= prog.deltas[:-1]).all()


#: bench runs at most: the CAN run's master is a Python process whose SYNC jitters, and on
#: a loaded machine an early SYNC finds the drive's answers still waiting for the bus
#: (75 % of it in each 1 ms cycle), a timing fault the feed-forward check would read as
#: the feed-forward's; such a fault does not repeat in the next run
ATTEMPTS = 3


def test_hil_bench_can_prints_the_five_runs(config, tmp_path, multicast_group, capsys):
    program = tmp_path / "move.nc"
    program.write_text(MOVE)
    group, port = multicast_group
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--config", str(config), "--program", str(program), "--group",
                              group, "--port", str(port), "--json"])
    failures = []
    for attempt in range(1, ATTEMPTS + 1):
        assert run_from_args(args) == 0
        runs = json.loads(capsys.readouterr().out)["runs"]
        assert set(runs) == {"lockstep", "can", "udp", "lockstep_ff", "can_ff"}
        ls = runs["lockstep"]
        assert ls["difference_to_lockstep_max_um"] == 0.0
        assert 1000 < ls["fe_max_um"] < 2000  # v / K_v at 50 mm/s: 1.5 mm
        for name in ("can", "udp"):
            row = runs[name]
            print(name, row)
            assert row["fe_max_um"] == pytest.approx(ls["fe_max_um"], rel=0.5), name
            assert row["difference_to_lockstep_max_um"] < 0.5 * ls["fe_max_um"], name
            assert row["ticks"] > 0 and row["overruns"] >= 0
        for name in ("can", "can_ff"):
            assert 0 < runs[name]["bus_load_mean"] <= runs[name]["bus_load_max"] <= 1.0
        assert 0 < runs["can"]["bus_plan_load"] < 1
        ff, can_ff = runs["lockstep_ff"], runs["can_ff"]
        print("lockstep_ff", ff, "\ncan_ff", can_ff)
        assert ff["difference_to_lockstep_max_um"] == 0.0
        assert ff["fe_max_um"] < 0.1 * ls["fe_max_um"]  # 85 against 1430 µm (2026-11-29)
        if (can_ff["fe_max_um"] < 0.25 * runs["can"]["fe_max_um"]
                and can_ff["difference_to_lockstep_max_um"] < 0.5 * ls["fe_max_um"]):
            break
        failures.append(f"attempt {attempt}: can {runs['can']}, can_ff {can_ff}")
    else:
        pytest.fail("the feed-forward's gain over CAN did not show in any run:\n"
                    + "\n".join(failures))
