"""``roadmap3d serve``: a warm worker that runs ``roadmap3d register`` for this user's commands.

One process keeps the engine imported, its kernels loaded, the volumes it read (the last
``keep``, by path and the files' sizes and times) and their preparations in memory, and answers
on a Unix socket that only its user can open (the folder 0700, the socket 0600, and each peer's
user id checked). The console script (:mod:`app.launch`) sends it a ``register`` with the
client's folder; the command runs here exactly as it would there, one at a time, and its output
and exit code go back to the client. A request with other code or other ``ROADMAP3D_*`` settings
than the worker's is answered "stale", and the client runs the command itself.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import socket
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from app.cli.configs import Serve
from app.cli.errors import UserError
from app.launch import PROTOCOL, WORKER_COMMANDS, peer_uid, settings, socket_path, source_fingerprint

#: The longest request line read (bytes): a command line, its folder and settings.
MAX_REQUEST_BYTES = 1 << 20
#: Seconds a connected client has to send its request.
REQUEST_TIMEOUT_S = 10.0


class _Sink(io.TextIOBase):
    """A text stream that sends what is written, line by line, to the client as ``{kind: text}``;
    a client that went away is not written to again (the command finishes regardless)."""

    def __init__(self, send: Callable[[dict], None], kind: str) -> None:
        self._send, self._kind, self._buffer = send, kind, ""

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        self._buffer += text
        if "\n" in self._buffer:
            head, _, self._buffer = self._buffer.rpartition("\n")
            self._send({self._kind: head + "\n"})
        return len(text)

    def flush(self) -> None:
        if self._buffer:
            self._send({self._kind: self._buffer})
            self._buffer = ""


class VolumeMemory:
    """The last ``keep`` volumes read, by path: a volume is read again when any of its files
    changed size or time (a DICOM folder: each file in it)."""

    def __init__(self, read: Callable[[Any], Any], keep: int) -> None:
        self._read, self.keep = read, max(1, int(keep))
        self._volumes: OrderedDict[tuple, Any] = OrderedDict()

    def read(self, path: Any, *args: Any, **kwargs: Any) -> Any:
        if args or kwargs:
            return self._read(path, *args, **kwargs)
        from registration.io.dicom import DicomError
        from registration.io.volume_cache import files_state

        where = Path(path).resolve()
        try:
            key = (str(where), files_state(where))
        except (OSError, DicomError):
            return self._read(path)  # the reader names the file and the problem
        if key in self._volumes:
            self._volumes.move_to_end(key)
            return self._volumes[key]
        volume = self._read(path)
        self._volumes[key] = volume
        while len(self._volumes) > self.keep:
            self._volumes.popitem(last=False)
        return volume


def warm_up() -> None:
    """One small registration and its assessment (a 64^3 skull of 2 mm voxels against its own
    128-pixel DRR): every kernel a ``register --confidence`` runs is loaded once."""
    import numpy as np

    from registration.core.assess import assess
    from registration.core.drr import DRRRenderer
    from registration.core.geometry import TABLE_I, CArm, offsets_to_matrix
    from registration.core.images import XRayImage
    from registration.core.preparation import Preparation
    from registration.core.register import register
    from registration.core.volume import Volume

    n, mm = 64, 2.0
    k, j, i = (np.mgrid[0:n, 0:n, 0:n] - (n - 1) / 2.0) * mm
    r = np.sqrt((i / 70.0) ** 2 + (j / 85.0) ** 2 + (k / 60.0) ** 2)
    data = np.where(r < 0.92, 40.0, -1000.0) + np.where((r > 0.8) & (r < 0.92), 1200.0, 0.0)
    data += 300.0 * (np.abs(i - 0.3 * k) < 3.0) * (r < 0.8)  # a ridge inside, not symmetric
    affine = np.diag([mm, mm, mm, 1.0])
    affine[:3, 3] = -(n - 1) / 2.0 * mm
    volume = Volume(data.astype(np.float32), affine, label="warm-up")
    geometry = CArm.for_format(27.0, pixels=128)
    truth = offsets_to_matrix(TABLE_I["T1"], geometry)
    drr = DRRRenderer(volume).render(geometry, truth)
    view = XRayImage(drr, np.ones(drr.shape, dtype=bool), geometry, kind="drr")
    prepared = Preparation.of(volume, view)
    assess(register(volume, view, renderer=prepared.renderer), [view], prepared)


@contextlib.contextmanager
def _in_folder(folder: str) -> Iterator[None]:
    before = os.getcwd()
    os.chdir(folder)
    try:
        yield
    finally:
        os.chdir(before)


def private_socket(path: Path) -> socket.socket:
    """A listening Unix socket at ``path`` in a folder only this user can open; a socket file
    left by a worker that ended is replaced; a worker that answers there is not."""
    folder = path.parent
    folder.mkdir(parents=True, exist_ok=True, mode=0o700)
    st = folder.stat()
    if st.st_uid != os.getuid() or st.st_mode & 0o077:
        raise UserError(f"{folder}: the worker's folder must belong to this user with no access for others "
                        f"(mode {oct(st.st_mode & 0o777)}); choose another with --socket")  # fmt: skip
    if path.exists() or path.is_symlink():
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(str(path))
        except OSError:
            path.unlink()  # left by a worker that ended
        else:
            raise UserError(f"{path}: a worker already listens there (stop it first, or give --socket)")
        finally:
            probe.close()
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    old = os.umask(0o177)
    try:
        server.bind(str(path))
    finally:
        os.umask(old)
    os.chmod(path, 0o600)
    server.listen(16)
    return server


class Worker:
    """Runs clients' commands one at a time (see the module)."""

    def __init__(self, keep: int = 2) -> None:
        self.fingerprint = source_fingerprint()
        self.settings = settings()
        self.keep = keep
        self.served = 0

    def warm(self) -> float:
        """Import the engine and load its kernels (compiling them when none are on disk), and have
        ``register`` read volumes through this worker's memory. Returns the seconds it took."""
        began = time.perf_counter()
        from app.cli import register_command
        from registration.io import dicom

        warm_up()
        register_command.use_volume_reader(VolumeMemory(dicom.read_volume, self.keep).read)
        return time.perf_counter() - began

    def answer(self, conn: socket.socket) -> str:
        """Read one request from ``conn``, run it, send its output and exit code; returns what was done."""
        lost = False

        def send(message: dict) -> None:
            nonlocal lost
            if lost:
                return
            try:
                conn.sendall(json.dumps(message).encode() + b"\n")
            except OSError:
                lost = True

        uid = peer_uid(conn)
        if uid is not None and uid != os.getuid():
            send({"err": "error: this worker serves its own user only\n"})
            send({"exit": 2})
            return f"refused user {uid}"
        conn.settimeout(REQUEST_TIMEOUT_S)
        try:
            line = conn.makefile("rb").readline(MAX_REQUEST_BYTES)
            req = json.loads(line)
            argv, folder = [str(a) for a in req["argv"]], str(req["cwd"])
        except (OSError, ValueError, KeyError, TypeError):
            return "no request"  # not a client of ours, or one that gave up: nothing to answer
        conn.settimeout(None)
        if req.get("protocol") != PROTOCOL or req.get("fingerprint") != self.fingerprint:
            send({"stale": "runs other code than this command"})
            return "declined: other code"
        if req.get("settings") != self.settings:
            send({"stale": "runs with other ROADMAP3D_* settings than this command"})
            return "declined: other settings"
        if not argv or argv[0] not in WORKER_COMMANDS:
            send({"err": f"error: the worker runs {', '.join(WORKER_COMMANDS)} only\n"})
            send({"exit": 2})
            return f"refused {argv[0] if argv else 'an empty command'}"
        from app.cli import commands, execute

        out, err = _Sink(send, "out"), _Sink(send, "err")
        try:
            with _in_folder(folder), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                commands.client_startup(req.get("client_startup_s"))
                try:
                    code = execute(argv, in_worker=True)
                finally:
                    commands.client_startup(None)
                    out.flush()
                    err.flush()
        except FileNotFoundError:
            send({"err": f"error: {folder}: the command's folder is gone\n"})
            code = 2
        except Exception as exc:  # noqa: BLE001 - the worker outlives a command's unexpected error
            send({"err": f"error: the worker failed on this command ({type(exc).__name__}: {exc}); "
                         "rerun with ROADMAP3D_WORKER=off to run it here\n"})  # fmt: skip
            code = 1
        send({"exit": int(code)})
        self.served += 1
        return f"served {argv[0]} (exit code {code})"


def run_serve(options: Serve) -> int:
    """``roadmap3d serve``: listen until Ctrl-C or SIGTERM, then remove the socket."""
    if not hasattr(os, "getuid") or not hasattr(socket, "AF_UNIX"):
        raise UserError("roadmap3d serve needs a POSIX system (a private Unix socket)")
    path = Path(options.socket) if options.socket is not None else socket_path()
    server = private_socket(path)
    worker = Worker(keep=options.keep)
    print(f"roadmap3d worker: loading the engine ... (socket {path})", flush=True)
    try:
        seconds = worker.warm()
    except BaseException:
        server.close()
        path.unlink(missing_ok=True)
        raise
    print(f"roadmap3d worker: ready in {seconds:.1f} s; `roadmap3d register` of this user runs here "
          "(ROADMAP3D_WORKER=off runs it in its own process); Ctrl-C stops", flush=True)  # fmt: skip

    def stop(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)
    try:
        while True:
            conn, _ = server.accept()
            with conn:
                began = time.perf_counter()
                done = worker.answer(conn)
                if options.verbose:
                    print(f"{done} in {time.perf_counter() - began:.2f} s", flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
        path.unlink(missing_ok=True)
    print(f"roadmap3d worker: stopped after {worker.served} command{'s' if worker.served != 1 else ''}")
    return 0
