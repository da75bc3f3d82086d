"""The server under abuse (issues 12 and 15): upload budgets in total, idle transfers dropped,
reads abandoned after their time budget, readers that cannot outlive the server, honest binding."""

from __future__ import annotations

import io
import threading
import time
import zipfile
from pathlib import Path

import pytest

from app.web.main import network_warning
from app.web.upload import UploadBudget, read_upload, shutdown_readers
from registration.io.dicom import UploadError
from tests.app.conftest import TEST_CONFIG

MB = 1_000_000


def _state(client: str, name: str, total: int, received: int = 0) -> dict:
    return {"client_id": client, "filename": name, "total_bytes": total, "transferred_bytes": received}


def test_forty_unfinished_transfers_do_not_fit_the_budget_of_one_upload() -> None:
    """40 transfers of 7.5 MB against --max-upload-mb 8 pinned +231 MB until the client left."""
    budget = UploadBudget(8 * MB)
    states: dict = {}
    admitted = 0
    for n in range(40):
        states[f"t{n}"] = _state("tab", f"part{n}.zip", int(7.5 * MB))
        why = budget.admit(states, f"t{n}")
        if why is None:
            admitted += 1
        else:
            states.pop(f"t{n}")
            assert "this tab's uploads in flight" in why and "budget of 8 MB" in why
    assert admitted == 1  # the tab holds at most one upload's worth: 7.5 MB, not 300 MB
    assert sum(s["total_bytes"] for s in states.values()) <= 8 * MB


def test_the_server_budget_holds_across_clients() -> None:
    budget = UploadBudget(8 * MB)  # server budget: 2 uploads' worth
    states: dict = {}
    for n in range(2):
        states[f"t{n}"] = _state(f"tab{n}", f"f{n}.zip", 6 * MB)
        assert budget.admit(states, f"t{n}") is None
    states["t2"] = _state("tab2", "f2.zip", 6 * MB)
    why = budget.admit(states, "t2")
    assert why is not None and "on the server would hold 18.0 MB" in why and "budget of 16 MB" in why


def test_a_client_that_lies_about_the_size_is_caught_by_the_bytes_received() -> None:
    budget = UploadBudget(8 * MB)
    states = {"t": _state("tab", "small.zip", 1000, received=9 * MB)}
    assert "over the upload limit of 8 MB" in (budget.admit(states, "t") or "")


def test_idle_transfers_are_dropped_after_the_timeout() -> None:
    budget = UploadBudget(8 * MB, idle_timeout_s=60.0)
    states = {"slow": _state("tab", "slow.zip", MB), "busy": _state("tab2", "busy.zip", MB)}
    assert budget.admit(states, "slow", now=0.0) is None
    assert budget.admit(states, "busy", now=0.0) is None
    assert budget.sweep(states, now=30.0) == []
    assert budget.admit(states, "busy", now=50.0) is None  # a part arrived
    dropped = budget.sweep(states, now=61.0)
    assert dropped == [("tab", "slow.zip: upload dropped, no data for 60 s")]
    assert list(states) == ["busy"]  # its buffered parts are freed with the state


def _upload() -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("case/readme.txt", "nothing to read here")
    return buffer.getvalue()


def hanging_reader(zip_path: Path, folder: Path, name: str, max_bytes: int) -> tuple:
    """A reader stuck forever (called in the reading process)."""
    folder.mkdir()
    (folder / "partial.dcm").write_bytes(b"half a file")
    while True:
        time.sleep(1.0)


def test_a_hung_read_is_abandoned_after_its_time_budget() -> None:
    start = time.monotonic()
    with pytest.raises(UploadError, match=r"case.zip: reading took longer than 1 s and was abandoned"):
        read_upload("case.zip", _upload(), max_bytes=MB, config=TEST_CONFIG, timeout_s=1.0, reader=hanging_reader)
    assert time.monotonic() - start < 30.0  # abandoned, not waited for (generous: the first read starts a process)
    assert not list(Path(_tmp_root()).glob("roadmap3d-upload-*/files/partial.dcm"))


def _tmp_root() -> str:
    import tempfile

    return tempfile.gettempdir()


def test_shutdown_ends_a_hung_reader_and_removes_its_folder() -> None:
    """A hung reader outlived the server (SIGTERM printed 'Server stopped', SIGKILL needed) and
    its upload folder stayed."""
    outcome: dict = {}

    def upload() -> None:
        try:
            read_upload("case.zip", _upload(), max_bytes=MB, config=TEST_CONFIG, timeout_s=600, reader=hanging_reader)
        except UploadError as exc:
            outcome["error"] = str(exc)

    before = set(Path(_tmp_root()).glob("roadmap3d-upload-*"))
    thread = threading.Thread(target=upload, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not list(Path(_tmp_root()).glob("roadmap3d-upload-*/files/partial.dcm")):
        time.sleep(0.1)
    assert list(Path(_tmp_root()).glob("roadmap3d-upload-*/files/partial.dcm")), "the reader never started"
    shutdown_readers()
    thread.join(10.0)
    assert not thread.is_alive()
    assert "ended without an answer" in outcome["error"]
    assert set(Path(_tmp_root()).glob("roadmap3d-upload-*")) <= before


def test_a_valid_upload_still_reads(tmp_path: Path) -> None:
    import numpy as np

    from registration.core.volume import Volume
    from registration.io import dicom
    from tests.registration.io.test_fuzz import _xray

    volume = Volume(np.random.default_rng(0).normal(0, 300, (6, 6, 6)).astype(np.float32), np.eye(4), label="mine")
    dicom.write_npz(volume, tmp_path / "v.npz")
    dicom.write_xray(_xray(), tmp_path / "xa.dcm")
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.write(tmp_path / "v.npz", "case/v.npz")
        archive.write(tmp_path / "xa.dcm", "case/xa.dcm")
    data = read_upload("case.zip", buffer.getvalue(), max_bytes=10 * MB, config=TEST_CONFIG)
    assert data.label == "mine" and data.source == "upload case.zip"
    assert data.fixed_xray is not None and data.fixed_xray.image.shape == (24, 24)


@pytest.mark.parametrize(
    ("host", "warned"), [("127.0.0.1", False), ("localhost", False), ("0.0.0.0", True), ("192.168.1.7", True)]
)
def test_binding_beyond_this_machine_is_warned_about(host: str, warned: bool) -> None:
    text = network_warning(host, 8080)
    assert (text is not None) == warned
    if text:
        assert "token" in text and "--certfile" in text and "docs/deployment.md" in text
        assert ("every network interface" in text) == (host == "0.0.0.0")


SERVER_WITH_A_HUNG_READER = """
import threading, time
import app.web.main as main
from app.web.upload import read_upload
from tests.app.conftest import TEST_CONFIG
from tests.app.test_upload_server import _upload, hanging_reader

class App:
    def close(self):
        pass

def build_app(server, config, **kwargs):
    # an upload whose reader hangs, in a non-daemon thread as viser's callbacks are ...
    def upload():
        try:
            read_upload("case.zip", _upload(), max_bytes=10**6, config=TEST_CONFIG, timeout_s=3600,
                        reader=hanging_reader)
        except ValueError as exc:  # what the controller shows in the page
            print("upload refused:", exc, flush=True)
    threading.Thread(target=upload).start()
    # ... and a callback that never returns
    threading.Thread(target=lambda: time.sleep(3600)).start()
    return App()

main.build_app = build_app
main.run_app(host="127.0.0.1", port=0, volume=None, image=None)
"""


def test_sigterm_ends_a_server_with_a_hung_reader_and_removes_its_folder(tmp_path: Path) -> None:
    """SIGTERM printed 'Server stopped' but the process needed SIGKILL and its upload folder stayed."""
    import os
    import signal
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "TMPDIR": str(tmp_path), "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-c", SERVER_WITH_A_HUNG_READER], cwd=root, env=env, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not list(tmp_path.glob("roadmap3d-upload-*/files/partial.dcm")):
            assert proc.poll() is None, proc.stdout.read() if proc.stdout else ""
            time.sleep(0.2)
        assert list(tmp_path.glob("roadmap3d-upload-*/files/partial.dcm")), "the hung reader never started"
        proc.send_signal(signal.SIGTERM)
        start = time.monotonic()
        proc.wait(timeout=30)
        assert time.monotonic() - start < 15.0  # EXIT_GRACE_S (5 s) plus a loaded machine's slack
    finally:
        if proc.poll() is None:
            proc.kill()
    output = proc.stdout.read() if proc.stdout else ""
    assert "Traceback" not in output, output
    assert "upload refused: case.zip: the reader ended without an answer" in output
    assert not list(tmp_path.glob("roadmap3d-upload-*")), "the upload folder outlived the server"


def test_an_all_zero_uploaded_volume_is_not_registered_in_the_app() -> None:
    """An all-zero uploaded volume got the "REGISTERED" badge at the search bounds."""
    import numpy as np

    from app.web.data import FileData
    from app.web.session import Session
    from registration.core.volume import Volume
    from tests.registration.io.test_fuzz import _xray

    zeros = Volume(np.zeros((16, 16, 16), np.float32), np.diag([2.0, 2.0, 2.0, 1.0]), label="zeros")
    session = Session(FileData(zeros, _xray(64), source="upload zeros.zip", config=TEST_CONFIG), TEST_CONFIG)
    done = threading.Event()
    assert session.start_registration(on_done=done.set)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and session.run.running:
        time.sleep(0.05)
    assert not session.run.running
    assert session.run.result is None
    assert "cannot register: the volume 'zeros' is constant" in (session.run.error or "")
    np.testing.assert_array_equal(session.estimate, np.eye(4))  # the roadmap keeps its pose


def test_the_printed_address_is_the_one_listened_on() -> None:
    """`--host 0.0.0.0` printed http://localhost:PORT while listening on every interface."""
    from app.web.main import url_of

    class Server:
        def __init__(self, host: str) -> None:
            self.host = host

        def get_host(self) -> str:
            return self.host

        def get_port(self) -> int:
            return 8080

    assert url_of(Server("0.0.0.0")) == "http://0.0.0.0:8080"
    assert url_of(Server("127.0.0.1")) == "http://127.0.0.1:8080"
    assert url_of(Server("::")) == "http://[::]:8080"


def test_an_upload_without_a_volume_says_so_in_plain_words() -> None:
    with pytest.raises(UploadError, match="case.zip: found no volume; expected"):
        read_upload("case.zip", _upload(), max_bytes=MB, config=TEST_CONFIG)


def test_the_budget_is_wired_into_viser_s_upload_handlers() -> None:
    """The 40 unfinished transfers of issue 15, sent as viser messages to a real server."""
    import asyncio

    import viser
    from viser import _messages

    from app.web.upload import limit_uploads

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        button = server.gui.add_upload_button("Upload")
        refusals: list[str] = []
        limit_uploads(server, 8 * MB, lambda _client, why: refusals.append(why))
        states = server.gui._current_file_upload_states  # noqa: SLF001 - what the budget guards
        for n in range(40):
            start = _messages.FileTransferStartUpload(
                source_component_uuid=button._impl.uuid,  # noqa: SLF001
                transfer_uuid=f"t{n}", filename=f"part{n}.zip", mime_type="application/zip", part_count=8,
                size_bytes=int(7.5 * MB),
            )  # fmt: skip
            asyncio.run(server._websock_server._handle_incoming_message(7, start))  # noqa: SLF001
        assert list(states) == ["t0"] and len(refusals) == 39
        assert all("budget of 8 MB" in why for why in refusals)
    finally:
        server.stop()
