"""``seqvpr view`` pages in a real browser (headless Chromium driven by Selenium, the system's browser and driver):
Gardens Point Walking's night walk matched against its day walk by two methods, and localised against a day map.
A click on a wrong query shows that query's top-K rows of ``predictions.csv`` in order with the true matches
marked; the keyboard steps to the next failure; the distances zoom and a click there selects its query; scrubbing
a localisation's timeline shows ``stream.csv``'s row; nothing is fetched from the network."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import pytest

from tests.helpers import QuietCapsys, run_cli

pytestmark = pytest.mark.slow
BROWSER, DRIVER = shutil.which("chromium"), shutil.which("chromedriver")
webdriver = pytest.importorskip("selenium.webdriver", reason="selenium (the test extra) is not installed")
if not (BROWSER and DRIVER):
    pytest.skip("no chromium and chromedriver on PATH (Debian: apt-get install chromium chromium-driver)",
                allow_module_level=True)


@pytest.fixture(scope="module")
def pages(shared_data, tmp_path_factory):
    """Two match runs and a localisation of night_right against day_left (patch-normalised), and their pages."""
    root = tmp_path_factory.mktemp("view")
    walk = shared_data / "gardenspoint_walking"
    with pytest.MonkeyPatch.context() as patch:
        capsys = QuietCapsys()
        for name, args in (("m5", ("-L", "5")), ("m1", ("--method", "single", "-L", "1"))):
            _ok(run_cli(patch, capsys, "match", "-r", walk / "day_left", "-q", walk / "night_right", "--radius",
                        "2f", *args, "--out", root / name))
        _ok(run_cli(patch, capsys, "map", "build", walk / "day_left", "--out", root / "map"))
        _ok(run_cli(patch, capsys, "localize", "--map", root / "map", "-q", walk / "night_right", "--radius", "2f",
                    "--threshold", "0.01", "--out", root / "loc"))
        _ok(run_cli(patch, capsys, "view", root / "m5", root / "m1", "--out", root / "cmp"))
        _ok(run_cli(patch, capsys, "view", root / "loc"))
    return root


def _ok(result) -> None:
    assert result[0] == 0, result[2]


@pytest.fixture(scope="module")
def browser():
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = BROWSER
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1400,1000"):
        options.add_argument(argument)
    driver = webdriver.Chrome(service=Service(DRIVER), options=options)
    driver.execute_cdp_cmd("Network.enable", {})
    driver.execute_cdp_cmd("Network.setBlockedURLs", {"urls": ["http://*", "https://*", "ws://*", "wss://*"]})
    yield driver
    driver.quit()


def open_page(browser, page: Path):
    browser.get(page.as_uri())
    fetched = browser.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    assert all(name.startswith(page.parent.as_uri()) for name in fetched), fetched
    return browser


def click_canvas(browser, canvas_id: str, x: float, y: float) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    canvas = browser.find_element(By.ID, canvas_id)
    browser.execute_script("arguments[0].scrollIntoView({block: 'center'})", canvas)  # offsets are from the centre
    size = canvas.size                                                                  # of the part in view
    ActionChains(browser).move_to_element_with_offset(canvas, x - size["width"] / 2, y - size["height"] / 2) \
        .click().perform()


def predictions(run: Path) -> dict[int, tuple[list[int], str]]:
    with open(run / "predictions.csv", newline="") as handle:
        return {int(r["query"]): ([int(v) for v in r["references"].split()], r["correct"])
                for r in csv.DictReader(handle)}


def shown(browser, method: int) -> list[tuple[int, int]]:
    from selenium.webdriver.common.by import By

    frames = browser.find_elements(By.CSS_SELECTOR, f'[data-method="{method}"] [data-ref]')
    return [(int(f.get_attribute("data-ref")), int(f.get_attribute("data-true"))) for f in frames]


def test_a_wrong_query_clicked_on_the_route_shows_its_predictions_in_order(pages, browser, tmp_path):
    from selenium.webdriver.common.by import By

    open_page(browser, pages / "cmp" / "index.html")
    table = {"m5": predictions(pages / "m5"), "m1": predictions(pages / "m1")}
    wrong = next(q for q, (_, correct) in sorted(table["m5"].items()) if correct == "0")
    x, y = browser.execute_script("return seqvprView.pointOf(arguments[0])", wrong)
    click_canvas(browser, "route", x, y)
    assert browser.execute_script("return seqvprView.selected()") == wrong
    for method, run in enumerate(("m5", "m1")):
        refs, _ = table[run][wrong]
        got = shown(browser, method)
        assert [r for r, _ in got] == refs[:5]
        assert [t for _, t in got] == [int(abs(r - wrong) <= 2) for r in refs[:5]]  # the 2-frame ground truth
    assert browser.execute_script("return [...document.images].every(i => i.complete && i.naturalWidth > 0)")
    assert "wrong" in browser.find_element(By.CSS_SELECTOR, '[data-method="0"] h3').text
    browser.save_screenshot(str(tmp_path / "match.png"))


def test_the_keyboard_steps_to_the_next_failure(pages, browser):
    from selenium.webdriver.common.by import By

    open_page(browser, pages / "cmp" / "index.html")
    failures = [q for q, (_, correct) in sorted(predictions(pages / "m5").items()) if correct == "0"]
    browser.execute_script("seqvprView.select(arguments[0])", failures[0])
    body = browser.find_element(By.TAG_NAME, "body")
    body.send_keys("n")
    assert browser.execute_script("return seqvprView.selected()") == failures[1]
    body.send_keys("p")
    assert browser.execute_script("return seqvprView.selected()") == failures[0]
    from selenium.webdriver.common.keys import Keys

    body.send_keys(Keys.ARROW_RIGHT)
    assert browser.execute_script("return seqvprView.selected()") == failures[0] + 1


def test_the_distances_zoom_and_a_click_selects_that_query(pages, browser, tmp_path):
    from selenium.webdriver.common.by import By

    open_page(browser, pages / "cmp" / "index.html")
    target = 120
    browser.execute_script("seqvprView.select(arguments[0])", target)
    body = browser.find_element(By.TAG_NAME, "body")
    body.send_keys("+")
    body.send_keys("+")
    assert browser.execute_script("return seqvprView.state.zoom") == 4
    top = predictions(pages / "m5")[target + 3][0][0]
    x, y = browser.execute_script("return seqvprView.matrixPointOf(arguments[0], arguments[1])", target + 3, top)
    assert 0 <= x <= 640 and 0 <= y <= 420  # zoomed about the selected query: its neighbours are in view
    click_canvas(browser, "second", x, y)
    assert browser.execute_script("return seqvprView.selected()") == target + 3
    browser.save_screenshot(str(tmp_path / "zoomed.png"))


def test_scrubbing_a_localisation_shows_its_stream_row(pages, browser, tmp_path):
    from selenium.webdriver.common.by import By

    open_page(browser, pages / "loc" / "view" / "index.html")
    with open(pages / "loc" / "stream.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    for frame in (10, 150, 199):
        x = browser.execute_script("return seqvprView.timelineX(arguments[0])", frame)
        click_canvas(browser, "second", x, 200)
        assert browser.execute_script("return seqvprView.selected()") == frame
        assert browser.find_element(By.ID, "status").text == rows[frame]["status"]
        cells = {c.get_attribute("data-column"): c.text for c in browser.find_elements(By.CSS_SELECTOR, "#stream-row td")}
        assert cells["score"] == rows[frame]["score"] and cells["best_row"] == rows[frame]["best_row"]
    browser.save_screenshot(str(tmp_path / "localize.png"))
