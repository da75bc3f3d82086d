"""A user's region of interest for a registration: a label mask on the volume's grid
(:class:`registration.core.roi.RegionOfInterest`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from registration.core.roi import RegionOfInterest, dense_left_out_ml
from registration.core.volume import Volume


def read_roi_mask(path: str | os.PathLike[str], volume: Volume) -> RegionOfInterest:
    """A user's label mask on ``volume``'s grid: non-zero labels are the region. ``.npz``: an
    array ``mask`` shaped as the volume's data (k, j, i); NIfTI (``.nii``, ``.nii.gz``): read as
    the project reads NIfTI volumes (CONVENTIONS §8), its grid must be the volume's (affine within
    0.01 mm); DICOM SEG (``.dcm``, or any file DICOM recognises as a Segmentation): every
    segment's frames placed on the volume's slices by their position (:func:`read_seg_mask`).
    ValueError naming the file otherwise."""
    p = Path(path)
    name = p.name.lower()
    if name.endswith(".npz"):
        try:
            with np.load(p, allow_pickle=False) as f:
                if "mask" not in f:
                    raise ValueError(f"{p}: no array named 'mask' (found {', '.join(f.files) or 'none'})")
                mask = np.asarray(f["mask"])
        except (OSError, EOFError) as e:
            raise ValueError(f"{p}: not a readable .npz file ({e})") from None
        if mask.shape != volume.shape:
            raise ValueError(f"{p}: mask shape {mask.shape} does not match the volume's {volume.shape} (k, j, i)")
    elif name.endswith((".nii", ".nii.gz")):
        from registration.io.volume_files import read_volume_file

        labels = read_volume_file(p)
        if labels.shape != volume.shape or not np.allclose(labels.index_to_world, volume.index_to_world, atol=0.01):
            raise ValueError(f"{p}: the mask's grid is not the volume's (shape {labels.shape} vs {volume.shape})")
        mask = labels.data
    elif name.endswith(".dcm") or _is_dicom(p):
        mask = read_seg_mask(p, volume)
    else:
        raise ValueError(f"{p}: a region mask must be .npz or NIfTI (.nii, .nii.gz), or a DICOM SEG")
    region = np.asarray(mask) != 0
    if not region.any():
        raise ValueError(f"{p}: the mask is empty")
    return RegionOfInterest(region, str(p.name), left_out_ml=dense_left_out_ml(volume, region))


#: SOP Class UID of a DICOM Segmentation.
SEGMENTATION_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.66.4"


def _is_dicom(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except OSError:
        return False


def read_seg_mask(path: str | os.PathLike[str], volume: Volume) -> np.ndarray:
    """A DICOM Segmentation's voxels on ``volume``'s grid (k, j, i), all segments together.

    Each frame must lie on one of the volume's slices: the same in-plane orientation and pixel
    spacing (0.01 mm), the same rows and columns, its ImagePositionPatient on a slice (0.01 mm).
    ValueError naming the file and what does not match."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    p = Path(path)
    try:
        ds = pydicom.dcmread(p)
    except (InvalidDicomError, OSError, EOFError) as e:
        raise ValueError(f"{p}: not a readable DICOM file ({e})") from None
    if str(ds.get("SOPClassUID", "")) != SEGMENTATION_SOP_CLASS:
        raise ValueError(f"{p}: not a DICOM Segmentation (SOP class {ds.get('SOPClassUID', 'missing')})")
    try:
        frames = np.asarray(ds.pixel_array)
    except Exception as e:  # noqa: BLE001 - pydicom raises many kinds for broken pixel data
        raise ValueError(f"{p}: its pixel data cannot be read ({e})") from None
    if frames.ndim == 2:
        frames = frames[None]
    nk, nj, ni = volume.shape
    if frames.shape[1:] != (nj, ni):
        raise ValueError(f"{p}: frames of {frames.shape[2]}x{frames.shape[1]} pixels, the volume's slices {ni}x{nj}")
    a = volume.index_to_world
    shared = ds.get("SharedFunctionalGroupsSequence", [None])[0]
    per_frame = ds.get("PerFrameFunctionalGroupsSequence", [])
    if len(per_frame) != len(frames):
        raise ValueError(f"{p}: {len(frames)} frames but {len(per_frame)} per-frame functional groups")

    def item(group: object, name: str) -> object:
        for source in (group, shared):
            if source is not None and name in source:
                return source[name].value[0]
        raise ValueError(f"{p}: no {name} for a frame")

    to_index = np.linalg.inv(a)
    mask = np.zeros(volume.shape, dtype=bool)
    for frame, group in zip(frames, per_frame, strict=True):
        orientation = np.asarray(item(group, "PlaneOrientationSequence").ImageOrientationPatient, dtype=np.float64)
        spacing = np.asarray(item(group, "PixelMeasuresSequence").PixelSpacing, dtype=np.float64)
        position = np.asarray(item(group, "PlanePositionSequence").ImagePositionPatient, dtype=np.float64)
        # the frame's column step (along a row) and row step, as the volume's i and j axes
        steps = np.stack([orientation[:3] * spacing[1], orientation[3:] * spacing[0]], axis=1)
        if not np.allclose(steps, a[:3, :2], atol=0.01):
            raise ValueError(f"{p}: a frame's orientation or pixel spacing is not the volume's slices'")
        index = to_index[:3, :3] @ position + to_index[:3, 3]
        k = int(round(index[2]))
        if abs(index[0]) > 0.01 or abs(index[1]) > 0.01 or abs(index[2] - k) > 0.01 or not 0 <= k < nk:
            raise ValueError(f"{p}: a frame at {position.round(2).tolist()} mm lies on none of the volume's slices")
        mask[k] |= frame != 0
    return mask
