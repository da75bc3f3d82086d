"""A small on-disk cache for generated phantoms, volumes, reconstructions and meshes.

Entries live under the user's cache directory (``platformdirs``; override with the
``ROADMAP3D_CACHE`` environment variable), never in the repository, keyed by a hash of
their parameters. Writes are atomic (temporary file, then rename), so a killed process
never leaves a half-written entry.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
import threading
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import platformdirs

#: Bump when the meaning of cached data changes (phantom model, reconstruction, ...).
CACHE_VERSION = 1
#: Prepared volumes (:class:`PreparationCache`) kept at most, in bytes on disk together (the
#: least recently used go first); one real CT's entry is ~25 MB.
PREPARED_MAX_BYTES = 512 * 1024**2
#: The kinds of entry a :class:`PreparationCache` writes (file name prefixes).
PREPARED_KINDS = ("prepared-blocks", "prepared-levels", "cranium")

log = logging.getLogger(__name__)


def cache_dir() -> Path:
    root = os.environ.get("ROADMAP3D_CACHE")
    path = Path(root) if root else Path(platformdirs.user_cache_dir("roadmap3d"))
    path.mkdir(parents=True, exist_ok=True)
    return path


def cache_key(kind: str, params: dict) -> str:
    """A stable file name for ``kind`` with ``params`` (JSON-serialisable values)."""
    blob = json.dumps({"kind": kind, "v": CACHE_VERSION, **params}, sort_keys=True, default=str)
    return f"{kind}-{hashlib.sha256(blob.encode()).hexdigest()[:20]}"


def cached_arrays(
    kind: str, params: dict, build: Callable[[], dict[str, np.ndarray]], *, enabled: bool = True
) -> dict[str, np.ndarray]:
    """Load the arrays for (kind, params) from the cache, or build and store them."""
    if not enabled or os.environ.get("ROADMAP3D_NO_CACHE") == "1":
        return build()
    path = cache_dir() / f"{cache_key(kind, params)}.npz"
    if path.exists():
        try:
            with np.load(path, allow_pickle=False) as data:
                return {k: data[k] for k in data.files}
        except (OSError, ValueError, EOFError):
            path.unlink(missing_ok=True)  # corrupt entry: rebuild
    arrays = build()
    _write_npz_atomic(path, arrays)
    return arrays


def is_cached(kind: str, params: dict) -> bool:
    return (cache_dir() / f"{cache_key(kind, params)}.npz").exists()


def write_atomic(path: Path, write: Callable[[Any], object]) -> None:
    """``write(file)`` into a temporary file beside ``path``, then renamed onto it: readers see the
    old file or the whole new one, and a killed process leaves no half-written ``path``."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _write_npz_atomic(path: Path, arrays: dict[str, np.ndarray]) -> None:
    write_atomic(path, lambda f: np.savez(f, **arrays))


def prune_least_recent(entries: list[Path], max_bytes: int, *, keep: Path | None = None,
                       remove: Callable[[Path], None] = lambda p: p.unlink(missing_ok=True)) -> None:  # fmt: skip
    """``remove`` the least recently modified of ``entries`` until the rest fit ``max_bytes``
    together (never ``keep``; an entry that cannot be looked at is left alone)."""
    sized = []
    for p in entries:
        try:
            st = p.stat()
        except OSError:
            continue
        sized.append((st.st_mtime, st.st_size, p))
    total = sum(size for _, size, _ in sized)
    for _, size, p in sorted(sized, key=lambda e: e[0]):
        if total <= max_bytes:
            break
        if keep is not None and p == keep:
            continue
        remove(p)
        total -= size


class CacheFolder:
    """A kind of entry in :func:`cache_dir` (or ``root``), kept under ``max_bytes`` together;
    ``ROADMAP3D_NO_CACHE=1`` turns it off (``enabled``)."""

    def __init__(self, root: Path | None = None, *, max_bytes: int) -> None:
        self._root = None if root is None else Path(root)
        self.max_bytes = int(max_bytes)
        self.enabled = os.environ.get("ROADMAP3D_NO_CACHE") != "1"

    @property
    def root(self) -> Path:
        if self._root is None:
            return cache_dir()
        self._root.mkdir(parents=True, exist_ok=True)
        return self._root


class PreparationCache(CacheFolder):
    """Prepared volumes on disk (:class:`registration.core.prepare.PreparationStore`).

    Entries are ``.npz`` files in :func:`cache_dir` (or ``root``) named by a hash of their key
    (the volume's SHA-256 and the preparation's parameters and version); each holds its key,
    which a load compares, so a foreign or stale file of the same name is never used. Writes
    are atomic; a damaged, unreadable or mismatching entry is removed and reported as missing
    (the caller builds and saves it again), never an exception. The entries of this kind are
    kept under ``max_bytes`` together, the least recently used removed first.
    ``ROADMAP3D_NO_CACHE=1`` turns it off (nothing read, nothing written). ``background``: each
    :meth:`save` writes from a thread of its own (the caller goes on registering: the first run
    on a CT writes ~20 MB) and :meth:`flush` waits for the writes; the arrays given to
    :meth:`save` must not change afterwards.
    """

    def __init__(self, root: Path | None = None, *, max_bytes: int = PREPARED_MAX_BYTES,
                 background: bool = False) -> None:  # fmt: skip
        super().__init__(root, max_bytes=max_bytes)
        self.background = bool(background)
        self._writers: list[threading.Thread] = []
        self._lock = threading.Lock()

    def path(self, kind: str, key: dict) -> Path:
        if kind not in PREPARED_KINDS:
            raise ValueError(f"unknown prepared-volume entry kind {kind!r}")
        return self.root / f"{cache_key(kind, key)}.npz"

    @staticmethod
    def _key_bytes(kind: str, key: dict) -> np.ndarray:
        blob = json.dumps({"kind": kind, **key}, sort_keys=True, default=str).encode()
        return np.frombuffer(blob, dtype=np.uint8)

    def load(self, kind: str, key: dict) -> dict[str, np.ndarray] | None:
        if not self.enabled:
            return None
        try:
            path = self.path(kind, key)
        except OSError as exc:  # no cache folder can be made: prepare without one
            log.warning("prepared-volume cache unavailable: %s", exc)
            return None
        if not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
            if not np.array_equal(arrays.pop("__key__", None), self._key_bytes(kind, key)):
                raise ValueError("the entry belongs to another key")
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
            log.warning("prepared-volume cache entry %s unusable (%s): rebuilt", path.name, exc)
            path.unlink(missing_ok=True)
            return None
        try:
            os.utime(path)  # recently used: pruned last
        except OSError:
            pass
        return arrays

    def save(self, kind: str, key: dict, arrays: dict[str, np.ndarray]) -> None:
        if not self.enabled:
            return
        if self.background:
            writer = threading.Thread(target=self._save_quietly, args=(kind, key, dict(arrays)),
                                      name="roadmap3d-cache-write")  # fmt: skip
            with self._lock:
                self._writers.append(writer)
            writer.start()
            return
        self._save(kind, key, arrays)

    def flush(self) -> None:
        """Wait for the background writes (nothing to do without ``background``)."""
        with self._lock:
            writers, self._writers = self._writers, []
        for writer in writers:
            writer.join()

    def _save_quietly(self, kind: str, key: dict, arrays: dict[str, np.ndarray]) -> None:
        """:meth:`_save` in a writer thread: whatever fails is a warning (the run is prepared
        either way; the next one builds the entry again), never a thread's traceback."""
        try:
            self._save(kind, key, arrays)
        except Exception as exc:  # noqa: BLE001
            log.warning("prepared-volume cache not written: %s: %s", type(exc).__name__, exc)

    def _save(self, kind: str, key: dict, arrays: dict[str, np.ndarray]) -> None:
        try:
            path = self.path(kind, key)
            _write_npz_atomic(path, {**arrays, "__key__": self._key_bytes(kind, key)})
            self.prune(keep=path)
        except OSError as exc:  # a full or read-only disk: this run is prepared, the next builds again
            log.warning("prepared-volume cache not written: %s", exc)

    def entries(self) -> list[Path]:
        return [p for kind in PREPARED_KINDS for p in self.root.glob(f"{kind}-*.npz")]

    def prune(self, *, keep: Path | None = None) -> None:
        """Remove the least recently used entries until they fit ``max_bytes`` (never ``keep``)."""
        with self._lock:  # one writer prunes at a time
            self._prune(keep)

    def _prune(self, keep: Path | None) -> None:
        prune_least_recent(self.entries(), self.max_bytes, keep=keep)
