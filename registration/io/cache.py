"""A small on-disk cache for generated phantoms, volumes, reconstructions and meshes.

Entries live under the user's cache directory (``platformdirs``; override with the
``ROADMAP3D_CACHE`` environment variable), never in the repository, keyed by a hash of
their parameters. Writes are atomic (temporary file, then rename), so a killed process
never leaves a half-written entry.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import platformdirs

#: Bump when the meaning of cached data changes (phantom model, reconstruction, ...).
CACHE_VERSION = 1


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
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp.npz")
    os.close(fd)
    try:
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return arrays


def is_cached(kind: str, params: dict) -> bool:
    return (cache_dir() / f"{cache_key(kind, params)}.npz").exists()
