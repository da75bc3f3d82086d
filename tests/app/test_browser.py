"""End to end in Debian's headless Chromium: the page renders, T4 + Register converge.

Skipped with a message when /usr/bin/chromium is missing (``apt-get install chromium``);
``.ci/run`` installs it so CI runs this test.
"""

from __future__ import annotations

import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from app.web.gui import RoadmapApp
from app.web.main import url_of
from registration.io import audit
from tests.app.conftest import TEST_GUARD

from .conftest import READOUT, parse_readout

CHROMIUM = Path("/usr/bin/chromium")

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(
        not CHROMIUM.exists() and shutil.which("chromium") is None,
        reason="Debian chromium not installed (apt-get install chromium): browser test skipped",
    ),
]


@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed")
    with sync_api.sync_playwright() as pw:
        chromium = pw.chromium.launch(
            executable_path=str(CHROMIUM if CHROMIUM.exists() else shutil.which("chromium")),
            args=["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader"],
        )
        yield chromium
        chromium.close()


def canvas_is_drawn(page) -> bool:
    import io

    from PIL import Image

    # A clip of the page, not Locator.screenshot: that waits for the (always animating) canvas to be "stable".
    # The 3D scene is the largest canvas on the page (charts in the panels are canvases too, some
    # of them zero-sized in a closed tab).
    box = page.evaluate(
        """() => {
            let best = null;
            for (const c of document.querySelectorAll("canvas")) {
                const r = c.getBoundingClientRect();
                if (!best || r.width * r.height > best.width * best.height)
                    best = {x: r.x, y: r.y, width: r.width, height: r.height};
            }
            return best;
        }"""
    )
    assert box is not None and box["width"] > 100 and box["height"] > 100, f"no 3D canvas: {box}"
    png = page.screenshot(clip=box, timeout=180_000)  # software WebGL on 2 busy cores is slow
    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("L"), dtype=np.float32)
    return float(pixels.std()) > 5.0  # a blank canvas is one flat colour


def readout_of(page) -> str:
    return page.get_by_text(READOUT).first.inner_text()


def test_page_renders_and_t4_register_converges(fresh: RoadmapApp, browser) -> None:
    app = fresh
    url = url_of(app.server, TEST_GUARD, with_token=True)
    log = audit.audit_log()
    before = len(list(log.lines()))
    # Generous timeouts: Chromium draws WebGL in software here, on the same 2 cores as the app.
    page = browser.new_page(viewport={"width": 1280, "height": 760})
    second = browser.new_page(viewport={"width": 800, "height": 500})
    try:
        page.goto(url)
        page.get_by_role("button", name="Register").wait_for(timeout=90_000)
        # viser's "software WebGL" notice floats over the canvas: hide it so only the scene counts.
        page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")
        deadline = time.monotonic() + 90
        while not canvas_is_drawn(page) and time.monotonic() < deadline:
            time.sleep(1.0)
        assert canvas_is_drawn(page), "the 3D canvas stayed blank"

        page.get_by_role("button", name="T4", exact=True).click(force=True)  # skip waits for a still canvas
        page.get_by_text(re.compile(r"Residual: [3-9]\.\d\d mm in-plane")).wait_for(timeout=60_000)

        second.goto(url)  # a second tab joins the shared session...
        page.get_by_role("button", name="Register").click(force=True)
        page.get_by_text("REGISTERING…", exact=True).wait_for(timeout=60_000)
        second.close()  # ...and is closed mid-run: nothing breaks
        page.get_by_text(re.compile(r"· done")).wait_for(timeout=240_000)
        deadline = time.monotonic() + 30
        while True:
            inplane, _, rotation = parse_readout(readout_of(page))
            if inplane < 1.0 or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        assert inplane < 1.0, readout_of(page)
        assert rotation < 3.0
        page.get_by_text("REGISTERED").first.wait_for(timeout=30_000)
        assert page.get_by_role("button", name="Register").is_enabled()

        # A tab opened now shows the same, shared state.
        third = browser.new_page(viewport={"width": 800, "height": 500})
        try:
            third.goto(url)
            third.get_by_text(READOUT).first.wait_for(timeout=90_000)
            assert parse_readout(readout_of(third)) == parse_readout(readout_of(page))
        finally:
            third.close()
    finally:
        page.close()
        if not second.is_closed():
            second.close()
    # The audit log: one line per action of this test (three tabs signed in, one registration and
    # its correction), each from the browser's address; UIDs only, no name of any patient.
    new = list(log.lines())[before:]
    actions = [line["action"] for line in new]
    assert actions.count("sign-in") == 3 and actions.count("registration") == 1, actions
    assert actions.count("correction") == 1 and set(actions) == {"sign-in", "registration", "correction"}, actions
    assert all(line["client"] == "127.0.0.1" for line in new), new
    (correction,) = [line for line in new if line["action"] == "correction"]
    assert correction["result"].startswith("applied"), correction
    text = "".join(path.read_text() for path in log.files())
    assert "^" not in text and "PatientName" not in text and TEST_GUARD.token not in text
    allowed = {"time", "client", "action", "result", "study_uid", "series_uids", "instance_uid", "sop_class_uid",
               "ae_title", "count"}  # fmt: skip
    assert all(set(line) <= allowed for line in log.lines())


def test_biplane_mode_in_the_page(fresh: RoadmapApp, browser) -> None:
    """Biplane on from the page: plane B's controls, the out-of-plane readout, Register corrects tz."""
    app = fresh
    page = browser.new_page(viewport={"width": 1280, "height": 760})
    out_of_plane = re.compile(r"out-of-plane (\d+\.\d\d) mm")
    try:
        page.goto(url_of(app.server, TEST_GUARD, with_token=True))
        page.get_by_role("button", name="Register").wait_for(timeout=90_000)
        page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")
        page.get_by_text("Biplane", exact=True).click(force=True, timeout=120_000)  # software WebGL: slow page
        assert _wait(lambda: app.session.biplane, 30), "the Biplane checkbox did not reach the session"
        page.get_by_role("tab", name="C-arm").click(force=True, timeout=120_000)
        page.get_by_text("Plane B (lateral C-arm)").wait_for(timeout=60_000)
        app.offset_sliders[2].value = 10.0  # the patient moves along plane A's beam (shared session)
        page.get_by_text(re.compile(r"out-of-plane 10\.00 mm")).wait_for(timeout=60_000)
        page.get_by_role("button", name="Register").click(force=True)
        page.get_by_text(re.compile(r"· done")).wait_for(timeout=240_000)
        deadline = time.monotonic() + 30
        while True:
            text = page.get_by_text(out_of_plane).first.inner_text()
            _, total, rotation = parse_readout(text)
            if total < 1.0 or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        assert total < 1.0 and rotation < 3.0, text  # CONVENTIONS §6: the 3-D criterion
        assert float(out_of_plane.search(text)[1]) < 1.0, text
    finally:
        page.close()
        app.session.stop_registration(wait=True)
        app.biplane.value = False


def _wait(predicate, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.1)
    return predicate()


def _tile(page, size: int) -> np.ndarray:
    """The fluoro tile of the Roadmap tab's picture as the page shows it (RGB)."""
    import io

    from PIL import Image

    png = page.locator("img").first.screenshot(timeout=180_000)
    shown = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    return shown[:, : shown.shape[1] * size // (2 * size + 4)]  # left of the two tiles (4 px gap)


def test_overlay_modes_in_the_page(fresh: RoadmapApp, browser, tmp_path) -> None:
    """Every overlay mode chosen from the page's Compare tab: each screenshot drawn and distinct."""
    from PIL import Image

    from app.web.qa_panel import ComparePanel
    from registration.studies.qa_images import OVERLAY_LABELS, OVERLAY_MODES

    app = fresh
    panel = next(p for p in app.panels if isinstance(p, ComparePanel))
    page = browser.new_page(viewport={"width": 1280, "height": 760})
    try:
        page.goto(url_of(app.server, TEST_GUARD, with_token=True))
        page.get_by_role("button", name="Register").wait_for(timeout=90_000)
        page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")
        app.table_buttons["T4"].value = True  # the shared session: the patient moves (the page shows it)
        page.get_by_text(re.compile(r"Residual: [3-9]\.\d\d mm in-plane")).wait_for(timeout=120_000)
        page.get_by_role("tab", name="Compare").click(force=True, timeout=120_000)
        combo = page.locator(f'[id="{page.locator("label", has_text="Overlay").first.get_attribute("for")}"]')
        shots = {}
        for mode in OVERLAY_MODES:
            combo.click(force=True, timeout=120_000)
            page.get_by_role("option", name=OVERLAY_LABELS[mode], exact=True).click(force=True, timeout=60_000)
            assert _wait(lambda mode=mode: panel.settings().mode == mode, 30), mode
            for _ in range(2):  # the second frame began after the change
                frames = app.presenter.frames_shown
                app.presenter.force_refresh()
                assert _wait(lambda frames=frames: app.presenter.frames_shown > frames, 60)
            time.sleep(1.5)  # the newest picture reaches the page (updates leave every 1/60 s; a busy machine)
            shots[mode] = _tile(page, app.session.config.display_px)
            Image.fromarray(shots[mode]).save(tmp_path / f"overlay_{mode}.png")
        for mode, tile in shots.items():
            assert tile.shape[0] > 100 and tile.std() > 10, mode  # drawn, not blank
        differs = {
            (a, b): float(np.mean(np.abs(shots[a].astype(int) - shots[b].astype(int)).max(axis=2) > 8))
            for i, a in enumerate(OVERLAY_MODES)
            for b in OVERLAY_MODES[i + 1 :]
        }
        # the machine-based pose is 5.7 mm / 5.4 deg off: checkerboard and difference change much of the tile
        assert differs[("outline", "checkerboard")] > 0.10, differs
        assert differs[("outline", "difference")] > 0.10, differs
        assert all(v > 0.002 for v in differs.values()), differs  # every pair differs (line-only modes a little)
    finally:
        page.close()


def test_default_camera_frames_the_vessels(fresh: RoadmapApp, browser) -> None:
    """The 3-D view's default camera: the vessels' screen box spans >= 1/3 of the canvas height,
    by the tab's own camera (as it reports it) and in the screenshot (the red vessel pixels)."""
    import io

    from PIL import Image

    from app.web.scene import screen_extent

    app = fresh
    page = browser.new_page(viewport={"width": 1280, "height": 760})
    try:
        page.goto(url_of(app.server, TEST_GUARD, with_token=True))
        page.get_by_role("button", name="Register").wait_for(timeout=90_000)
        page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")
        assert _wait(lambda: len(app.server.get_clients()) > 0, 60)
        client = list(app.server.get_clients().values())[-1]
        time.sleep(5)  # the canvas settles and the camera is aimed at its shape
        camera = client.camera
        vessels = app.session.data.meshes(app.session.settings.volume_format_cm)["vessels"]
        points = np.asarray(vessels.vertices) * 1e-3
        height, width = screen_extent(points, camera.position, camera.look_at, camera.up_direction, camera.fov,
                                      camera.aspect)  # fmt: skip
        assert height >= 1 / 3 and width <= 1.0, (height, width, camera.aspect)
        deadline = time.monotonic() + 90
        while not canvas_is_drawn(page) and time.monotonic() < deadline:
            time.sleep(1.0)
        box = page.evaluate(
            """() => { let best = null;
                for (const c of document.querySelectorAll("canvas")) { const r = c.getBoundingClientRect();
                    if (!best || r.width * r.height > best.width * best.height)
                        best = {x: r.x, y: r.y, width: r.width, height: r.height}; }
                return best; }"""
        )
        rgb = np.asarray(Image.open(io.BytesIO(page.screenshot(clip=box, timeout=180_000))).convert("RGB")).astype(int)
        red = (rgb[..., 0] > 120) & (rgb[..., 0] > 2 * rgb[..., 1]) & (rgb[..., 0] > 2 * rgb[..., 2])
        rows = np.flatnonzero(red.any(axis=1))
        assert rows.size, "no vessel drawn"
        # the screenshot's vessel pixels (some hidden behind bone): a quarter of the height at least
        assert (rows[-1] - rows[0] + 1) / rgb.shape[0] >= 0.25, (rows[0], rows[-1], rgb.shape)
    finally:
        page.close()
