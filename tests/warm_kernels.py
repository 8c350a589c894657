"""Fill numba's on-disk cache for the suite while its first tests run (``conftest.py``
starts this in a process of its own on a cold cache).

The cache folder is keyed on a hash of every source file (:mod:`plant._cache`), so on a
fresh clone -- CI's case -- every kernel compiles in the suite, one after another on the
suite's core, more than a minute of it; the machine has a second core.  This compiles the
kernels most tests load, in the order the suite meets them roughly: the lock-step
simulation of the machines the tests run (plant, drive paths, the NC's tick), and for each
the emulator's compiled UDP loop and the controller's, as ``hil run`` and ``hil
controller`` build them.  A kernel the suite needs before this has cached it is compiled
there as before: nothing waits for this process, and it changes no result.

Run: ``python -m tests.warm_kernels`` (prints what it warmed and how long it took); one
machine's: ``python -m tests.warm_kernels MACHINE_FILE``.
"""

import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tests.conftest import CONFIGS, ROOT

#: machine files, in the order they are warmed
MACHINES = (CONFIGS / "arrow500_x.toml", CONFIGS / "machines" / "arrow500_xy_2khz.toml",
            CONFIGS / "machines" / "geiss_5axis.toml")
PROGRAM = ROOT / "programs" / "demo_moves.nc"
#: written in the cache folder once every kernel above is there
MARKER = "suite-kernels-warm"


def warm_machine(config: Path, folder: Path) -> None:
    """The kernels of ``config``'s lock-step, emulator loop and controller loop."""
    from hil.runtime.common import StopFlag
    from hil.runtime.controller_proc import ControllerProcess, ControllerRunConfig
    from hil.runtime.controller_steady import ControllerSteady
    from hil.runtime.emulator import Emulator
    from hil.runtime.emulator_config import RuntimeConfig
    from hil.sim import warm
    from io_adapters import open_endpoint
    from plant.machines import load_machine_set

    machine = load_machine_set(config)
    warm(machine)
    rc = RuntimeConfig(config, "udp://127.0.0.1:0", run_dir=folder, realtime=False)
    emulator = Emulator(rc, machine, log=lambda message: None)
    url = emulator.open()
    try:
        proc = ControllerProcess(ControllerRunConfig(config, url, PROGRAM, realtime=False),
                                 StopFlag())
        proc.ep = open_endpoint(url, "controller")
        try:
            steady = ControllerSteady.for_process(proc)
            if steady is not None:
                steady.warm()
        finally:
            proc.ep.close()
    finally:
        emulator.endpoint.close()


def main(argv: list[str]) -> int:
    """Every machine of :data:`MACHINES`, each in a process of its own (``argv``: the
    machine file such a process warms): a process that compiles the kernels of one machine
    and then another's caches code for the second that is slower than its own process
    would compile (seen: the five-axis loopback's compiled loops missing ticks after the
    Arrow's were compiled first in the same process), and ``hil run`` serves one machine."""
    if argv:
        with tempfile.TemporaryDirectory(prefix="warm-kernels-") as tmp:
            warm_machine(Path(argv[0]), Path(tmp))
        return 0
    from plant._cache import configure

    marker = configure() / MARKER
    if marker.exists():
        return 0
    start = time.monotonic()
    for config in MACHINES:
        subprocess.run([sys.executable, "-m", "tests.warm_kernels", str(config)], check=True)
        print(f"{config.name}: warm at {time.monotonic() - start:.1f} s", flush=True)
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.write_text(f"{time.monotonic() - start:.1f} s\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
