"""Uploads from the browser: a zip with the user's volume and X-ray image.

The archive is size-limited twice: while it streams in (an oversized transfer is dropped
before it is buffered whole) and when it is unpacked by :func:`registration.io.dicom.unpack_upload`
(no path from the archive is trusted: no ``..``, absolute names or links; zip bombs refused).
It is unpacked into a private temporary folder that is deleted as soon as the data is read,
and read with the same readers and checks as the command line.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import viser
from viser import _messages

from app.data import AppConfig, FileData

log = logging.getLogger(__name__)

EXPECTED = (
    "a .zip holding your volume (a DICOM series folder, one multi-frame file or the project's .npz) "
    "and one XA/RF image file"
)


def limit_uploads(server: viser.ViserServer, max_bytes: int, on_refused: Callable[[Any, str], None]) -> None:
    """Drop browser uploads larger than ``max_bytes`` while they stream in (viser has no limit)."""
    gui = server.gui
    states: dict = gui._current_file_upload_states  # noqa: SLF001 - viser keeps transfers here

    def too_big(client_id: Any, transfer_uuid: str, size: int) -> None:
        state = states.pop(transfer_uuid, None)
        if state is not None:
            mb = max_bytes / 1e6
            on_refused(client_id, f"{state['filename']}: {size / 1e6:.1f} MB is over the upload limit of {mb:.0f} MB")

    def on_start(client_id: Any, message: _messages.FileTransferStartUpload) -> None:
        if message.size_bytes > max_bytes:
            too_big(client_id, message.transfer_uuid, message.size_bytes)

    def on_part(client_id: Any, message: _messages.FileTransferPart) -> None:
        state = states.get(message.transfer_uuid)
        if state is not None and state["transferred_bytes"] > max_bytes:  # a client that lied about the size
            too_big(client_id, message.transfer_uuid, state["transferred_bytes"])

    # Registered after viser's own handlers, so they run right after them.
    server._websock_server.register_handler(_messages.FileTransferStartUpload, on_start)  # noqa: SLF001
    server._websock_server.register_handler(_messages.FileTransferPart, on_part)  # noqa: SLF001


def read_upload(name: str, content: bytes, *, max_bytes: int, config: AppConfig) -> FileData:
    """The volume and image in an uploaded zip; ValueError (with a message for the page) if not."""
    from registration.io.dicom import UploadError, classify_upload, unpack_upload

    if not name.lower().endswith(".zip"):
        raise UploadError(f"{name}: expected {EXPECTED}")
    tmp = Path(tempfile.mkdtemp(prefix="roadmap3d-upload-"))  # mode 0700: private to this user
    try:
        folder = tmp / "files"
        try:
            unpack_upload(content, folder, max_bytes=max_bytes)
        except UploadError as exc:  # name the upload: the archive's own messages do not know it
            raise UploadError(f"{name}: {exc}") from None
        found = classify_upload(folder)
        if found["volume"] is None or found["image"] is None:
            missing = "volume" if found["volume"] is None else "XA/RF image"
            raise UploadError(f"{name}: found no {missing}; expected {EXPECTED}")
        data = FileData.from_paths(found["volume"], found["image"], frame=None, config=config)
        data.source = f"upload {name}"
        return data
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # nothing of the patient's stays on disk
