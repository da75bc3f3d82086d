"""The errors of the DICOM package and how they name a tag (imported by every module of it)."""

from __future__ import annotations

import os

from pydicom.datadict import tag_for_keyword


class DicomError(ValueError):
    """A file or folder the project cannot read, with the file and the tag at fault."""

    def __init__(self, path: str | os.PathLike[str], message: str) -> None:
        self.path = str(path)
        super().__init__(f"{path}: {message}")


class UploadError(ValueError):
    """An uploaded archive that is refused (size, unsafe names, links, not a zip)."""


def tag_name(keyword: str) -> str:
    """``'DistanceSourceToDetector (0018,1110)'`` for a DICOM keyword."""
    tag = tag_for_keyword(keyword)
    if tag is None:
        return keyword
    return f"{keyword} ({tag >> 16:04X},{tag & 0xFFFF:04X})"
