"""A headless Chromium on a scope page, for the tests and ``hil bench scope``: Debian's
``chromium`` and ``chromium-driver`` driven by Selenium (nothing downloaded), and the page's
Bokeh models read from the browser.

:func:`missing` says what is not installed; :func:`headless_chromium` starts one.
"""

import importlib.util
import os
import shutil
import tempfile
import weakref

#: what each part is and where it comes from
_NEEDS = (("selenium", "selenium (pip install -e '.[test]')"),
          ("chromium", "chromium (apt-get install chromium, or .ci/test-deps)"),
          ("chromedriver", "chromedriver (apt-get install chromium-driver, or .ci/test-deps)"))

#: the value of a model of the page's Bokeh document: arguments[0] its name, arguments[1]
#: the property; a data source's columns as plain arrays (NaN as null)
_READ = """
const docs = window.Bokeh ? window.Bokeh.documents : [];
if (!docs.length) return null;
const m = docs[0].get_model_by_name(arguments[0]);
if (m == null) return null;
const v = m[arguments[1]];
if (arguments[1] !== 'data') return v;
const out = {};
for (const [k, col] of (v instanceof Map ? v.entries() : Object.entries(v)))
  out[k] = Array.from(col, x => (x == null || Number.isNaN(x)) ? null : x);
return out;
"""
#: set a widget's value as a user's choice would (synchronised to the server)
_SET = """
const m = window.Bokeh.documents[0].get_model_by_name(arguments[0]);
m[arguments[1]] = arguments[2];
"""
#: click the button of the page's model named arguments[0] as the user would (its view's
#: own <button>: nothing happens while it is disabled); false: no such button shown
_CLICK = """
const m = window.Bokeh.documents[0].get_model_by_name(arguments[0]);
const v = m == null ? null : window.Bokeh.index.find_one(m);
if (v == null || v.button_el == null) return false;
v.button_el.click();
return true;
"""


#: where Chromium's profile and shared memory go: /dev/shm (memory) when it holds at least
#: SHM_MIN_BYTES, else /tmp with --disable-dev-shm-usage (a container's 64 MB /dev/shm is too
#: small for its shared memory).  On disk, the browser's writes come back as block-device
#: interrupts on whichever CPU serves the disk, the loop's on this project's VM
#: (docs/scope.md)
SHM, SHM_MIN_BYTES = "/dev/shm", 512 * 2**20
#: nothing from the network the page does not ask for (updates, sync, metrics): each reply
#: is a network interrupt on some CPU, maybe the loop's
_QUIET = ("--disable-background-networking", "--disable-component-update", "--disable-sync",
          "--disable-default-apps", "--disable-breakpad", "--no-first-run",
          "--disk-cache-size=1")


def _shm_fits() -> bool:
    try:
        st = os.statvfs(SHM)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize >= SHM_MIN_BYTES


def missing() -> list[str]:
    """What a headless Chromium needs and is not installed, in words (empty: nothing)."""
    found = {"selenium": importlib.util.find_spec("selenium") is not None,
             "chromium": shutil.which("chromium") is not None,
             "chromedriver": shutil.which("chromedriver") is not None}
    return [words for key, words in _NEEDS if not found[key]]


def headless_chromium(page_load_s: float = 20.0):
    """A Selenium driver of a headless Chromium, 1700 x 1200 pixels, its profile in a
    folder of its own (in memory where :data:`SHM` fits), removed with the driver."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    in_memory = _shm_fits()
    profile = tempfile.mkdtemp(prefix="hil-chromium-", dir=SHM if in_memory else None)
    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    # --no-sandbox: Chromium's sandbox refuses to run as root (CI's containers)
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", f"--user-data-dir={profile}",
                "--window-size=1700,1200", *_QUIET,
                *(() if in_memory else ("--disable-dev-shm-usage",))):
        options.add_argument(arg)
    try:
        driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")),
                                  options=options)
    except BaseException:
        shutil.rmtree(profile, ignore_errors=True)
        raise
    weakref.finalize(driver, shutil.rmtree, profile, True)
    driver.set_page_load_timeout(page_load_s)
    return driver


def read_model(driver, name: str, prop: str = "text"):
    """Property ``prop`` of the page's model named ``name`` (None: no such model, or no
    page yet); a data source's ``data`` as name -> list."""
    return driver.execute_script(_READ, name, prop)


def set_model(driver, name: str, prop: str, value) -> None:
    """Set property ``prop`` of the page's model ``name`` as the user would."""
    driver.execute_script(_SET, name, prop, value)


def click(driver, name: str) -> bool:
    """Click the page's button ``name`` as the user would; False: no such button shown."""
    return bool(driver.execute_script(_CLICK, name))
