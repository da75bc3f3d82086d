"""The ``roadmap3d`` console script: a ``register`` goes to a running worker (``roadmap3d serve``)
when one answers on this user's socket, everything else to :func:`app.cli.main`.

A worker keeps the engine's compiled kernels, the volumes it read and their preparations in one
process, so that a ``register`` skips the interpreter's start-up, the imports, the reading of the
volume and its preparation. This module is what runs before that choice: the standard library
only, so that a command given to the worker costs the client a few tens of milliseconds.

The worker is used only when it runs the same code as this client (a fingerprint of the
package's sources) and the same ``ROADMAP3D_*`` settings; otherwise, when no worker answers, or
with ``ROADMAP3D_WORKER=off``, the command runs here as always.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import sys
from pathlib import Path

#: Protocol version of a request; a worker answers another version with "stale".
PROTOCOL = 1
#: Commands a worker runs (the others gain nothing from a warm engine).
WORKER_COMMANDS = ("register",)
#: Seconds a client waits to connect (a worker busy with another command accepts later: the
#: queue is the socket's backlog, and a connection in it is accepted at once).
CONNECT_TIMEOUT_S = 2.0


def socket_path() -> Path:
    """Where this user's worker listens: ``ROADMAP3D_WORKER_SOCKET``, else ``worker.sock`` in
    ``$XDG_RUNTIME_DIR/roadmap3d``, else in ``/tmp/roadmap3d-<uid>`` (a folder only its user can open)."""
    given = os.environ.get("ROADMAP3D_WORKER_SOCKET")
    if given:
        return Path(given)
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and Path(runtime).is_dir():
        return Path(runtime) / "roadmap3d" / "worker.sock"
    return Path("/tmp") / f"roadmap3d-{os.getuid()}" / "worker.sock"


def source_fingerprint() -> str:
    """Size and modification time of every Python source of the project's packages: a worker
    started before an update or an edit answers with other code, and is not used."""
    root = Path(__file__).resolve().parents[1]
    parts = []
    for package in ("app", "registration"):
        for path in sorted((root / package).rglob("*.py")):
            try:
                st = path.stat()
            except OSError:
                continue
            parts.append(f"{path.relative_to(root)}:{st.st_size}:{st.st_mtime_ns}")
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]


def settings() -> dict[str, str]:
    """The ``ROADMAP3D_*`` environment variables that change what a command does (the worker's
    own socket and switch left out)."""
    skip = {"ROADMAP3D_WORKER", "ROADMAP3D_WORKER_SOCKET"}
    return {k: v for k, v in sorted(os.environ.items()) if k.startswith("ROADMAP3D_") and k not in skip}


def process_age_s() -> float | None:
    """Seconds since this process started (Linux), None elsewhere."""
    try:
        ticks = os.sysconf("SC_CLK_TCK")
        start = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19]) / ticks
        return float(Path("/proc/uptime").read_text().split()[0]) - start
    except (OSError, ValueError, IndexError):
        return None


def request(argv: list[str]) -> dict:
    return {
        "protocol": PROTOCOL,
        "argv": argv,
        "cwd": os.getcwd(),
        "fingerprint": source_fingerprint(),
        "settings": settings(),
        "client_startup_s": process_age_s(),
    }


def _not_private(path: Path) -> str:
    """Why the socket at ``path`` may be someone else's ("" when it and its folder are this
    user's and the folder is closed to others)."""
    try:
        folder, sock = path.parent.stat(), path.stat()
    except OSError as exc:
        return exc.strerror or "unreadable"
    if folder.st_uid != os.getuid() or sock.st_uid != os.getuid():
        return "it belongs to another user"
    if folder.st_mode & 0o077:
        return "its folder is open to other users"
    return ""


def peer_uid(conn: socket.socket) -> int | None:
    """The user id of the process at the other end (Linux), None where the system does not say."""
    import struct

    try:
        creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    except (AttributeError, OSError):
        return None
    return struct.unpack("3i", creds)[1]


def run_on_worker(argv: list[str], path: Path | None = None) -> int | None:
    """Run ``roadmap3d ARGV`` on the worker: its output printed here as it comes, its exit code
    returned. None when no worker took it (none answers, or it runs other code or settings): the
    caller runs the command itself. A worker lost after it began answering gives exit code 1."""
    path = socket_path() if path is None else path
    if not path.exists():
        return None
    doubt = _not_private(path)
    if doubt:
        print(f"note: {path} is not used ({doubt}): running here", file=sys.stderr)
        return None
    conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    conn.settimeout(CONNECT_TIMEOUT_S)
    began = False
    try:
        conn.connect(str(path))
        if peer_uid(conn) not in (None, os.getuid()):
            print(f"note: {path} is served by another user: running here", file=sys.stderr)
            return None
        conn.settimeout(None)
        conn.sendall(json.dumps(request(argv)).encode() + b"\n")
        for line in conn.makefile("rb"):
            message = json.loads(line)
            if "stale" in message:
                print(f"note: the worker at {path} {message['stale']}: running here (restart `roadmap3d serve`)",
                      file=sys.stderr)  # fmt: skip
                return None
            began = True
            if "exit" in message:
                return int(message["exit"])
            stream = sys.stdout if "out" in message else sys.stderr
            stream.write(message.get("out", message.get("err", "")))
            stream.flush()
    except (OSError, ValueError) as exc:
        if not began:
            if isinstance(exc, TimeoutError):
                print(f"note: the worker at {path} did not answer: running here", file=sys.stderr)
            return None  # a socket left by a worker that ended, or one that cannot take it
        print(f"error: the worker at {path} was lost during the command ({exc})", file=sys.stderr)
        return 1
    finally:
        conn.close()
    if not began:
        return None
    print(f"error: the worker at {path} ended without finishing the command", file=sys.stderr)
    return 1


def main() -> None:
    """The console script."""
    argv = sys.argv[1:]
    if (
        argv
        and hasattr(os, "getuid")  # a POSIX system: the worker's socket and its checks exist there
        and argv[0] in WORKER_COMMANDS
        and not {"-h", "--help"} & set(argv)
        and os.environ.get("ROADMAP3D_WORKER", "").lower() not in ("off", "0", "no")
    ):
        try:
            code = run_on_worker(argv)
        except KeyboardInterrupt:
            print("interrupted (the worker finishes the command it started)", file=sys.stderr)
            sys.exit(130)
        if code is not None:
            sys.stdout.flush()
            sys.exit(code)
    from app.cli import main as cli_main

    cli_main()
