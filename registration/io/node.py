"""A DICOM node for the C-arm: C-ECHO and C-STORE SCP (pynetdicom).

:class:`DicomNode` accepts associations only from the calling AE titles it is given (and only
when they call it by its own AE title), binds 127.0.0.1 unless told otherwise, and writes every
received instance, byte for byte as sent, into a private folder (0700; files 0600):
``<folder>/<StudyInstanceUID>/<SeriesInstanceUID>/<SOPInstanceUID>.dcm``. A file appears
complete or not at all, and the node answers the C-STORE only after that: when the sender sees
success, the file is there to read. Each received instance is then reported to the
``on_received`` callback as a :class:`Received` (the command line registers it, the app shows
it); a failing callback is logged and never changes the answer.

Nobody can stall it or fill its memory, allowed or not:

* every read has a deadline: a new connection must deliver its whole A-ASSOCIATE-RQ within
  :data:`ASSOCIATION_TIMEOUT_S`, each later PDU must arrive whole within :data:`PDU_TIMEOUT_S`
  of its first byte, and an association idle for :data:`IDLE_TIMEOUT_S` is aborted;
* a PDU longer than :data:`MAX_PDU_BYTES` (the maximum the node negotiates) ends the
  connection when its header is read, before any of it is buffered;
* a C-STORE's dataset is streamed to a file in the private folder as its fragments arrive (one
  PDU in memory at a time); past :data:`MAX_INSTANCE_BYTES` the rest is discarded and the
  C-STORE answered "out of resources";
* connections that have not yet been accepted (no AE title checked) are limited per peer
  address (:data:`MAX_PENDING_PER_PEER`) and in all (:data:`MAX_PENDING`), so strangers
  cannot take the slots of the C-arm; :meth:`DicomNode.stop` closes every connection at once.

A C-STORE is refused with a failure status, and nothing is written, when its dataset is
truncated or unreadable (0xC000), when its SOP class or instance differs from the command's
or its native pixel data is shorter than its rows, columns, frames and bits say (0xA900), and
when another instance already has its SOP Instance UID (0x0111; the same bytes sent again are
answered with success and kept once).

Errors (a folder others can read, a port in use) are :class:`NodeError` (a ``ValueError``).
"""

from __future__ import annotations

import contextlib
import filecmp
import io
import logging
import os
import re
import shutil
import socket
import stat
import struct
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pynetdicom.dul import DULServiceProvider
from pynetdicom.transport import RequestHandler, ThreadedAssociationServer

log = logging.getLogger(__name__)

DEFAULT_AE_TITLE = "ROADMAP3D"
DEFAULT_PORT = 11112
#: An instance larger than this (bytes as encoded) is refused with "out of resources".
MAX_INSTANCE_BYTES = 2 * 1024**3
#: The largest PDU accepted, and the maximum PDU length the node negotiates for P-DATA.
MAX_PDU_BYTES = 256 * 1024
#: A command set (or the dataset of a message other than C-STORE) longer than this ends the connection.
MAX_MESSAGE_PART_BYTES = 1024**2
#: Seconds a new connection has to deliver its whole A-ASSOCIATE-RQ.
ASSOCIATION_TIMEOUT_S = 5.0
#: Seconds a PDU may take to arrive whole once its first byte has come.
PDU_TIMEOUT_S = 30.0
#: Seconds an association may stay silent before the node aborts it.
IDLE_TIMEOUT_S = 60.0
#: Connections not yet accepted (AE titles unchecked) from one peer address, and from all.
MAX_PENDING_PER_PEER = 8
MAX_PENDING = 32
#: Accepted associations at once.
MAX_ASSOCIATIONS = 16
#: DICOM status codes the node answers with.
STATUS_SUCCESS = 0x0000
STATUS_DUPLICATE_INSTANCE = 0x0111
STATUS_OUT_OF_RESOURCES = 0xA700
STATUS_DOES_NOT_MATCH = 0xA900
STATUS_CANNOT_UNDERSTAND = 0xC000

_UID = re.compile(r"^[0-9]+(\.[0-9]+)*$")
_AE = re.compile(r"^[\x20-\x7e]{1,16}$")
_C_STORE_RQ = 0x0001
_NO_DATASET = 0x0101
_COPY_CHUNK = 1024**2


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
    instance_uid: str = ""
    #: The peer's address (host) as the node saw it.
    peer: str = ""

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


# --------------------------------------------------------------------------------------
# The guarded transport: deadlines, PDU cap, datasets streamed to disk
# --------------------------------------------------------------------------------------
@dataclass
class _Spool:
    """A C-STORE dataset as it arrives: its fragments appended to a private file."""

    message_id: int
    path: Path
    handle: Any
    size: int = 0
    over: bool = False
    done: bool = False


class _GuardedDUL(DULServiceProvider):
    """pynetdicom's upper layer with a deadline on every read, a cap on every PDU, and C-STORE
    datasets written to a spool file instead of memory (their PDVs passed on empty)."""

    def __init__(self, assoc: Any, node: DicomNode) -> None:
        super().__init__(assoc)
        self.daemon = True  # a stalled peer never keeps the process alive
        self._node = node
        self._opened = time.monotonic()
        self._command = bytearray()
        self._other_dataset = 0
        self._current: _Spool | None = None
        self._spools: dict[int, _Spool] = {}
        self.peer = ""

    # ----- reading ---------------------------------------------------------------------
    def _recv_exact(self, count: int, deadline: float) -> bytes | str:
        """``count`` bytes, or why not: ``late`` (the deadline passed), ``closed`` (the peer
        ended the connection) or ``stopping``. The socket's own timeout (used by the sends of
        the same thread) is restored."""
        raw = self.socket.socket if self.socket is not None else None
        if raw is None:
            return "closed"
        data = bytearray()
        saved = raw.gettimeout()
        try:
            while len(data) < count:
                left = deadline - time.monotonic()
                if self._node._stopping.is_set():
                    return "stopping"
                try:
                    # past the deadline, bytes already waiting are still taken (a starved thread is no stall)
                    raw.settimeout(min(left, 0.5) if left > 0 else 0.0)
                    chunk = raw.recv(min(count - len(data), 65536))
                except (TimeoutError, BlockingIOError):
                    if left <= 0:
                        return "late"
                    continue
                except OSError:
                    return "closed"
                if not chunk:
                    return "closed"
                data += chunk
        finally:
            with contextlib.suppress(OSError):
                raw.settimeout(saved)
        return bytes(data)

    def _drop(self, reason: str) -> None:
        log.warning("DICOM node: connection from %s closed: %s", self.peer or "?", reason)
        self._node._audit("dicom-connection-refused", client=self.peer, result=reason)
        self._discard_spools()
        if self.socket is not None:
            self.socket.close()  # Evt17: the state machine ends the association

    def _read_pdu_data(self) -> None:
        # before the association request (Sta2); the association's own flag lags behind the
        # A-ASSOCIATE-AC, and a peer may send P-DATA the moment the AC arrives
        established = self.state_machine.current_state not in ("Sta1", "Sta2")
        now = time.monotonic()
        deadline = now + PDU_TIMEOUT_S if established else self._opened + ASSOCIATION_TIMEOUT_S
        header = self._recv_exact(6, deadline)
        if isinstance(header, str):
            if header == "late":
                self._drop(f"{'a PDU' if established else 'the association request'} did not arrive in time")
            elif self.socket is not None:
                self.socket.close()  # Evt17: the peer ended the connection (or the node stops)
            return
        pdu_type, _, length = struct.unpack(">BBL", header)
        if pdu_type not in (0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07):
            self._drop(f"not DICOM (PDU type 0x{pdu_type:02X})")
            return
        if not established and pdu_type != 0x01:
            self._drop(f"PDU type 0x{pdu_type:02X} before an association request")
            return
        if length > MAX_PDU_BYTES:
            self._drop(f"a PDU of {length} bytes claimed (at most {MAX_PDU_BYTES})")
            return
        body = self._recv_exact(length, deadline)
        if isinstance(body, str):
            if body == "late":
                self._drop(f"a PDU of {length} bytes did not arrive whole in time")
            else:
                self._drop(f"the connection ended inside a PDU of {length} bytes")
            return
        data = header + body
        if pdu_type == 0x04:
            data = self._spool_pdata(data)
            if data is None:
                return
        try:
            pdu, event = self._decode_pdu(bytearray(data))
        except Exception as exc:
            log.warning("DICOM node: undecodable PDU from %s (%s)", self.peer or "?", type(exc).__name__)
            self.event_queue.put("Evt19")
            return
        self.event_queue.put(event)
        self._recv_pdu.put(pdu)

    # ----- P-DATA: datasets to disk ------------------------------------------------------
    def _spool_pdata(self, data: bytes) -> bytes | None:
        """The P-DATA-TF PDU with each C-STORE dataset fragment written to its spool and
        replaced by an empty fragment; None when the connection was dropped."""
        out = bytearray(data[:6])
        offset = 6
        while offset < len(data):
            if offset + 6 > len(data):
                return data  # malformed: pynetdicom's decoder says so
            (item_length,) = struct.unpack(">L", data[offset : offset + 4])
            end = offset + 4 + item_length
            if item_length < 2 or end > len(data):
                return data
            context_id, control = data[offset + 4], data[offset + 5]
            payload = data[offset + 6 : end]
            offset = end
            if control & 1:  # command fragment
                self._command += payload
                if len(self._command) > MAX_MESSAGE_PART_BYTES:
                    self._drop(f"a command set over {MAX_MESSAGE_PART_BYTES} bytes")
                    return None
                if control & 2 and not self._start_message():
                    return None
            elif self._current is not None:
                if not self._write_fragment(payload, last=bool(control & 2)):
                    return None
                payload = b""
            else:
                self._other_dataset = 0 if control & 2 else self._other_dataset + len(payload)
                if self._other_dataset > MAX_MESSAGE_PART_BYTES:
                    self._drop(f"a dataset over {MAX_MESSAGE_PART_BYTES} bytes outside C-STORE")
                    return None
            out += struct.pack(">LBB", len(payload) + 2, context_id, control) + payload
        struct.pack_into(">L", out, 2, len(out) - 6)
        return bytes(out)

    def _start_message(self) -> bool:
        from pynetdicom.dsutils import decode

        command, self._command = bytes(self._command), bytearray()
        try:
            cs = decode(io.BytesIO(command), True, True)
            field_ = int(cs.get("CommandField", 0))
            has_dataset = int(cs.get("CommandDataSetType", _NO_DATASET)) != _NO_DATASET
            message_id = int(cs.get("MessageID", 0))
        except Exception:
            return True  # pynetdicom decodes it again and answers an unreadable command
        if field_ == _C_STORE_RQ and has_dataset:
            if message_id in self._spools:
                self._drop(f"C-STORE message ID {message_id} reused while in progress")
                return False
            fd, name = tempfile.mkstemp(prefix=".store-", suffix=".part", dir=self._node._incoming)
            spool = _Spool(message_id, Path(name), os.fdopen(fd, "wb"))
            self._spools[message_id] = spool
            self._current = spool
        return True

    def _write_fragment(self, payload: bytes, *, last: bool) -> bool:
        spool = self._current
        assert spool is not None
        spool.size += len(payload)
        if not spool.over and spool.size > MAX_INSTANCE_BYTES:
            spool.over = True  # the rest is discarded; the C-STORE is answered "out of resources"
            spool.handle.truncate(0)
        try:
            if not spool.over:
                spool.handle.write(payload)
            if last:
                spool.handle.close()
                spool.done = True
                self._current = None
        except OSError as exc:
            self._drop(f"cannot write the received dataset ({exc.strerror})")
            return False
        return True

    def take_spool(self, message_id: int) -> _Spool | None:
        """The finished dataset of C-STORE ``message_id`` (the caller removes its file)."""
        spool = self._spools.pop(message_id, None)
        return spool if spool is not None and spool.done else None

    def _discard_spools(self) -> None:
        for spool in list(self._spools.values()):
            with contextlib.suppress(OSError):
                spool.handle.close()
            with contextlib.suppress(OSError):
                spool.path.unlink()
        self._spools.clear()
        self._current = None

    def run_reactor(self) -> None:
        try:
            super().run_reactor()
        finally:
            self._discard_spools()


class _GuardedHandler(RequestHandler):
    """Creates each association with the guarded upper layer."""

    def _create_association(self) -> Any:
        assoc = super()._create_association()
        node: DicomNode = self.server.node  # type: ignore[attr-defined]
        old = assoc.dul
        dul = _GuardedDUL(assoc, node)
        dul.peer = str(self.client_address[0])
        dul.event_queue = old.event_queue  # holds the connection's Evt5
        dul.socket = old.socket
        dul.artim_timer.timeout = assoc.acse_timeout
        dul._idle_timer.timeout = assoc.network_timeout
        assoc.dul = dul
        return assoc


@dataclass
class _Connection:
    peer: str
    sock: socket.socket
    accepted: bool = False
    opened: float = field(default_factory=time.monotonic)


class _GuardedServer(ThreadedAssociationServer):
    """Refuses connections beyond the pending limits; closes every connection on stop."""

    daemon_threads = True
    block_on_close = False

    def __init__(self, *args: Any, node: DicomNode, **kwargs: Any) -> None:
        self.node = node
        self.connections: list[_Connection] = []
        self.connections_lock = threading.Lock()
        super().__init__(*args, request_handler=_GuardedHandler, **kwargs)

    def _prune(self) -> None:
        self.connections = [c for c in self.connections if c.sock.fileno() != -1]

    def process_request(self, request: Any, client_address: Any) -> None:
        peer = str(client_address[0])
        with self.connections_lock:
            self._prune()
            pending = [c for c in self.connections if not c.accepted]
            from_peer = sum(c.peer == peer for c in pending)
            reason = None
            if self.node._stopping.is_set():
                reason = "the node is stopping"
            elif from_peer >= MAX_PENDING_PER_PEER:
                reason = f"{from_peer} connections from this address are not yet associated"
            elif len(pending) >= MAX_PENDING:
                reason = f"{len(pending)} connections are not yet associated"
            elif len(self.connections) >= MAX_PENDING + MAX_ASSOCIATIONS:
                reason = "too many connections"
            if reason is None:
                self.connections.append(_Connection(peer, request))
        if reason is not None:
            log.warning("DICOM node: connection from %s refused: %s", peer, reason)
            self.node._audit("dicom-connection-refused", client=peer, result=reason)
            self.shutdown_request(request)
            return
        super().process_request(request, client_address)

    def mark_accepted(self, sock: Any) -> bool:
        """Count ``sock``'s connection as an association; False when the associations are full."""
        with self.connections_lock:
            self._prune()
            if sum(c.accepted for c in self.connections) >= MAX_ASSOCIATIONS:
                return False
            for c in self.connections:
                if c.sock is sock:
                    c.accepted = True
            return True

    def close_all(self) -> None:
        with self.connections_lock:
            for c in self.connections:
                with contextlib.suppress(OSError):
                    c.sock.shutdown(socket.SHUT_RDWR)
            self.connections = []


# --------------------------------------------------------------------------------------
# The node
# --------------------------------------------------------------------------------------
class DicomNode:
    """C-ECHO + C-STORE SCP. ``allowed`` calling AE titles only (none: nobody is accepted).

    ``audit``: called as ``audit(action, **fields)`` for each association and stored or refused
    instance (:func:`registration.io.audit.record` takes them); None records nothing."""

    def __init__(
        self,
        folder: str | os.PathLike[str],
        *,
        allowed: Iterable[str],
        ae_title: str = DEFAULT_AE_TITLE,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        on_received: Callable[[Received], None] | None = None,
        audit: Callable[..., Any] | None = None,
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
        self.audit = audit
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._incoming = self.folder / ".incoming"
        self.received: list[Received] = []

    def _audit(self, action: str, **fields: Any) -> None:
        if self.audit is not None:
            try:
                self.audit(action, **fields)
            except Exception:
                log.exception("the audit log failed")

    # ----- life cycle ------------------------------------------------------------------
    def start(self) -> DicomNode:
        from pynetdicom import AE, ALL_TRANSFER_SYNTAXES, evt
        from pynetdicom.sop_class import Verification  # type: ignore[attr-defined]

        ae = AE(ae_title=self.ae_title)
        ae.require_calling_aet = list(self.allowed)
        ae.require_called_aet = True
        ae.acse_timeout = ASSOCIATION_TIMEOUT_S
        ae.network_timeout = IDLE_TIMEOUT_S
        ae.dimse_timeout = PDU_TIMEOUT_S
        ae.maximum_pdu_size = MAX_PDU_BYTES
        # pynetdicom counts every connection's thread; the node's own limits come first
        ae.maximum_associations = MAX_ASSOCIATIONS + 2 * MAX_PENDING + 16
        ae.add_supported_context(Verification)
        for sop_class in _storage_classes():
            ae.add_supported_context(sop_class, ALL_TRANSFER_SYNTAXES)
        handlers = [
            (evt.EVT_C_STORE, self._handle_store),
            (evt.EVT_C_ECHO, self._handle_echo),
            (evt.EVT_ACCEPTED, self._handle_accepted),
            (evt.EVT_REJECTED, self._handle_rejected),
        ]
        self._incoming.mkdir(mode=0o700, exist_ok=True)
        self._stopping.clear()
        try:
            server = ae.make_server(
                (self.host, self.requested_port), evt_handlers=handlers, server_class=_GuardedServer, node=self
            )
        except OSError as exc:
            raise NodeError(f"cannot listen on {self.host}:{self.requested_port} ({exc.strerror or exc})") from None
        self._server = server
        ae._servers.append(server)  # as AE.start_server does: shutdown() takes it out
        self._thread = threading.Thread(
            target=server.serve_forever, kwargs={"poll_interval": 0.2}, name="roadmap3d-dicom-node", daemon=True
        )
        self._thread.start()
        log.info("DICOM node %s listening on %s:%d", self.ae_title, self.host, self.port)
        return self

    @property
    def port(self) -> int:
        if self._server is None:
            return self.requested_port
        return int(self._server.server_address[1])

    def stop(self) -> None:
        """Stop listening and close every connection (whatever the peers do; within a second)."""
        server, self._server = self._server, None
        if server is None:
            return
        self._stopping.set()
        server.shutdown()  # the accept loop ends (it polls every 0.2 s)
        server.close_all()  # every reader sees its connection end
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        shutil.rmtree(self._incoming, ignore_errors=True)

    def __enter__(self) -> DicomNode:
        return self.start() if self._server is None else self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ----- handlers --------------------------------------------------------------------
    def _handle_accepted(self, event: Any) -> None:
        assoc = event.assoc
        peer = str(assoc.requestor.address)
        calling = str(assoc.requestor.ae_title).strip()
        server = self._server
        sock = assoc.dul.socket.socket if assoc.dul.socket is not None else None
        if server is not None and not server.mark_accepted(sock):
            log.warning("DICOM node: association from %s (%s) aborted: %d associations open", calling, peer,
                        MAX_ASSOCIATIONS)  # fmt: skip
            self._audit("dicom-association", client=peer, ae_title=calling, result="aborted: too many associations")
            assoc.abort()
            return
        self._audit("dicom-association", client=peer, ae_title=calling, result="accepted")

    def _handle_rejected(self, event: Any) -> None:
        assoc = event.assoc
        calling = str(assoc.requestor.ae_title).strip()
        self._audit("dicom-association", client=str(assoc.requestor.address), ae_title=calling, result="rejected")

    def _handle_echo(self, event: Any) -> int:
        log.info("C-ECHO from %s", event.assoc.requestor.ae_title)
        return STATUS_SUCCESS

    def _handle_store(self, event: Any) -> int:
        calling = str(event.assoc.requestor.ae_title).strip()
        peer = str(event.assoc.requestor.address)
        request = event.request
        sop_class = str(request.AffectedSOPClassUID or "")
        instance = str(request.AffectedSOPInstanceUID or "")
        dul = event.assoc.dul
        spool = dul.take_spool(int(request.MessageID)) if isinstance(dul, _GuardedDUL) else None

        def refuse(status: int, why: str, **uids: Any) -> int:
            log.warning("C-STORE from %s (%s): refused (0x%04X), %s", calling, peer, status, why)
            self._audit("dicom-store", client=peer, ae_title=calling, instance_uid=instance, sop_class_uid=sop_class,
                        result=f"refused 0x{status:04X}: {why}", **uids)  # fmt: skip
            return status

        if spool is None:
            return refuse(STATUS_CANNOT_UNDERSTAND, "no dataset")
        try:
            if spool.over:
                return refuse(STATUS_OUT_OF_RESOURCES, f"{spool.size} bytes exceed {MAX_INSTANCE_BYTES}")
            if not (_UID.match(instance) and len(instance) <= 64 and _UID.match(sop_class)):
                return refuse(STATUS_CANNOT_UNDERSTAND, "the command's SOP instance is not a DICOM UID")
            return self._store(event, spool, calling, peer, sop_class, instance, refuse)
        finally:
            with contextlib.suppress(OSError):
                spool.path.unlink()

    def _store(self, event: Any, spool: _Spool, calling: str, peer: str, sop_class: str, instance: str,
               refuse: Callable[..., int]) -> int:  # fmt: skip
        transfer_syntax = str(event.context.transfer_syntax)
        fd, name = tempfile.mkstemp(prefix=".file-", suffix=".part", dir=self._incoming)  # 0600
        tmp = Path(name)
        try:
            try:
                with os.fdopen(fd, "wb") as out, spool.path.open("rb") as src:
                    _write_file_header(out, sop_class, instance, transfer_syntax)
                    shutil.copyfileobj(src, out, _COPY_CHUNK)
            except OSError as exc:
                return refuse(STATUS_OUT_OF_RESOURCES, f"cannot write ({exc.strerror})")
            with contextlib.suppress(OSError):
                spool.path.unlink()  # the disk holds the instance once from here
            checked = _check_instance(tmp, transfer_syntax, sop_class, instance)
            if isinstance(checked, tuple):
                return refuse(*checked)
            ds = checked
            study = str(ds.get("StudyInstanceUID", ""))
            series = str(ds.get("SeriesInstanceUID", ""))
            if not all(_UID.match(u) and len(u) <= 64 for u in (study, series)):
                return refuse(STATUS_CANNOT_UNDERSTAND, "a UID is not a DICOM UID")
            target = self.folder / study / series / f"{instance}.dcm"
            try:
                placed = _place(tmp, target)
            except OSError as exc:
                return refuse(STATUS_OUT_OF_RESOURCES, f"cannot write {target} ({exc.strerror})")
            if placed == "conflict":
                return refuse(STATUS_DUPLICATE_INSTANCE, "another instance already has this SOP Instance UID",
                              study_uid=study, series_uids=[series])  # fmt: skip
        finally:
            with contextlib.suppress(OSError):
                tmp.unlink()
        try:
            frames = int(ds.get("NumberOfFrames", 1) or 1)
        except (TypeError, ValueError):
            frames = 1
        item = Received(target, calling, sop_class, study, series, str(ds.get("Modality", "")), frames, instance, peer)
        self._audit("dicom-store", client=peer, ae_title=calling, study_uid=study, series_uids=[series],
                    instance_uid=instance, sop_class_uid=sop_class,
                    result="stored" if placed == "new" else "stored before (same bytes)")  # fmt: skip
        if placed != "new":
            log.info("C-STORE from %s: %s received again (same bytes)", calling, target)
            return STATUS_SUCCESS
        with self._lock:
            self.received.append(item)
        log.info("C-STORE from %s: %s (%s, %d frame(s))", calling, target, item.modality, frames)
        if self.on_received is not None:
            try:
                self.on_received(item)
            except Exception:
                log.exception("the handler of received images failed on %s", target)
        return STATUS_SUCCESS


def _write_file_header(out: Any, sop_class: str, instance: str, transfer_syntax: str) -> None:
    """The DICOM file's preamble and file meta information (group 2) for a received dataset."""
    from pydicom.filewriter import write_file_meta_info
    from pynetdicom.dsutils import create_file_meta

    out.write(b"\x00" * 128 + b"DICM")
    write_file_meta_info(out, create_file_meta(sop_class_uid=sop_class, sop_instance_uid=instance,
                                                transfer_syntax=transfer_syntax))  # fmt: skip


def _check_instance(path: Path, transfer_syntax: str, sop_class: str, instance: str) -> Any:
    """The file's dataset (large values deferred, not read), or (status, reason) when it is
    truncated, unreadable, or inconsistent with its command or its own pixel description."""
    import warnings

    import pydicom
    from pydicom.filereader import data_element_generator, read_preamble
    from pydicom.uid import UID

    size = path.stat().st_size
    ts = UID(transfer_syntax)
    try:
        with path.open("rb") as fh, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            read_preamble(fh, False)
            pydicom.filereader._read_file_meta_info(fh)
            implicit, little = ts.is_implicit_VR, ts.is_little_endian
            # a deflated dataset is checked by inflating it below
            elements = () if ts.is_deflated else data_element_generator(fh, implicit, little, defer_size=4096)
            for elem in elements:
                length = int(elem.length)
                if length != 0xFFFFFFFF and elem.value_tell + length > size:
                    return STATUS_CANNOT_UNDERSTAND, (
                        f"truncated dataset: {elem.tag} declares {length} bytes, {size - elem.value_tell} present"
                    )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(path, defer_size=4096)
            declared_class, declared_instance = str(ds.get("SOPClassUID", "")), str(ds.get("SOPInstanceUID", ""))
    except (EOFError, OSError, ValueError, KeyError, TypeError, struct.error, NotImplementedError) as exc:
        return STATUS_CANNOT_UNDERSTAND, f"unreadable dataset ({type(exc).__name__}: {str(exc)[:120]})"
    if declared_class != sop_class:
        return (
            STATUS_DOES_NOT_MATCH,
            f"the dataset's SOP class {declared_class or '(none)'} is not the command's {sop_class}",
        )
    if declared_instance != instance:
        return STATUS_DOES_NOT_MATCH, "the dataset's SOP Instance UID is not the command's"
    if "PixelData" in ds and not ts.is_compressed:
        try:
            expected = (int(ds.Rows) * int(ds.Columns) * int(ds.get("SamplesPerPixel", 1) or 1)
                        * int(ds.get("NumberOfFrames", 1) or 1) * int(ds.BitsAllocated))  # fmt: skip
        except (AttributeError, TypeError, ValueError):
            return STATUS_DOES_NOT_MATCH, "pixel data without Rows, Columns or BitsAllocated"
        item = ds.get_item("PixelData")
        present = int(item.length) if hasattr(item, "length") else len(item.value or b"")
        if present != 0xFFFFFFFF and present * 8 < expected:
            return STATUS_DOES_NOT_MATCH, f"pixel data of {present} bytes, {(expected + 7) // 8} described"
    return ds


def _place(tmp: Path, target: Path) -> str:
    """Link ``tmp`` to ``target`` without ever replacing a file: ``new``, ``same`` (the file
    there has the same bytes) or ``conflict``."""
    for parent in (target.parent.parent, target.parent):
        if not parent.exists():
            parent.mkdir(mode=0o700, exist_ok=True)
    try:
        os.link(tmp, target)
    except FileExistsError:
        return "same" if filecmp.cmp(tmp, target, shallow=False) else "conflict"
    return "new"


#: Environment set by ``roadmap3d app --listen-port P --allow AE ...`` for the app's DICOM node
#: (the command line sets it, the web app's PACS panel reads it).
ENV_APP_NODE_PORT = "ROADMAP3D_APP_NODE_PORT"
ENV_APP_NODE_ALLOW = "ROADMAP3D_APP_NODE_ALLOW"
ENV_APP_NODE_AE = "ROADMAP3D_APP_NODE_AE"
