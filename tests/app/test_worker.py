"""``roadmap3d serve``: a register run on the warm worker gives what it gives in its own process,
bad input the same message and exit code; the console script runs a command itself when no
worker can take it; the socket is private."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from app.cli.errors import UserError
from app.cli.worker import VolumeMemory, private_socket
from app.launch import run_on_worker

#: The console script, as installed (app.launch:main), in a process of its own.
SCRIPT = [sys.executable, "-c", "import sys; sys.argv[0] = 'roadmap3d'; from app.launch import main; main()"]


def _env(sock: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "ROADMAP3D_WORKER"}
    return env | {"ROADMAP3D_WORKER_SOCKET": str(sock)} | extra


@pytest.fixture(scope="module")
def worker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, subprocess.Popen, list[str]]]:
    """A worker on a socket of its own; yields the socket, the process and the lines it printed."""
    folder = tmp_path_factory.mktemp("worker") / "private"
    sock = folder / "worker.sock"
    proc = subprocess.Popen([*SCRIPT, "serve", "--socket", str(sock), "--verbose"], env=_env(sock),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)  # fmt: skip
    lines: list[str] = []
    assert proc.stdout is not None
    deadline = time.monotonic() + 300  # the warm-up compiles the kernels when no compiled copy is on disk
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if "ready in" in line:
            break
    assert any("ready in" in x for x in lines), "".join(lines)
    yield sock, proc, lines
    proc.terminate()
    rest, _ = proc.communicate(timeout=60)
    lines.append(rest)
    assert proc.returncode == 0
    assert not sock.exists()  # removed on SIGTERM


def _served(proc_lines: list[str], proc: subprocess.Popen) -> None:
    assert proc.stdout is not None
    proc_lines.append(proc.stdout.readline())


def test_socket_is_private(worker) -> None:
    sock, _, _ = worker
    assert sock.is_socket()
    assert sock.stat().st_mode & 0o777 == 0o600
    assert sock.parent.stat().st_mode & 0o777 == 0o700


def test_register_on_the_worker_equals_its_own_process(worker, small_export: Path, tmp_path: Path, capsys) -> None:
    from app import cli

    sock, proc, lines = worker
    args = ["register", "--volume", str(small_export / "volume"), "--image", str(small_export / "xa_fluoro.dcm"),
            "--truth", str(small_export / "truth.json"), "--verbose"]  # fmt: skip
    with pytest.raises(SystemExit) as info:
        cli.main([*args, "--out", str(tmp_path / "here.json")])
    assert info.value.code == 0
    here_out = capsys.readouterr().out
    # relative output path: the worker runs in the client's folder
    done = subprocess.run([*SCRIPT, *args, "--out", "there.json"], env=_env(sock), cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    _served(lines, proc)
    assert "served register (exit code 0)" in lines[-1]  # the worker ran it, not the client
    assert "the worker's engine was warm" in done.stderr
    here = json.loads((tmp_path / "here.json").read_text())
    there = json.loads((tmp_path / "there.json").read_text())
    # the same seed and inputs: the same estimate, bit for bit, and the same cost
    assert there["patient_motion"] == here["patient_motion"]
    assert there["drr_count"] == here["drr_count"]
    assert [x for x in done.stdout.splitlines() if "residual" in x] == [
        x for x in here_out.splitlines() if "residual" in x
    ]
    # a second run reads the volume from the worker's memory
    again = subprocess.run([*SCRIPT, *args], env=_env(sock), capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    _served(lines, proc)
    assert "reading the volume 0.00 s" in again.stderr


def test_bad_input_on_the_worker_exits_2_with_the_message(worker, small_export: Path, tmp_path: Path) -> None:
    sock, proc, lines = worker
    done = subprocess.run([*SCRIPT, "register", "--volume", str(tmp_path / "nope"), "--image",
                           str(small_export / "xa_fluoro.dcm"), "--out", "result.json"], env=_env(sock), cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    _served(lines, proc)
    assert done.returncode == 2
    assert done.stderr.startswith("error: ") and "nope" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "result.json").exists()
    assert "served register (exit code 2)" in lines[-1]


def test_other_settings_run_in_the_clients_own_process(worker, small_export: Path, tmp_path: Path) -> None:
    sock, proc, lines = worker
    env = _env(sock, ROADMAP3D_NO_CACHE="1")
    done = subprocess.run([*SCRIPT, "register", "--volume", str(tmp_path / "nope"), "--image",
                           str(small_export / "xa_fluoro.dcm")], env=env, capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    assert done.returncode == 2
    assert "other ROADMAP3D_* settings" in done.stderr and "running here" in done.stderr
    assert "error: " in done.stderr and "nope" in done.stderr
    _served(lines, proc)
    assert "declined: other settings" in lines[-1]


def test_no_worker_means_run_here(tmp_path: Path) -> None:
    assert run_on_worker(["register"], tmp_path / "absent.sock") is None
    # a socket file left by a worker that ended: nobody answers, the client runs the command
    left = tmp_path / "left.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(left))
    s.close()
    assert left.exists()
    assert run_on_worker(["register"], left) is None


def test_a_socket_others_could_have_made_is_not_used(tmp_path: Path, capsys) -> None:
    folder = tmp_path / "open"
    folder.mkdir()
    folder.chmod(0o755)
    sock = folder / "worker.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(sock))
    s.listen(1)
    try:
        assert run_on_worker(["register"], sock) is None  # never connected to
    finally:
        s.close()
    assert "its folder is open to other users" in capsys.readouterr().err


def test_second_worker_on_one_socket_is_refused(worker) -> None:
    sock, _, _ = worker
    with pytest.raises(UserError, match="already listens"):
        private_socket(sock)


def test_open_folder_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "open"
    folder.mkdir(mode=0o755)
    folder.chmod(0o755)
    with pytest.raises(UserError, match="no access for others"):
        private_socket(folder / "worker.sock")


def test_volume_memory_reads_again_when_a_file_changes(tmp_path: Path) -> None:
    reads: list[str] = []

    def read(path: object) -> str:
        reads.append(str(path))
        return f"volume {len(reads)}"

    memory = VolumeMemory(read, keep=1)
    series = tmp_path / "series"
    series.mkdir()
    (series / "1.dcm").write_bytes(b"a")
    other = tmp_path / "other.nii"
    other.write_bytes(b"b")
    assert memory.read(series) == memory.read(series) == "volume 1"
    (series / "1.dcm").write_bytes(b"changed")
    assert memory.read(series) == "volume 2"  # a file of the series changed size
    assert memory.read(other) == "volume 3"
    assert memory.read(series) == "volume 4"  # keep=1: the series was let go for the other volume
    assert len(reads) == 4
