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
