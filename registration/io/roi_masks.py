"""A user's region of interest for a registration: a label mask on the volume's grid
(:class:`registration.core.roi.RegionOfInterest`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from registration.core.roi import RegionOfInterest
from registration.core.volume import Volume


def read_roi_mask(path: str | os.PathLike[str], volume: Volume) -> RegionOfInterest:
    """A user's label mask on ``volume``'s grid: non-zero labels are the region. ``.npz``: an
    array ``mask`` shaped as the volume's data (k, j, i); NIfTI (``.nii``, ``.nii.gz``): read as
    the project reads NIfTI volumes (CONVENTIONS §8), its grid must be the volume's (affine within
    0.01 mm). ValueError naming the file otherwise."""
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
    else:
        raise ValueError(f"{p}: a region mask must be .npz or NIfTI (.nii, .nii.gz)")
    region = np.asarray(mask) != 0
    if not region.any():
        raise ValueError(f"{p}: the mask is empty")
    return RegionOfInterest(region, str(p.name))
