"""The QA page in a real headless browser (Debian's Chromium through ChromeDriver, from file://
with no server): it loads with no console error, the thumbnails load, a click opens the full
image, F flips between the all-in-focus image and the target, the focus slider walks the
sweep, Z zooms to 100 % and 400 %, the arrows step through samples and the filters hide rows.
`make test` installs Chromium where it can (root with apt-get, as on CI)."""
from __future__ import annotations

import os
import shutil

import pytest

from dofsynth.cli import main

CHROMIUM, DRIVER = shutil.which("chromium") or "/usr/bin/chromium", shutil.which("chromedriver") or "/usr/bin/chromedriver"


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service

    if not (os.path.exists(CHROMIUM) and os.path.exists(DRIVER)):
        why = f"Chromium and ChromeDriver are not installed ({CHROMIUM}, {DRIVER}; `make test` installs them as root)"
        if os.environ.get("CI"):
            pytest.fail(f"{why}; CI must run the browser test")
        pytest.skip(why)
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
              "--disable-background-networking", "--disable-component-update", "--disable-sync",
              "--disable-dev-shm-usage", "--window-size=1200,900",
              f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}"):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(DRIVER), options=opts)
    yield driver
    driver.quit()


@pytest.fixture(scope="module")
def page(smoke_set, tmp_path_factory):
    out = tmp_path_factory.mktemp("qa") / "page"
    assert main(["sheet", str(smoke_set), "--html", str(out), "--split", "all", "--n", "3", "--sweep", "2",
                 "--sweep-steps", "5", "--thumb", "64", "-q"]) == 0
    return out / "index.html"


def _js(driver, script, *args):
    return driver.execute_script(script, *args)


def _src(driver) -> str:
    return driver.find_element("id", "view-img").get_attribute("src").rsplit("/", 1)[-1]


def _key(driver, key: str) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    ActionChains(driver).send_keys(key).perform()


def test_the_page_loads_without_console_errors_and_its_thumbnails_load(browser, page):
    browser.get(page.as_uri())
    errors = [e for e in browser.get_log("browser") if e["level"] in ("SEVERE", "WARNING")]
    assert errors == []
    rows = browser.find_elements("css selector", ".sample")
    assert len(rows) == 5   # 3 train + 2 test (the smoke set has 2)
    first = rows[0].find_elements("css selector", "img")
    browser.execute_script("window.scrollTo(0, document.body.scrollHeight)")   # lazy thumbnails load
    for img in first:
        assert _js(browser, "return arguments[0].complete && arguments[0].naturalHeight", img) == 64
        assert img.get_attribute("src").endswith(".t.jpg")
    assert "5 of 5 shown" in browser.find_element("id", "count").text


def test_click_opens_the_full_image_and_keys_flip_zoom_and_step(browser, page):
    browser.get(page.as_uri())
    browser.find_element("css selector", ".sample figure[data-view='0']").click()
    assert browser.find_element("id", "viewer").is_displayed()
    first = _src(browser)
    assert first.endswith(".aif.png")
    key = first.split(".")[0]
    _key(browser, "2")                  # target 1
    assert _src(browser) == f"{key}.dof.1.png"
    _key(browser, "f")                  # flip to the all-in-focus image and back to target 1
    assert _src(browser) == f"{key}.aif.png"
    _key(browser, "f")
    assert _src(browser) == f"{key}.dof.1.png"
    _key(browser, "d")
    assert _src(browser) == f"{key}.disparity.png"
    natural = _js(browser, "return document.getElementById('view-img').naturalWidth")
    _key(browser, "z")
    assert _js(browser, "return document.getElementById('view-img').getBoundingClientRect().width") == natural
    _key(browser, "z")
    assert _js(browser, "return document.getElementById('view-img').getBoundingClientRect().width") == 4 * natural
    _key(browser, "\ue014")             # arrow right: the next sample
    assert not _src(browser).startswith(key)
    _key(browser, "\ue00c")             # Esc
    assert not browser.find_element("id", "viewer").is_displayed()


def test_the_focus_slider_walks_the_focus_sweep(browser, page):
    browser.get(page.as_uri())
    browser.find_element("css selector", ".sample figure").click()
    assert browser.find_element("id", "sweep-box").is_displayed()
    seen = []
    for value in (0.0, 0.5, 1.0):
        _js(browser, "const s = document.getElementById('focus-slider'); s.value = arguments[0];"
                     "s.dispatchEvent(new Event('input'))", value)
        seen.append(_src(browser))
    key = seen[0].split(".")[0]
    assert seen == [f"{key}.sweep.0.png", f"{key}.sweep.2.png", f"{key}.sweep.4.png"]
    assert "focus sweep: focus 1.00" in browser.find_element("id", "label").text
    loaded = _js(browser, "const i = document.getElementById('view-img'); return i.complete && i.naturalWidth")
    assert loaded == 64


def test_filters_hide_rows(browser, page):
    browser.get(page.as_uri())

    def visible():
        return [r.get_attribute("data-key") for r in browser.find_elements("css selector", ".sample") if r.is_displayed()]

    assert len(visible()) == 5
    _js(browser, "const s = document.getElementById('f-split'); s.value = 'test'; s.dispatchEvent(new Event('input'))")
    assert [k.split("-")[0] for k in visible()] == ["test", "test"]
    assert "2 of 5 shown" in browser.find_element("id", "count").text
    _js(browser, "const s = document.getElementById('f-split'); s.value = ''; s.dispatchEvent(new Event('input'))")
    browser.find_element("id", "f-asset").send_keys("no such asset")
    assert visible() == []
    browser.find_element("id", "f-asset").clear()
    _js(browser, "document.getElementById('f-asset').dispatchEvent(new Event('input'))")
    cocs = _js(browser, "return DATA.samples.map(s => Math.max(...s.max_coc))")
    cut = sorted(cocs)[2]
    browser.find_element("id", "f-coc-lo").send_keys(str(cut))
    assert len(visible()) == sum(c >= cut for c in cocs) < 5
    assert browser.get_log("browser") == []
