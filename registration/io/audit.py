"""The audit trail: one JSON line per action on patients' images.

Every registration, applied or withheld correction, Stop, upload, PACS load or store and DICOM
association is recorded as one line ``{"time", "client", "action", "result", ...UIDs}`` in
``<user data dir>/roadmap3d/audit/audit.jsonl`` (``ROADMAP3D_AUDIT_DIR`` moves it). The file is
appended to, never rewritten (0600 in a 0700 folder); past ``max_bytes`` it is rotated to
``audit.1.jsonl`` .. ``audit.<keep>.jsonl`` (the oldest dropped). Several processes may write
at once: a lock file serialises appends and rotation.

What a line may hold is fixed: UIDs (checked to be DICOM UIDs), an AE title, counts and a short
result text written by the program. Patient names, IDs, paths and pixel data have no field.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

ENV_AUDIT_DIR = "ROADMAP3D_AUDIT_DIR"
#: The live file is rotated when a line would take it past this many bytes.
MAX_BYTES = 10 * 1024**2
#: Rotated files kept besides the live one.
KEEP = 9
FILE_NAME = "audit.jsonl"

_UID = re.compile(r"^[0-9]+(\.[0-9]+)*$")
_AE = re.compile(r"^[\x20-\x7e]{0,16}$")
#: Fields a line may carry besides time, client, action and result (and what each must be).
_UID_FIELDS = ("study_uid", "series_uid", "instance_uid", "sop_class_uid")
_TEXT_LIMIT = 300


def default_folder() -> Path:
    """``ROADMAP3D_AUDIT_DIR``, else ``<user data dir>/roadmap3d/audit``."""
    env = os.environ.get(ENV_AUDIT_DIR)
    if env:
        return Path(env).expanduser()
    from platformdirs import user_data_dir

    return Path(user_data_dir("roadmap3d")) / "audit"


def _uid(value: Any) -> str | None:
    text = str(value).strip()
    return text if _UID.match(text) and len(text) <= 64 else None


class AuditLog:
    """Append-only JSON-lines audit file with size rotation (thread- and process-safe)."""

    def __init__(self, folder: str | os.PathLike[str] | None = None, *, max_bytes: int = MAX_BYTES,
                 keep: int = KEEP) -> None:  # fmt: skip
        self.folder = Path(folder).expanduser() if folder is not None else default_folder()
        self.max_bytes = int(max_bytes)
        self.keep = max(1, int(keep))
        self._lock = threading.Lock()

    @property
    def path(self) -> Path:
        return self.folder / FILE_NAME

    def _rotated(self, n: int) -> Path:
        return self.folder / f"audit.{n}.jsonl"

    def record(
        self,
        action: str,
        *,
        client: str = "",
        result: str = "ok",
        study_uid: Any = None,
        series_uids: Iterable[Any] = (),
        instance_uid: Any = None,
        sop_class_uid: Any = None,
        ae_title: str | None = None,
        count: int | None = None,
    ) -> dict[str, Any]:
        """Append one line and return it. Values that are not what their field holds (a name in
        a UID field) are left out, never written."""
        line: dict[str, Any] = {
            "time": _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z"),
            "client": str(client)[:80],
            "action": str(action)[:60],
        }
        for key, value in (("study_uid", study_uid), ("instance_uid", instance_uid), ("sop_class_uid", sop_class_uid)):
            if value is not None and (uid := _uid(value)):
                line[key] = uid
        series = [u for u in (_uid(s) for s in series_uids) if u]
        if series:
            line["series_uids"] = series
        if ae_title is not None and _AE.match(str(ae_title)):
            line["ae_title"] = str(ae_title).strip()
        if count is not None:
            line["count"] = int(count)
        line["result"] = str(result)[:_TEXT_LIMIT]
        self._append((json.dumps(line, ensure_ascii=True) + "\n").encode())
        return line

    def _append(self, data: bytes) -> None:
        import fcntl

        with self._lock:
            self.folder.mkdir(mode=0o700, parents=True, exist_ok=True)
            lock_fd = os.open(self.folder / ".lock", os.O_WRONLY | os.O_CREAT, 0o600)
            try:
                fcntl.flock(lock_fd, fcntl.LOCK_EX)
                try:
                    size = self.path.stat().st_size
                except FileNotFoundError:
                    size = 0
                if size and size + len(data) > self.max_bytes:
                    self._rotate()
                fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
                try:
                    os.write(fd, data)
                finally:
                    os.close(fd)
            finally:
                os.close(lock_fd)

    def _rotate(self) -> None:
        oldest = self._rotated(self.keep)
        if oldest.exists():
            oldest.unlink()
        for n in range(self.keep - 1, 0, -1):
            if self._rotated(n).exists():
                os.replace(self._rotated(n), self._rotated(n + 1))
        os.replace(self.path, self._rotated(1))

    def files(self) -> list[Path]:
        """The audit files, oldest first."""
        rotated = [self._rotated(n) for n in range(self.keep, 0, -1)]
        return [p for p in [*rotated, self.path] if p.is_file()]

    def lines(self) -> Iterator[dict[str, Any]]:
        """Every recorded line, oldest first (a damaged line is skipped)."""
        for path in self.files():
            with path.open("rb") as fh:
                for raw in fh:
                    try:
                        yield json.loads(raw)
                    except ValueError:
                        continue


_default: AuditLog | None = None
_default_lock = threading.Lock()


def audit_log() -> AuditLog:
    """The process's audit log (in :func:`default_folder`, looked up again when it changes)."""
    global _default
    with _default_lock:
        folder = default_folder()
        if _default is None or _default.folder != folder:
            _default = AuditLog(folder)
        return _default


def record(action: str, **fields: Any) -> None:
    """Append a line to the process's audit log; a log that cannot be written is reported on
    stderr once per failure and never stops the action."""
    try:
        audit_log().record(action, **fields)
    except OSError as exc:
        import sys

        print(f"roadmap3d: cannot write the audit log ({exc.strerror or exc})", file=sys.stderr, flush=True)
