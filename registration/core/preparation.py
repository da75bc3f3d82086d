"""One preparation of a volume for registering it to some views: built by its caller and held.

A :class:`Preparation` is what ``roadmap3d register``, ``track``, the app and every study
register with: the volume cropped to the patient's body that the views' fields can reach over
the search, on isotropic levels in millimetres (:func:`registration.core.prepare.prepare_volume`
through :func:`registration.core.register.prepared_volume`), and the levels the confidence's
probes render at (:meth:`Preparation.probe_renderer`, built on first use and kept by the object).
The caller decides how long it lives: keep the object to reuse it, pass a ``store``
(:class:`registration.core.prepare.PreparationStore`) to keep its view-independent part across
processes.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from registration.core.drr import DRRRenderer
from registration.core.geometry import check_rigid
from registration.core.images import XRayImage
from registration.core.prepare import PreparationStore, PreparedVolume, mask_outside_body, probe_blocks
from registration.core.prepare.body import body_region
from registration.core.prepare.params import MIN_LEVEL0_MM
from registration.core.volume import Volume

if TYPE_CHECKING:
    from registration.core.register import RegistrationOptions

#: The confidence's evidence renders at the level nearest this many voxels across
#: (``registration_evidence``'s ``volume_voxels``; its rule was calibrated on such DRRs).
EVIDENCE_VOXELS = 128


@dataclass
class Preparation:
    """The volume as a registration of ``planes`` views renders it (``prepared``: crop, body
    mask, mm levels; ``renderer``) and the confidence's probe levels (:meth:`probe_renderer`).
    ``seconds``: what building it took (the probe levels apart)."""

    volume: Volume
    prepared: PreparedVolume
    planes: int
    seconds: float = 0.0
    _probes: DRRRenderer | None = field(default=None, init=False, repr=False)

    @classmethod
    def of(
        cls,
        volume: Volume,
        views: XRayImage | Sequence[XRayImage],
        *,
        initial_motion: ArrayLike | None = None,
        options: RegistrationOptions | None = None,
        store: PreparationStore | None = None,
    ) -> Preparation:
        """Prepare ``volume`` for ``views`` (one, or a biplane pair) and the search of ``options``
        (a :class:`registration.core.register.RegistrationOptions`, the defaults by default)
        from ``initial_motion`` (identity by default)."""
        from registration.core.register import RegistrationOptions, prepared_volume

        views = (views,) if isinstance(views, XRayImage) else tuple(views)
        start = np.eye(4) if initial_motion is None else check_rigid(initial_motion, name="initial motion")
        began = time.perf_counter()
        prepared = prepared_volume(volume, views, start, options or RegistrationOptions(), store=store)
        return cls(volume, prepared, len(views), time.perf_counter() - began)

    def __repr__(self) -> str:
        """A line a notebook shows: the volume, its levels' voxel sizes, the views, the cost."""
        levels = ", ".join(f"{s:.3g}" for s in self.prepared.spacing_mm)
        views = f"{self.planes} view" + ("s" if self.planes != 1 else "")
        return f"Preparation({self.volume!r}; levels at ({levels}) mm for {views}, {self.seconds:.2f} s)"

    @property
    def renderer(self) -> DRRRenderer:
        """The registration's renderer (cropped, body only, isotropic levels in mm)."""
        return self.prepared.renderer

    def probe_renderer(self) -> DRRRenderer:
        """The renderer the confidence's probes use (:func:`probe_renderer`), built once."""
        if self._probes is None:
            self._probes = probe_renderer(self.prepared, planes=self.planes)
        return self._probes


def probe_renderer(prepared: PreparedVolume, *, planes: int = 1) -> DRRRenderer:
    """The registration's own prepared levels, and level 0 where the confidence's probes render
    there.

    The rule was calibrated with the index pyramid of whole 3DRAs (``DRRRenderer(volume,
    levels=3)``): the evidence at the level nearest ``EVIDENCE_VOXELS`` voxels across, the depth
    probe at level 1, the depth scan (one plane) at level 0. On a 256^3 3DRA the prepared levels
    1 and 2 are that pyramid's levels (block averages, cropped); level 0 is the volume's own grid
    over the prepared box (an axis finer than ``MIN_LEVEL0_MM`` block-averaged up to it), the body
    only (as in the prepared levels): needed by one plane's depth
    scan, and by the evidence of a coarse volume (128^3: level 0 is the one ~128 voxels across).
    A CT's cropped 2 mm level is ~128 voxels or more across already. Built once per preparation
    and number of planes (kept in ``prepared.derived``: a cached preparation brings it along)."""
    key = ("probe renderer", planes)
    if key not in prepared.derived:
        prepared.derived[key] = _probe_renderer(prepared, planes)
    return prepared.derived[key]


def _probe_renderer(prepared: PreparedVolume, planes: int) -> DRRRenderer:
    renderer = prepared.renderer
    if renderer.has_level(0):
        return renderer
    finest = next(k for k in range(renderer.n_levels) if renderer.has_level(k))
    across = max(renderer.level_volume(finest).shape)
    finer_wanted = abs(math.log(2 * across / EVIDENCE_VOXELS)) < abs(math.log(across / EVIDENCE_VOXELS))
    if planes > 1 and not finer_wanted:
        return renderer
    volume = prepared.volume
    lo, hi = np.asarray(prepared.box_lo), np.asarray(prepared.box_hi)  # (i, j, k), inclusive
    blocks = None
    if prepared.body:
        blocks = prepared.blocks if prepared.blocks is not None else probe_blocks(volume)
    factors = _floor_factors(volume, MIN_LEVEL0_MM)
    if blocks is not None and factors == (1, 1, 1):
        level0 = body_region(volume, lo, hi, blocks)  # the crop and its mask in one pass
    else:
        affine = volume.index_to_world.copy()
        affine[:3, 3] = volume.index_to_world[:3, :3] @ lo + volume.index_to_world[:3, 3]
        data = volume.data[lo[2] : hi[2] + 1, lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
        level0 = Volume(data, affine, label=volume.label, meta=volume.meta).downsample(factors)
        if blocks is not None:
            level0 = mask_outside_body(level0, volume, blocks)
    # the prepared levels shared, not converted again; level 0 written as its views' rays need it
    return renderer.with_levels({0: level0}, lazy=True)


def _floor_factors(volume: Volume, floor_mm: float) -> tuple[int, int, int]:
    """Per axis (i, j, k), the whole factor that block-averages an axis finer than ``floor_mm``
    to at most that coarse (a 0.5 x 0.5 x 2.5 mm grid becomes 1 x 1 x 2.5 mm, as the prepared
    levels ignore a grid finer than the floor); 1 for an axis that is not."""
    fi, fj, fk = (max(1, int(floor_mm / s + 1e-6)) for s in volume.spacing_mm)
    return fi, fj, fk
