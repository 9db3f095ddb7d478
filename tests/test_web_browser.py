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

import concurrent.futures
import math
import os
import re
import shutil
import socket
import statistics
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from drivers.mavlink_observer import DistanceObserver
from drivers.net import free_port
from drivers.sources.synthetic import builtin_camera
from service.core.camera import save_camera
from tests.daemon_harness import render_frames
from tests.stream_peers import Streamer, ffmpeg_exe
from tests.web_harness import TOKEN, WebDaemon

CHROMIUM = os.environ.get("NETPOSE_CHROMIUM") or shutil.which("chromium") or ""
LAUNCH_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--disable-sync"]
NOMINAL_CAMERA = (b"image_width: 1280\nimage_height: 720\ncamera_name: nominal\n"
                  b"camera_matrix: {rows: 3, cols: 3, "
                  b"data: [736, 0, 639.5, 0, 736, 359.5, 0, 0, 1]}\n"
                  b"distortion_model: plumb_bob\n"
                  b"distortion_coefficients: {rows: 1, cols: 5, data: [-0.28, 0.09, 0, 0, 0]}\n")

# A net 1.0 m away along the camera axis, tilted 35 deg: 0.82 m perpendicular to it.
TILTED_NET = "synthetic:?width=640&height=360&fps=10&realtime=1&trajectory=static&range=1.0&tilt=35"

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
    # No autopilot is heard (the link sends to a port nobody reads): the badge says so, not
    # the filter's green "tracking".
    page.wait_for_function("document.getElementById('state').textContent === 'no autopilot'",
                           timeout=30_000)
    assert "notsent" in page.get_attribute("#state", "class")
    # The distance plot is beside the live view, above the fold (it began at y = 991 px of a
    # 1400x900 window, an empty damage card in its place: pilot review).
    plot_box = page.eval_on_selector("#plot-distance", "c => c.getBoundingClientRect().bottom")
    assert plot_box < 600, plot_box
    # Health: every row, with the source streaming.
    page.wait_for_selector("#health tr[data-row='Source']")
    rows = page.eval_on_selector_all("#health tr", "trs => trs.map(t => t.dataset.row)")
    assert rows == ["Service", "Source", "Autopilot link", "Telemetry", "Frame rate", "CPU",
                    "Inspection", "Latency"]
    assert "frames searched" in page.text_content("#health tr[data-row='Inspection']")
    assert "streaming" in page.text_content("#health tr[data-row='Source']")
    # The net-hold applet's input and why it is not sent (no autopilot: its clock unknown).
    assert "net hold input: held: the autopilot's clock is not confirmed" in page.text_content(
        "#health tr[data-row='Autopilot link']")
    # CPU and latency are judged, not always green: a loop that lowered its work (budget level
    # 2) and a p99 past half the freshness limit show as warnings.
    dots = page.evaluate("""() => {
        const s = JSON.parse(JSON.stringify(window.netpose.status));
        s.estimator.budget_level = 2;
        s.latency_ms.capture_to_link_p99 = 1000 * s.autopilot.freshness_s;
        onStatus(s);
        const dot = (row) => document.querySelector(`#health tr[data-row='${row}'] .dot`).className;
        return [dot("CPU"), dot("Latency")]; }""")
    assert dots == ["dot warn", "dot warn"], dots
    # A distance below the rangefinder's minimum is no distance to the autopilot (it reads
    # OutOfRangeLow): the header says so, not a plain "0.25 m to the autopilot".
    below = page.evaluate("""() => {
        const s = JSON.parse(JSON.stringify(window.netpose.status));
        s.autopilot.state = "connected"; s.autopilot.sending_distance = true;
        s.autopilot.min_distance_m = 0.3;
        onStatus(s);
        const m = JSON.parse(JSON.stringify(window.netpose.lastEstimate));
        m.filtered = Object.assign({}, m.filtered, {autopilot: "good", valid: true,
            autopilot_distance_m: 0.25, autopilot_along: "optical_axis"});
        m.time_mono = s.time_mono;
        onEstimate(m);
        renderHeader(window.netpose.health);
        return [document.getElementById("distance-kind").textContent,
                document.getElementById("distance").className]; }""")
    assert below[0].startswith("below the rangefinder's 0.30 m minimum"), below
    # Beyond the maximum the autopilot reads no distance: not the filter's green.
    beyond = page.evaluate("""() => {
        const s = JSON.parse(JSON.stringify(window.netpose.status));
        s.autopilot.state = "connected"; s.autopilot.sending_distance = true;
        s.autopilot.max_distance_m = 8.0;
        onStatus(s);
        const m = JSON.parse(JSON.stringify(window.netpose.lastEstimate));
        m.filtered = Object.assign({}, m.filtered, {state: "tracking", autopilot: "good",
            valid: true, autopilot_distance_m: 9.5, autopilot_along: "optical_axis"});
        m.time_mono = s.time_mono;
        onEstimate(m);
        renderHeader(window.netpose.health);
        return [document.getElementById("state").textContent,
                document.getElementById("state").className]; }""")
    assert beyond == ["not sent", "badge notsent"], beyond
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
    # The restart costs the autopilot its distance for seconds: asked first; declined, nothing.
    asked: list[str] = []

    def decline(dialog: Any) -> None:
        asked.append(dialog.message)
        dialog.dismiss()

    page.once("dialog", decline)
    page.click("#restart")
    page.wait_for_timeout(500)
    assert asked and "no distance for a few seconds" in asked[0], asked
    assert "restarting with the saved configuration" not in daemon.log()
    assert page.is_visible("#restart-banner")
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
    """The widget in the boxes Cockpit gives it (its default: a fifth of the screen's width
    and 36 % of its height, 384x389 on a 1920x1080 laptop, 273x276 on 1366x768): header, live
    view and the whole distance plot, without scrolling, the plot's labels drawn at their size.
    At those sizes the page scrolled, 32 or 0 of the plot's 90 px showed, and its labels were
    5-7 px; every load logged a missing favicon (pilot review)."""
    console: list[str] = []

    def on_console(msg: Any) -> None:
        if msg.type == "error":
            console.append(msg.text)

    for width, height in ((480, 420), (384, 389), (273, 276)):
        page = browser.new_page(viewport={"width": width, "height": height})
        page.on("console", on_console)
        page.goto(daemon.base + "/widget")
        page.wait_for_function("window.netpose.frames >= 3 && window.netpose.points.length > 5",
                               timeout=30_000)
        page.wait_for_timeout(1200)  # the plot redrawn at its size
        assert page.text_content("#distance") != ""
        shown = page.evaluate("""() => {
            const plot = document.getElementById("plot-distance").getBoundingClientRect();
            const img = document.getElementById("live").getBoundingClientRect();
            const canvas = document.getElementById("plot-distance");
            return {scroll: document.scrollingElement.scrollHeight, inner: innerHeight,
                    plotTop: plot.top, plotBottom: plot.bottom, plotHeight: plot.height,
                    imgHeight: img.height, canvasWidth: canvas.width,
                    cssWidth: plot.width, dpr: devicePixelRatio}; }""")
        assert shown["scroll"] <= shown["inner"] + 1, shown
        assert shown["plotBottom"] <= shown["inner"] + 1 and shown["plotHeight"] >= 85, shown
        assert shown["imgHeight"] >= 60, shown
        assert abs(shown["canvasWidth"] - shown["cssWidth"] * shown["dpr"]) <= 1, shown
        assert not console, console
        page.screenshot(path=str(shots / f"web-widget-{width}x{height}.png"))
        if (width, height) == (480, 420):
            page.screenshot(path=str(shots / "web-widget.png"))
        page.close()


def test_another_site_cannot_frame_the_page(daemon: WebDaemon, browser: Any) -> None:
    """Clickjacking, in the browser that enforces it: a page of another site framing the page
    gets Chromium's blocked frame, not the page and its Restart button; a page of the
    vehicle's own host on another port (BlueOS's sidebar, Cockpit) frames it; the Cockpit
    widget may be framed anywhere. The framing page is served on loopback, reached as
    127.0.0.1 (the page's own host) and as `localhost` (another host: a local one, as
    Chromium's local-network rules block a public site's frame for a reason of their own)."""
    import http.server
    import threading

    port = daemon.base.rsplit(":", 1)[1]
    parent = (f'<iframe id="full" src="http://127.0.0.1:{port}/"></iframe>'
              f'<iframe id="widget" src="http://127.0.0.1:{port}/widget"></iframe>'
              ).encode()

    class Parent(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(parent)))
            self.end_headers()
            self.wfile.write(parent)

        def log_message(self, *args: Any) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Parent)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()

    def shown(host: str) -> dict[str, bool]:
        page = browser.new_page()
        try:
            page.goto(f"http://{host}:{server.server_address[1]}/")
            result = {}
            for name in ("full", "widget"):
                try:
                    page.frame_locator(f"#{name}").locator("#distance").wait_for(
                        state="attached", timeout=10_000)
                    result[name] = True
                except Exception:
                    result[name] = False
            return result
        finally:
            page.close()

    try:
        assert shown("localhost") == {"full": False, "widget": True}
        assert shown("127.0.0.1") == {"full": True, "widget": True}
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5.0)


def _started(daemon: WebDaemon) -> WebDaemon:
    """daemon.start() beside Playwright's event loop (its asyncio.run needs a thread without
    one), for a daemon a test starts once the browser is up."""
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        return pool.submit(daemon.start).result()


def _shown_m(page: Any) -> float:
    """The header's distance, metres ("1.00 m")."""
    text = page.text_content("#distance")
    assert text.endswith(" m"), text
    return float(text.removesuffix(" m"))


def test_the_header_shows_the_distance_the_autopilot_gets(browser: Any, tmp_path: Path) -> None:
    """Page and widget show what DISTANCE_SENSOR carries, named for what it is, and follow a
    change of service.autopilot_distance. They showed the perpendicular distance as "along the
    camera axis" while the autopilot got the range along the axis: 0.82 m against 100 cm at
    35 deg tilt."""
    observer = DistanceObserver(as_autopilot=True)
    daemon = WebDaemon(tmp_path, sections={"camera": {"url": TILTED_NET},
                                           "mavlink": {"url": observer.url}})
    try:
        _started(daemon)
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        widget = browser.new_page(viewport={"width": 480, "height": 420})
        errors: list[str] = []
        for view in (page, widget):
            view.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(daemon.base + "/")
        widget.goto(daemon.base + "/widget")
        cases = (("optical_axis", 1.0, "along the camera axis"),
                 ("perpendicular", math.cos(math.radians(35.0)), "perpendicular to the net"))
        for kind, expected_m, label in cases:
            if kind != "optical_axis":  # the default first, then a change (page's API, reload)
                status, reply = daemon.request(
                    "POST", "/api/settings",
                    {"changes": {"service.autopilot_distance": kind}}, token=True)
                assert status == 200 and reply["message"] == "saved and applied", reply
            for view in (page, widget):
                view.wait_for_function(
                    f"document.getElementById('distance-kind').textContent === "
                    f"'to the autopilot, {label}'", timeout=30_000)
            time.sleep(1.5)  # a second of DISTANCE_SENSOR of this kind
            for view in (page, widget):
                shown = _shown_m(view)
                recent = [a.current_cm for a in observer.arrivals()
                          if a.t_received > time.monotonic() - 1.0]
                assert len(recent) >= 5, recent
                sent_cm = statistics.median(recent)
                print(f"{kind}: shown {shown:.2f} m, DISTANCE_SENSOR {sent_cm} cm")
                assert abs(100.0 * shown - sent_cm) <= 1.0, (shown, recent)
                assert shown == pytest.approx(expected_m, abs=0.03)  # 0.18 m from the other
                assert label in view.get_attribute("#distance", "title")
            # The plot draws the same distance, and says which.
            point = page.evaluate("window.netpose.points[window.netpose.points.length - 1]")
            assert point[6] == kind and point[3] == pytest.approx(expected_m, abs=0.03)
            assert page.text_content("#plot-kind") == label
        # The autopilot goes quiet (its link lost, the router restarting): what is sent
        # reaches nothing, and the header no longer says "to the autopilot".
        observer.close()
        for view in (page, widget):
            view.wait_for_function(
                "document.getElementById('distance-kind').textContent === "
                "'autopilot link lost: nothing reaches it'", timeout=30_000)
            assert "unsent" in view.get_attribute("#distance", "class")
            # ... and the badge no longer shows the filter's green: red, "link lost".
            assert view.text_content("#state") == "link lost"
            assert "bad" in view.get_attribute("#state", "class")
        assert not errors, errors
    finally:
        assert daemon.stop() == 0, daemon.log()
        observer.close()


def test_too_close_is_the_loudest_state_and_a_dead_daemons_health_is_not_shown_live(
        browser: Any, shots: Path, tmp_path: Path) -> None:
    """Near the net the page read a grey LOST beside a struck-through "too close", with "no
    net:" under it, and a measured 0.25 m (below the rangefinder's 0.30 m minimum) greyed and
    struck through: the most dangerous state looked the calmest (pilot review). Now both say
    TOO CLOSE in red, the distance is not struck through, and the line under it says to back
    off. Then the daemon stops: its Health rows were still green ("heartbeat 0.2 s ago ·
    sending distance") 15 s later; now they are greyed and said to be the last status."""
    # (The measured 0.25 m may read 0.24-0.26 m: any distance below the 0.30 m minimum.)
    cases = (("0.13", "^too close$"), ("0.25", "^0\\.2[3-7] m$"))
    errors: list[str] = []
    for range_m, shown in cases:
        observer = DistanceObserver(as_autopilot=True)
        folder = tmp_path / range_m
        folder.mkdir()
        daemon = WebDaemon(folder, sections={
            "camera": {"url": "synthetic:?width=640&height=360&fps=10&realtime=1"
                              f"&trajectory=static&range={range_m}&tilt=10&seed=5"},
            "mavlink": {"url": observer.url}})
        try:
            _started(daemon)
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.goto(daemon.base + "/")
            # One predicate, read at one moment: the header is redrawn four times a second,
            # and at 0.13 m a frame that shows no lattice at all ends "too close". Its text,
            # colours and the line under it are set together, so all of them hold at once.
            back_off = ("true" if range_m != "0.13"
                        else "$('tilt').textContent.startsWith('back off')")
            page.wait_for_function(f"""() => {{
                const $ = (id) => document.getElementById(id);
                return $('state').textContent === 'too close'
                    && $('state').classList.contains('tooclose')
                    && /{shown}/.test($('distance').textContent)
                    && $('distance').classList.contains('close')
                    && !$('distance').classList.contains('unsent')
                    && !$('tilt').textContent.startsWith('no net') && {back_off}; }}""",
                timeout=30_000)
            name = "too-close" if range_m == "0.13" else "below-minimum"
            page.screenshot(path=str(shots / f"web-page-{name}.png"))
            page.wait_for_function("document.querySelectorAll('#health tbody tr').length > 3",
                                   timeout=30_000)
            assert page.evaluate("document.getElementById('health').classList"
                                 ".contains('stale')") is False
            assert not errors, errors
        finally:
            assert daemon.stop() == 0, daemon.log()
            observer.close()
    page.wait_for_function("document.getElementById('health').classList.contains('stale')",
                           timeout=15_000)
    assert "the daemon is not answering" in page.text_content("#digest")


def test_an_open_page_comes_back_in_step_with_a_restarted_daemon(
        browser: Any, tmp_path: Path) -> None:
    """The daemon restarted from outside (systemd, BlueOS, a power cycle of the Pi) while the
    page was open: its "Restart now" banner stayed up although nothing was pending, and its
    plot went from a thousand points to the new daemon's twenty. The page reloads the settings
    on a reconnect and keeps the points from before the restart."""
    daemon = WebDaemon(tmp_path)
    try:
        _started(daemon)
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(daemon.base + "/")
        page.wait_for_function("window.netpose.points.length > 30", timeout=30_000)
        status, reply = daemon.request("POST", "/api/settings",
                                       {"changes": {"mavlink.sensor_id": 1}}, token=True)
        assert status == 200 and reply["restart_needed"] == ["mavlink"], reply
        page.wait_for_selector("#restart-banner:not([hidden])", timeout=30_000)
        assert daemon.stop() == 0, daemon.log()
        page.wait_for_function("!window.netpose.health.connected", timeout=15_000)
        before = page.evaluate("window.netpose.points.length")
        first_before = page.evaluate("window.netpose.points[0][0]")
        _started(daemon)
        page.wait_for_function("window.netpose.health.live", timeout=60_000)
        page.wait_for_selector("#restart-banner", state="hidden", timeout=30_000)
        points = page.evaluate("window.netpose.points")
        assert len(points) >= before and points[0][0] == first_before, (len(points), before)
        # A computer that rebooted runs another monotonic clock: the points from before would
        # sit "in the future" of the new ones (the diff review's plot off its canvas), so a
        # hello from another boot drops them.
        left = page.evaluate("""() => {
            onMessage({kind: "hello", instance: "another", boot_id: "another boot",
                       history_s: 300, live_hz: 4, push_hz: 10, token_required: false,
                       vehicle: "demo"});
            return window.netpose.points.length; }""")
        assert left == 0
        assert not errors, errors
    finally:
        assert daemon.stop() == 0, daemon.log()


def _mpegts_to(port: int) -> list[str]:
    return ["-f", "mpegts", "-muxdelay", "0", "-muxpreload", "0",
            f"udp://127.0.0.1:{port}?pkt_size=1316"]  # fmt: skip


def _looks_stale(view: Any) -> dict[str, Any]:
    """What a person sees of the header and the live view, and the page's own judgement."""
    return view.evaluate("""() => {
        const $ = (id) => document.getElementById(id);
        return {live: window.netpose.health.live, link: $("link").textContent,
                linkClass: $("link").className, distance: $("distance").textContent,
                state: $("state").textContent, stateClass: $("state").className,
                tilt: $("tilt").textContent, imageStale: $("live").classList.contains("stale"),
                note: $("live-note").hidden ? null : $("live-note").textContent}; }""")


# Stale as a person sees it: the connection line is not "live" (red), no distance, the badge
# says stale or camera down, the raw line no longer reads as current, the picture is greyed
# with the reason over it.
STALE_SHOWN = """() => {
    const $ = (id) => document.getElementById(id);
    return !window.netpose.health.live && $("link").textContent !== "live" &&
        $("link").classList.contains("down") && $("distance").textContent === "–" &&
        ["stale", "camera down"].includes($("state").textContent) &&
        $("state").classList.contains("stale") && !$("tilt").textContent.startsWith("raw") &&
        $("live").classList.contains("stale") && !$("live-note").hidden &&
        $("live-note").textContent !== ""; }"""


def test_a_stalled_camera_does_not_look_live(
        browser: Any, shots: Path, tmp_path: Path) -> None:
    """A UDP stream that stops sending: within a few seconds the page and the Cockpit widget
    say the view is stale, then that the camera is reconnecting; no distance is shown as
    current, the picture is greyed with the reason over it, the plot's "now" runs on past the
    last point and the frame rate falls to none. They went on showing TRACKING, the last
    distance, a green "live" and 2.4 frames/s for as long as the camera was away. When the
    stream comes back, so does the live view."""
    exe = ffmpeg_exe()
    frames = [f.image for f in render_frames(
        "synthetic:?width=640&height=360&trajectory=static&range=1.0&tilt=20", 10)]
    save_camera(builtin_camera(640, 360), tmp_path / "camera.yaml")
    port = free_port(socket.SOCK_DGRAM)
    streamer = Streamer(exe, _mpegts_to(port), frames=frames, fps=10)
    daemon = WebDaemon(tmp_path, sections={"camera": {"url": f"udp://127.0.0.1:{port}",
                                                      "calibration": "camera.yaml"}})
    try:
        _started(daemon)
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        widget = browser.new_page(viewport={"width": 480, "height": 420})
        errors: list[str] = []
        views = (page, widget)
        for view, path in zip(views, ("/", "/widget"), strict=True):
            view.on("pageerror", lambda exc: errors.append(str(exc)))
            view.goto(daemon.base + path)
        for view in views:
            view.wait_for_function("window.netpose.health && window.netpose.health.live && "
                                   "window.netpose.frames >= 2", timeout=60_000)
            seen = _looks_stale(view)
            assert seen["link"] == "live" and seen["distance"].endswith(" m"), seen
            assert not seen["imageStale"] and seen["note"] is None, seen

        streamer.held.set()  # the stream pauses: nothing arrives, nothing says so
        held_at = time.monotonic()
        for view in views:
            view.wait_for_function(STALE_SHOWN, timeout=10_000)
        stale_after_s = time.monotonic() - held_at
        print(f"page and widget stale {stale_after_s:.1f} s after the stream paused")
        assert stale_after_s < 5.0
        # The status names the cause once the source gives up on the stream (stale_after_s 2).
        for view in views:
            view.wait_for_function(
                "document.getElementById('link').textContent.startsWith('camera reconnecting')",
                timeout=15_000)
            seen = _looks_stale(view)
            assert seen["state"] == "camera down" and "camera reconnecting" in seen["note"], seen
        # The plot's time axis runs on (a gap after the last point), the frame rate falls.
        page.wait_for_function("plotEnd() - window.netpose.points[window.netpose.points.length"
                               " - 1][0] > 5", timeout=15_000)
        page.wait_for_function(
            "document.getElementById('live-rate').textContent.startsWith('no frame for')",
            timeout=15_000)
        page.screenshot(path=str(shots / "web-page-camera-down.png"))
        widget.screenshot(path=str(shots / "web-widget-camera-down.png"))

        streamer.held.clear()  # back: the source re-opens the stream, the view is live again
        for view in views:
            view.wait_for_function("window.netpose.health.live && document.getElementById("
                                   "'distance').textContent.endsWith(' m')", timeout=60_000)
            seen = _looks_stale(view)
            assert seen["link"] == "live" and not seen["imageStale"], seen
        assert not errors, errors
    finally:
        streamer.stop()
        assert daemon.stop() == 0, daemon.log()


def test_a_recording_is_deleted_from_the_page(daemon: WebDaemon, browser: Any) -> None:
    """The card BlueOS shares filled up with recordings the page could not delete: a
    recording's Delete button, confirmed, removes it from the list and from the card."""
    import json

    from drivers.recorder import MANIFEST

    name = "netpose-demo-20260101T120000Z"
    folder = daemon.folder / "recordings" / name
    (folder / "frames").mkdir(parents=True)
    (folder / MANIFEST).write_text(json.dumps({"finished": True, "frames": 1, "bytes": 3}))
    (folder / "frames" / "00000001.png").write_bytes(b"png")
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    asked: list[str] = []

    def confirm(dialog: Any) -> None:
        asked.append(dialog.message)
        dialog.accept()

    page.on("dialog", confirm)
    try:
        page.goto(daemon.base + "/")
        page.fill("#token", TOKEN)
        row = page.locator("#recordings tr", has_text=name)
        row.wait_for(timeout=15_000)
        row.locator("button", has_text="Delete").click()
        page.wait_for_function(
            "(n) => ![...document.querySelectorAll('#recordings tr')]"
            ".some((tr) => tr.textContent.includes(n))", arg=name, timeout=15_000)
        assert asked and name in asked[0]
        assert "deleted" in page.text_content("#record-message")
        assert not folder.exists()
        assert errors == []
    finally:
        page.close()
