"""The preparation's parameters (HU thresholds, grid steps, cache sizes, version)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


#: Voxels above this HU are tissue (skin, fat at -100, soft tissue, bone); a CT's air lies at
#: -1000 +- noise and contributes ~0 attenuation: the crop drops what lies outside the tissue.
TISSUE_HU = -500.0
#: Image pixels across the field at pyramid level 0 (level L: 256 / 2**L).
LEVEL0_PIXELS = 256
#: Level 0 of an anisotropic grid (a CT's slices) is never finer than this (mm): a head CT's finer
#: grid (0.5 x 0.5 x 2.5 mm) registers as its 1 x 1 x 3 mm grid does, at the same cost.
MIN_LEVEL0_MM = 1.0
#: A level's spacing this close (relative) to a power-of-two multiple of an isotropic volume's
#: own spacing uses that grid (block averages of the volume, no resampling).
SNAP_TOLERANCE = 0.1
#: Grid step (mm) at which the crop tests voxels for reach (each tested block counts whole).
CROP_PROBE_MM = 4.0
#: Cached preparations kept in memory (each holds a few million voxels).
CACHE_ENTRIES = 4
#: Levels prepared by default: the capture and refine level (2) and the polish level (1).
DEFAULT_LEVELS = (1, 2)
#: The body (:func:`body_blocks`): probe blocks mostly (at least half their voxels) above this
#: HU are body (fat -100, skin, soft tissue, bone); the CT's couch, head rest and mask are too.
BODY_HU = -300.0
#: Structures thinner than this (mm) that join the body (a couch plate, a head rest's legs, a
#: thermoplastic mask) are cut at the join by a morphological opening of this width.
BODY_OPENING_MM = 20.0
#: What lies within this (mm) of the opened body is kept (skin, ears and nose the opening
#: shaved, the interpolation at the skin); everything farther is set to air.
BODY_KEEP_MM = 12.0
#: Voxels below this HU are air (their attenuation, < 10 % of water's, is a CT's noise around
#: -1000 HU): set to -1000 with the outside of the body, so that rays leap over them.
AIR_HU = -900.0
#: Bump when what a preparation computes changes (it is part of the keys of stored bases).
PREPARE_VERSION = 2
#: Parts of the opened body at least this share of the largest one are body (a head and, cut
#: from it by the scan's edge or the opening, shoulders); smaller ones (pieces of a couch or a
#: mask the opening left) are not.
BODY_PART_SHARE = 0.1
#: The body is used only if its parts hold at least this share of the body blocks (a body, not
#: a collection of small objects).
BODY_MIN_SHARE = 0.5
