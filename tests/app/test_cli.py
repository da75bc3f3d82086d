"""`roadmap3d app` as a user runs it: prints its real URL, serves, stops cleanly on Ctrl-C."""

from __future__ import annotations

import http.cookiejar
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from .test_user_data import exported  # noqa: F401 - the module fixture writing the user's files

ROOT = Path(__file__).resolve().parents[2]


def start(*args: str) -> subprocess.Popen[str]:
    env = {
        **os.environ,
        "ROADMAP3D_APP_VOXELS": "128",
        "ROADMAP3D_APP_PIXELS": "256",
        "ROADMAP3D_APP_VOLUME": "resampled",  # the quick stand-in (the FDK 3DRA is tested by the engine)
        "PYTHONUNBUFFERED": "1",
    }
    return subprocess.Popen(
        [sys.executable, "-c", "from app.cli import main; main()", *args],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def wait_for_line(proc: subprocess.Popen[str], pattern: str, timeout: float) -> re.Match[str]:
    seen = []
    end = time.monotonic() + timeout
    assert proc.stdout is not None
    while time.monotonic() < end:
        line = proc.stdout.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        seen.append(line)
        match = re.search(pattern, line)
        if match:
            return match
    proc.kill()
    raise AssertionError(f"no line matching {pattern!r}; output:\n{''.join(seen)}")


@pytest.mark.parametrize("command", ["demo", "app-with-files"])
def test_serves_and_stops_on_ctrl_c(command: str, exported: Path) -> None:  # noqa: F811
    files = ["--volume", str(exported / "volume.npz"), "--image", str(exported / "image.dcm")]
    proc = start("demo", "--port", "0") if command == "demo" else start("app", "--port", "0", *files)
    try:
        # the printed address carries the sign-in token (/?token=...): a user opens exactly it
        url = wait_for_line(proc, r"serving on (http://127\.0\.0\.1:\d+\S*)", 60)[1]
        wait_for_line(proc, r"ready after", 120)
        # /?token= answers with the sign-in cookie and a redirect to the page, as for a browser
        opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(http.cookiejar.CookieJar()))
        with opener.open(url, timeout=10) as response:
            assert response.status == 200
        proc.send_signal(signal.SIGINT)
        t0 = time.monotonic()
        assert proc.wait(timeout=15) == 0
        assert time.monotonic() - t0 < 10
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "Traceback" not in (proc.stdout.read() if proc.stdout else "")


@pytest.mark.parametrize(
    "args",
    [
        ["app", "--volume", "/nonexistent/volume", "--image", "/nonexistent/image.dcm"],
        ["app", "--volume", "/nonexistent/volume"],
    ],
)
def test_app_refuses_bad_paths_with_a_message(args: list[str]) -> None:
    proc = start(*args, "--port", "0")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 2, out
    assert "error:" in out and "Traceback" not in out


@pytest.mark.parametrize("args", [["--help"], ["register", "--help"], ["validate", "table1", "--help"]])
def test_help_loads_neither_numba_nor_viser(args: list[str]) -> None:
    # The declarations import their runners lazily: --help prints without the engine's compiler or the web server.
    code = (
        "import sys\n"
        "from app.cli import main\n"
        "try:\n"
        f"    main({args!r})\n"
        "except SystemExit as exc:\n"
        "    assert exc.code == 0, exc.code\n"
        "heavy = sorted(m for m in ('numba', 'viser') if m in sys.modules)\n"
        "assert not heavy, heavy\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "usage: roadmap3d" in done.stdout
