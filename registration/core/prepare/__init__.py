"""The volume a registration needs, not the one it was given.

A scanner's CT holds far more than the X-ray field sees (a 511 mm field of view, the neck,
shoulders and couch) on a grid the scanner chose (1 x 1 x 3 mm, 0.5 x 0.5 x 2.5 mm, ...). A
registration only ever renders the part of the volume that rays through the collimated field
can reach while the search moves the anatomy within its bounds, and only at the resolutions
of its pyramid. :func:`prepare_volume` makes that volume once:

0. **The body** (:func:`probe_blocks`): the patient's body is found on blocks of about
   ``CROP_PROBE_MM`` (mostly above ``BODY_HU``, opened by ``BODY_OPENING_MM`` so that a CT's
   couch, head rest and immobilisation mask are cut off where thin parts join them to the body,
   its large parts, holes filled, grown by ``BODY_KEEP_MM``); what lies outside it, and air
   below ``AIR_HU`` anywhere, is set to -1000 HU in the prepared levels
   (:func:`mask_outside_body`): the angiography suite has its own table, the CT's couch is not
   in its images, and the renderer's rays leap over the exact zeros (:mod:`registration.core.drr`).
   (Images formed from the CT itself keep its couch: the DRRs then lack it, a small handicap.)
1. **Crop** (:func:`needed_box`): keep the voxels that hold tissue of the body (above
   ``TISSUE_HU``; the noisy air of a CT around the head is dropped, its attenuation is ~0) and that some ray
   through a view's field can reach under any motion of the search (:class:`Reach`: a
   translation and a rotation about the iso-center, every voxel displaced by at most
   ``translation_mm + 2 sin(rotation / 2) |X - c|``). The crop never changes a DRR inside
   the field for motions within the reach; it only removes what no such ray meets.
2. **Resample per pyramid level to isotropic grids chosen in millimetres**
   (:func:`level_spacing_mm`): level ``L`` has voxels of ``D / (256 / 2**L)`` mm, where ``D``
   is the diameter at the iso-center of what the image can show of the anatomy (the field's
   diameter there, or the anatomy's extent across the beam when that is smaller). So level 2,
   the capture level, has voxels as large as the pixels of a 64-pixel image of the field at
   the iso-center (2.85 mm for a 27 cm format), level 1, the polish level, those of a 128-pixel
   image (1.42 mm): DRR samples as fine as the image pixels they are compared with, whatever
   grid the scanner used, but level 0 is never finer than the volume's own finest spacing
   (resampling adds no detail; levels L then have 2**L times that) nor, on an anisotropic grid,
   than ``MIN_LEVEL0_MM`` (1 mm: a CT's finer in-plane grid costs samples, not accuracy): a
   1 x 1 x 3 mm CT and a 0.5 x 0.5 x 2.5 mm CT both get 2 and 4 mm at levels 1 and 2, an
   isotropic 0.71 mm 3DRA 1.42 and 2.85 mm, a coarse 64^3 volume its own pyramid. When a
   level's spacing lies within ``SNAP_TOLERANCE`` of a power-of-two multiple of an isotropic
   volume's own spacing (a 3DRA whose format is the image format), that grid is used and made
   by block averages, exactly the volume's own pyramid.
3. **Cache** (:func:`prepare_volume`): what does not depend on the views (the probe blocks
   and, per level spacing, the body's box of the volume resampled and set to air outside the
   body: :class:`PreparedBase`) is kept per volume (by identity) and, given a ``store``
   (:class:`PreparationStore`, for example :class:`registration.io.cache.PreparationCache` on
   disk), per volume content (a SHA-256 of its voxels and affine, with the preparation's
   parameters and ``PREPARE_VERSION``): a later process skips the resampling. Each view's
   levels are slices of the base levels (the level grid's voxels covering the view's crop
   box), so a cached and a freshly built preparation hold the same voxels. The prepared levels
   and their renderer are also kept per volume (by identity), per view and per reach, and
   reused by later registrations whose views and searches they cover.
"""

from __future__ import annotations

from registration.core.prepare.body import ProbeBlocks, _crop, mask_outside_body, needed_box, probe_blocks
from registration.core.prepare.params import (
    AIR_HU,
    BODY_HU,
    BODY_KEEP_MM,
    BODY_MIN_SHARE,
    BODY_OPENING_MM,
    BODY_PART_SHARE,
    CACHE_ENTRIES,
    CROP_PROBE_MM,
    DEFAULT_LEVELS,
    LEVEL0_PIXELS,
    PREPARE_VERSION,
    SNAP_TOLERANCE,
    TISSUE_HU,
)
from registration.core.prepare.prepared import Crop, PreparedVolume, clear_cache, crop_of, prepare_volume, recrop
from registration.core.prepare.reach import Reach, field_extent_mm, level_spacing_mm
from registration.core.prepare.resample import resample_isotropic
from registration.core.prepare.store import PreparationStore, PreparedBase, _blocks_from, _blocks_key, volume_digest

__all__ = [
    "AIR_HU",
    "BODY_HU",
    "BODY_KEEP_MM",
    "BODY_MIN_SHARE",
    "BODY_OPENING_MM",
    "BODY_PART_SHARE",
    "CACHE_ENTRIES",
    "CROP_PROBE_MM",
    "Crop",
    "DEFAULT_LEVELS",
    "LEVEL0_PIXELS",
    "PREPARE_VERSION",
    "PreparationStore",
    "PreparedBase",
    "PreparedVolume",
    "ProbeBlocks",
    "Reach",
    "SNAP_TOLERANCE",
    "TISSUE_HU",
    "_blocks_from",
    "_blocks_key",
    "_crop",
    "clear_cache",
    "crop_of",
    "field_extent_mm",
    "level_spacing_mm",
    "mask_outside_body",
    "needed_box",
    "prepare_volume",
    "probe_blocks",
    "recrop",
    "resample_isotropic",
    "volume_digest",
]
