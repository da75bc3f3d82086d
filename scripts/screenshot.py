"""Regenerate docs/app.png (the README's picture of the web app) with Playwright + Chromium.

Starts the app in this process on a free port, opens it in Debian's headless Chromium, presses
T4 and Register, waits for the registration to finish and saves a screenshot. The volume is the
app's default (the FDK 3DRA; ``ROADMAP3D_APP_VOLUME=resampled`` for the stand-in). With
``--calibration PATH`` it then opens the Calibration tab, ticks it, shows a rotational-run frame
and saves that too.

    python scripts/screenshot.py [--out docs/app.png] [--chromium /usr/bin/chromium] [--no-register]
        [--calibration /tmp/calibration.png] [--playback /tmp/playback.png]

``--playback PATH`` then opens the Play run tab, presses Play and saves the run as it plays
(after a sudden move has been corrected, or after ``--playback-seconds``). ``--biplane PATH``
at last turns Biplane on, moves the patient 10 mm along plane A's beam on top of T4, registers
both planes and saves that screen.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def dismiss_notifications(page) -> None:
    """Hide viser's notices (headless Chromium gets "Software WebGL rendering detected")."""
    page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")


def _calibration_view(page: Any, path: Path) -> None:
    """The Calibration tab with the simulated rotational run's first frame."""
    page.get_by_role("tab", name="Calibration").click()
    page.get_by_text("Show the calibration").click()
    page.get_by_text(re.compile(r"Calibration error: [0-9.]+ mm")).wait_for(timeout=60_000)
    page.get_by_role("button", name=re.compile("Simulate the rotational run|Simulated")).click()
    page.get_by_text(re.compile(r"Frame 1 of \d+")).wait_for(timeout=180_000)
    time.sleep(2.0)
    page.screenshot(path=str(path), timeout=180_000)


def _playback_view(page: Any, path: Path, seconds: float) -> None:
    """The Play run tab after ``seconds`` of the phantom's run."""
    page.get_by_role("tab", name="Play run").click()
    page.get_by_role("button", name="Play", exact=True).click()
    try:
        page.get_by_text(re.compile(r"motion corrected")).first.wait_for(timeout=180_000)
    except Exception:  # noqa: BLE001 - no correction yet: take the picture anyway
        pass
    time.sleep(seconds)
    dismiss_notifications(page)
    page.screenshot(path=str(path), timeout=180_000)
    print(f"wrote {path}")


def _biplane_view(page: Any, app: Any, path: Path) -> None:
    """Biplane mode registered from T4's offsets plus 10 mm along plane A's beam."""
    page.get_by_text("Biplane", exact=True).click(force=True)
    page.get_by_role("tab", name="C-arm").click(force=True)
    page.get_by_text(re.compile(r"out-of-plane [0-9.]+ mm")).wait_for(timeout=120_000)
    app.session.stop_registration(wait=True)
    app.offset_sliders[2].value = 10.0  # T4's offsets plus 10 mm along plane A's beam
    deadline = time.monotonic() + 120
    while app.presenter.shown_version != app.session.version and time.monotonic() < deadline:
        time.sleep(0.2)
    page.get_by_role("button", name="Register").click(force=True)
    deadline = time.monotonic() + 60
    while not app.session.running and time.monotonic() < deadline:
        time.sleep(0.1)
    app.session.wait(240)
    time.sleep(3.0)  # the presenter's last frame and the 3D view settle
    dismiss_notifications(page)
    page.screenshot(path=str(path), timeout=180_000)
    print(f"wrote {path}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "app.png")
    parser.add_argument("--chromium", default="/usr/bin/chromium")
    parser.add_argument("--width", type=int, default=1600)
    parser.add_argument("--height", type=int, default=900)
    parser.add_argument("--no-register", action="store_true", help="only T4, no registration")
    parser.add_argument("--calibration", type=Path, default=None, help="also save the calibration view here")
    parser.add_argument("--playback", type=Path, default=None, help="also save the Play run tab here")
    parser.add_argument("--playback-seconds", type=float, default=14.0)
    parser.add_argument("--biplane", type=Path, default=None, help="also save biplane mode, registered, here")
    args = parser.parse_args()
    if not Path(args.chromium).exists():
        print(f"error: {args.chromium} not found (apt-get install chromium)", file=sys.stderr)
        return 2

    from playwright.sync_api import sync_playwright

    from app.web.main import build_app, make_server, url_of

    server = make_server("127.0.0.1", 0)
    app = build_app(server)
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(
                executable_path=args.chromium, args=["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader"]
            )
            page = browser.new_page(viewport={"width": args.width, "height": args.height})
            page.set_default_timeout(180_000)  # software WebGL on a busy machine is slow
            page.goto(url_of(server))
            page.get_by_role("button", name="Register").wait_for(timeout=30_000)
            page.get_by_role("button", name="T4", exact=True).click()
            time.sleep(1.0)
            if not args.no_register:
                page.get_by_role("button", name="Register").click()
                page.get_by_text(re.compile(r"Time [0-9.]+ s · \d+ DRRs · done")).wait_for(timeout=120_000)
            time.sleep(1.5)  # let the last frame and the 3D view settle
            dismiss_notifications(page)
            time.sleep(0.5)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(args.out), timeout=180_000)
            if args.calibration is not None:
                _calibration_view(page, args.calibration)
            if args.playback is not None:
                _playback_view(page, args.playback, args.playback_seconds)
            if args.biplane is not None:
                _biplane_view(page, app, args.biplane)
            browser.close()
    finally:
        app.close()
        server.stop()
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
