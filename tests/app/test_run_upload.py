"""Runs for Play run under abuse: read in the upload sandbox (a separate process, capped memory,
a time limit, the one upload budget), refused with a message naming the file, the server alive.

Every case goes through :meth:`app.web.playback.PlaybackPanel.load_run` (what the "Upload a run"
button calls) or ``load_run_file`` (what the DICOM node calls), as the Data tab's hostile-upload
tests go through the app's upload handler."""

from __future__ import annotations

import asyncio
import io
import tempfile
import time
from pathlib import Path

import numpy as np
import pydicom
import pytest

from app.web.gui import RoadmapApp
from app.web.upload import read_run_upload
from registration.io import dicom
from tests.registration.io.test_fuzz import _xray

MB = 1_000_000


def _run_bytes(tmp_path: Path, frames: int = 4) -> bytes:
    images = [_xray(32, primary=10.0, seed=n) for n in range(frames)]
    path = dicom.write_xray_run(images, tmp_path / "run.dcm", times_s=np.arange(frames) / 15.0)
    return path.read_bytes()


def _edited(raw: bytes, **tags: object) -> bytes:
    ds = pydicom.dcmread(io.BytesIO(raw))
    for keyword, value in tags.items():
        setattr(ds, keyword, value)
    out = io.BytesIO()
    ds.save_as(out)
    return out.getvalue()


def hanging_run_reader(path: Path, folder: Path, name: str, max_bytes: int) -> None:
    """A run reader stuck forever (called in the reading process)."""
    while True:
        time.sleep(1.0)


def swelling_run_reader(path: Path, folder: Path, name: str, max_bytes: int) -> None:
    """A run reader that asks for 16 GB (beyond the reading process's address space)."""
    return bytearray(16 * 1024**3)  # type: ignore[return-value]


def _refused(app: RoadmapApp, name: str, content: bytes, *needles: str) -> str:
    panel = app.playback
    before = panel.user_run
    start = time.monotonic()
    assert not panel.load_run(name, content)
    text = panel.message.content
    assert name in text and "refused" in text, text
    for needle in needles:
        assert needle in text, f"{needle!r} not in {text!r}"
    assert "⚠" in app.status.content and name in app.status.content  # the status line says it too
    assert panel.user_run is before  # the run to play stays what it was
    return f"{time.monotonic() - start:.1f} s"


def test_hostile_runs_are_refused_by_the_panels_handler(fresh: RoadmapApp, tmp_path: Path) -> None:
    raw = _run_bytes(tmp_path)
    pixel_data_at = raw.rindex(b"\xe0\x7f\x10\x00")  # (7FE0,0010): cut the file inside the pixels
    cases = [
        # 2^31-1 frames of 512 x 512 declared in a 20 kB file: refused before anything is allocated
        ("frames.dcm", _edited(raw, NumberOfFrames=2**31 - 1), "2147483647 x 32 x 32 pixels"),
        ("huge.dcm", _edited(raw, NumberOfFrames=20_000, Rows=4096, Columns=4096), "too large"),
        ("truncated.dcm", raw[: pixel_data_at + 200], "PixelData"),
        ("garbage.dcm", np.random.default_rng(0).bytes(50_000), "not a DICOM file"),
        ("empty.dcm", b"", "not a DICOM file"),
        ("one-frame.dcm", _run_bytes(tmp_path, frames=1), "one frame, not a run"),
    ]
    for name, content, needle in cases:
        _refused(fresh, name, content, needle)
    # the temporary copy (it lived in the sandbox's private folder) does not name the message
    assert "roadmap3d-upload-" not in fresh.playback.message.content
    # the server goes on: a genuine run still reads after all of them
    assert fresh.playback.load_run("good.dcm", raw)
    assert len(fresh.playback.user_run.frames) == 4
    assert {f.meta["source"] for f in fresh.playback.user_run.frames} == {"good.dcm"}  # not the deleted copy
    fresh.playback.use_phantom_run()


def test_a_run_whose_reader_hangs_or_swells_is_abandoned(
    fresh: RoadmapApp, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import app.web.upload

    raw = _run_bytes(tmp_path)
    private = tmp_path / "tmp"
    private.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(private))  # the sandbox's folders, away from others'
    monkeypatch.setenv("ROADMAP3D_UPLOAD_READ_S", "1")
    monkeypatch.setattr(app.web.upload, "_read_run", hanging_run_reader)  # pickled by name: the child runs it
    _refused(fresh, "stuck.dcm", raw, "reading took longer than 1 s and was abandoned")
    monkeypatch.setenv("ROADMAP3D_UPLOAD_READ_S", "60")
    monkeypatch.setattr(app.web.upload, "_read_run", swelling_run_reader)
    _refused(fresh, "swell.dcm", raw, "needs more than 6.4 GB of memory")  # READER_MEMORY_BYTES, 6 GiB
    assert not list(private.iterdir())  # the abandoned readers' folders (the run's copy) are removed


def test_a_received_run_is_read_in_the_sandbox_too(
    fresh: RoadmapApp, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What the DICOM node hands Play run (a file in its folder) goes through the same reader."""
    import app.web.upload

    path = tmp_path / "received.dcm"
    path.write_bytes(_edited(_run_bytes(tmp_path), NumberOfFrames=2**31 - 1))
    assert not fresh.playback.load_run_file(path, "XA run from CARM")
    assert "XA run from CARM" in fresh.playback.message.content and str(path) not in fresh.playback.message.content
    monkeypatch.setenv("ROADMAP3D_UPLOAD_READ_S", "1")
    monkeypatch.setattr(app.web.upload, "_read_run", hanging_run_reader)
    assert not fresh.playback.load_run_file(path, "XA run from CARM")
    assert "abandoned" in fresh.playback.message.content


def test_read_run_upload_holds_the_upload_limit() -> None:
    with pytest.raises(dicom.UploadError, match="run.dcm: upload of 2000 bytes exceeds the limit of 1000 bytes"):
        read_run_upload("run.dcm", content=bytes(2000), max_bytes=1000)


def test_run_uploads_count_in_the_one_upload_budget(fresh: RoadmapApp) -> None:
    """A run upload and a Data upload in flight from one tab share its budget (one upload's worth)."""
    from viser import _messages

    server = fresh.server
    states = server.gui._current_file_upload_states  # noqa: SLF001 - what the budget guards
    limit = fresh.max_upload_bytes
    try:
        for uuid, button in (("data", fresh.upload), ("run", fresh.playback.run_upload)):
            start = _messages.FileTransferStartUpload(
                source_component_uuid=button._impl.uuid,  # noqa: SLF001
                transfer_uuid=uuid, filename=f"{uuid}.bin", mime_type="application/octet-stream", part_count=64,
                size_bytes=int(0.6 * limit),
            )  # fmt: skip
            asyncio.run(server._websock_server._handle_incoming_message(7, start))  # noqa: SLF001
        assert list(states) == ["data"]  # the run's transfer was dropped: 1.2 uploads' worth from one tab
        assert "run.bin: this tab's uploads in flight" in fresh.status.content
    finally:
        states.clear()


def test_reads_in_flight_share_one_budget(fresh: RoadmapApp, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two uploads being read (each may use the reader's memory cap) hold the server's readers: a
    run uploaded meanwhile is refused at once with a message, not queued; it reads when they end."""
    import threading

    from app.web.upload import MAX_READERS, read_upload, shutdown_readers
    from tests.app.conftest import TEST_CONFIG
    from tests.app.test_upload_server import _upload, hanging_reader

    private = tmp_path / "tmp"
    private.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(private))
    outcomes: list[str] = []

    def hung(name: str) -> None:
        try:
            read_upload(name, _upload(), max_bytes=MB, config=TEST_CONFIG, timeout_s=120, reader=hanging_reader)
        except ValueError as exc:
            outcomes.append(str(exc))

    threads = [threading.Thread(target=hung, args=(f"case{n}.zip",), daemon=True) for n in range(MAX_READERS)]
    for thread in threads:
        thread.start()
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(list(private.glob("*/files/partial.dcm"))) < MAX_READERS:
            time.sleep(0.1)
        assert len(list(private.glob("*/files/partial.dcm"))) == MAX_READERS, "the readers never started"
        start = time.monotonic()
        _refused(fresh, "run.dcm", _run_bytes(tmp_path), "2 uploads are being read already", "case0.zip")
        assert time.monotonic() - start < 5.0  # refused, not queued behind the hung reads
    finally:
        shutdown_readers()  # ends the hung readers (what stopping the server does)
        for thread in threads:
            thread.join(10.0)
    assert len(outcomes) == MAX_READERS and all("ended without an answer" in text for text in outcomes)
    assert fresh.playback.load_run("run.dcm", _run_bytes(tmp_path))  # the readers are free again
    fresh.playback.use_phantom_run()
