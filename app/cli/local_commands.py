"""The commands that work on this machine's own files: ``audit`` (the audit trail) and
``password`` (a password file for the web app's sign-in)."""

from __future__ import annotations

import getpass
import json
import sys

from app.cli.configs import Audit, Password
from app.cli.errors import UserError
from registration.io.audit import AuditLog
from registration.io.dicom import write_text_atomic
from registration.io.passwords import PasswordHash


def _audit_line(line: dict) -> str:
    """One audit line as text: time, client, action, result and the UIDs it names."""
    uids = []
    if "study_uid" in line:
        uids.append(f"study {line['study_uid']}")
    if line.get("series_uids"):
        uids.append("series " + ",".join(line["series_uids"]))
    if "instance_uid" in line:
        uids.append(f"instance {line['instance_uid']}")
    if "ae_title" in line:
        uids.append(f"AE {line['ae_title']}")
    extra = f"  [{'; '.join(uids)}]" if uids else ""
    return (f"{line.get('time', '?')}  {line.get('client') or '-':<15}  {line.get('action', '?'):<24}  "
            f"{line.get('result', '')}{extra}")  # fmt: skip


def run_audit(options: Audit) -> int:
    """Print the audit trail's last lines (or all of them), as text or as the stored JSON."""
    log = AuditLog(options.folder)
    lines = list(log.lines())
    if not lines:
        print(f"no audit lines in {log.folder}", file=sys.stderr)
        return 0
    for line in lines if options.all_lines else lines[-max(0, options.last) :]:
        print(json.dumps(line) if options.as_json else _audit_line(line))
    return 0


def run_password(options: Password) -> int:
    """Ask for a password twice (or read one line of standard input) and write its salted hash."""
    file = options.file
    if file.is_dir():
        raise UserError(f"{file}: is a folder; give the password file's name")
    if file.exists() and not options.force:
        raise UserError(f"{file}: exists; give --force to replace it")
    if sys.stdin.isatty():
        first = getpass.getpass("Password: ")
        if getpass.getpass("Again: ") != first:
            raise UserError("the two passwords differ; nothing written")
    else:
        first = sys.stdin.readline().rstrip("\r\n")
    try:
        line = PasswordHash.of(first).text()
    except ValueError as exc:
        raise UserError(f"{exc}; nothing written") from None
    write_text_atomic(file, line + "\n", mode=0o600)  # readable by you alone, from its first byte
    print(f"wrote {file} (the password's hash; start the app with --password-file {file})")
    return 0
