"""Ask the OS to read ahead the files a command is about to need (Linux; elsewhere nothing).

A first ``roadmap3d register`` after a while finds little in the OS page cache (this kind of
VM reclaims idle file pages within minutes): the CT's slices, the prepared volume on disk and
numba's compiled kernels are then read from disk file by file while the process waits. Telling
the kernel up front (``posix_fadvise(POSIX_FADV_WILLNEED)``, from a daemon thread so that the
command never waits on it) has it read them while the interpreter imports its modules. (numba's
LLVM library, 170 MB, is left alone: reading it whole slowed the imports more than it saved.)
A hint only: nothing is read into this process, a missing or unreadable file is skipped, and on a
warm page cache it costs a few milliseconds. Light: imports nothing beyond the standard library.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable, Sequence
from pathlib import Path

#: Files of one folder (a DICOM series) read ahead at most.
MAX_FOLDER_FILES = 4000
#: The most recently used prepared volumes in the cache folder read ahead (bytes together).
PREPARED_BYTES = 96 * 1024**2


def kernel_files() -> list[Path]:
    """The engine's compiled kernels (numba's cache beside ``registration/core``)."""
    core = Path(__file__).resolve().parents[2] / "registration" / "core" / "__pycache__"
    return sorted(core.glob("*.nbi")) + sorted(core.glob("*.nbc"))


def input_files(paths: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """The files of ``paths``: a file itself, a folder's files (one level, as a slice series)."""
    out: list[Path] = []
    for p in paths:
        path = Path(p)
        try:
            if path.is_dir():
                with os.scandir(path) as entries:
                    files = [Path(e.path) for e in entries if e.is_file() and not e.name.startswith(".")]
                out += sorted(files)[:MAX_FOLDER_FILES]
            elif path.is_file():
                out.append(path)
        except OSError:
            continue
    return out


def prepared_files(cache_root: Path | None) -> list[Path]:
    """The most recently used prepared-volume entries of the cache folder (``PREPARED_BYTES``)."""
    if cache_root is None or not cache_root.is_dir():
        return []
    entries = []
    for p in cache_root.glob("prepared-*.npz"):
        try:
            st = p.stat()
        except OSError:
            continue
        entries.append((st.st_mtime, st.st_size, p))
    out, total = [], 0
    for _, size, p in sorted(entries, reverse=True):
        if total + size > PREPARED_BYTES:
            break
        out.append(p)
        total += size
    return out


def _advise(files: Sequence[Path]) -> None:
    for path in files:
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            continue
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_WILLNEED)
        except OSError:
            pass
        finally:
            os.close(fd)


def read_ahead(files: Sequence[Path]) -> threading.Thread | None:
    """Have the OS read ``files`` into its page cache in the background (a daemon thread);
    None where ``posix_fadvise`` does not exist."""
    if not hasattr(os, "posix_fadvise") or not files:
        return None
    thread = threading.Thread(target=_advise, args=(list(files),), name="roadmap3d-read-ahead", daemon=True)
    thread.start()
    return thread


def read_ahead_for_register(volume: str | os.PathLike[str], images: Sequence[str | os.PathLike[str]]) -> None:
    """What ``roadmap3d register`` reads: the volume's files and the image(s), the engine's
    compiled kernels and the recently prepared volumes (``ROADMAP3D_CACHE``)."""
    root = os.environ.get("ROADMAP3D_CACHE")
    cache = Path(root) if root else None
    if cache is None:
        try:
            import platformdirs

            cache = Path(platformdirs.user_cache_dir("roadmap3d"))
        except ImportError:
            cache = None
    read_ahead(input_files([volume, *images]) + kernel_files() + prepared_files(cache))
