"""Decoded volumes kept on disk: a DICOM series decoded once is loaded, not decoded again, by the
next command that reads the same files.

An entry belongs to a folder and to the exact state of every file in it: each file's name,
size, modification and change times (ns) and inode. Writing to a file changes its change time,
so an edited, replaced, added or removed file makes another key, and the series is decoded
again. An entry holds the voxels (``decoded-<key>.npy``, memory-mapped copy-on-write when
loaded: pages are read as the engine touches them, and nothing is ever written back) and beside
it ``decoded-<key>.json``: the key, the affine, the label, the reader's metadata and warnings,
and the voxels' digest (:func:`registration.core.prepare.store.volume_digest`, so that a
prepared volume on disk is found without hashing the voxels again). The JSON is written last
and both atomically: a killed process leaves no entry that loads. A damaged, foreign or
mismatching entry is removed and the series decoded (never an exception). The entries are kept
under ``max_bytes`` together, the least recently used removed first; ``ROADMAP3D_NO_CACHE=1``
turns it off.
"""

from __future__ import annotations

import json
import logging
import os
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from registration.core.volume import Volume
from registration.io.cache import CacheFolder, cache_key, prune_least_recent, write_atomic
from registration.io.dicom._common import DicomError, _candidate_files

#: Bump when what a decoded entry means changes (the reader's output for the same files).
DECODED_VERSION = 1
#: Decoded volumes kept at most, in bytes on disk together (one 512 x 512 x 90 CT: 94 MB).
DECODED_MAX_BYTES = 1024**3
#: The entries' file name prefix in the cache folder.
DECODED_KIND = "decoded"

log = logging.getLogger(__name__)


def files_state(path: Path, *, identity: bool = False) -> tuple:
    """The state of the files a volume at ``path`` is read from (a folder: every file the DICOM
    reader reads in it and in its subfolders): each one's path within it, size and modification
    time (ns); with ``identity`` also the change time (ns) and inode. Raises ``OSError`` when a
    file cannot be looked at, :class:`~registration.io.dicom.DicomError` when the folder holds
    too many."""
    files = _candidate_files(path) if path.is_dir() else [path]
    state = []
    for p in files:
        st = p.stat()
        name = str(p.relative_to(path)) if path.is_dir() else p.name
        state.append((name, st.st_size, st.st_mtime_ns) + ((st.st_ctime_ns, st.st_ino) if identity else ()))
    return tuple(state)


class DecodedVolumes(CacheFolder):
    """The decoded-volume entries of a cache folder (see the module)."""

    def __init__(self, root: Path | None = None, *, max_bytes: int = DECODED_MAX_BYTES) -> None:
        super().__init__(root, max_bytes=max_bytes)

    def read(self, path: str | os.PathLike[str], reader: Callable[[Path], Volume]) -> Volume:
        """The volume of the folder ``path``: from its entry when the files are as they were,
        else ``reader(path)``, kept for the next time. A path that is not a folder, or a cache
        that cannot be used, is read by ``reader`` alone."""
        folder = Path(path)
        if not self.enabled or not folder.is_dir():
            return reader(folder)
        try:
            key = {"folder": str(folder.resolve()), "files": files_state(folder, identity=True),
                   "version": DECODED_VERSION}  # fmt: skip
            name = cache_key(DECODED_KIND, key)
            root = self.root
        except (OSError, DicomError):
            return reader(folder)  # the reader names the file and the problem
        key = json.loads(json.dumps(key))  # as the JSON holds it (tuples as lists)
        found = self._load(root, name, key, folder)
        if found is not None:
            return found
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            volume = reader(folder)
        for w in caught:  # said again on every load of the entry, as on this read
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        self._save(root, name, key, volume, [str(w.message) for w in caught])
        return volume

    def _load(self, root: Path, name: str, key: dict, folder: Path) -> Volume | None:
        from registration.core.prepare.store import remember_digest

        doc_path, voxels_path = root / f"{name}.json", root / f"{name}.npy"
        if not doc_path.exists():
            return None
        try:
            doc = json.loads(doc_path.read_text())
            if doc.get("key") != key:
                raise ValueError("the entry belongs to other files")
            data = np.load(voxels_path, mmap_mode="c", allow_pickle=False)
            if list(data.shape) != doc["shape"] or data.dtype != np.float32:
                raise ValueError("the voxels do not match the entry")
            meta = doc["meta"] | ({"source": str(folder)} if "source" in doc["meta"] else {})  # as given this time
            volume = Volume(data, np.asarray(doc["index_to_world"], dtype=np.float64), label=doc["label"],
                            meta=meta)  # fmt: skip
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("decoded-volume cache entry %s unusable (%s): decoded again", name, exc)
            for p in (doc_path, voxels_path):
                p.unlink(missing_ok=True)
            return None
        remember_digest(volume, str(doc["digest"]))
        for message in doc.get("warnings", []):
            warnings.warn(message, stacklevel=3)
        for p in (doc_path, voxels_path):
            try:
                os.utime(p)  # recently used: pruned last
            except OSError:
                pass
        return volume

    def _save(self, root: Path, name: str, key: dict, volume: Volume, said: list[str]) -> None:
        from registration.core.prepare.store import volume_digest

        try:
            doc = {
                "key": key,
                "shape": list(volume.data.shape),
                "index_to_world": volume.index_to_world.tolist(),
                "label": volume.label,
                "meta": json.loads(json.dumps(volume.meta, default=str)),
                "warnings": said,
                "digest": volume_digest(volume),
            }
            write_atomic(root / f"{name}.npy", lambda f: np.save(f, np.ascontiguousarray(volume.data)))
            write_atomic(root / f"{name}.json", lambda f: f.write(json.dumps(doc).encode()))
            self.prune(keep=name)
        except (OSError, TypeError, ValueError) as exc:  # a full or read-only disk: decoded again next time
            log.warning("decoded-volume cache not written: %s", exc)

    def entries(self) -> list[Path]:
        return sorted(self.root.glob(f"{DECODED_KIND}-*.npy"))

    def prune(self, *, keep: str | None = None) -> None:
        """Remove the least recently used entries until they fit ``max_bytes`` (never ``keep``)."""

        def remove(voxels: Path) -> None:
            voxels.with_suffix(".json").unlink(missing_ok=True)  # the JSON first: no entry without its voxels
            voxels.unlink(missing_ok=True)

        kept = None if keep is None else self.root / f"{keep}.npy"
        prune_least_recent(self.entries(), self.max_bytes, keep=kept, remove=remove)


def read_volume_cached(path: str | os.PathLike[str], *, cache: bool = True) -> Volume:
    """:func:`registration.io.dicom.read_volume`, a DICOM folder's decoded volume kept on disk
    (:class:`DecodedVolumes`) with ``cache``."""
    from registration.io.dicom import read_volume

    if not cache:
        return read_volume(path)
    return DecodedVolumes().read(path, read_volume)
