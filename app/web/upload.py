"""Uploads from the browser: a zip with the user's volume and X-ray image.

The archive is size-limited twice: while it streams in (an oversized transfer is dropped
before it is buffered whole) and when it is unpacked by :func:`registration.io.dicom.unpack_upload`
(no path from the archive is trusted: no ``..``, absolute names or links; zip bombs refused).
All transfers in flight together are held to a budget, per client and for the whole server,
and a transfer that stops sending parts is dropped after a timeout (:func:`limit_uploads`).

The archive is unpacked and read in a separate process (:func:`read_upload`), so a file that
makes a reader hang or swell cannot block the app: the read is abandoned after its time budget
with a message in the page, the process's memory is capped, at most :data:`MAX_READERS` reads run
at once in the server (Data tab, Play run and the DICOM node's runs share them), and :func:`shutdown_readers`
(called when the server stops) ends every reader and removes its temporary folder. The
folder is private (0700) and deleted as soon as the data is read; the readers and checks are
the command line's.
"""

from __future__ import annotations

import atexit
import logging
import math
import multiprocessing
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
import viser
from viser import _messages

from app.web.data import AppConfig, FileData

log = logging.getLogger(__name__)

#: Seconds a read of an upload may take before it is abandoned (ROADMAP3D_UPLOAD_READ_S).
READ_TIMEOUT_S = 120.0
#: Address space of the reading process (bytes, ROADMAP3D_UPLOAD_READ_MB): the readers' own
#: ceilings keep genuine data far below; this stops whatever they miss.
READER_MEMORY_BYTES = 6 * 1024**3
#: Reading processes at once for the whole server (each may use READER_MEMORY_BYTES): a further
#: upload is refused until one ends, never queued (ROADMAP3D_UPLOAD_READERS).
MAX_READERS = 2
#: A transfer that sends no part for this long is dropped (seconds).
IDLE_TIMEOUT_S = 60.0
#: All transfers in flight together, as multiples of the single-upload limit: per client, per server.
CLIENT_BUDGET_UPLOADS = 1.0
SERVER_BUDGET_UPLOADS = 2.0

EXPECTED = (
    "a .zip holding your volume (a DICOM series folder, one multi-frame file or the project's .npz) "
    "and one XA/RF image file"
)


class UploadBudget:
    """Admission of browser transfers: each under ``max_bytes``, and all in flight together under
    ``client_bytes`` per client and ``server_bytes`` for the server (declared sizes, and bytes
    received for a client that lies); transfers idle for ``idle_timeout_s`` are dropped.

    Works on viser's transfer states (``{uuid: {"client_id", "filename", "total_bytes",
    "transferred_bytes", ...}}``); :meth:`admit` and :meth:`sweep` return the refusals to report.
    """

    def __init__(
        self, max_bytes: int, *, client_bytes: int | None = None, server_bytes: int | None = None,
        idle_timeout_s: float = IDLE_TIMEOUT_S,
    ) -> None:  # fmt: skip
        if max_bytes <= 0:
            raise ValueError(f"max_bytes must be positive, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self.client_bytes = int(client_bytes if client_bytes is not None else CLIENT_BUDGET_UPLOADS * max_bytes)
        self.server_bytes = int(server_bytes if server_bytes is not None else SERVER_BUDGET_UPLOADS * max_bytes)
        self.idle_timeout_s = float(idle_timeout_s)
        self._last_seen: dict[str, float] = {}
        self._lock = threading.Lock()

    @staticmethod
    def _size(state: dict) -> int:
        return max(int(state.get("total_bytes") or 0), int(state.get("transferred_bytes") or 0))

    def admit(self, states: dict, transfer_uuid: str, *, now: float | None = None) -> str | None:
        """None if the transfer may go on, else why it is refused (the caller drops it)."""
        with self._lock:
            state = states.get(transfer_uuid)
            if state is None:
                return None
            self._last_seen[transfer_uuid] = time.monotonic() if now is None else now
            size = self._size(state)
            mb = 1e6
            if size > self.max_bytes:
                return (
                    f"{state['filename']}: {size / mb:.1f} MB is over the upload limit of {self.max_bytes / mb:.0f} MB"
                )
            others = [s for uid, s in list(states.items()) if uid != transfer_uuid]
            client = size + sum(self._size(s) for s in others if s.get("client_id") == state.get("client_id"))
            if client > self.client_bytes:
                return (
                    f"{state['filename']}: this tab's uploads in flight would hold {client / mb:.1f} MB, over its "
                    f"budget of {self.client_bytes / mb:.0f} MB: wait for the others to finish"
                )
            total = size + sum(self._size(s) for s in others)
            if total > self.server_bytes:
                return (
                    f"{state['filename']}: uploads in flight on the server would hold {total / mb:.1f} MB, over its "
                    f"budget of {self.server_bytes / mb:.0f} MB: try again in a moment"
                )
            return None

    def sweep(self, states: dict, *, now: float | None = None) -> list[tuple[Any, str]]:
        """Drop transfers idle for longer than the timeout; (client id, message) of each."""
        now = time.monotonic() if now is None else now
        dropped = []
        with self._lock:
            for uid in list(self._last_seen):
                if uid not in states:
                    self._last_seen.pop(uid, None)
            for uid, state in list(states.items()):
                seen = self._last_seen.setdefault(uid, now)
                if now - seen > self.idle_timeout_s and states.pop(uid, None) is not None:
                    self._last_seen.pop(uid, None)
                    dropped.append(
                        (
                            state.get("client_id"),
                            f"{state['filename']}: upload dropped, no data for {self.idle_timeout_s:.0f} s",
                        )
                    )
        return dropped


def limit_uploads(
    server: viser.ViserServer, max_bytes: int, on_refused: Callable[[Any, str], None], *,
    budget: UploadBudget | None = None,
) -> UploadBudget:  # fmt: skip
    """Hold browser uploads to ``budget`` (default: :class:`UploadBudget` of ``max_bytes``)
    while they stream in (viser has no limit); refused and idle transfers are dropped, their
    buffered parts freed, and ``on_refused(client_id, message)`` says why."""
    budget = budget or UploadBudget(max_bytes)
    gui = server.gui
    states: dict = gui._current_file_upload_states  # noqa: SLF001 - viser keeps transfers here

    def check(client_id: Any, transfer_uuid: str) -> None:
        why = budget.admit(states, transfer_uuid)
        if why is not None and states.pop(transfer_uuid, None) is not None:
            on_refused(client_id, why)

    def on_start(client_id: Any, message: _messages.FileTransferStartUpload) -> None:
        check(client_id, message.transfer_uuid)

    def on_part(client_id: Any, message: _messages.FileTransferPart) -> None:
        check(client_id, message.transfer_uuid)  # a client that lied about the size is caught here

    # Registered after viser's own handlers, so they run right after them.
    server._websock_server.register_handler(_messages.FileTransferStartUpload, on_start)  # noqa: SLF001
    server._websock_server.register_handler(_messages.FileTransferPart, on_part)  # noqa: SLF001

    def sweeper() -> None:
        while True:
            time.sleep(max(1.0, min(10.0, budget.idle_timeout_s / 4)))
            for client_id, why in budget.sweep(states):
                try:
                    on_refused(client_id, why)
                except Exception:  # the tab or the server is going away
                    log.debug("could not report a dropped upload", exc_info=True)

    threading.Thread(target=sweeper, name="upload-sweeper", daemon=True).start()
    return budget


# --------------------------------------------------------------------------------------
# Reading in a separate process
# --------------------------------------------------------------------------------------
_ACTIVE_LOCK = threading.Lock()
_READING: list[str] = []  # the uploads being read now (names), at most MAX_READERS
_ACTIVE_PROCESSES: set[Any] = set()
_ACTIVE_FOLDERS: set[Path] = set()
_CONTEXT: Any = None


def _context() -> Any:
    """A forkserver context preloaded with the readers: a read starts in milliseconds, forked
    from a clean single-threaded process (never from the server's threads)."""
    global _CONTEXT
    with _ACTIVE_LOCK:
        if _CONTEXT is None:
            method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
            ctx = multiprocessing.get_context(method)
            if method == "forkserver":
                ctx.set_forkserver_preload(["app.web.upload", "registration.io.dicom"])
            _CONTEXT = ctx
        return _CONTEXT


def _env_float(name: str, default: float) -> float:
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{name} must be a number, got {text!r}") from None
    if not value > 0:
        raise ValueError(f"{name} must be positive, got {text!r}")
    return value


def _read_in_child(
    zip_path: str, folder: str, name: str, max_bytes: int, memory_bytes: int, conn: Connection,
    reader: Callable[[Path, Path, str, int], Any] | None = None,
    distances_mm: tuple[float | None, float | None] = (None, None),
) -> None:  # fmt: skip
    """The reading process: ``reader(path, folder, name, max_bytes)`` (default: unpack the zip,
    find and read the volume and the image), its result sent back."""
    try:
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))
    except (ImportError, ValueError, OSError):
        pass
    try:
        if reader is None:
            sid_mm, sod_mm = distances_mm
            result = _unpack_and_read(Path(zip_path), Path(folder), name, max_bytes, sid_mm=sid_mm, sod_mm=sod_mm)
        else:
            result = reader(Path(zip_path), Path(folder), name, max_bytes)
        conn.send(("ok", result))
    except ValueError as exc:  # UploadError, DicomError: the message for the page (named, not the temporary path)
        conn.send(("refused", str(exc).replace(zip_path, name)))
    except MemoryError:
        conn.send(("refused", f"{name}: reading it needs more than {memory_bytes / 1e9:.1f} GB of memory"))
    except BaseException as exc:  # a reader bug: still a message, never a hung page
        conn.send(("refused", f"{name}: cannot read it ({type(exc).__name__}: {str(exc)[:200]})"))
    finally:
        conn.close()


def _unpack_and_read(
    zip_path: Path, folder: Path, name: str, max_bytes: int, *, sid_mm: float | None = None, sod_mm: float | None = None
) -> tuple[Any, Any]:
    from registration.io.dicom import UploadError, classify_upload, read_volume, read_xray, unpack_upload

    try:
        unpack_upload(zip_path.read_bytes(), folder, max_bytes=max_bytes)
    except UploadError as exc:  # name the upload: the archive's own messages do not know it
        raise UploadError(f"{name}: {exc}") from None
    found = classify_upload(folder)
    if found["volume"] is None or found["image"] is None:
        missing = "volume" if found["volume"] is None else "XA/RF image"
        raise UploadError(f"{name}: found no {missing}; expected {EXPECTED}")
    from registration.io.isocenter import resolve_isocenter

    volume = read_volume(found["volume"])
    iso, _ = resolve_isocenter(None, volume)  # the volume's IsocenterPosition, else the origin (as register)
    return volume, read_xray(found["image"], frame=None, isocenter_mm=iso, sid_mm=sid_mm, sod_mm=sod_mm)


def shutdown_readers(timeout_s: float = 2.0) -> None:
    """End every reading process and remove every upload folder (when the server stops)."""
    with _ACTIVE_LOCK:
        processes = list(_ACTIVE_PROCESSES)
        folders = list(_ACTIVE_FOLDERS)
    for process in processes:
        if process.is_alive():
            process.kill()
    for process in processes:
        process.join(timeout_s)
    for folder in folders:
        shutil.rmtree(folder, ignore_errors=True)


atexit.register(shutdown_readers)


def distance_mm(text: str, what: str) -> float | None:
    """An optional distance typed into the Data tab: empty gives None, else a positive number of mm."""
    text = text.strip().removesuffix("mm").strip()
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{what} must be a number of mm (or empty), got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{what} must be a positive number of mm (or empty), got {text!r}")
    return value


#: How far outside the volume's voxel grid (mm) a typed iso-center may lie: the C-arm's iso-center
#: is inside the anatomy, and a typo (a dropped minus, a missing decimal point) lands far outside.
ISOCENTER_MARGIN_MM = 50.0
#: The Data tab's keyword for the center of the volume's grid (as ``--isocenter volume-center``).
VOLUME_CENTER_WORDS = ("volume center", "volume-center", "volume centre", "volume-centre")
#: The Data tab's keyword for the middle of the head (as ``--isocenter head``).
HEAD_WORDS = ("head", "head center", "head centre", "middle of the head")


def isocenter_field(text: str, volume: Any) -> tuple[tuple[float, float, float], str]:
    """The iso-center typed into the Data tab: ``"x, y, z"`` in mm (the volume's patient
    coordinates, LPS; commas or spaces, an optional "mm"), "head" (the middle of the head,
    :func:`registration.io.isocenter.head_isocenter_mm`) or "volume center", and where it came
    from. ValueError (a message for the page) unless three finite numbers within
    :data:`ISOCENTER_MARGIN_MM` of the volume's grid."""
    raw = text.strip()
    if raw.lower() in VOLUME_CENTER_WORDS:
        center = [float(v) for v in volume.center_mm]
        return (center[0], center[1], center[2]), "the center of the volume's grid (Data tab)"
    if raw.lower() in HEAD_WORDS:
        from registration.io.isocenter import head_isocenter_mm

        try:
            return head_isocenter_mm(volume), "the middle of the head (Data tab)"
        except ValueError as e:
            raise ValueError(f"Iso-center: {e}") from None
    parts = raw.removesuffix("mm").replace(",", " ").split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"Iso-center: expected three numbers 'x, y, z' in mm, 'head' or 'volume center', got {text!r}")
    corners = np.asarray(volume.world_corners_mm())
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    iso = np.asarray(values)
    outside = float(np.linalg.norm(np.maximum(lo - iso, 0.0) + np.maximum(iso - hi, 0.0)))
    if outside > ISOCENTER_MARGIN_MM:
        box = ", ".join(f"{axis} {a:.0f}..{b:.0f}" for axis, a, b in zip("xyz", lo, hi, strict=True))
        raise ValueError(
            f"Iso-center ({values[0]:g}, {values[1]:g}, {values[2]:g}) mm lies {outside:.0f} mm outside the volume "
            f"({box} mm; at most {ISOCENTER_MARGIN_MM:g} mm outside): not changed"
        )
    return (values[0], values[1], values[2]), "the Data tab"


def read_upload(
    name: str, content: bytes, *, max_bytes: int, config: AppConfig, timeout_s: float | None = None,
    memory_bytes: int | None = None, reader: Callable[[Path, Path, str, int], tuple[Any, Any]] | None = None,
    sid_mm: float | None = None, sod_mm: float | None = None,
) -> FileData:  # fmt: skip
    """The volume and image in an uploaded zip, read in a separate process within ``timeout_s``
    (default READ_TIMEOUT_S or ROADMAP3D_UPLOAD_READ_S) and ``memory_bytes``; ValueError
    (UploadError, with a message for the page) if refused, abandoned or failed.

    ``reader(zip_path, folder, name, max_bytes) -> (volume, xray)`` replaces the unpacking and
    reading (a module-level function: it is called in the reading process; tests hang it).
    ``sid_mm`` / ``sod_mm`` supply the distances of an X-ray image that lacks them
    (:func:`registration.io.dicom.read_xray`).
    """
    from registration.io.dicom import UploadError

    if not name.lower().endswith(".zip"):
        raise UploadError(f"{name}: expected {EXPECTED}")
    _check_size(name, len(content), max_bytes)
    volume, xray = read_sandboxed(
        name, content=content, max_bytes=max_bytes, timeout_s=timeout_s, memory_bytes=memory_bytes, reader=reader,
        distances_mm=(sid_mm, sod_mm), file_name="upload.zip",
    )  # fmt: skip
    from registration.io.isocenter import resolve_isocenter

    iso, iso_from = resolve_isocenter(None, volume)  # how the reader placed the image (as register)
    if not np.allclose(xray.geometry.isocenter_mm, iso):
        iso_from = "the image's geometry"
    return FileData(volume, xray, source=f"upload {name}", config=config, isocenter_from=iso_from)


def _check_size(name: str, size: int, max_bytes: int) -> None:
    from registration.io.dicom import UploadError

    if size > max_bytes:
        raise UploadError(f"{name}: upload of {size} bytes exceeds the limit of {max_bytes} bytes")


def read_sandboxed(
    name: str, *, content: bytes | None = None, path: Path | None = None, max_bytes: int,
    reader: Callable[[Path, Path, str, int], Any] | None, timeout_s: float | None = None,
    memory_bytes: int | None = None, distances_mm: tuple[float | None, float | None] = (None, None),
    file_name: str = "upload.bin",
) -> Any:  # fmt: skip
    """``reader(file, folder, name, max_bytes)`` run in a separate process on ``content`` (written
    to a private temporary folder as ``file_name``) or on ``path`` (a file already on disk, e.g.
    one the DICOM node received), within ``timeout_s`` and ``memory_bytes`` (defaults as for
    :func:`read_upload`); its result, or UploadError naming ``name`` and the problem (refused,
    abandoned after the time budget, or a reader that died). ``reader=None`` unpacks and reads
    an uploaded zip (volume, image). At most MAX_READERS (ROADMAP3D_UPLOAD_READERS) reads run at
    once in the server, whoever asks (Data tab, Play run, the DICOM node): one more is refused at
    once with a message. Every reader process and folder is ended by :func:`shutdown_readers`."""
    from registration.io.dicom import UploadError

    if (content is None) == (path is None):
        raise ValueError("read_sandboxed needs content or path, not both")
    timeout_s = _env_float("ROADMAP3D_UPLOAD_READ_S", READ_TIMEOUT_S) if timeout_s is None else float(timeout_s)
    if memory_bytes is None:
        memory_bytes = int(_env_float("ROADMAP3D_UPLOAD_READ_MB", READER_MEMORY_BYTES / 1024**2) * 1024**2)
    readers = int(_env_float("ROADMAP3D_UPLOAD_READERS", MAX_READERS))
    with _ACTIVE_LOCK:  # the readers in flight share one budget: memory_bytes each, at most `readers`
        if len(_READING) >= readers:
            busy = ", ".join(_READING)
            raise UploadError(
                f"{name}: {len(_READING)} uploads are being read already ({busy}); try again when they finish"
            )
        _READING.append(name)
    try:
        return _read_in_process(name, content, path, max_bytes, reader, timeout_s, memory_bytes, distances_mm,
                                file_name)  # fmt: skip
    finally:
        with _ACTIVE_LOCK:
            _READING.remove(name)


def _read_in_process(
    name: str, content: bytes | None, path: Path | None, max_bytes: int, reader: Any, timeout_s: float,
    memory_bytes: int, distances_mm: tuple[float | None, float | None], file_name: str,
) -> Any:  # fmt: skip
    from registration.io.dicom import UploadError

    tmp = Path(tempfile.mkdtemp(prefix="roadmap3d-upload-"))  # mode 0700: private to this user
    with _ACTIVE_LOCK:
        _ACTIVE_FOLDERS.add(tmp)
    process = None
    try:
        if content is not None:
            file_path = tmp / file_name
            file_path.write_bytes(content)
        else:
            file_path = Path(path)  # type: ignore[arg-type]
        ctx = _context()
        receiver, sender = ctx.Pipe(duplex=False)
        process = ctx.Process(
            target=_read_in_child,
            args=(str(file_path), str(tmp / "files"), name, max_bytes, memory_bytes, sender, reader, distances_mm),
            name="roadmap3d-upload-reader",
            daemon=True,
        )
        with _ACTIVE_LOCK:
            _ACTIVE_PROCESSES.add(process)
        process.start()
        sender.close()
        try:
            ready = receiver.poll(timeout_s)
            reply = receiver.recv() if ready else None
        except (EOFError, OSError):
            process.join(5.0)
            code = process.exitcode
            why = "it was stopped" if code is not None and code < 0 else f"exit code {code}"
            raise UploadError(f"{name}: the reader ended without an answer ({why}; out of memory?)") from None
        finally:
            receiver.close()
        if reply is None:
            raise UploadError(
                f"{name}: reading took longer than {timeout_s:g} s and was abandoned (a damaged or hostile file?); "
                "the app goes on with what it showed"
            )
        status, result = reply
        if status != "ok":
            raise UploadError(result)
        return result
    finally:
        if process is not None and process.pid is not None:  # started (a start that failed has no pid)
            if process.is_alive():
                process.kill()
            process.join(5.0)
        with _ACTIVE_LOCK:
            _ACTIVE_PROCESSES.discard(process)
        shutil.rmtree(tmp, ignore_errors=True)  # nothing of the patient's stays on disk
        with _ACTIVE_LOCK:
            _ACTIVE_FOLDERS.discard(tmp)


# --------------------------------------------------------------------------------------
# Runs for the Play run panel
# --------------------------------------------------------------------------------------
#: Decoded frames of a run sent back to the server (bytes: float32 image + mask per pixel).
MAX_RUN_DECODED_BYTES = 1536 * 1024**2


@dataclass(frozen=True)
class ReadRun:
    """A run read for playing: every frame decoded (XRayImage, with its geometry), its times."""

    frames: list
    times_s: np.ndarray
    times_from: str


def _read_run(path: Path, _folder: Path, name: str, _max_bytes: int) -> ReadRun:
    """The reading process's work for a run (module level: called there)."""
    from registration.io import dicom

    run = dicom.read_xray_run(path)
    if len(run) < 2:
        raise dicom.UploadError(f"{name}: one frame, not a run")
    first = run.geometries[0]
    decoded = len(run) * first.rows * first.cols * 5  # float32 attenuation + bool mask
    if decoded > MAX_RUN_DECODED_BYTES:
        raise dicom.UploadError(
            f"{name}: {len(run)} frames of {first.rows} x {first.cols} pixels decode to {decoded / 1024**2:.0f} MB, "
            f"over Play run's limit of {MAX_RUN_DECODED_BYTES / 1024**2:.0f} MB"
        )
    frames = run.frames()
    for frame in frames:  # the sandbox's temporary copy is gone once read: the frames name the upload
        frame.meta["source"] = name
    return ReadRun(frames, np.asarray(run.times_s, np.float64), run.times_from)


def read_run_upload(
    name: str, *, content: bytes | None = None, path: Path | None = None, max_bytes: int,
    timeout_s: float | None = None, memory_bytes: int | None = None,
    reader: Callable[[Path, Path, str, int], ReadRun] | None = None,
) -> ReadRun:  # fmt: skip
    """A multi-frame XA/RF run (uploaded ``content``, or a received file at ``path``) read with
    its frame times by :func:`registration.io.dicom.read_xray_run` in the upload sandbox (a
    separate process, capped memory, a time limit: :func:`read_sandboxed`); UploadError naming
    ``name`` and the problem. ``reader`` replaces the reading (tests hang it)."""
    if content is not None:
        _check_size(name, len(content), max_bytes)
    return read_sandboxed(
        name, content=content, path=path, max_bytes=max_bytes, reader=reader or _read_run, timeout_s=timeout_s,
        memory_bytes=memory_bytes, file_name="run.dcm",
    )  # fmt: skip
