"""The patient's body in a CT, apart from the couch and head holder it lies on.

:func:`registration.core.prepare.probe_blocks` finds the body on probe blocks by a morphological
opening: whatever joins it through something thinner than the opening (a couch plate, a head
rest, a mask) is cut off there. The opening also shaves what protrudes thinly from the body
itself, the nose first. :func:`with_protrusions` gives those parts back: a piece the opening cut
off is the patient's when it touches the body, is small beside it and reaches no farther than a
nose does; the couch with its head rest is one large piece spanning the scan and stays cut off.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

#: A piece cut off by the opening is given back when it holds at most this share of the body.
PROTRUSION_MAX_SHARE = 0.03
#: ... and spans at most this (mm) along every axis (the front of a face the opening shaved: about
#: 110 x 100 x 110 mm; the couch with its head rest spans the scan, 470 mm).
PROTRUSION_MAX_MM = 150.0


def with_protrusions(
    core: NDArray[np.bool_], seed: NDArray[np.bool_], block_mm: NDArray[np.float64]
) -> tuple[NDArray[np.bool_], int]:
    """``core`` (the opened body on blocks (k, j, i) of ``block_mm``) with the pieces of ``seed``
    (the blocks of dense tissue) outside it that are small protrusions of it (see the module);
    and how many blocks were given back."""
    rest = seed & ~core
    if not rest.any() or not core.any():
        return core, 0
    labels, n = ndimage.label(rest)
    if n == 0:
        return core, 0
    touching = np.zeros(n + 1, dtype=bool)
    rim = ndimage.binary_dilation(core) & rest
    touching[np.unique(labels[rim])] = True
    touching[0] = False
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    small = sizes <= PROTRUSION_MAX_SHARE * core.sum()
    spans = ndimage.find_objects(labels)
    compact = np.zeros(n + 1, dtype=bool)
    for lab, sl in enumerate(spans, start=1):
        if sl is not None:
            extent = np.array([s.stop - s.start for s in sl]) * np.asarray(block_mm)
            compact[lab] = bool(np.all(extent <= PROTRUSION_MAX_MM))
    give_back = touching & small & compact
    back = give_back[labels]
    return core | back, int(back.sum())
