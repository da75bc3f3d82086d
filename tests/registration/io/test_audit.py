"""The audit log (registration/io/audit.py) and ``roadmap3d audit``."""

from __future__ import annotations

import json
import stat
import threading
from pathlib import Path

import pytest

from registration.io.audit import AuditLog


def test_lines_hold_uids_only_and_are_private(tmp_path: Path) -> None:
    log = AuditLog(tmp_path / "audit")
    line = log.record("pacs-load", client="10.0.0.7", study_uid="1.2.840.1", series_uids=["1.2.840.1.2", "Doe^Jane"],
                      instance_uid="../etc/passwd", ae_title="CARM", result="ok")  # fmt: skip
    assert line["series_uids"] == ["1.2.840.1.2"] and "instance_uid" not in line  # not UIDs: left out
    (stored,) = [json.loads(t) for t in log.path.read_text().splitlines()]
    assert stored == line and set(stored) == {"time", "client", "action", "study_uid", "series_uids", "ae_title",
                                              "result"}  # fmt: skip
    assert stat.S_IMODE(log.path.stat().st_mode) == 0o600
    assert stat.S_IMODE(log.folder.stat().st_mode) == 0o700
    with pytest.raises(TypeError):
        log.record("upload", patient_name="Doe^Jane")  # type: ignore[call-arg]  # no such field


def test_appends_from_threads_and_rotation_keep_every_line(tmp_path: Path) -> None:
    log = AuditLog(tmp_path, max_bytes=2000, keep=50)

    def write(k: int) -> None:
        for i in range(25):
            log.record("dicom-store", client=f"thread-{k}", count=i)

    threads = [threading.Thread(target=write, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    lines = list(log.lines())
    assert len(lines) == 100 and len(log.files()) > 1  # rotated, nothing lost
    assert all(p.stat().st_size <= 2000 for p in log.files())
    for k in range(4):
        assert [line["count"] for line in lines if line["client"] == f"thread-{k}"] == list(range(25))
    few = AuditLog(tmp_path / "few", max_bytes=300, keep=2)
    for i in range(30):
        few.record("stop", count=i)
    assert len(few.files()) == 3 and [line["count"] for line in few.lines()][-1] == 29  # the oldest dropped


def test_the_audit_command_prints_the_lines(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from app.cli import main

    log = AuditLog(tmp_path)
    log.record("registration", client="127.0.0.1", study_uid="1.2.3", result="started (Register)")
    log.record("correction", client="127.0.0.1", study_uid="1.2.3", result="applied: 5.7 mm")
    with pytest.raises(SystemExit) as info:
        main(["audit", "--folder", str(tmp_path), "--last", "1"])
    assert info.value.code == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 1 and "correction" in out[0] and "applied: 5.7 mm" in out[0] and "study 1.2.3" in out[0]
    with pytest.raises(SystemExit):
        main(["audit", "--folder", str(tmp_path), "--all-lines", "--as-json"])
    assert [json.loads(t)["action"] for t in capsys.readouterr().out.splitlines()] == ["registration", "correction"]
