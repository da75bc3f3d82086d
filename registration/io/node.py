"""A DICOM node for the C-arm: C-ECHO and C-STORE SCP (pynetdicom).

:class:`DicomNode` accepts associations only from the calling AE titles it is given (and only
when they call it by its own AE title), binds 127.0.0.1 unless told otherwise, and writes every
received instance, byte for byte as sent, into a private folder (0700; files 0600):
``<folder>/<StudyInstanceUID>/<SeriesInstanceUID>/<SOPInstanceUID>.dcm``. A file appears
complete or not at all (written to a temporary name, then renamed), and the node answers the
C-STORE only after that: when the sender sees success, the file is there to read. Each received
instance is then reported to the ``on_received`` callback as a :class:`Received` (the command
line registers it, the app shows it); a failing callback is logged and never changes the answer.

Errors (a folder others can read, a port in use) are :class:`NodeError` (a ``ValueError``).
"""

from __future__ import annotations

import logging
import os
import re
import stat
import tempfile
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

DEFAULT_AE_TITLE = "ROADMAP3D"
DEFAULT_PORT = 11112
#: An instance larger than this (bytes as encoded) is refused with "out of resources".
MAX_INSTANCE_BYTES = 2 * 1024**3
#: DICOM status codes the node answers with.
STATUS_SUCCESS = 0x0000
STATUS_OUT_OF_RESOURCES = 0xA700
STATUS_CANNOT_UNDERSTAND = 0xC000

_UID = re.compile(r"^[0-9]+(\.[0-9]+)*$")
_AE = re.compile(r"^[\x20-\x7e]{1,16}$")


class NodeError(ValueError):
    """A DICOM node that cannot start as configured."""


def _storage_classes() -> list[str]:
    """SOP classes the node stores: what the project reads, and its results (REG, captures)."""
    from pydicom import uid

    return [
        uid.XRayAngiographicImageStorage,
        uid.EnhancedXAImageStorage,
        uid.XRayRadiofluoroscopicImageStorage,
        uid.EnhancedXRFImageStorage,
        uid.CTImageStorage,
        uid.EnhancedCTImageStorage,
        uid.LegacyConvertedEnhancedCTImageStorage,
        uid.XRay3DAngiographicImageStorage,
        uid.XRay3DCraniofacialImageStorage,
        uid.SecondaryCaptureImageStorage,
        uid.SpatialRegistrationStorage,
    ]


#: SOP classes whose instances are X-ray images or runs (fed to registration / live mode) ...
XRAY_SOP_CLASSES = frozenset(
    {"1.2.840.10008.5.1.4.1.1.12.1", "1.2.840.10008.5.1.4.1.1.12.1.1", "1.2.840.10008.5.1.4.1.1.12.2",
     "1.2.840.10008.5.1.4.1.1.12.2.1"}
)  # fmt: skip
#: ... and volumes (CT slices, enhanced CT, 3D XA).
VOLUME_SOP_CLASSES = frozenset(
    {"1.2.840.10008.5.1.4.1.1.2", "1.2.840.10008.5.1.4.1.1.2.1", "1.2.840.10008.5.1.4.1.1.2.2",
     "1.2.840.10008.5.1.4.1.1.13.1.1", "1.2.840.10008.5.1.4.1.1.13.1.2"}
)  # fmt: skip


@dataclass(frozen=True)
class Received:
    """One stored instance: where it is and what it is."""

    path: Path
    calling_ae: str
    sop_class_uid: str
    study_uid: str
    series_uid: str
    modality: str
    frames: int

    @property
    def role(self) -> str:
        """``xray`` (an XA/RF image or run), ``volume`` (a CT slice / 3D volume) or ``other``."""
        if self.sop_class_uid in XRAY_SOP_CLASSES:
            return "xray"
        if self.sop_class_uid in VOLUME_SOP_CLASSES:
            return "volume"
        return "other"


def private_folder(folder: str | os.PathLike[str]) -> Path:
    """Create ``folder`` (0700) or check an existing one is the user's alone; return it."""
    folder = Path(folder).expanduser()
    if folder.exists():
        info = folder.lstat()
        if not stat.S_ISDIR(info.st_mode):
            raise NodeError(f"{folder}: exists and is not a folder")
        if hasattr(os, "getuid") and info.st_uid != os.getuid():
            raise NodeError(f"{folder}: belongs to another user; received images must stay private")
        if info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise NodeError(f"{folder}: others can read it (mode {info.st_mode & 0o777:o}); chmod 700 {folder}")
    else:
        folder.mkdir(parents=True, mode=0o700)
        folder.chmod(0o700)
    return folder


def check_ae_title(title: str, what: str = "AE title") -> str:
    """A DICOM AE title: 1..16 printable ASCII characters, not only spaces."""
    if not isinstance(title, str) or not _AE.match(title) or not title.strip() or "\\" in title:
        raise NodeError(f"{what} {title!r}: must be 1 to 16 printable ASCII characters (no backslash)")
    return title.strip()


class DicomNode:
    """C-ECHO + C-STORE SCP. ``allowed`` calling AE titles only (none: nobody is accepted)."""

    def __init__(
        self,
        folder: str | os.PathLike[str],
        *,
        allowed: Iterable[str],
        ae_title: str = DEFAULT_AE_TITLE,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        on_received: Callable[[Received], None] | None = None,
    ) -> None:
        self.ae_title = check_ae_title(ae_title)
        self.allowed = tuple(check_ae_title(a, "allowed calling AE title") for a in allowed)
        if not self.allowed:
            raise NodeError("no calling AE title is allowed: give the C-arm's AE title (--allow AE)")
        if not 0 <= int(port) <= 65535:
            raise NodeError(f"port {port}: must be 0..65535")
        self.folder = private_folder(folder)  # last: a refused configuration leaves nothing behind
        self.host = host
        self.requested_port = int(port)
        self.on_received = on_received
        self._server: Any = None
        self._lock = threading.Lock()
        self.received: list[Received] = []

    # ----- life cycle ------------------------------------------------------------------
    def start(self) -> DicomNode:
        from pynetdicom import AE, ALL_TRANSFER_SYNTAXES, evt
        from pynetdicom.sop_class import Verification  # type: ignore[attr-defined]

        ae = AE(ae_title=self.ae_title)
        ae.require_calling_aet = list(self.allowed)
        ae.require_called_aet = True
        ae.add_supported_context(Verification)
        for sop_class in _storage_classes():
            ae.add_supported_context(sop_class, ALL_TRANSFER_SYNTAXES)
        handlers = [(evt.EVT_C_STORE, self._handle_store), (evt.EVT_C_ECHO, self._handle_echo)]
        try:
            self._server = ae.start_server((self.host, self.requested_port), block=False, evt_handlers=handlers)
        except OSError as exc:
            raise NodeError(f"cannot listen on {self.host}:{self.requested_port} ({exc.strerror or exc})") from None
        log.info("DICOM node %s listening on %s:%d", self.ae_title, self.host, self.port)
        return self

    @property
    def port(self) -> int:
        if self._server is None:
            return self.requested_port
        return int(self._server.server_address[1])

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server = None

    def __enter__(self) -> DicomNode:
        return self.start() if self._server is None else self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ----- handlers --------------------------------------------------------------------
    def _handle_echo(self, event: Any) -> int:
        log.info("C-ECHO from %s", event.assoc.requestor.ae_title)
        return STATUS_SUCCESS

    def _handle_store(self, event: Any) -> int:
        calling = str(event.assoc.requestor.ae_title).strip()
        try:
            ds = event.dataset
            sop_class = str(event.request.AffectedSOPClassUID)
            instance = str(event.request.AffectedSOPInstanceUID)
            study = str(ds.get("StudyInstanceUID", ""))
            series = str(ds.get("SeriesInstanceUID", ""))
        except Exception as exc:  # a dataset pydicom cannot decode
            log.warning("C-STORE from %s: unreadable dataset (%s)", calling, type(exc).__name__)
            return STATUS_CANNOT_UNDERSTAND
        if not all(_UID.match(u) and len(u) <= 64 for u in (instance, study, series)):
            log.warning("C-STORE from %s: refused, a UID is not a DICOM UID", calling)
            return STATUS_CANNOT_UNDERSTAND
        data = event.encoded_dataset()
        if len(data) > MAX_INSTANCE_BYTES:
            log.warning("C-STORE from %s: refused, %d bytes exceed %d", calling, len(data), MAX_INSTANCE_BYTES)
            return STATUS_OUT_OF_RESOURCES
        target = self.folder / study / series / f"{instance}.dcm"
        try:
            _write_private(target, data)
        except OSError as exc:
            log.error("C-STORE from %s: cannot write %s (%s)", calling, target, exc.strerror)
            return STATUS_OUT_OF_RESOURCES
        try:
            frames = int(ds.get("NumberOfFrames", 1) or 1)
        except (TypeError, ValueError):
            frames = 1
        item = Received(target, calling, sop_class, study, series, str(ds.get("Modality", "")), frames)
        with self._lock:
            self.received.append(item)
        log.info("C-STORE from %s: %s (%s, %d frame(s))", calling, target, item.modality, frames)
        if self.on_received is not None:
            try:
                self.on_received(item)
            except Exception:
                log.exception("the handler of received images failed on %s", target)
        return STATUS_SUCCESS


def _write_private(path: Path, data: bytes) -> None:
    for parent in (path.parent.parent, path.parent):
        if not parent.exists():
            parent.mkdir(mode=0o700, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".", suffix=".part", dir=path.parent)  # mode 0600
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
