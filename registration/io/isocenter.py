"""Where a user's data is imaged about: the iso-center of ``--isocenter``, the volume's
IsocenterPosition (300A,012C), or the world origin (CONVENTIONS §1). Shared by the command line
and the web app."""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from registration.core.volume import Volume

#: ``--isocenter`` keyword: the center of the volume's voxel grid.
VOLUME_CENTER = "volume-center"
#: ``--isocenter`` keyword: the middle of the head (:func:`head_isocenter_mm`).
HEAD = "head"
#: How far below the volume's top (mm) the head is looked for (:func:`head_isocenter_mm`).
HEAD_TOP_MM = 180.0


def from_volume(text: str | None) -> bool:
    """Whether ``--isocenter`` names a point found in the volume (``head``, ``volume-center``):
    it can be resolved only once the volume is read."""
    return text is not None and text.strip().lower() in (HEAD, VOLUME_CENTER)


def head_isocenter_mm(
    volume: Volume, *, top_mm: float = HEAD_TOP_MM, tissue_hu: float = -300.0
) -> tuple[float, float, float]:
    """A point inside the skull: the middle of the bounding box of the largest connected tissue
    in the volume's top ``top_mm`` (by world z, the patient's head end; CONVENTIONS §1): on a
    head-and-neck CT the middle of the head, where a neuro C-arm is aimed (a couch or head rest
    apart from the patient is left out; the grid's centre may lie in the neck)."""
    nk, nj, ni = volume.shape
    k = np.arange(nk)
    a = volume.index_to_world
    z = a[2, 0] * (ni - 1) / 2 + a[2, 1] * (nj - 1) / 2 + a[2, 2] * k + a[2, 3]  # slice centers
    top = np.flatnonzero(z >= z.max() - top_mm)
    tissue = volume.data[top[0] : top[-1] + 1] > tissue_hu
    labels, n = ndimage.label(tissue)
    if n == 0:
        raise ValueError(f"no tissue above {tissue_hu:g} HU in the top {top_mm:g} mm of the volume")
    largest = 1 + int(np.argmax(np.bincount(labels.ravel())[1:]))
    # the largest component's bounding box in one pass (no index arrays of its voxels)
    box = ndimage.find_objects(labels, max_label=largest)[largest - 1]
    kk, jj, ii = ((s.start, s.stop - 1) for s in box)
    mid = np.array([sum(ii) / 2, sum(jj) / 2, sum(kk) / 2 + top[0]])
    p = volume.index_to_world[:3, :3] @ mid + volume.index_to_world[:3, 3]
    return (float(p[0]), float(p[1]), float(p[2]))


def resolve_isocenter(text: str | None, volume: Volume | None = None) -> tuple[tuple[float, float, float], str]:
    """The iso-center (mm, world frame) for ``--isocenter`` and where it came from.

    * ``"x,y,z"``: as given;
    * ``"volume-center"``: the center of the volume's voxel grid (``Volume.center_mm``);
    * ``"head"``: the middle of the head (:func:`head_isocenter_mm`);
    * absent: IsocenterPosition (300A,012C) when the volume's files carry it (read into
      ``volume.meta["isocenter_mm"]``), else the world origin (CONVENTIONS §1).
    """
    if text is None or text.strip() == "":
        if volume is not None and volume.meta.get("isocenter_mm") is not None:
            iso = tuple(float(v) for v in volume.meta["isocenter_mm"])
            return (iso[0], iso[1], iso[2]), str(volume.meta.get("isocenter_from", "the volume's files"))
        return (0.0, 0.0, 0.0), "the world origin (default)"
    if text.strip().lower() == VOLUME_CENTER:
        if volume is None:
            raise ValueError(f"--isocenter {VOLUME_CENTER} needs the volume (--volume)")
        center = [float(v) for v in volume.center_mm]
        return (center[0], center[1], center[2]), "the center of the volume's grid (--isocenter volume-center)"
    if text.strip().lower() == HEAD:
        if volume is None:
            raise ValueError(f"--isocenter {HEAD} needs the volume (--volume)")
        where = f"the middle of the head: the largest tissue within {HEAD_TOP_MM:g} mm of the volume's top"
        return head_isocenter_mm(volume), f"{where} (--isocenter head)"
    parts = text.replace(" ", "").split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError(
            f"--isocenter must be three numbers 'x,y,z' in mm, '{HEAD}' or '{VOLUME_CENTER}', got {text!r}"
        ) from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(
            f"--isocenter must be three finite numbers 'x,y,z' in mm, '{HEAD}' or '{VOLUME_CENTER}', got {text!r}"
        )
    return (values[0], values[1], values[2]), "--isocenter"
