"""The page in a real browser: Debian's headless Chromium driven by Playwright, against the
real daemon on the demo source (tests/web_harness.py).

Checked as a person would: the live view updates, the plots gain points, a bad setting shows
its one-line error and leaves the file as it was, a good one is applied (the estimated distance
follows the new mesh size), a calibration upload shows its undistorted preview. Screenshots go
to $NETPOSE_SCREENSHOTS when set (docs/images is made that way), else to the test's folder.

Needs `chromium` (Debian: apt-get install chromium) and the `playwright` package (the `test`
extra); Playwright's own browser download is never used.
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.web_harness import TOKEN, WebDaemon

CHROMIUM = os.environ.get("NETPOSE_CHROMIUM") or shutil.which("chromium") or ""
LAUNCH_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--disable-sync"]
NOMINAL_CAMERA = (b"image_width: 1280\nimage_height: 720\ncamera_name: nominal\n"
                  b"camera_matrix: {rows: 3, cols: 3, "
                  b"data: [736, 0, 639.5, 0, 736, 359.5, 0, 0, 1]}\n"
                  b"distortion_model: plumb_bob\n"
                  b"distortion_coefficients: {rows: 1, cols: 5, data: [-0.28, 0.09, 0, 0, 0]}\n")

pytestmark = pytest.mark.skipif(
    not CHROMIUM, reason="no Chromium: install Debian's chromium package (apt-get install "
    "chromium) or point NETPOSE_CHROMIUM at one")


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[WebDaemon]:
    d = WebDaemon(tmp_path_factory.mktemp("browser")).start()
    try:
        yield d
    finally:
        assert d.stop() == 0, d.log()


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    playwright_api = pytest.importorskip("playwright.sync_api")
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=LAUNCH_ARGS)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture(scope="module")
def shots(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = os.environ.get("NETPOSE_SCREENSHOTS")
    path = Path(folder) if folder else tmp_path_factory.mktemp("screenshots")
    path.mkdir(parents=True, exist_ok=True)
    return path


def test_the_page_shows_live_data_and_sets_up_the_daemon(
        daemon: WebDaemon, browser: Any, shots: Path, tmp_path: Path) -> None:
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(daemon.base + "/")

    # Live view: frames arrive and the picture changes.
    page.wait_for_function("window.netpose.frames >= 3", timeout=30_000)
    first_src = page.eval_on_selector("#live", "img => img.src")
    page.wait_for_function("window.netpose.frames >= 8", timeout=30_000)
    assert page.eval_on_selector("#live", "img => img.naturalWidth") == 640
    assert page.eval_on_selector("#live", "img => img.src") != first_src
    # Plots: points keep coming (pushed, not polled).
    points = page.evaluate("window.netpose.points.length")
    page.wait_for_function(f"window.netpose.points.length > {points + 10}", timeout=30_000)
    state = page.text_content("#state")
    assert state in ("tracking", "coasting", "lost")
    # Health: every row, with the source streaming.
    page.wait_for_selector("#health tr[data-row='Source']")
    rows = page.eval_on_selector_all("#health tr", "trs => trs.map(t => t.dataset.row)")
    assert rows == ["Service", "Source", "Autopilot link", "Telemetry", "Frame rate", "CPU",
                    "Latency"]
    assert "streaming" in page.text_content("#health tr[data-row='Source']")
    page.wait_for_timeout(5000)
    rate = page.evaluate("""() => { const t = window.netpose.frameTimes;
                                    return 1000 * (t.length - 1) / (t[t.length - 1] - t[0]); }""")
    print(f"live view: {rate:.1f} frames/s in the browser over 5 s (web.live_hz = 4)")
    assert rate >= 1.0
    page.screenshot(path=str(shots / "web-page.png"), full_page=True)

    # A bad setting: its error, naming the key, and the file as it was.
    page.fill("#token", TOKEN)
    before = daemon.config.read_bytes()
    mesh = page.locator("fieldset", has_text="mesh.bar_length_m")
    mesh.locator("input[name='mesh.bar_length_m']").fill("-1")
    mesh.locator("button", has_text="Save").click()
    message = mesh.locator(".message.error")
    message.wait_for(timeout=15_000)
    assert message.text_content().startswith(
        "configuration error: mesh.bar_length_m: must be")
    assert daemon.config.read_bytes() == before
    mesh.screenshot(path=str(shots / "web-setup-error.png"))

    # A good setting: saved, reloaded, and the estimates follow it (distance scales with the
    # bar length: 0.03 / 0.025 = 1.2 times the rendered truth).
    mesh.locator("input[name='mesh.bar_length_m']").fill("0.03")
    mesh.locator("button", has_text="Save").click()
    # The form is drawn again when the daemon announces the change; the message stays.
    page.wait_for_function(
        """() => [...document.querySelectorAll('fieldset')].some(f =>
               f.textContent.includes('mesh.bar_length_m') &&
               !['', 'saving…'].includes(f.querySelector('.message').textContent))""",
        timeout=60_000)
    assert mesh.locator(".message").text_content() == "saved and applied"
    assert re.search(rb"^bar_length_m = 0\.03$", daemon.config.read_bytes(), re.M)
    page.wait_for_function(
        """() => { const e = window.netpose.lastEstimate;
                   return e && e.detected && e.truth && e.truth.distance_m &&
                          Math.abs(e.distance_m / e.truth.distance_m - 1.2) < 0.03; }""",
        timeout=30_000)

    # Calibration: upload, undistorted preview, use it (a restart is then offered).
    camera = tmp_path / "camera.yaml"
    camera.write_bytes(NOMINAL_CAMERA)
    page.set_input_files("#calibration-file", str(camera))
    page.click("#calibration-form button")
    page.wait_for_function("document.getElementById('calibration-preview').naturalWidth > 0",
                           timeout=30_000)
    assert "1280x720" in page.text_content("#calibration-message")
    page.click("#calibration-apply")
    page.wait_for_selector("#restart-banner:not([hidden])", timeout=30_000)
    assert "camera" in page.text_content("#restart-sections")
    assert re.search(rb'^calibration = "calibration-[0-9a-f]{8}\.yaml"$',
                     daemon.config.read_bytes(), re.M)
    page.locator("section.setup").screenshot(path=str(shots / "web-calibration.png"))

    # A frame whose plane was too uncertain for a distance reads "net seen", not "no net".
    seen = page.evaluate("""() => {
        const m = Object.assign({}, window.netpose.lastEstimate, {
            detected: false, net_seen: true, approx_range_m: 0.83, approx_sigma_range_m: 0.031,
            distance_m: null, range_m: null,
            reason: "plane too uncertain (range +- 4%, normal +- 2 deg): the ROIs ..."});
        onEstimate(m);
        return [document.getElementById("tilt").textContent,
                window.netpose.points[window.netpose.points.length - 1]]; }""")
    assert seen[0].startswith("net seen, ~0.83 ± 0.03 m: no distance (plane too uncertain"), seen
    assert seen[1][1] is None and seen[1][5] == 0.83  # a hollow point on the plot, no raw one
    page.wait_for_timeout(300)  # a frame drawn with it: no page error
    assert not errors, errors


def test_the_cockpit_widget_page(daemon: WebDaemon, browser: Any, shots: Path) -> None:
    page = browser.new_page(viewport={"width": 480, "height": 420})
    page.goto(daemon.base + "/widget")
    page.wait_for_function("window.netpose.frames >= 3 && window.netpose.points.length > 5",
                           timeout=30_000)
    assert page.text_content("#distance") != ""
    page.screenshot(path=str(shots / "web-widget.png"))
