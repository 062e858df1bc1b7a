"""The web view in a real browser: Debian's chromium, driven by Playwright, against
``pipescan serve``'s app on a database of simulated surveys (``test_web_api.build_network``).

Each test checks what a person sees: the map's lines and their colours, a reading per
inspection on a pipe's trend, the report's charts, a download that opens, and pages that fit
a 1280x800 screen and a 390-pixel-wide phone. Screenshots go to the test's temporary folder,
or to ``$PIPESCAN_WEB_SCREENSHOTS`` when set (docs/web.md's come from there).

Without /usr/bin/chromium the tests are skipped locally, and fail in CI (``CI`` set), where
``scripts/bootstrap.sh`` installs it.
"""

from __future__ import annotations

import contextlib
import http.server
import io
import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

from tests.test_web_api import PIPES, YEARS, build_network

CHROMIUM = Path(os.environ.get("PIPESCAN_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--disable-sync",
]

if not CHROMIUM.exists():
    if os.environ.get("CI"):
        pytest.fail(
            f"{CHROMIUM} is missing: scripts/bootstrap.sh installs Debian's chromium",
            pytrace=False,
        )
    pytest.skip(
        f"no browser at {CHROMIUM}: `apt-get install chromium` (scripts/bootstrap.sh does)",
        allow_module_level=True,
    )

playwright_api = pytest.importorskip("playwright.sync_api")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def _serving(app) -> Iterator[str]:
    """``app`` on a free port of 127.0.0.1, in a thread: its base URL."""
    import uvicorn

    port = _free_port()
    config = uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning")
    uv = uvicorn.Server(config)
    thread = threading.Thread(target=uv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not uv.started:
        if time.monotonic() > deadline:
            raise RuntimeError("the web app did not start in 30 s")
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        uv.should_exit = True
        thread.join(timeout=10)


@pytest.fixture(scope="module")
def network_db(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("web-browser") / "network.db"
    build_network(f"sqlite:///{path}")
    return path


@pytest.fixture(scope="module")
def server(network_db: Path) -> Iterator[str]:
    from pipescan.web import WebConfig, create_app

    app = create_app(WebConfig(database_url=f"sqlite:///{network_db}", database_label="sqlite"))
    with _serving(app) as url:
        yield url


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture
def shots(tmp_path: Path) -> Path:
    folder = Path(os.environ.get("PIPESCAN_WEB_SCREENSHOTS", tmp_path))
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _page(browser, width: int, height: int, **options):
    context = browser.new_context(
        viewport={"width": width, "height": height}, accept_downloads=True, **options
    )
    # Nothing may leave the machine: any request to another host fails the test.
    outside: list[str] = []
    context.on(
        "request",
        lambda r: (
            outside.append(r.url)
            if not r.url.startswith(("http://127.0.0.1", "data:", "about:"))
            else None
        ),
    )
    return context, context.new_page(), outside


def _fits(page, width: int) -> None:
    """Nothing makes the page scroll sideways (tables scroll inside their own box)."""
    scroll = page.evaluate("document.documentElement.scrollWidth")
    assert scroll <= width + 1, f"page is {scroll} px wide in a {width} px window"


def _pixels(page):
    """The page as the screen shows it (a PIL image)."""
    import io

    from PIL import Image

    return Image.open(io.BytesIO(page.screenshot())).convert("RGB")


def _midpoint(line) -> tuple[float, float]:
    """Where on the screen the middle of an SVG line is, in CSS pixels."""
    x, y = line.evaluate(
        """e => { const p = e.getPointAtLength(e.getTotalLength() / 2);
                  const m = e.getScreenCTM();
                  return [p.x * m.a + p.y * m.c + m.e, p.x * m.b + p.y * m.d + m.f]; }"""
    )
    return float(x), float(y)


def _rgb(hex_colour: str) -> str:
    r, g, b = (int(hex_colour[i : i + 2], 16) for i in (1, 3, 5))
    return f"rgb({r}, {g}, {b})"


def test_network_map_shows_each_pipe_in_its_class_colour(server, browser, shots) -> None:
    import httpx

    from pipescan.web.figures import grade_colour

    pipes = {p["asset_id"]: p for p in httpx.get(f"{server}/api/pipes").json()["items"]}
    context, page, outside = _page(browser, 1280, 800)
    try:
        page.goto(server + "/")
        lines = page.locator("svg.network-map polyline.pipe")
        located = [a for a, p in pipes.items() if p["line"] is not None]
        assert lines.count() == len(located)
        shot = _pixels(page)
        for asset_id in located:
            line = page.locator(f'svg.network-map polyline[data-asset="{asset_id}"]')
            box = line.bounding_box()
            assert box is not None and max(box["width"], box["height"]) > 20  # drawn, not a dot
            expected = grade_colour(pipes[asset_id]["condition_class"])
            assert line.evaluate("e => getComputedStyle(e).stroke") == _rgb(expected)
            # What the screen shows halfway along the line is that colour.
            x, y = _midpoint(line)
            seen = shot.getpixel((round(x), round(y)))[:3]
            want = tuple(int(expected[i : i + 2], 16) for i in (1, 3, 5))
            assert max(abs(a - b) for a, b in zip(seen, want, strict=True)) < 40, (asset_id, seen)
        # The table lists every pipe, the one without a line too.
        rows = page.locator("table.pipes tbody tr")
        assert rows.count() == len(PIPES)
        assert page.get_by_text("Not on the map (no line): MH5-MH6").is_visible()
        page.screenshot(path=str(shots / "network.png"), full_page=False)
        _fits(page, 1280)
        # Search narrows the table and fades the other lines.
        page.fill("#top-q", "MH2")
        page.press("#top-q", "Enter")
        page.wait_for_load_state()
        assert page.locator("table.pipes tbody tr").count() == 3
        assert page.locator("svg.network-map polyline.faint").count() == len(located) - 3
        # Sorting by peak blockage puts the worst first.
        page.goto(server + "/")
        page.get_by_role("link", name="Peak blockage").click()
        first = page.locator("table.pipes tbody tr").first.get_attribute("data-asset")
        worst = max(pipes, key=lambda a: pipes[a]["peak_blockage_ratio"] or 0)
        assert first == worst
        # The wheel zooms in where the pointer is, and a double-click shows it all again.
        world = page.locator("svg.network-map")
        whole = world.get_attribute("viewBox")
        box = world.bounding_box()
        page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        page.mouse.wheel(0, -300)
        page.wait_for_function(
            "w => document.querySelector('svg.network-map').getAttribute('viewBox') !== w",
            arg=whole,
        )
        zoomed = [float(v) for v in world.get_attribute("viewBox").split()]
        assert zoomed[2] < float(whole.split()[2])
        world.dblclick(position={"x": 5, "y": 5})
        assert world.get_attribute("viewBox") == whole
        # A click on a line opens its pipe.
        # (Playwright calls a horizontal line "not visible": its box has no height.)
        page.mouse.click(*_midpoint(page.locator('svg.network-map polyline[data-asset="MH1-MH2"]')))
        page.wait_for_url("**/pipes/MH1-MH2")
        assert page.locator("h1").inner_text().startswith("MH1-MH2")
    finally:
        context.close()
    assert outside == []


def test_pipe_page_has_a_reading_per_inspection(server, browser, shots) -> None:
    context, page, outside = _page(browser, 1280, 800)
    try:
        page.goto(server + "/pipes/MH1-MH2?at=7.5")
        readings = page.locator("figure.at-chainage circle.reading")
        assert readings.count() == YEARS
        for i in range(YEARS):
            assert readings.nth(i).is_visible()
        xs = [readings.nth(i).bounding_box()["x"] for i in range(YEARS)]
        assert xs == sorted(xs)  # in time order, left to right
        ys = [readings.nth(i).bounding_box()["y"] for i in range(YEARS)]
        assert ys[0] > ys[-1]  # the deposit grew: the latest reading sits higher
        assert page.locator("figure.at-chainage rect.noise").is_visible()
        assert page.get_by_text("growing").first.is_visible()
        profiles = page.locator("svg.profiles polyline.profile")
        assert profiles.count() >= YEARS
        page.screenshot(path=str(shots / "pipe.png"), full_page=True)
        _fits(page, 1280)
        # A click on the profile picks another chainage.
        page.goto(server + "/pipes/MH2-MH3")
        assert page.locator("svg.profiles rect.unmeasured").count() >= 1  # hatched gaps
        page.locator("svg.profiles rect.cell").nth(105).click()
        page.wait_for_url("**/pipes/MH2-MH3?at=*")
        assert page.locator("figure.at-chainage circle.reading").count() >= 1
    finally:
        context.close()
    assert outside == []


def test_inspection_page_and_a_download_that_opens(server, browser, shots, tmp_path) -> None:
    import httpx

    inspection_id = httpx.get(f"{server}/api/pipes/MH1-MH2").json()["last_inspection_id"]
    context, page, outside = _page(browser, 1280, 800)
    try:
        page.goto(f"{server}/inspections/{inspection_id}")
        chart = page.locator("img.report-chart")
        assert chart.is_visible()
        assert chart.evaluate("e => e.complete && e.naturalWidth") > 300  # the SVG decoded
        assert page.locator("table.defect-list tbody tr").count() >= 1
        assert page.locator(".figures-grid img").first.is_visible()
        page.screenshot(path=str(shots / "inspection.png"), full_page=False)
        _fits(page, 1280)
        with page.expect_download() as pdf:
            page.get_by_role("link", name="PDF report").click()
        saved = tmp_path / pdf.value.suggested_filename
        pdf.value.save_as(saved)
        assert saved.name.endswith(f"_inspection-{inspection_id}.pdf")
        from pypdf import PdfReader

        text = "".join(p.extract_text() for p in PdfReader(saved).pages[:2])
        assert "MH1-MH2" in text
        with page.expect_download() as csv:
            page.get_by_role("link", name="Sections, CSV").click()
        lines = Path(csv.value.path()).read_text(encoding="utf-8").splitlines()
        assert lines[0].startswith("asset_id,inspection_id") and len(lines) == 181
    finally:
        context.close()
    assert outside == []


@pytest.mark.parametrize("path", ["/", "/pipes/MH2-MH3?at=10.5", "inspection", "/runs", "/api"])
def test_every_page_fits_a_phone(server, browser, shots, path: str) -> None:
    import httpx

    if path == "inspection":
        inspection_id = httpx.get(f"{server}/api/pipes/MH2-MH3").json()["last_inspection_id"]
        path = f"/inspections/{inspection_id}"
    context, page, outside = _page(
        browser, 390, 844, device_scale_factor=2, is_mobile=True, has_touch=True
    )
    try:
        page.goto(server + path)
        _fits(page, 390)
        assert page.locator("h1").is_visible()
        name = {"/": "network", "/runs": "runs", "/api": "api"}.get(path)
        if path.startswith("/pipes"):
            name = "pipe"
            assert page.locator("figure.at-chainage circle.reading").count() >= 1
        elif path.startswith("/inspections"):
            name = "inspection"
        if path == "/":
            assert page.locator("svg.network-map polyline.pipe").first.is_visible()
        page.screenshot(path=str(shots / f"phone-{name}.png"), full_page=False)
    finally:
        context.close()
    assert outside == []


TILE_RGB = (200, 225, 245)


@contextlib.contextmanager
def _tile_server() -> Iterator[tuple[str, list[str]]]:
    """A tile server on 127.0.0.1: every tile one pale blue square; the paths asked for."""
    from PIL import Image

    png = io.BytesIO()
    Image.new("RGB", (256, 256), TILE_RGB).save(png, format="PNG")
    body = png.getvalue()
    asked: list[str] = []

    class Tiles(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            asked.append(self.path)
            self.send_response(200)
            self.send_header("Content-Type", "image/png")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args) -> None:
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Tiles)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}", asked
    finally:
        httpd.shutdown()


def test_a_basemap_under_the_lines(network_db, browser, shots) -> None:
    from pipescan.web import WebConfig, create_app
    from pipescan.web.figures import grade_colour

    with _tile_server() as (tiles, asked):
        app = create_app(
            WebConfig(database_url=f"sqlite:///{network_db}", tile_url=tiles + "/{z}/{x}/{y}.png")
        )
        with _serving(app) as server:
            context, page, outside = _page(browser, 1280, 800)
            try:
                page.goto(server + "/")
                page.wait_for_function(
                    "() => [...document.querySelectorAll('svg.network-map image')].length > 0"
                )
                page.wait_for_load_state("networkidle")
                assert asked and all(p.count("/") == 3 for p in asked)  # /z/x/y.png
                shot = _pixels(page)
                # Beside the lines the tiles show; on a line, its class colour.
                box = page.locator("svg.network-map").bounding_box()
                corner = shot.getpixel((round(box["x"] + 8), round(box["y"] + 8)))[:3]
                assert max(abs(a - b) for a, b in zip(corner, TILE_RGB, strict=True)) < 12
                line = page.locator('svg.network-map polyline[data-asset="MH1-MH2"]')
                seen = shot.getpixel(tuple(round(v) for v in _midpoint(line)))[:3]
                want = grade_colour(int(line.get_attribute("data-grade")))
                rgb = tuple(int(want[i : i + 2], 16) for i in (1, 3, 5))
                assert max(abs(a - b) for a, b in zip(seen, rgb, strict=True)) < 40
                page.screenshot(path=str(shots / "network-basemap.png"))
            finally:
                context.close()
    assert outside == []  # the tile server is on 127.0.0.1 too
