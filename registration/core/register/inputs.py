"""The checked inputs of one registration, and the volume prepared for them."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from registration.core.depth import DEPTH_VOLUME_LEVEL
from registration.core.drr import DRRRenderer
from registration.core.geometry import check_rigid
from registration.core.images import XRayImage
from registration.core.landmarks import LandmarkStart
from registration.core.prepare import PreparationStore, PreparedVolume, Reach, prepare_volume
from registration.core.register.options import CAPTURE_64, RegistrationOptions
from registration.core.volume import Volume

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Inputs:
    """The checked inputs of one registration."""

    volume: Volume
    views: tuple[XRayImage, ...]
    initial_motion: Array
    truth: Array | None
    renderer: DRRRenderer
    #: The landmark start the registration starts from (None: the machine-based pose).
    landmarks: LandmarkStart | None = None


def check_inputs(
    volume: Volume,
    views: XRayImage | Sequence[XRayImage],
    initial_motion: ArrayLike | None,
    truth: ArrayLike | None,
    renderer: DRRRenderer | None,
    options: RegistrationOptions,
) -> Inputs:
    """Validate what the caller gave (ValueError saying what is wrong) and prepare the renderer."""
    if not isinstance(volume, Volume):
        raise ValueError(f"volume must be a Volume, got {type(volume).__name__}")
    if not isinstance(views, XRayImage | Sequence):
        raise ValueError(f"views must be an XRayImage or a sequence of them, got {type(views).__name__}")
    views = (views,) if isinstance(views, XRayImage) else tuple(views)
    if not views:
        raise ValueError("at least one X-ray view is needed")
    for n, view in enumerate(views):
        if not isinstance(view, XRayImage):
            raise ValueError(f"view {n} must be an XRayImage, got {type(view).__name__}")
    _check_directions(views)
    m_init = np.eye(4) if initial_motion is None else check_rigid(initial_motion, name="initial motion")
    truth_m = None if truth is None else check_rigid(truth, name="true motion")
    if renderer is None:
        renderer = prepared_renderer(volume, views, m_init, options)
    elif renderer.volume is not volume:
        raise ValueError("renderer was prepared for another volume")
    return Inputs(volume, views, m_init, truth_m, renderer)


#: Views registered together must look along beams at least this far apart (degrees, the lines'
#: angle): closer, the depth they share is unresolved (the same beam twice: not at all).
MIN_VIEW_ANGLE_DEG = 2.0


def _check_directions(views: tuple[XRayImage, ...]) -> None:
    """ValueError when two views look along (nearly) the same line."""
    for a in range(len(views)):
        for b in range(a + 1, len(views)):
            da, db = (np.asarray(views[n].geometry.direction, dtype=np.float64) for n in (a, b))
            cos = abs(float(da @ db)) / max(float(np.linalg.norm(da) * np.linalg.norm(db)), 1e-12)
            angle = float(np.degrees(np.arccos(min(1.0, cos))))
            if angle < MIN_VIEW_ANGLE_DEG:
                raise ValueError(
                    f"views {a} and {b} look along beams {angle:.1f} deg apart: views registered together must "
                    f"look from directions at least {MIN_VIEW_ANGLE_DEG:g} deg apart (two planes of a biplane "
                    "system, not two frames or copies of one plane)"
                )


def with_landmarks(inputs: Inputs, landmarks: LandmarkStart | None) -> Inputs:
    """``inputs`` registered from ``landmarks`` (their views must be the registration's)."""
    if landmarks is None:
        return inputs
    if not isinstance(landmarks, LandmarkStart):
        raise ValueError(f"landmarks must be a LandmarkStart, got {type(landmarks).__name__}")
    if landmarks.geometries and len(landmarks.geometries) != len(inputs.views):
        raise ValueError(
            f"the landmarks were picked on {len(landmarks.geometries)} view(s), "
            f"the registration has {len(inputs.views)}"
        )
    return replace(inputs, landmarks=landmarks)


def landmark_wall(inputs: Inputs, options: RegistrationOptions) -> Callable[[NDArray[np.float64]], float] | None:
    """The search's soft wall around the poses the landmarks allow (two or more views from
    landmarks, ``StartOptions.landmark_wall``), or None."""
    weight = options.start.landmark_wall
    if inputs.landmarks is None or weight is None or len(inputs.views) < 2:
        return None
    return inputs.landmarks.wall(weight)


def prepared_renderer(
    volume: Volume, views: tuple[XRayImage, ...], initial_motion: Array, options: RegistrationOptions
) -> DRRRenderer:
    """The renderer of the volume prepared for these views and this search (cropped to what the
    fields can reach, isotropic levels in mm; :func:`registration.core.prepare.prepare_volume`,
    cached per volume and field)."""
    return prepared_volume(volume, views, initial_motion, options).renderer


def prepared_volume(
    volume: Volume,
    views: tuple[XRayImage, ...],
    initial_motion: Array,
    options: RegistrationOptions,
    *,
    store: PreparationStore | None = None,
) -> PreparedVolume:
    """:func:`prepared_renderer`'s preparation itself; ``store``: where its view-independent part
    is looked up and kept across processes (:class:`registration.core.prepare.PreparationStore`)."""
    reach = Reach.of_search(
        options.bound_mm,
        options.bound_deg,
        initial_motion=initial_motion,
        isocenter_mm=views[0].geometry.isocenter_mm,
        translations=3 if options.optimizes_tz(len(views)) else 2,
    )
    levels = [k for k in options.volume_levels() if k <= CAPTURE_64.volume_level or supports_level(volume, k)]
    if len(views) == 1:  # the confidence's depth probe renders one view's estimate at its own level
        levels = sorted({*levels, DEPTH_VOLUME_LEVEL})
    if scans_level0(volume, len(views), options):
        levels = [0, *levels]
    return prepare_volume(volume, [v.geometry for v in views], reach=reach, levels=levels, store=store)


#: A pyramid level coarser than the 64 px capture's is prepared only with at least this many
#: voxels along the volume's longest axis (a coarser capture falls back to that capture).
MIN_LEVEL_VOXELS = 16


def supports_level(volume: Volume, level: int) -> bool:
    """Whether ``volume`` has at least :data:`MIN_LEVEL_VOXELS` voxels along its longest axis at
    pyramid ``level`` (each level halves the grid)."""
    return max(volume.shape) >> level >= MIN_LEVEL_VOXELS


def scans_level0(volume: Volume, n_views: int, options: RegistrationOptions) -> bool:
    """Whether one view's depth correction gets the volume's level 0 to scan on: a coarse volume
    (at most ``options.depth.level0_max_voxels`` voxels), where level 1's voxel is twice the
    3DRA's and the truncated reconstruction's coarse scales bias the scan toward the source."""
    d = options.depth
    return n_views == 1 and d.enabled and 0 < volume.data.size <= d.level0_max_voxels


def coarse_level(renderer: DRRRenderer, options: RegistrationOptions, n_views: int) -> int:
    """The coarsest annealing level's volume level for ``n_views`` views, or the nearest finer one
    ``renderer`` has."""
    coarsest = max(lv.volume_level for lv in (options.capture_level(n_views), *options.levels[1:]))
    return next((k for k in range(coarsest, -1, -1) if renderer.has_level(k)), 0)
