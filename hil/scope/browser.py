"""A headless Chromium on a scope page, for the tests and ``hil bench scope``: Debian's
``chromium`` and ``chromium-driver`` driven by Selenium (nothing downloaded), and the page's
Bokeh models read from the browser.

:func:`missing` says what is not installed; :func:`headless_chromium` starts one.
"""

import importlib.util
import shutil

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


def missing() -> list[str]:
    """What a headless Chromium needs and is not installed, in words (empty: nothing)."""
    found = {"selenium": importlib.util.find_spec("selenium") is not None,
             "chromium": shutil.which("chromium") is not None,
             "chromedriver": shutil.which("chromedriver") is not None}
    return [words for key, words in _NEEDS if not found[key]]


def headless_chromium(page_load_s: float = 20.0):
    """A Selenium driver of a headless Chromium, 1700 x 1200 pixels."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    # --no-sandbox: Chromium's sandbox refuses to run as root (CI's containers)
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1700,1200"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
    driver.set_page_load_timeout(page_load_s)
    return driver


def read_model(driver, name: str, prop: str = "text"):
    """Property ``prop`` of the page's model named ``name`` (None: no such model, or no
    page yet); a data source's ``data`` as name -> list."""
    return driver.execute_script(_READ, name, prop)


def set_model(driver, name: str, prop: str, value) -> None:
    """Set property ``prop`` of the page's model ``name`` as the user would."""
    driver.execute_script(_SET, name, prop, value)
