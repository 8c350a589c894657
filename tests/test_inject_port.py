"""The bench's injection port (``hil run --inject-port``, io_adapters/inject_port.py) and
the scope page's checks before it sends (hil/scope/inject_panel.py): what is not a
well-formed INJECT is counted and dropped, a request naming no axis of the machine is
refused with an event, every request taken is recorded with its source ``bench``, and a
setting that does not check never leaves the page."""

import json
import math
import socket
import threading
import time

import msgpack
import pytest

from hil.runtime.record_reader import Recording
from io_adapters import Setpoint
from io_adapters.base import AdapterConfigError, AdapterError
from io_adapters.codec import encode, encode_hello, encode_inject
from io_adapters.inject_port import (
    MAX_WAITING,
    InjectClient,
    InjectPort,
    header,
    parse_address,
)
from io_adapters.messages import InjectRequest
from tests.runtime_helpers import ARROW, SLOW_2KHZ, Children, machine_variant, terminate

#: longest wait for a datagram's count or an event, s
WAIT_S = 20.0
GOOD = InjectRequest(0, "friction_growth", {"growth_pct": 20.0, "ramp_s": 0.1})


def _until(what: str, check, timeout: float = WAIT_S):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = check()
        if value:
            return value
        time.sleep(0.05)
    pytest.fail(f"{what} not within {timeout} s")


def _stranger_datagrams() -> dict[str, list[bytes]]:
    """Datagrams the port must count and drop, by the counter they belong in."""
    return {"malformed": [b"", b"\x00not msgpack", msgpack.packb([1, 2, 3]),
                          msgpack.packb((2, 5, 0, 0, 0, "friction_growth", {"a": 1.0})),
                          msgpack.packb((1, 5, 0, 0, 0, "friction_growth", {})),
                          msgpack.packb((1, 5, 0, 0, 300, "friction_growth", {"a": 1.0}))],
            "foreign": [encode(Setpoint(), 7, 0), encode_hello(7, 0)],
            "refused_nonfinite": [encode_inject(7, 0, InjectRequest(
                0, "friction_growth", {"growth_pct": math.nan}))]}


def test_the_port_counts_and_drops_what_is_not_a_well_formed_inject():
    """Over real sockets: strangers' bytes are malformed, a setpoint or a HELLO (meant for
    a controller's link) foreign, an INJECT with a NaN refused; only the well-formed
    INJECT is queued, as sent.  Closing stops the receive thread (twice is harmless)."""
    strangers = _stranger_datagrams()
    with InjectPort(0) as port, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
        port.start()
        assert any(t.name == "hil-inject-port" for t in threading.enumerate())
        for datagrams in strangers.values():
            for d in datagrams:
                raw.sendto(d, port.address)
        with InjectClient(port.address) as client:
            client.send(GOOD)
        total = sum(map(len, strangers.values())) + 1
        _until("every datagram counted", lambda: port.stats.datagrams == total)
        assert list(port.requests) == [GOOD]
        s = port.stats
        assert (s.malformed, s.foreign, s.refused_nonfinite, s.injections, s.overflow) == (
            len(strangers["malformed"]), len(strangers["foreign"]), 1, 1, 0), s
        port.close()
    assert not any(t.name == "hil-inject-port" for t in threading.enumerate())


def test_the_port_holds_at_most_max_waiting_requests():
    """Requests beyond MAX_WAITING not taken by the loop are counted in overflow (what a
    page sends is one at a time; a flood is bounded)."""
    with InjectPort(0) as port:  # no thread: the datagrams handed in directly
        for _ in range(MAX_WAITING + 3):
            port.take(encode_inject(1, 0, GOOD))
        assert len(port.requests) == MAX_WAITING
        assert (port.stats.injections, port.stats.overflow) == (MAX_WAITING, 3)


def test_beyond_its_datagrams_a_second_the_port_waits_and_then_reads_on():
    """Eight datagrams at once to a port reading five a second: it pauses once its five
    are read, and reads the other three after (the kernel held them meanwhile)."""
    with InjectPort(0, max_per_s=5) as port, InjectClient(port.address) as client:
        port.start()
        for _ in range(8):
            client.send(GOOD)
        _until("every datagram read", lambda: port.stats.datagrams == 8)
        assert port.stats.paused >= 1 and port.stats.overflow == 0
        assert list(port.requests) == [GOOD] * 8


def test_header_reads_the_first_bytes_of_every_message_of_the_wire():
    """(version, kind) from the array's first elements, whatever the array's size (a
    fixarray, an array 16 for a Feedback of 17 elements); None for anything else."""
    from io_adapters import Feedback
    assert header(encode(Setpoint(), 1, 0)) == (1, 1)
    assert header(encode(Feedback(), 1, 0)) == (1, 2)
    assert header(encode_inject(1, 0, GOOD)) == (1, 5)
    assert header(b"") is None and header(b"\x94\x01") is None
    assert header(b"\x00\x01\x02") is None and header(msgpack.packb([1, 2, 3])) is None


def test_only_a_loopback_port_is_addressed():
    assert parse_address("127.0.0.1:41000") == ("127.0.0.1", 41000)
    for text in ("10.0.0.1:41000", "127.0.0.1:0", "localhost:41000", "127.0.0.1"):
        with pytest.raises(AdapterConfigError):
            parse_address(text)
    with pytest.raises(AdapterConfigError):
        InjectPort(70000)
    with InjectPort(0) as port, pytest.raises(AdapterError, match="cannot bind"):
        InjectPort(port.address[1])


def _inject_events(run) -> list[dict]:
    """The recording's inject events so far, oldest first."""
    try:
        ev = Recording(run).events()
    except (OSError, ValueError):  # not there yet
        return []
    rows = [{k: v[i] for k, v in ev.items()} for i in range(ev["tick"].size)]
    return [e for e in rows if e["source"] == "inject"]


def _from_bench(e: dict) -> bool:
    """An inject event of a request of the injection port (its ramp's end names none)."""
    return (e["reason"].startswith("bench:") or e["reason"].endswith("(bench)")
            or (e["kind"] == "request" and json.loads(e["reason"])["source"] == "bench"))


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    return machine_variant(tmp_path_factory.mktemp("cfg") / "arrow_2khz.toml", SLOW_2KHZ)


def test_hil_run_takes_the_ports_injections_and_records_them(config, tmp_path):
    """hil run --inject-port 0 (no controller: the injector acts all the same): its
    metadata names the port; garbage and a setpoint sent there are counted and dropped; an
    INJECT naming axis 3 of this one-axis machine is refused with an event of its tick, one
    with a fault the machine does not know is refused by the injector's check, a good one is
    requested, injected and reached, each event saying it came from the bench; report.json
    has the port's counts and the level at the end; hil replay, which hands the requests on
    again in their ticks, reproduces the recording."""
    run = tmp_path / "run"
    with Children(tmp_path) as children:
        proc, _ = children.emulator(config, "udp://127.0.0.1:0", run, "--no-rt",
                                    "--inject-port", 0)
        address = parse_address(Recording(run).meta["inject_port"])
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw, \
                InjectClient(address) as client:
            raw.sendto(b"\xc1 garbage", address)
            raw.sendto(encode(Setpoint(), 9, 0), address)
            client.send(InjectRequest(3, "friction_growth", {"growth_pct": 20.0}))
            client.send(InjectRequest(0, "bearing_seizure", {"level": 1.0}))
            client.send(GOOD)
            every = _until("the injection's ramp ended", lambda: (
                e := _inject_events(run)) and any(x["kind"] == "reached" for x in e) and e)
        assert terminate(proc) == 0, children.log("emulator")
    events = [e for e in every if _from_bench(e)]
    report = json.loads((run / "report.json").read_text())
    assert report["inject_port"]["address"] == f"{address[0]}:{address[1]}"
    assert report["inject_port"]["stats"] == {
        "datagrams": 5, "injections": 3, "malformed": 1, "foreign": 1,
        "refused_nonfinite": 0, "overflow": 0, "paused": 0}
    assert report["adapter"]["stats"]["injections"] == 0
    assert report["injections"]["X"]["levels_at_end"] == {"friction_growth": 20.0}
    kinds = [e["kind"] for e in events]
    assert kinds == ["refused", "request", "refused", "request", "injected"], events
    bad_axis, unknown = events[0], events[2]
    assert "bench: axis 3 of an injection request" in bad_axis["reason"]
    assert bad_axis["tick"] >= 0 and bad_axis["axis"] == "X"
    assert "bench: unknown fault [inject.bearing_seizure]" in unknown["reason"]
    assert json.loads(events[3]["reason"]) == {"fault": "friction_growth", "settings": {
        "growth_pct": 20.0, "ramp_s": 0.1}, "source": "bench"}
    assert events[4]["reason"] == "friction_growth growth_pct=20 on arrival, ramp 0.1 s (bench)"
    # one request a tick: each taken in a tick of its own, in the order sent
    assert events[0]["tick"] < events[1]["tick"] < events[3]["tick"]
    from hil.replay.replay import replay_run
    replayed = replay_run(run)
    assert replayed.matches, replayed.line()


def test_without_the_option_hil_run_opens_no_port(config, tmp_path):
    """The port is opened only when asked: the metadata and report.json say none."""
    run = tmp_path / "run"
    with Children(tmp_path) as children:
        proc, _ = children.emulator(config, "udp://127.0.0.1:0", run, "--no-rt",
                                    "--duration", 0.2)
        assert proc.wait(timeout=60) == 0, children.log("emulator")
    assert Recording(run).meta["inject_port"] is None
    assert json.loads((run / "report.json").read_text())["inject_port"] is None


# -- the page's checks (hil/scope/inject_panel.py), without a browser -----------------------

class _View:
    """What the panel reads of the page's view: a live run of ARROW with a port."""

    def __init__(self, address):
        self.rec = type("Rec", (), {})()
        self.rec.meta = {"inject_port": f"{address[0]}:{address[1]}",
                         "machine_file": str(ARROW),
                         "machine_files": {str(ARROW): ARROW.read_text()}}
        self.rec.folder = "run"
        self.events, self.events_read, self.end_s = [], 0, 1.0

    def state(self) -> str:
        return "live"


def test_the_page_refuses_a_bad_setting_before_sending():
    """The panel's button with a level beyond its range, an unknown key or text that is
    not KEY=NUMBER: the answer says why and that nothing was sent, and nothing reaches the
    port; a good one is sent as the request the emulator's check takes."""
    pytest.importorskip("bokeh")
    from hil.scope.inject_panel import InjectPanel
    with InjectPort(0) as port:
        port.start()
        panel = InjectPanel(_View(port.address))
        assert panel.target.axes == ("X",)
        assert "friction_growth" in panel.fault.options
        assert panel.keys.text.startswith("<div style='font-size:12px'><b>growth_pct</b> [%] "
                                          "-90..1000, required"), panel.keys.text
        panel.fault.value = "friction_growth"
        for bad, says in (("growth_pct=5000", "growth_pct"), ("growth=5", "growth"),
                          ("growth_pct=lots", "'growth_pct=lots' is not KEY=NUMBER"),
                          ("", "settings")):
            panel.settings.value = bad
            panel.send()
            assert "not sent" in panel.answer.text and says in panel.answer.text, (
                bad, panel.answer.text)
        panel.settings.value = "growth_pct=20,ramp_s=0.1"
        panel.send()
        assert panel.answer.text.startswith("<b>sent</b>"), panel.answer.text
        # a datagram sent before it would have come first (one socket to another on the
        # loopback: in order)
        _until("the request", lambda: port.requests)
        assert port.stats.datagrams == 1 and list(port.requests) == [GOOD]


def test_the_answer_after_sending_follows_the_runs_events():
    """What the panel says of a request sent, from the events read since: none of the
    bench's yet (another source's injection, a ramp's end) says nothing; its request, its
    start, its refusal each say so."""
    pytest.importorskip("bokeh")
    from hil.scope.inject_panel import outcome
    from hil.scope.view import EventRow

    def ev(kind: str, reason: str, source: str = "inject") -> EventRow:
        return EventRow(2.5, "X", source, kind, 0, reason)

    adapter = ev("injected", "friction_growth growth_pct=20 on arrival (adapter)")
    assert outcome([adapter, ev("reached", "friction_growth growth_pct=20"),
                    ev("tripped", "bench: not an injection", source="watchdog")]) is None
    request = ev("request", json.dumps({"fault": "preload_loss", "settings": {
        "loss_pct": 10.0, "at_s": 9.0}, "source": "bench"}))
    assert outcome([adapter, request]).startswith("taken by the run at t = 2.500 s")
    started = ev("injected", "preload_loss loss_pct=10 at 9 s (bench)")
    assert "injected</b> at t = 2.500 s: preload_loss" in outcome([request, started])
    refused = ev("refused", "bench: axis 4 of an injection request: this machine has 1 "
                 "axis(es)")
    assert "refused by the run</b> at t = 2.500 s: bench: axis 4" in outcome([refused])
