"""The command line's start-up and exit tweaks, each measured, none reaching into another
library's private API.

- :func:`small_pages`: numpy without transparent huge pages for a short process.
- :func:`read_ahead_for_register`: the OS reads the input files while the engine is imported.
- :func:`exit_without_teardown`: the process ends after the exit handlers, without the interpreter's teardown.

Read-ahead (Linux; elsewhere nothing):

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

import atexit
import logging
import os
import sys
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


def small_pages() -> None:
    """numpy without transparent huge pages (``NUMPY_MADVISE_HUGEPAGE=0`` unless the caller set it,
    only before numpy is imported): a fresh process read the real CT in 0.19 s instead of 0.30-0.39 s."""
    if "numpy" not in sys.modules:
        os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")


_exit_code: list[int] = []


def _end_process() -> None:
    if _exit_code:
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a closed pipe (| head): nothing more can be said
                pass
        os._exit(_exit_code[0])


def exit_without_teardown() -> None:
    """Have the process end right after the exit handlers registered later than this call, skipping
    the interpreter's teardown of numba, llvmlite and scipy (~0.4 s after a command's work).

    Registered first, it runs last (``atexit`` runs handlers in reverse order); other threads are
    waited for before any handler runs. Call :func:`exit_code` with the code before ``sys.exit``."""
    atexit.register(_end_process)


def exit_code(code: int) -> int:
    """Remember ``code`` for :func:`exit_without_teardown`; returns it."""
    _exit_code[:] = [code]
    return code
