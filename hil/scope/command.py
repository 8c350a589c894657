"""``hil scope RUN_FOLDER [--port N]``: the run's status and signals in a browser.

A Bokeh server on 127.0.0.1 in this process, apart from the emulator's: it reads the run
folder's files (the recording, flushed every 0.25 s, and the events), never the loop's
memory, talks to its process only to send the injections of the page's panel to the run's
injection port (``hil run --inject-port``, :mod:`hil.scope.inject_panel`), and keeps off
the loop's CPU where it may run elsewhere (as the recording's writer does).  Each browser
tab gets its own page (:mod:`hil.scope.page`).  It prints ``hil scope:
http://127.0.0.1:PORT/`` once it serves, and runs until Ctrl-C (SIGINT) or SIGTERM.
"""

import argparse
import os
import signal
import socket
import sys
from pathlib import Path

from hil.runtime.run_folder import RECORDING


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil scope``."""
    p.add_argument("run", help="run folder of hil run --record DIR (live or finished), or "
                   "the --out folder of hil soak or hil demo")
    p.add_argument("--port", type=int, default=5006,
                   help="TCP port on 127.0.0.1 (default %(default)s; 0: any free one)")


def _keep_off_the_loop(meta: dict) -> None:
    """Run on the CPUs but the run's loop's (``--cpu``, by default the last one when it runs
    in real time), where there are others."""
    from hil.rt.scheduling import last_cpu

    runtime = meta.get("runtime", {})
    loop_cpu = runtime.get("cpu")
    if loop_cpu is None and runtime.get("realtime"):
        loop_cpu = last_cpu()
    others = os.sched_getaffinity(0) - {loop_cpu}
    if loop_cpu is not None and others:
        os.sched_setaffinity(0, others)


def _free_port() -> int:
    """A TCP port on 127.0.0.1 free now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_from_args(args: argparse.Namespace) -> int:
    folder = Path(args.run)
    if not (folder / RECORDING).is_file() and (folder / "emulator" / RECORDING).is_file():
        folder = folder / "emulator"  # hil soak's --out, hil demo's: the run is in there
    if not (folder / RECORDING).is_file():
        raise FileNotFoundError(f"{folder}: no {RECORDING}: not a run folder, or the run "
                                "has not started recording yet")
    if not 0 <= args.port <= 65535:
        raise KeyError(f"--port {args.port}: 0..65535")
    from bokeh.application import Application
    from bokeh.application.handlers import FunctionHandler
    from bokeh.server.server import Server

    from hil.runtime.record_reader import Recording, RecordingError
    from hil.scope.page import make_app

    try:
        _keep_off_the_loop(Recording(folder).meta)  # an unreadable recording says so here
    except RecordingError as e:
        print(f"hil scope: {e}", file=sys.stderr)
        return 2
    port = args.port or _free_port()
    try:
        # the page's websocket comes from the address the browser was given, either name
        server = Server({"/": Application(FunctionHandler(make_app(folder)))},
                        address="127.0.0.1", port=port, num_procs=1,
                        allow_websocket_origin=[f"127.0.0.1:{port}", f"localhost:{port}"])
    except OSError as e:  # the port is taken
        print(f"hil scope: cannot serve on 127.0.0.1:{port}: {e} (another --port?)",
              file=sys.stderr)
        return 2
    server.start()
    print(f"hil scope: http://127.0.0.1:{server.port}/ ({folder})", flush=True)

    def stop(signum, frame):
        server.io_loop.add_callback_from_signal(server.io_loop.stop)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    server.io_loop.start()
    print("hil scope: stopped", file=sys.stderr, flush=True)
    return 0
