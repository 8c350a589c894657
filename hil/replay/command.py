"""The ``hil replay`` command: replay a run folder, print the comparison's line.

Exit status: 0 when the replay matches the recording, 1 when it does not, 2 when the run
folder cannot be replayed (the reason printed)."""

import argparse
import json

from hil.replay.machine_files import ReplayError
from hil.replay.replay import TOLERANCE, replay_run
from hil.runtime.common import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, eprint


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil replay``."""
    p.add_argument("run", help="run folder of hil run (--record DIR)")
    p.add_argument("--tolerance", type=float, default=TOLERANCE,
                   help="largest relative difference of a match (default %(default)g)")
    p.add_argument("--json", action="store_true", help="the result as JSON on stdout")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil replay``: returns the exit status."""
    try:
        result = replay_run(args.run, args.tolerance)
    except ReplayError as e:
        eprint(f"hil replay: {e}")
        return EXIT_BAD_INPUT
    print(json.dumps(result.as_dict(), indent=1) if args.json else f"hil replay: "
          f"{result.line()}")
    return EXIT_OK if result.matches else EXIT_FAILED
