"""A small, fast configuration of the app shared by the app tests."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator

import pytest

from app.web.data import AppConfig
from app.web.gui import RoadmapApp
from app.web.main import build_app, make_server
from app.web.signin import Guard
from registration.io import audit

#: Small grids so the suite stays fast (registration still has to reach < 1 mm in-plane), a
#: coarse skull (the browser test draws it with software WebGL on the same 2 cores), the quick
#: resampled stand-in volume instead of the FDK 3DRA (a minute to build the first time) and a
#: short low-resolution rotational run for the calibration view.
TEST_CONFIG = AppConfig(
    voxels=128, pixels=256, display_px=256, skull_detail=32, volume_source="resampled", run_pixels=64,
    run_projections=12,
)  # fmt: skip

READOUT = re.compile(r"Residual: (\d+\.\d\d) mm in-plane, (\d+\.\d\d) mm total, (\d+\.\d\d)° rotation")


def parse_readout(text: str) -> tuple[float, float, float]:
    match = READOUT.search(text)
    assert match, f"readout not in the expected form: {text!r}"
    return float(match[1]), float(match[2]), float(match[3])


def wait_until(predicate, timeout: float, step: float = 0.05) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


#: The shared app's sign-in token (the browser tests open the page with it, as a user does).
TEST_TOKEN = "test-token-0123456789abcdef"
#: Its guard: sign-in and the origin check, as ``roadmap3d app`` serves.
TEST_GUARD = Guard(TEST_TOKEN, audit=audit.record)


@pytest.fixture(scope="session", autouse=True)
def _audit_in_tmp(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The audit log of the app tests in a folder of the test run, not the user's (for the whole
    session: the shared app's threads write to it between tests too)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(audit.ENV_AUDIT_DIR, str(tmp_path_factory.mktemp("audit")))
        yield


@pytest.fixture(scope="session")
def app() -> Iterator[RoadmapApp]:
    server = make_server("127.0.0.1", 0, guard=TEST_GUARD)
    built = build_app(server, TEST_CONFIG)
    yield built
    built.close()
    server.stop()


@pytest.fixture()
def fresh(app: RoadmapApp) -> RoadmapApp:
    """The shared app, idle, with no patient motion and the default C-arm."""
    app.session.stop_registration(wait=True)
    app.autocorrect.value = False
    app.primary.value = 0.0
    app.secondary.value = 0.0
    app.sid.value = 1200.0
    app.image_format.value = "27 cm"
    app.volume_format.value = "27 cm"
    app.kind.value = "fluoro"
    app.reset_button.value = True
    # On screen before the test acts: the presenter draws these changes in its own thread (a new
    # volume format loads its surfaces and says so in the status line, which a test reading the
    # status right after its own action would otherwise see).
    assert wait_until(lambda: app._shown_version == app.session.version, 60)  # noqa: SLF001
    return app
