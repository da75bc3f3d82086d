"""The DICOM node against peers that stall, flood or lie (registration/io/node.py).

Real pynetdicom peers play the C-arm; raw sockets play the rest. Strangers connect from other
loopback addresses (127.0.0.2, 127.0.0.3) as they would from other machines, so the per-peer
limit is what keeps the C-arm's slots free. Deadlines here are the node's own bounds
(ASSOCIATION_TIMEOUT_S, the 5 s of a stop), not speed measurements.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, generate_uid
from pynetdicom import AE, _config
from pynetdicom.sop_class import Verification, XRayAngiographicImageStorage  # type: ignore[attr-defined]

from registration.io import node as node_module
from registration.io.node import DicomNode, Received

XA = "1.2.840.10008.5.1.4.1.1.12.1"
CT = "1.2.840.10008.5.1.4.1.1.2"


def xa_dataset(seed: int, *, rows: int = 32, study: str | None = None, series: str | None = None) -> Dataset:
    """A small, complete XA image (16-bit, ``rows`` x ``rows``) with random pixels."""
    ds = Dataset()
    ds.SOPClassUID = XA
    ds.SOPInstanceUID = generate_uid()
    ds.StudyInstanceUID = study or generate_uid()
    ds.SeriesInstanceUID = series or generate_uid()
    ds.Modality = "XA"
    ds.PatientName = "Hostile^Test"
    ds.Rows = ds.Columns = rows
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated = ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0
    ds.PixelData = np.random.default_rng(seed).integers(0, 4096, (rows, rows), dtype=np.uint16).tobytes()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta.MediaStorageSOPClassUID = ds.SOPClassUID
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    return ds


def scu(title: str = "CARM") -> AE:
    ae = AE(ae_title=title)
    ae.add_requested_context(Verification)
    ae.add_requested_context(XRayAngiographicImageStorage, ExplicitVRLittleEndian)
    ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = 60  # bounds a broken run only (a loaded machine is slow)
    return ae


def association_request(port_holder: list[int] | None = None) -> bytes:
    """The bytes of a real A-ASSOCIATE-RQ (pynetdicom calling a socket that only listens)."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    got: list[bytes] = []

    def accept() -> None:
        conn, _ = listener.accept()
        conn.settimeout(5)
        header = conn.recv(6, socket.MSG_WAITALL)
        (length,) = struct.unpack(">L", header[2:6])
        got.append(header + conn.recv(length, socket.MSG_WAITALL))
        conn.close()

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    ae = scu()
    ae.acse_timeout = 2
    ae.associate("127.0.0.1", port, ae_title="ROADMAP3D")
    thread.join(5)
    listener.close()
    return got[0]


def open_from(source: str, port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind((source, 0))
    sock.connect(("127.0.0.1", port))
    return sock


def still_open(sock: socket.socket) -> bool:
    """True while the node has not closed ``sock`` (no end of stream, no reset)."""
    sock.setblocking(False)
    try:
        return sock.recv(1, socket.MSG_PEEK) != b""
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        sock.setblocking(True)


@pytest.fixture()
def node(tmp_path: Path):
    got: list[Received] = []
    audit: list[tuple[str, dict]] = []
    with DicomNode(tmp_path / "received", allowed=["CARM"], port=0, on_received=got.append,
                   audit=lambda action, **f: audit.append((action, f))) as n:  # fmt: skip
        n.got = got  # type: ignore[attr-defined]
        n.audit_lines = audit  # type: ignore[attr-defined]
        yield n


def hostile_connections(port: int, request: bytes) -> list[socket.socket]:
    """Ten stalled association requests (40 of their bytes, then silence) from 127.0.0.2 and
    ten connections of random bytes from 127.0.0.3, all left open."""
    rng = np.random.default_rng(26)
    socks = []
    for _ in range(10):
        s = open_from("127.0.0.2", port)
        s.sendall(request[:40])
        socks.append(s)
    for _ in range(10):
        s = open_from("127.0.0.3", port)
        s.sendall(rng.integers(0, 256, 220, dtype=np.uint8).tobytes())
        socks.append(s)
    return socks


def test_stalled_and_random_peers_leave_the_c_arm_served(node: DicomNode) -> None:
    request = association_request()
    assert request[0] == 0x01 and len(request) > 40
    socks = hostile_connections(node.port, request)
    try:
        start = time.monotonic()
        assoc = scu().associate("127.0.0.1", node.port, ae_title="ROADMAP3D")
        assert assoc.is_established
        ds = xa_dataset(1)
        assert assoc.send_c_store(ds).Status == 0x0000
        assoc.release()
        served_s = time.monotonic() - start
        # Served while the stalled requests still hold their connections: the C-arm did not wait
        # for their deadline (measured ~0.05 s on 2 busy cores; the bound is 1 s).
        print(f"C-arm served in {served_s:.3f} s with 20 hostile connections open")
        assert served_s < node_module.ASSOCIATION_TIMEOUT_S
        assert sum(still_open(s) for s in socks[:8]) >= 1
        (item,) = node.got  # type: ignore[attr-defined]
        assert item.instance_uid == ds.SOPInstanceUID and item.path.is_file()
        # every stalled request is closed by its deadline (ASSOCIATION_TIMEOUT_S, 5 s; 10 s allowed)
        end = time.monotonic() + node_module.ASSOCIATION_TIMEOUT_S + 10
        while time.monotonic() < end and any(still_open(s) for s in socks):
            time.sleep(0.2)
        assert not any(still_open(s) for s in socks)
    finally:
        for s in socks:
            s.close()
    reasons = [f["result"] for a, f in node.audit_lines if a == "dicom-connection-refused"]  # type: ignore[attr-defined]
    assert any("did not arrive" in r for r in reasons)
    assert any("not DICOM" in r or "claimed" in r or "before an association" in r for r in reasons)


def test_pending_connections_per_peer_are_limited(node: DicomNode) -> None:
    socks = [open_from("127.0.0.2", node.port) for _ in range(node_module.MAX_PENDING_PER_PEER + 3)]
    try:
        time.sleep(0.5)
        open_count = sum(still_open(s) for s in socks)
        assert open_count == node_module.MAX_PENDING_PER_PEER  # the rest closed at once
        assoc = scu().associate("127.0.0.1", node.port, ae_title="ROADMAP3D")
        assert assoc.is_established and assoc.send_c_echo().Status == 0x0000
        assoc.release()
    finally:
        for s in socks:
            s.close()


def test_a_huge_pdu_claim_is_refused_at_its_header(node: DicomNode) -> None:
    for first in (b"\x01\x00" + struct.pack(">L", 0xFFFFFFFF), b"\x04\x00" + struct.pack(">L", 0xFFFFFFF0)):
        s = open_from("127.0.0.2", node.port)
        s.settimeout(10)
        sent = 0
        try:
            s.sendall(first)
            chunk = b"\0" * 65536
            while sent < 64 * 1024**2:
                s.sendall(chunk)
                sent += len(chunk)
        except OSError:
            pass  # reset by the node
        finally:
            s.close()
        assert sent < 64 * 1024**2  # the node stopped reading long before
    assoc = scu().associate("127.0.0.1", node.port, ae_title="ROADMAP3D")
    assert assoc.is_established and assoc.send_c_echo().Status == 0x0000
    assoc.release()


def _send_file(path: Path, port: int, monkeypatch: pytest.MonkeyPatch) -> int:
    """C-STORE a file's bytes as they are (pynetdicom's chunked send: no re-encoding)."""
    monkeypatch.setattr(_config, "STORE_SEND_CHUNKED_DATASET", True)
    assoc = scu().associate("127.0.0.1", port, ae_title="ROADMAP3D")
    assert assoc.is_established
    try:
        return int(assoc.send_c_store(path).Status)
    finally:
        assoc.release()
        monkeypatch.setattr(_config, "STORE_SEND_CHUNKED_DATASET", False)


def test_truncated_pixel_data_is_refused(node: DicomNode, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ds = xa_dataset(2)
    whole = tmp_path / "whole.dcm"
    ds.save_as(whole, enforce_file_format=True)
    raw = whole.read_bytes()
    at = raw.rfind(b"\xe0\x7f\x10\x00")
    # PixelData declared 0xFFFFFFF0 bytes long, 1 KiB present
    bad = raw[:at] + b"\xe0\x7f\x10\x00OW\x00\x00" + struct.pack("<L", 0xFFFFFFF0) + b"\x01" * 1024
    (tmp_path / "bad.dcm").write_bytes(bad)
    assert _send_file(tmp_path / "bad.dcm", node.port, monkeypatch) == node_module.STATUS_CANNOT_UNDERSTAND
    # pixel data shorter than rows x columns x bits says, with a consistent element length
    short = xa_dataset(3)
    short.PixelData = short.PixelData[:100]
    short.save_as(tmp_path / "short.dcm", enforce_file_format=True)
    assert _send_file(tmp_path / "short.dcm", node.port, monkeypatch) == node_module.STATUS_DOES_NOT_MATCH
    assert node.got == []  # type: ignore[attr-defined]
    assert not list(node.folder.glob("*/*/*.dcm"))
    assert not any((node.folder / ".incoming").iterdir())


def test_sop_class_inconsistent_with_the_command_is_refused(
    node: DicomNode, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ds = xa_dataset(4)
    ds.SOPClassUID = CT  # the file meta (and so the command) still says XA
    ds.preamble = b"\x00" * 128
    ds.save_as(tmp_path / "ct_in_xa.dcm", enforce_file_format=False)
    assert _send_file(tmp_path / "ct_in_xa.dcm", node.port, monkeypatch) == node_module.STATUS_DOES_NOT_MATCH
    assert node.got == [] and not list(node.folder.glob("*/*/*.dcm"))  # type: ignore[attr-defined]


def test_a_reused_instance_uid_never_overwrites(node: DicomNode) -> None:
    first = xa_dataset(5)
    other = xa_dataset(6, study=first.StudyInstanceUID, series=first.SeriesInstanceUID)
    other.SOPInstanceUID = first.SOPInstanceUID  # another image under the same UID
    assoc = scu().associate("127.0.0.1", node.port, ae_title="ROADMAP3D")
    try:
        assert assoc.send_c_store(first).Status == 0x0000
        (item,) = node.got  # type: ignore[attr-defined]
        kept = item.path.read_bytes()
        assert assoc.send_c_store(other).Status == node_module.STATUS_DUPLICATE_INSTANCE
        assert assoc.send_c_store(first).Status == 0x0000  # the same bytes again: success, kept once
    finally:
        assoc.release()
    assert item.path.read_bytes() == kept
    assert len(node.got) == 1 and len(list(node.folder.glob("*/*/*.dcm"))) == 1  # type: ignore[attr-defined]


def test_oversized_instance_is_refused_without_buffering(node: DicomNode, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(node_module, "MAX_INSTANCE_BYTES", 100_000)
    big = xa_dataset(7, rows=256)  # 131 kB of pixels
    small = xa_dataset(8)
    assoc = scu().associate("127.0.0.1", node.port, ae_title="ROADMAP3D")
    try:
        assert assoc.send_c_store(big).Status == node_module.STATUS_OUT_OF_RESOURCES
        assert assoc.send_c_store(small).Status == 0x0000  # the association goes on
    finally:
        assoc.release()
    assert [r.instance_uid for r in node.got] == [small.SOPInstanceUID]  # type: ignore[attr-defined]


@pytest.mark.slow
def test_500_instances_over_8_associations_arrive_complete(node: DicomNode) -> None:
    study, series = generate_uid(), generate_uid()
    sent = [xa_dataset(100 + i, rows=16, study=study, series=series) for i in range(500)]
    statuses: list[int] = []
    failures: list[str] = []
    lock = threading.Lock()

    def send(part: list[Dataset]) -> None:
        assoc = scu().associate("127.0.0.1", node.port, ae_title="ROADMAP3D")
        if not assoc.is_established:
            failures.append(f"association not established (rejected {assoc.is_rejected})")
            return
        for ds in part:
            status = int(assoc.send_c_store(ds).Status)
            with lock:
                statuses.append(status)
        assoc.release()

    threads = [threading.Thread(target=send, args=(sent[i::8],)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(240)
    assert not failures and statuses == [0] * 500, (failures, sorted(set(statuses)))
    uids = sorted(r.instance_uid for r in node.got)  # type: ignore[attr-defined]
    assert uids == sorted(ds.SOPInstanceUID for ds in sent)  # none lost, none twice
    for ds in sent[::50]:
        stored = node.folder / study / series / f"{ds.SOPInstanceUID}.dcm"
        from pydicom import dcmread

        assert dcmread(stored).PixelData == ds.PixelData
