"""The QA page in a real headless browser (Debian's Chromium through ChromeDriver, from file://
with no server): it loads with no console error, the thumbnails load, a click opens the full
image, F flips between the all-in-focus image and the target, the focus slider walks the
sweep, Z zooms to 100 % and 400 %, the arrows step through samples and the filters hide rows.
`make test` installs Chromium where it can (root with apt-get, as on CI)."""
from __future__ import annotations

import os
import shutil
import time

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


def _loaded_height(driver, img, timeout: float = 60.0):
    """The image's natural height once it has loaded (images load asynchronously: waited for,
    generously, so a busy machine passes too), or what it is at the timeout."""
    loaded = lambda: _js(driver, "return arguments[0].complete && arguments[0].naturalHeight", img)  # noqa: E731
    deadline = time.monotonic() + timeout
    while not loaded() and time.monotonic() < deadline:
        time.sleep(0.05)
    return loaded()


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
    for img in first:  # lazy images load after the scroll, asynchronously: wait (generously) for each
        assert _loaded_height(browser, img) == 64
        assert img.get_attribute("src").endswith(".t.jpg")
    assert "5 of 5 shown" in browser.find_element("id", "count").text


def test_click_opens_the_full_image_and_keys_flip_zoom_and_step(browser, page):
    browser.get(page.as_uri())
    browser.find_element("css selector", ".sample figure[data-view='0']").click()
    assert browser.find_element("id", "viewer").is_displayed()
    first = _src(browser)
    assert first.endswith(".aif.webp")
    key = first.split(".")[0]
    _key(browser, "2")                  # target 1
    assert _src(browser) == f"{key}.dof.1.webp"
    _key(browser, "f")                  # flip to the all-in-focus image and back to target 1
    assert _src(browser) == f"{key}.aif.webp"
    _key(browser, "f")
    assert _src(browser) == f"{key}.dof.1.webp"
    _key(browser, "d")
    assert _src(browser) == f"{key}.disparity.webp"
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
    assert seen == [f"{key}.sweep.0.webp", f"{key}.sweep.2.webp", f"{key}.sweep.4.webp"]
    assert "focus sweep: focus 1.00" in browser.find_element("id", "label").text
    assert _loaded_height(browser, browser.find_element("id", "view-img")) == 64


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


@pytest.fixture(scope="module")
def review_set(smoke_set, tmp_path_factory):
    """A copy of the smoke set to review (the shared one stays unmarked) and its page."""
    import shutil

    out = tmp_path_factory.mktemp("review") / "set"
    shutil.copytree(smoke_set, out)
    page = out.parent / "page"
    assert main(["sheet", str(out), "--html", str(page), "--split", "all", "--n", "3", "--sweep", "1",
                 "--sweep-steps", "3", "--thumb", "64", "-q"]) == 0
    return out, page / "index.html"


def _rows(browser):
    return browser.find_elements("css selector", ".sample")


def test_marks_are_made_kept_downloaded_applied_and_leave_training(browser, review_set, tmp_path):
    import json

    from dofsynth.qa.marks import set_marks
    from dofsynth.train.segments import find_segments

    out, page = review_set
    downloads = tmp_path / "downloads"
    downloads.mkdir()
    browser.execute_cdp_cmd("Browser.setDownloadBehavior", {"behavior": "allow", "downloadPath": str(downloads)})
    browser.get(page.as_uri())
    _js(browser, "localStorage.clear()")
    browser.get(page.as_uri())
    rows = _rows(browser)
    bad, good = rows[0].get_attribute("data-key"), rows[1].get_attribute("data-key")
    rows[0].find_element("css selector", ".marks button[data-mark='reject']").click()
    rows[0].find_element("css selector", ".marks input").send_keys("halo at the hair")
    rows[1].find_element("css selector", ".marks button[data-mark='keep']").click()
    assert "reject" in rows[0].get_attribute("class")
    assert browser.find_element("id", "download").text == "download marks (2)"
    # the viewer's keys mark too: X rejects the sample shown, again unmarks it
    rows[2].find_element("css selector", "figure[data-view='0']").click()
    _key(browser, "x")
    assert browser.find_element("id", "label").text.endswith("reject")
    _key(browser, "x")
    _key(browser, "\ue00c")
    browser.get(page.as_uri())                         # marks survive a reload (the browser keeps them)
    rows = _rows(browser)
    assert "reject" in rows[0].get_attribute("class")
    assert rows[0].find_element("css selector", ".marks input").get_attribute("value") == "halo at the hair"
    _js(browser, "const f = document.getElementById('f-mark'); f.value = 'reject'; f.dispatchEvent(new Event('change'))")
    assert [r.get_attribute("data-key") for r in _rows(browser) if r.is_displayed()] == [bad]
    browser.find_element("id", "download").click()
    got = downloads / "qa-marks.json"
    for _ in range(200):
        if got.is_file() and got.stat().st_size:
            break
        time.sleep(0.05)
    marks = json.loads(got.read_text())
    assert marks["format"] == "dofsynth-qa-marks/1" and [m["key"] for m in marks["marks"]] == sorted([bad, good])
    by_key = {m["key"]: m for m in marks["marks"]}
    assert by_key[bad]["mark"] == "reject" and by_key[bad]["note"] == "halo at the hair" and by_key[good]["mark"] == "keep"
    # apply, verify, and training leaves the rejected sample out
    assert main(["qa", "apply", str(got), str(out)]) == 0
    assert set(set_marks(out)) == {bad, good}
    assert main(["verify", str(out)]) == 0
    split = bad.split("-")[0]
    kept = {f"{split}-{i:07d}" for s in find_segments(out, split, exclude={bad}) for i in range(s.lo, s.hi)}
    assert bad not in kept and good in kept
    from dofsynth.train.config import load
    from dofsynth.train.segments import excluded

    assert excluded(load("train-tiny"), out) == {bad}
    assert main(["sheet", str(out), "--marked", "--split", split, "--png", str(tmp_path / "marked.png"), "-q"]) == 0


def test_the_focus_slider_keeps_its_arrow_keys(browser, page):
    browser.get(page.as_uri())
    browser.find_element("css selector", ".sample figure").click()
    first = browser.find_element("id", "label").text.split()[0]
    slider = browser.find_element("id", "focus-slider")
    slider.click()
    before = float(slider.get_attribute("value"))
    _key(browser, "\ue014")                            # arrow right, with the slider focused
    assert float(slider.get_attribute("value")) > before
    assert browser.find_element("id", "label").text.split()[0] == first   # the same sample
    assert "focus sweep" in browser.find_element("id", "label").text


def test_filters_answer_change_events_too(browser, page):
    browser.get(page.as_uri())
    _js(browser, "const s = document.getElementById('f-split'); s.value = 'test'; s.dispatchEvent(new Event('change'))")
    shown = [r for r in _rows(browser) if r.is_displayed()]
    assert len(shown) == 2 and "2 of 5 shown" in browser.find_element("id", "count").text
    _js(browser, "const s = document.getElementById('f-coc-lo'); s.value = '999'; s.dispatchEvent(new Event('change'))")
    assert not any(r.is_displayed() for r in _rows(browser))


def test_zoom_is_centred_and_thumbnail_columns_line_up(browser, page):
    browser.set_window_size(1920, 1000)
    try:
        browser.get(page.as_uri())
        lefts = [[f.location["x"] for f in r.find_elements("css selector", "figure")] for r in _rows(browser)]
        assert all(row == lefts[0][:len(row)] for row in lefts), lefts       # the same columns in every row
        browser.find_element("css selector", ".sample figure[data-view='0']").click()
        _key(browser, "z")                                                     # 100 %
        box = _js(browser, "return document.getElementById('view-img').getBoundingClientRect().toJSON()")
        stage = _js(browser, "return document.getElementById('stage').getBoundingClientRect().toJSON()")
        assert abs(box["x"] + box["width"] / 2 - (stage["x"] + stage["width"] / 2)) <= 1
        assert abs(box["y"] + box["height"] / 2 - (stage["y"] + stage["height"] / 2)) <= 1
    finally:
        browser.set_window_size(1200, 900)
