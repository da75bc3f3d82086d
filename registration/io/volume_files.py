"""Volumes in other tools' formats: NIfTI (``.nii``, ``.nii.gz``), NRRD (``.nrrd``, ``.nhdr``),
MetaImage (``.mha``, ``.mhd``), read and written following CONVENTIONS.md §8.

- NIfTI (read with nibabel, which keeps the file's affine exactly, sheared or not): the affine is
  the sform when its code is set, else the qform; a file with neither has no known orientation
  and is refused. Its affine maps (i, j, k) to RAS, so ``index_to_world = diag(-1, -1, 1, 1) @
  affine_RAS``, and ``data[i, j, k]`` becomes ``data[k, j, i]``.
- NRRD (read with SimpleITK): the header's ``space`` field must say ``left-posterior-superior``
  or ``right-anterior-superior`` (ITK turns RAS into LPS); a file without it is refused.
- MetaImage (read with SimpleITK): LPS by definition.

Values are taken as Hounsfield units (CONVENTIONS §2) after the file's own scaling (NIfTI
``scl_slope``/``scl_inter``). Errors are :class:`VolumeFileError` (a ``ValueError``) naming the
file; sizes are checked against the ceilings of :mod:`registration.io.dicom.limits` before the
voxels are read.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from registration.core.volume import Volume
from registration.io.dicom.limits import check_voxels

#: File name endings read and written here, and the format each names.
VOLUME_SUFFIXES = {
    ".nii": "NIfTI",
    ".nii.gz": "NIfTI",
    ".nrrd": "NRRD",
    ".nhdr": "NRRD",
    ".mha": "MetaImage",
    ".mhd": "MetaImage",
}
#: LPS from RAS and back (CONVENTIONS §8): x and y change sign.
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
_NRRD_SPACES = {
    "left-posterior-superior": "LPS",
    "lps": "LPS",
    "right-anterior-superior": "RAS",
    "ras": "RAS",
}


class VolumeFileError(ValueError):
    """A volume file the project cannot read or write: the file and the problem."""

    def __init__(self, path: str | os.PathLike[str], message: str) -> None:
        self.path = str(path)
        super().__init__(f"{path}: {message}")


def volume_format(path: str | os.PathLike[str]) -> str | None:
    """``"NIfTI"``, ``"NRRD"`` or ``"MetaImage"`` by the file name's ending; None for others."""
    name = Path(path).name.lower()
    return next((fmt for suffix, fmt in VOLUME_SUFFIXES.items() if name.endswith(suffix)), None)


def read_volume_file(path: str | os.PathLike[str], *, label: str | None = None) -> Volume:
    """A NIfTI, NRRD or MetaImage volume in the project's frame (LPS mm, ``data[k, j, i]``).

    Examples
    --------
    >>> import numpy as np, tempfile, pathlib
    >>> from registration.core.volume import Volume
    >>> v = Volume.from_grid(np.zeros((4, 5, 6)), (0.5, 0.5, 2.0))
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "ct.nii.gz"
    >>> _ = write_volume_file(v, path)
    >>> back = read_volume_file(path)
    >>> back.shape, bool(np.allclose(back.index_to_world, v.index_to_world))
    ((4, 5, 6), True)
    """
    path = Path(path)
    fmt = volume_format(path)
    if fmt is None:
        raise VolumeFileError(path, f"not a NIfTI, NRRD or MetaImage file name ({', '.join(VOLUME_SUFFIXES)})")
    if not path.is_file():
        raise VolumeFileError(path, "no such file")
    if fmt == "NIfTI":
        data, affine, how = _read_nifti(path)
    else:
        data, affine, how = _read_itk(path, fmt)
    meta = {"source": str(path), "format": fmt, "orientation_from": how}
    try:
        return Volume(data=data, index_to_world=affine, label=label or path.name, meta=meta)
    except ValueError as exc:
        raise VolumeFileError(path, f"not a usable volume: {exc}") from None


def _check_shape(path: Path, shape: tuple[int, ...]) -> tuple[int, int, int]:
    dims = tuple(int(n) for n in shape)
    while len(dims) > 3 and dims[-1] == 1:  # a 4-D file with one time point is a volume
        dims = dims[:-1]
    if len(dims) == 2 or (len(dims) == 3 and min(dims) == 1):
        raise VolumeFileError(path, f"a 2-D image ({' x '.join(map(str, dims))}): a volume needs three axes")
    if len(dims) != 3:
        raise VolumeFileError(path, f"{len(dims)}-D data ({' x '.join(map(str, dims))}): a volume has three axes")
    check_voxels(path, dims, what="volume size")
    return dims  # type: ignore[return-value]


def _read_nifti(path: Path) -> tuple[NDArray[np.float32], NDArray[np.float64], str]:
    import nibabel as nib

    try:
        image = nib.load(str(path))
    except Exception as exc:
        raise VolumeFileError(path, f"not a readable NIfTI file ({type(exc).__name__}: {exc})") from None
    header = image.header
    if not isinstance(image, nib.Nifti1Image | nib.Nifti2Image):
        raise VolumeFileError(path, f"not a NIfTI-1/2 image ({type(image).__name__})")
    shape = _check_shape(path, header.get_data_shape())
    sform_code, qform_code = int(header["sform_code"]), int(header["qform_code"])
    if sform_code > 0:
        affine, how = header.get_sform(), f"NIfTI sform (code {sform_code})"
    elif qform_code > 0:
        affine, how = header.get_qform(), f"NIfTI qform (code {qform_code})"
    else:
        raise VolumeFileError(
            path, "no orientation: sform_code and qform_code are both 0, so the voxels' position is unknown"
        )
    affine = np.asarray(affine, dtype=np.float64)
    if not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise VolumeFileError(path, f"the {how} is not an invertible affine")
    try:
        data = np.asarray(image.dataobj, dtype=np.float32).reshape(shape)
    except Exception as exc:
        raise VolumeFileError(path, f"cannot read the voxels ({type(exc).__name__}: {exc})") from None
    return np.ascontiguousarray(data.transpose(2, 1, 0)), LPS_FROM_RAS @ affine, how


def _nrrd_space(path: Path) -> str:
    """The ``space`` field of an NRRD header (read as text up to the blank line), as LPS or RAS."""
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    text = head.split(b"\n\n", 1)[0].decode("latin-1")
    if not text.startswith("NRRD"):
        raise VolumeFileError(path, "not an NRRD file (no NRRD magic line)")
    found = re.search(r"^space:\s*(.+?)\s*$", text, flags=re.MULTILINE)
    if found is None:
        raise VolumeFileError(
            path, "no 'space' field: the orientation is unknown (left-posterior-superior or right-anterior-superior)"
        )
    space = found.group(1).lower()
    if space not in _NRRD_SPACES:
        raise VolumeFileError(path, f"space {found.group(1)!r} is not a patient frame (LPS or RAS expected)")
    return _NRRD_SPACES[space]


def _read_itk(path: Path, fmt: str) -> tuple[NDArray[np.float32], NDArray[np.float64], str]:
    import SimpleITK as sitk

    how = f"NRRD space {_nrrd_space(path)}" if fmt == "NRRD" else "MetaImage (LPS)"
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    try:
        reader.ReadImageInformation()
    except RuntimeError as exc:
        raise VolumeFileError(path, f"not a readable {fmt} file ({_itk_message(exc)})") from None
    if reader.GetNumberOfComponents() != 1:
        raise VolumeFileError(path, f"{reader.GetNumberOfComponents()} values per voxel: a volume has one")
    _check_shape(path, tuple(reversed(reader.GetSize())))
    try:
        image = reader.Execute()
    except RuntimeError as exc:
        raise VolumeFileError(path, f"cannot read the voxels ({_itk_message(exc)})") from None
    data = sitk.GetArrayFromImage(image).astype(np.float32, copy=False)  # already (k, j, i)
    affine = np.eye(4)
    affine[:3, :3] = np.asarray(image.GetDirection(), dtype=np.float64).reshape(3, 3) * np.asarray(image.GetSpacing())
    affine[:3, 3] = image.GetOrigin()
    return np.ascontiguousarray(data), affine, how


def _itk_message(exc: Exception) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return lines[-1][:200] if lines else type(exc).__name__


def write_volume_file(volume: Volume, path: str | os.PathLike[str]) -> Path:
    """Write ``volume`` as NIfTI (RAS affine, sform and qform code 1), NRRD (LPS) or MetaImage.

    The inverse of :func:`read_volume_file`. NRRD and MetaImage hold direction cosines, so a
    sheared affine is written exactly only as NIfTI's sform.
    """
    path = Path(path)
    fmt = volume_format(path)
    if fmt is None:
        raise VolumeFileError(path, f"not a NIfTI, NRRD or MetaImage file name ({', '.join(VOLUME_SUFFIXES)})")
    if not path.parent.is_dir():
        raise VolumeFileError(path, f"no such folder: {path.parent}")
    tmp = path.with_name(f".{path.name}.partial{''.join(path.suffixes)}")
    try:
        if fmt == "NIfTI":
            import nibabel as nib

            affine = LPS_FROM_RAS @ volume.index_to_world
            image = nib.Nifti1Image(np.ascontiguousarray(volume.data.transpose(2, 1, 0)), affine)
            image.set_sform(affine, code=1)
            image.set_qform(affine, code=1)
            nib.save(image, str(tmp))
        else:
            import SimpleITK as sitk

            image = sitk.GetImageFromArray(volume.data)
            spacing = volume.spacing_mm
            image.SetSpacing([float(s) for s in spacing])
            image.SetDirection([float(x) for x in (volume.index_to_world[:3, :3] / spacing).reshape(-1)])
            image.SetOrigin([float(x) for x in volume.index_to_world[:3, 3]])
            sitk.WriteImage(image, str(tmp), True)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
