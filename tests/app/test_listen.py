"""``roadmap3d listen``: the DICOM node as a command, fed to ``register``.

The command runs in its own process (as a user starts it); pynetdicom's StoreSCU plays the
C-arm. The phantom's XA image is received, reported, and registered to the exported 3DRA; a
three-frame run is received and tracked; SIGTERM stops the node cleanly (exit code 0).
"""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pynetdicom import AE
from pynetdicom.sop_class import XRayAngiographicImageStorage  # type: ignore[attr-defined]

from registration.io import dicom

#: Registrations of whole commands: seconds each (the newest-releases CI job skips them).
pytestmark = pytest.mark.slow

#: Bounds a broken run only (the node starts in a few seconds; one small registration ~1-5 s).
LINE_TIMEOUT_S = 120.0


def _lines(proc: subprocess.Popen) -> queue.Queue[str | None]:
    """The process's stdout, line by line, read on a thread (no buffering surprises)."""
    lines: queue.Queue[str | None] = queue.Queue()

    def pump() -> None:
        for line in proc.stdout:  # type: ignore[union-attr]
            lines.put(line)
        lines.put(None)

    threading.Thread(target=pump, daemon=True).start()
    return lines


def _read_until(lines: queue.Queue[str | None], pattern: str, seen: list[str]) -> re.Match:
    end = time.monotonic() + LINE_TIMEOUT_S
    while time.monotonic() < end:
        try:
            line = lines.get(timeout=1.0)
        except queue.Empty:
            continue
        if line is None:
            break
        seen.append(line)
        if match := re.search(pattern, line):
            return match
    raise AssertionError(f"no line matching {pattern!r}; output so far: {''.join(seen)}")


def test_listen_receives_and_registers(tmp_path: Path, small_export: Path) -> None:
    folder = tmp_path / "received"
    cmd = [sys.executable, "-c", "from app.cli import main; main()", "listen", "--port", "0", "--allow", "CARM",
           "--folder", str(folder), "--volume", str(small_export / "volume")]  # fmt: skip
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    seen: list[str] = []
    lines = _lines(proc)
    try:
        port = int(_read_until(lines, r"listening on 127\.0\.0\.1:(\d+) as ROADMAP3D", seen)[1])
        ae = AE(ae_title="CARM")
        ae.add_requested_context(XRayAngiographicImageStorage)
        assoc = ae.associate("127.0.0.1", port, ae_title="ROADMAP3D")
        assert assoc.is_established
        ds = dicom.read_dataset(small_export / "xa_fluoro.dcm")
        assert assoc.send_c_store(ds).Status == 0x0000
        # readable the moment the sender sees success (the node answers after the rename)
        stored = folder / ds.StudyInstanceUID / ds.SeriesInstanceUID / f"{ds.SOPInstanceUID}.dcm"
        assert dicom.read_xray(stored).geometry == dicom.read_xray(small_export / "xa_fluoro.dcm").geometry
        # a short run (three frames of the same view, 1/15 s apart) is tracked, not registered
        image = dicom.read_xray(small_export / "xa_fluoro.dcm")
        run_file = dicom.write_xray_run([image, image, image], tmp_path / "run.dcm", times_s=[0.0, 1 / 15, 2 / 15])
        assert assoc.send_c_store(dicom.read_dataset(run_file)).Status == 0x0000
        assoc.release()
        intruder = AE(ae_title="INTRUDER")
        intruder.add_requested_context(XRayAngiographicImageStorage)
        refused = intruder.associate("127.0.0.1", port, ae_title="ROADMAP3D")
        assert refused.is_rejected  # an unknown calling AE title
        path = Path(_read_until(lines, r"received XA from CARM: (\S+)", seen)[1])
        assert path.is_file() and path.is_relative_to(folder)
        result = Path(_read_until(lines, r"registered \S+: .* -> (\S+)$", seen)[1])
        doc = json.loads(result.read_text())
        truth = json.loads((small_export / "truth.json").read_text())
        # The registration ran on the received file: its motion is near the truth (T4 is
        # 7-8 mm and 5-7 deg away from the start; a 48^3 / 96^2 export lands within a few mm).
        error_mm = np.abs(np.asarray(doc["patient_motion"])[:3, 3] - np.asarray(truth["patient_motion"])[:3, 3])
        assert error_mm.max() < 3.0, (error_mm, doc["patient_motion"])
        tracked = Path(_read_until(lines, r"tracked \S+: 3 frames \(.*\) -> (\S+)$", seen)[1])
        frames = json.loads(tracked.read_text())["frames"]
        assert [f["frame"] for f in frames] == [0, 1, 2] and all(f["status"] for f in frames)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    assert proc.returncode == 0, proc.stderr.read()  # type: ignore[union-attr]
    _read_until(lines, r"stopped; 2 instance\(s\) received", seen)


def _start_listen(tmp_path: Path, *extra: str) -> tuple[subprocess.Popen, queue.Queue[str | None], list[str], int]:
    cmd = [sys.executable, "-c", "from app.cli import main; main()", "listen", "--port", "0", "--allow", "CARM",
           "--folder", str(tmp_path / "received"), *extra]  # fmt: skip
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    seen: list[str] = []
    lines = _lines(proc)
    port = int(_read_until(lines, r"listening on 127\.0\.0\.1:(\d+) as ROADMAP3D", seen)[1])
    return proc, lines, seen, port


def _peak_rss_mb(pid: int) -> float:
    """The process's peak resident memory (VmHWM, Linux), MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux /proc for the memory reading")
def test_listen_ends_on_sigterm_whatever_peers_do(tmp_path: Path) -> None:
    import socket
    import struct

    from tests.registration.io.test_node_hostile import association_request, hostile_connections, open_from

    proc, lines, seen, port = _start_listen(tmp_path)
    socks = []
    try:
        # 4 GiB claimed in one PDU, then 256 MiB streamed into it: the node reads the header only
        for header in (b"\x01\x00" + struct.pack(">L", 0xFFFFFFFF), b"\x04\x00" + struct.pack(">L", 0xFFFFFFFF)):
            s = open_from("127.0.0.2", port)
            sent = 0
            try:
                s.sendall(header)
                chunk = b"\0" * (1024 * 1024)
                while sent < 256 * 1024**2:
                    s.sendall(chunk)
                    sent += len(chunk)
            except OSError:
                pass
            s.close()
            assert sent < 256 * 1024**2
        peak = _peak_rss_mb(proc.pid)
        print(f"listen peak memory after two 4 GiB PDU claims: {peak:.0f} MB")
        assert peak < 200  # the bound; measured ~90 MB
        socks = hostile_connections(port, association_request())
        idle = socket.create_connection(("127.0.0.1", port))  # a connection that never says anything
        socks.append(idle)
        time.sleep(0.5)
        start = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=5.0)  # the bound itself: SIGTERM ends listen within 5 s
        print(f"listen ended {time.monotonic() - start:.2f} s after SIGTERM with 21 hostile connections open")
    finally:
        for s in socks:
            s.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, proc.stderr.read()  # type: ignore[union-attr]
    _read_until(lines, r"stopped; 0 instance\(s\) received", seen)


def test_listen_at_15_fps_reports_every_frame(tmp_path: Path, small_export: Path) -> None:
    from pydicom.uid import generate_uid

    proc, lines, seen, port = _start_listen(tmp_path, "--volume", str(small_export / "volume"))
    names = []
    try:
        ae = AE(ae_title="CARM")
        ae.add_requested_context(XRayAngiographicImageStorage)
        assoc = ae.associate("127.0.0.1", port, ae_title="ROADMAP3D")
        assert assoc.is_established
        ds = dicom.read_dataset(small_export / "xa_fluoro.dcm")
        series = generate_uid()
        start = time.monotonic()
        for n in range(151):  # 10 s of single frames at 15 fps, each its own instance
            ds.SOPInstanceUID = generate_uid()
            ds.SeriesInstanceUID = series
            ds.InstanceNumber = n + 1
            assert assoc.send_c_store(ds).Status == 0x0000
            names.append(f"{ds.SOPInstanceUID}.dcm")
            time.sleep(max(0.0, start + (n + 1) / 15 - time.monotonic()))
        assoc.release()
        _read_until(lines, r"registered \S+: ", seen)  # at least one registration finished
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10)
    while True:  # the rest of the output, to its end (the pump thread reads stdout)
        try:
            line = lines.get(timeout=30)  # the pump ends with None at the end of the output; a loaded machine may lag
        except queue.Empty:
            break
        if line is None:
            break
        seen.append(line)
    text = "".join(seen)
    assert proc.returncode == 0
    outcome = {}
    for name in names:
        said = re.findall(rf"^(registered|skipped|not registered) {re.escape(name)}", text, flags=re.M)
        assert len(said) == 1, (name, said, [line for line in seen if name in line])
        outcome[name] = said[0]
    counts = {k: list(outcome.values()).count(k) for k in ("registered", "skipped", "not registered")}
    summary = re.search(r"registrations: (\d+) registered, 0 tracked, (\d+) skipped, 0 failed, (\d+) not registered",
                        text)  # fmt: skip
    assert summary, text[-2000:]
    assert (int(summary[1]), int(summary[2]), int(summary[3])) == (
        counts["registered"], counts["skipped"], counts["not registered"])  # fmt: skip
    print(f"151 frames at 15 fps: {counts}")
