"""Uploads from the web app: unpack a zip safely, find the volume and the X-ray image in it."""

from __future__ import annotations

import io
import os
import shutil
import stat
import zipfile
from pathlib import Path, PurePosixPath

from registration.io.dicom._common import (
    DicomError,
    UploadError,
    _candidate_files,
    _is_xray,
    _short,
    read_dataset,
)


def _safe_member_name(name: str) -> PurePosixPath | None:
    if "\x00" in name:
        raise UploadError(f"refused archive member {name!r}: NUL character in the name")
    normalized = name.replace("\\", "/")
    if normalized.startswith("/") or (len(normalized) > 1 and normalized[1] == ":"):
        raise UploadError(f"refused archive member {name!r}: absolute path")
    parts = [p for p in normalized.split("/") if p not in ("", ".")]
    if any(p == ".." for p in parts):
        raise UploadError(f"refused archive member {name!r}: '..' in the path")
    return PurePosixPath(*parts) if parts else None


def _empty_folder(dest: Path) -> Path:
    """``dest`` as an empty private folder (created when absent)."""
    if dest.exists():
        if not dest.is_dir() or dest.is_symlink():
            raise UploadError(f"{dest}: not a folder")
        if any(dest.iterdir()):
            raise UploadError(f"{dest}: not empty")
    else:
        dest.mkdir(mode=0o700, parents=True)
    return dest


def _checked_member(member: zipfile.ZipInfo, seen: set[str], dest: Path, root: Path) -> Path | None:
    """The member's path inside the upload folder; None for the folder itself or a folder (made
    here). UploadError for a link, a special file, an encrypted or duplicate member, or a path
    that leaves the folder."""
    relative = _safe_member_name(member.filename)
    if relative is None:
        return None
    mode = (member.external_attr >> 16) & 0o170000
    if mode == stat.S_IFLNK:
        raise UploadError(f"refused archive member {member.filename!r}: symbolic link")
    if mode not in (0, stat.S_IFREG, stat.S_IFDIR):
        raise UploadError(f"refused archive member {member.filename!r}: not a regular file")
    if member.flag_bits & 0x1:
        raise UploadError(f"refused archive member {member.filename!r}: encrypted")
    key = str(relative).lower()
    if key in seen:
        raise UploadError(f"refused archive member {member.filename!r}: duplicate name")
    seen.add(key)
    target = dest.joinpath(*relative.parts)
    if not target.resolve().is_relative_to(root):
        raise UploadError(f"refused archive member {member.filename!r}: leaves the upload folder")
    if member.is_dir() or mode == stat.S_IFDIR:
        target.mkdir(mode=0o700, parents=True, exist_ok=True)
        return None
    return relative


def _write_member(
    archive: zipfile.ZipFile, member: zipfile.ZipInfo, target: Path, root: Path, written: list[Path], total: int,
    max_bytes: int, max_ratio: float,
) -> int:  # fmt: skip
    """Inflate one member to ``target`` (a new private file, listed in ``written``), counting the
    bytes as they come; returns the running total of unpacked bytes."""
    if member.compress_size > 0 and member.file_size / member.compress_size > max_ratio:
        raise UploadError(f"refused archive member {member.filename!r}: compression ratio above {max_ratio:g}")
    target.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    if not target.parent.resolve().is_relative_to(root):
        raise UploadError(f"refused archive member {member.filename!r}: leaves the upload folder")
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
    fd = os.open(target, flags, 0o600)
    written.append(target)
    with os.fdopen(fd, "wb") as out, archive.open(member) as src:
        while True:
            chunk = src.read(1 << 16)
            if not chunk:
                break
            total += len(chunk)
            if total > max_bytes:
                raise UploadError(f"archive unpacks to more than the limit of {max_bytes} bytes")
            out.write(chunk)
    return total


def unpack_upload(
    zip_bytes: bytes,
    dest_dir: str | os.PathLike[str],
    *,
    max_bytes: int,
    max_files: int = 5000,
    max_ratio: float = 200.0,
) -> list[Path]:
    """Unpack an uploaded zip into ``dest_dir`` (created private, or empty) and list the files.

    Refused with :class:`UploadError` (nothing left behind): not a zip; more than
    ``max_bytes`` compressed or uncompressed (counted while inflating, so lying headers do not
    help a zip bomb); more than ``max_files`` members; a member compressed more than
    ``max_ratio`` times; absolute names, ``..``, links, encrypted or duplicate members.
    Directories in the archive are recreated; no path from the archive is trusted.
    """
    if max_bytes <= 0:
        raise ValueError(f"max_bytes must be positive, got {max_bytes}")
    if len(zip_bytes) > max_bytes:
        raise UploadError(f"upload of {len(zip_bytes)} bytes exceeds the limit of {max_bytes} bytes")
    dest = _empty_folder(Path(dest_dir))
    try:
        archive = zipfile.ZipFile(io.BytesIO(zip_bytes))
        members = archive.infolist()
    except Exception as exc:  # zipfile raises many types on corrupt archives
        raise UploadError(f"not a readable zip archive ({type(exc).__name__}: {_short(exc)})") from None
    written: list[Path] = []
    try:
        if len(members) > max_files:
            raise UploadError(f"archive holds {len(members)} members, more than {max_files}")
        declared = sum(max(0, m.file_size) for m in members)
        if declared > max_bytes:
            raise UploadError(f"archive unpacks to {declared} bytes, more than the limit of {max_bytes}")
        seen: set[str] = set()
        total = 0
        root = dest.resolve()
        for member in members:
            relative = _checked_member(member, seen, dest, root)
            if relative is None:  # "./" and the like, or a folder: recreated, nothing to write
                continue
            total = _write_member(archive, member, dest.joinpath(*relative.parts), root, written, total, max_bytes,
                                  max_ratio)  # fmt: skip
    except UploadError:
        _remove_tree_contents(dest)
        raise
    except Exception as exc:  # corrupt members: zlib.error, NotImplementedError, EOFError, ...
        _remove_tree_contents(dest)
        raise UploadError(f"cannot unpack the archive ({type(exc).__name__}: {_short(exc)})") from None
    finally:
        archive.close()
    return written


def _remove_tree_contents(folder: Path) -> None:
    for child in folder.iterdir():
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child, ignore_errors=True)
        else:
            child.unlink(missing_ok=True)


def classify_upload(folder: str | os.PathLike[str]) -> dict[str, Path | None]:
    """Find the volume (series folder, multi-frame, .npz, NIfTI, NRRD or MetaImage file) and the
    X-ray image (an XA/RF file, or a TIFF/PNG with its geometry side file ``<name>.json``) in ``folder``."""
    from registration.io.image_files import default_geometry_path, is_image_file
    from registration.io.volume_files import volume_format

    folder = Path(folder)
    xray: Path | None = None
    volume_files: list[Path] = []
    npz: Path | None = None
    for p in _candidate_files(folder):
        if p.suffix.lower() == ".npz" or volume_format(p) is not None:
            npz = npz or p
            continue
        if is_image_file(p):
            if default_geometry_path(p).is_file():
                xray = xray or p
            continue
        try:
            ds = read_dataset(p, stop_before_pixels=True)
        except DicomError:
            continue
        if _is_xray(ds):
            xray = xray or p
        else:
            volume_files.append(p)
    volume: Path | None = npz
    if volume is None and volume_files:
        parents = {p.parent for p in volume_files}
        volume = volume_files[0] if len(volume_files) == 1 else Path(os.path.commonpath(sorted(parents)))
    return {"volume": volume, "image": xray}
