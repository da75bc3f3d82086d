"""Output files written atomically (a temporary sibling renamed into place) and the project's JSON."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np


def _read_umask() -> int:
    mask = os.umask(0o022)  # the only portable way to read it: set and restore
    os.umask(mask)
    return mask


#: Read once at import (os.umask is process-wide; reading it later could race other threads).
_UMASK = _read_umask()


def _umask() -> int:
    return _UMASK


@contextmanager
def _atomic_path(path: Path, mode: int | None = None) -> Iterator[Path]:
    """A temporary sibling of ``path`` renamed onto it when the block succeeds (``mode``: the
    file's permissions; default the usual ones under the umask)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    tmp.chmod(0o666 & ~_umask() if mode is None else mode)  # mkstemp makes it private
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextmanager
def atomic_folder(folder: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary sibling folder renamed to ``folder`` (absent or empty) when the block succeeds."""
    folder = Path(folder)
    if folder.exists():
        if not folder.is_dir():
            raise ValueError(f"{folder}: exists and is not a folder")
        if any(folder.iterdir()):
            raise ValueError(f"{folder}: exists and is not empty; refusing to write into it")
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    tmp.chmod(0o777 & ~_umask())
    try:
        yield tmp
        if folder.exists():
            folder.rmdir()
        os.replace(tmp, folder)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def write_text_atomic(path: str | os.PathLike[str], text: str, *, mode: int | None = None) -> None:
    """Write a text file through a temporary file, never leaving a partial one (``mode``: its
    permissions, e.g. 0o600; default the usual ones)."""
    with _atomic_path(Path(path), mode) as tmp:
        tmp.write_text(text)


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Write a binary file through a temporary file, never leaving a partial one."""
    with _atomic_path(Path(path)) as tmp:
        tmp.write_bytes(data)


def json_dumps(data: Any) -> str:
    """Indented JSON with numpy values converted and each list of numbers on one line."""

    def plain(obj: Any) -> Any:
        if isinstance(obj, dict):
            return {str(k): plain(v) for k, v in obj.items()}
        if isinstance(obj, (list, tuple)):
            return [plain(v) for v in obj]
        if isinstance(obj, np.ndarray):
            return plain(obj.tolist())
        if isinstance(obj, (np.floating, np.integer, np.bool_)):
            return obj.item()
        if isinstance(obj, Path):
            return str(obj)
        return obj

    def flat(obj: Any) -> bool:
        return isinstance(obj, list) and all(
            isinstance(v, (int, float, bool, str)) or v is None or (isinstance(v, list) and flat(v) and len(v) <= 4)
            for v in obj
        )

    def dump(obj: Any, level: int) -> str:
        pad, inner = "  " * level, "  " * (level + 1)
        if isinstance(obj, dict) and obj:
            items = [f"{inner}{json.dumps(k)}: {dump(v, level + 1)}" for k, v in obj.items()]
            return "{\n" + ",\n".join(items) + "\n" + pad + "}"
        if isinstance(obj, list) and obj and not flat(obj):
            return "[\n" + ",\n".join(inner + dump(v, level + 1) for v in obj) + "\n" + pad + "]"
        if isinstance(obj, list) and obj and isinstance(obj[0], list):
            rows = [json.dumps(v) for v in obj]
            return "[" + (",\n" + inner).join(rows) + "]"
        return json.dumps(obj)

    return dump(plain(data), 0) + "\n"
