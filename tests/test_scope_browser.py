"""``hil scope`` in a real browser: a headless Chromium (Debian's ``chromium`` and
``chromium-driver``, driven by Selenium) on the page of a real ``hil run`` (with its
injection port) and ``hil controller`` pair, live, and then of the finished run.

What the page shows is read from its Bokeh document in the browser (the models named in
:mod:`hil.scope.page`: what the server sent the tab), and checked against the run's own
recording read afterwards with :class:`~hil.runtime.record_reader.Recording`.  A
screenshot of each state goes to the test's folder.

Skips, saying why, without Bokeh, Selenium, chromium or chromedriver (``.ci/test-deps``
installs the Debian packages, the ``test`` extra Selenium).
"""

import importlib.util
import json
import os
import time

import numpy as np
import pytest

from hil.runtime.record_reader import Recording
from hil.scope import browser
from tests.runtime_helpers import (
    EXIT_S,
    SLOW_1KHZ,
    Children,
    machine_variant,
    python_module,
    terminate,
    wait_for_enabled,
)

_MISSING = browser.missing() + (
    [] if importlib.util.find_spec("bokeh") else ["bokeh (pip install -e '.[scope]')"])
pytestmark = pytest.mark.skipif(bool(_MISSING), reason="hil scope's browser tests need "
                                + ", ".join(_MISSING))

#: where the table starts, mm: clear of the travel's ends
START_MM = 100.0
#: out by 5 mm and back, again and again (3 s a cycle): the trigger's position steps.  Three
#: minutes, far beyond the tests' own time: a controller whose program ended disables the drive,
#: and the watchdog then rightly stays quiet
PROGRAM = "G90 G71\n" + "G4 F1\nG1 X105 F600\nG4 F1\nG1 X100 F600\n" * 60 + "M30\n"
#: the trigger: the table passing 102.5 mm on its way out, m
LEVEL_M = 102.5e-3
#: the recording's flush period, s: how late the page may see a row
FLUSH_S = 0.25
#: longest wait for the page to show something the run has done, s
PAGE_S = 20.0
#: the fault injected from the page: mild, so the controller's contour stays within its
#: limits for the tests after it
INJECTED = "growth_pct=20,ramp_s=0.5"
#: the emulator's watchdog and the controller's patience without feedback: 1 s at 1 kHz, so
#: that a loop held up by the browser's start on a small machine does not end the run
PATIENCE_TICKS = 1000


def _read(driver, name: str, prop: str = "text"):
    return browser.read_model(driver, name, prop)


def _until(driver, what: str, check, timeout: float = PAGE_S):
    """``check()``'s first truthy value within ``timeout`` s, else the test fails naming
    ``what`` with a screenshot."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = check()
        if value:
            return value
        time.sleep(0.2)
    driver.save_screenshot(str(driver.screens / f"failed_{what.replace(' ', '_')}.png"))
    pytest.fail(f"the page did not show {what} within {timeout} s; trigger: "
                f"{_read(driver, 'scope_trig_info')!r}; status: "
                f"{_read(driver, 'scope_status')!r}")


def _scope(children: Children, run_dir, name: str) -> str:
    proc = children.start(name, python_module("hil.cli", "scope", run_dir, "--port", 0),
                          ready=True)
    line = proc.stdout.readline()
    assert line.startswith("hil scope: http://127.0.0.1:"), (line, children.log(name))
    return line.split()[2]


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """``hil run`` (1 kHz Arrow 500 X, recording, an injection port) with ``hil
    controller`` on PROGRAM,
    ``hil scope`` on the run folder and a headless Chromium on its page, once the drive is
    enabled: (driver, run folder, children, controller process, emulator process)."""
    folder = tmp_path_factory.mktemp("scope")
    screens = folder / "screens"
    screens.mkdir()
    config = machine_variant(folder / "arrow_1khz.toml", SLOW_1KHZ)
    program = folder / "steps.nc"
    program.write_text(PROGRAM)
    run_dir = folder / "run"
    cpus = sorted(os.sched_getaffinity(0))
    with Children(folder) as children:
        emulator, served = children.emulator(config, "udp://127.0.0.1:0", run_dir,
                                             "--cpu", cpus[-1], "--start", START_MM,
                                             "--watchdog-cycles", PATIENCE_TICKS,
                                             "--inject-port", 0)
        pin = ["--cpu", cpus[0]] if len(cpus) > 1 else []
        ctl = children.start("controller", python_module(
            "hil.runtime.controller_proc", config, "--adapter", served, "--program", program,
            "--out", folder / "controller", "--start", START_MM,
            "--feedback-timeout", PATIENCE_TICKS, *pin))
        # the browser starts once both loops run: its start-up is the machine's busiest
        wait_for_enabled(run_dir, ctl)
        url = _scope(children, run_dir, "scope")
        driver = browser.headless_chromium(PAGE_S)
        driver.screens = screens
        try:
            driver.get(url)
            yield driver, run_dir, children, ctl, emulator, url
        finally:
            driver.quit()


def test_the_status_shows_the_drive_enabled_and_the_controller_connected(live):
    driver = live[0]
    status = _until(driver, "OPERATION ENABLED and a connected controller", lambda: (
        (s := _read(driver, "scope_status")) and "OPERATION ENABLED" in s
        and "connected</b>" in s and s))
    assert "Operation enabled" in status, status  # the statusword's bit by its name
    driver.save_screenshot(str(driver.screens / "1_enabled.png"))


def test_the_plot_advances_while_the_run_goes_on(live):
    """The plotted curve's last time, read from the page's data source, moves on with the
    run: twice, a second apart."""
    driver = live[0]

    def last_t():
        data = _read(driver, "scope_data", "data")
        times = [t for t in (data or {}).get("t_s", []) if t is not None]
        return max(times) if times else None

    first = _until(driver, "a curve", last_t)
    time.sleep(1.5)
    second = _until(driver, "a later curve", lambda: (t := last_t()) and t > first and t)
    time.sleep(1.5)
    _until(driver, "a later curve again", lambda: (t := last_t()) and t > second)
    data = _read(driver, "scope_data", "data")
    assert "plant_table_pos" in data and any(v is not None for v in data["plant_table_pos"])


def test_a_trigger_on_the_position_step_fires_when_the_recording_crossed_the_level(live):
    """Level LEVEL_M rising on plant_table_pos, set through the page's widgets: the page's
    trigger time is the first rising crossing in the recording after it was armed, within
    one flush."""
    driver, run_dir = live[0], live[1]
    browser.set_model(driver, "scope_trig_level", "value", LEVEL_M)
    browser.set_model(driver, "scope_window", "value", 2.0)
    browser.set_model(driver, "scope_trig_channel", "value", "plant_table_pos")
    fired = _until(driver, "a trigger", lambda: (
        (d := _read(driver, "scope_trigger", "data")) and d.get("t_s") and d), timeout=15)
    at, armed = fired["t_s"][0], fired["armed_after_s"][0]
    rec = Recording(run_dir)
    pos = rec.read(["tick", "plant_table_pos"])
    t_s = pos["tick"] * rec.period_ns * 1e-9
    x = pos["plant_table_pos"]
    crossings = t_s[1:][(x[:-1] < LEVEL_M) & (x[1:] >= LEVEL_M)]
    expected = crossings[crossings > armed][0]
    assert abs(at - expected) <= FLUSH_S, (at, expected, armed)
    data = _read(driver, "scope_data", "data")
    times = [t for t in data["t_s"] if t is not None]
    assert min(times) < at < max(times)  # the capture holds the trigger, pre and post
    driver.save_screenshot(str(driver.screens / "2_triggered.png"))
    browser.set_model(driver, "scope_trig_channel", "value", "(free running)")


def test_a_fault_injected_from_the_page_is_in_its_events_and_the_recording(live):
    """The injection panel, through its widgets and its button: friction growth of 5000 %
    (beyond its 1000 %) is refused on the page and never sent; then INJECTED is sent, the
    page's events list it as injected from the bench, the answer says so, and the
    recording's events hold the request (source bench) and its start, once each."""
    driver, run_dir = live[0], live[1]
    _until(driver, "the injection panel enabled", lambda: _read(
        driver, "scope_inject_send", "disabled") is False)
    browser.set_model(driver, "scope_inject_fault", "value", "friction_growth")
    browser.set_model(driver, "scope_inject_settings", "value", "growth_pct=5000")
    assert browser.click(driver, "scope_inject_send")
    refused = _until(driver, "the bad setting refused", lambda: (
        (a := _read(driver, "scope_inject_answer")) and "not sent" in a and a))
    assert "growth_pct" in refused and "1000" in refused, refused
    browser.set_model(driver, "scope_inject_settings", "value", INJECTED)
    assert browser.click(driver, "scope_inject_send")
    started = "friction_growth growth_pct=20 on arrival, ramp 0.5 s (bench)"
    _until(driver, "the injection among the events", lambda: started in (
        _read(driver, "scope_events") or ""))
    _until(driver, "the answer: injected", lambda: "injected</b>" in (
        _read(driver, "scope_inject_answer") or ""))
    driver.save_screenshot(str(driver.screens / "3_injected.png"))
    ev = Recording(run_dir).events()
    rows = [(k, r) for s, k, r in zip(ev["source"], ev["kind"], ev["reason"])
            if s == "inject"]
    requests = [json.loads(r) for k, r in rows if k == "request"]
    assert requests == [{"fault": "friction_growth", "settings": {
        "growth_pct": 20.0, "ramp_s": 0.5}, "source": "bench"}], rows
    assert [r for k, r in rows if k == "injected"] == [started], rows


def test_stopping_the_controller_shows_it_silent_then_the_watchdog(live):
    """The controller killed (SIGKILL: no goodbye, as a crash; on SIGTERM it would disable
    the drive first, and the watchdog rightly stays quiet): the page says it is silent,
    then lists the watchdog's trip."""
    driver, _, _, ctl, _, _ = live
    assert ctl.poll() is None, "the controller ended before it was stopped"
    _until(driver, "the drive enabled before the stop", lambda: "OPERATION ENABLED" in (
        _read(driver, "scope_status") or ""))
    ctl.kill()
    ctl.wait(timeout=EXIT_S)
    _until(driver, "the controller silent", lambda: "SILENT" in (
        _read(driver, "scope_status") or ""))
    _until(driver, "the watchdog's event", lambda: "watchdog tripped" in (
        _read(driver, "scope_events") or ""))
    driver.save_screenshot(str(driver.screens / "4_silent.png"))


def test_the_finished_run_shows_its_whole_length(live):
    """After the run's stop a new page shows the recording from its first row to its
    last (its ends within two pixels' width)."""
    driver, run_dir, children, _, emulator, url = live
    assert terminate(emulator) == 0
    rec = Recording(run_dir)
    assert rec.closed_cleanly()
    period_s = rec.period_ns * 1e-9
    ticks = rec.read(["tick"])["tick"]
    first_s, last_s = ticks[0] * period_s, ticks[-1] * period_s
    driver.get(url)
    _until(driver, "the ended run", lambda: _read(driver, "scope_state") == "ended")
    data = _until(driver, "the whole curve", lambda: (
        (d := _read(driver, "scope_data", "data")) and len(d.get("t_s", [])) > 100 and d))
    times = np.array([t for t in data["t_s"] if t is not None])
    pixel_s = (last_s + period_s) / 1200
    assert times.min() <= first_s + 2 * pixel_s and times.max() >= last_s - 2 * pixel_s, (
        times.min(), times.max(), first_s, last_s)
    driver.save_screenshot(str(driver.screens / "5_finished.png"))


def test_the_finished_runs_injection_panel_is_disabled(live):
    """On the ended run's page the panel's widgets are disabled and it says why;
    report.json counts the one request the injection port took and names its thread
    among the helpers (real-time on the loop's CPU when the loop was)."""
    driver, run_dir = live[0], live[1]
    _until(driver, "the panel disabled", lambda: _read(
        driver, "scope_inject_send", "disabled") is True)
    assert _read(driver, "scope_inject_settings", "disabled") is True
    assert "no longer live" in _read(driver, "scope_inject_answer")
    report = json.loads((run_dir / "report.json").read_text())
    stats = report["inject_port"]["stats"]
    assert (stats["datagrams"], stats["injections"]) == (1, 1), stats
    helper = report["helper_threads"]
    if report["scheduling"]["fifo"]["granted"]:
        assert helper["hil-inject-port"].startswith("SCHED_FIFO"), helper
