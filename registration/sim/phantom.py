"""Analytic head phantom in Hounsfield units, and the stand-in registration volume.

The phantom is a FORBILD-like, ordered list of primitives in world millimetres
(CONVENTIONS.md §1: LPS, the circle of Willis near the iso-center). Each primitive is the
intersection of up to ``MAX_QUADRICS`` quadrics ``|A (x - c)|^2 <= 1`` (an ellipsoid, or an
elliptic cylinder when a row of ``A`` is zero) and up to ``MAX_PLANES`` half-spaces
``n . x <= d``, and holds one tissue value in HU. Later primitives are painted over earlier
ones (the scalp, then the skull, then the sinuses carved into it, then the arteries), so a
sinus is exactly air whatever lay there, and no point is ever below air (-1000 HU).

Everything is evaluated exactly: a point takes the value of the newest primitive holding it,
and the line integral of ``mu`` along a segment is the sum over the visible pieces of each
primitive's chord (painter's algorithm along the ray, newest first) times its attenuation
``mu = MU_WATER_PER_MM (1 + HU / 1000)`` per mm (:func:`registration.core.volume.hu_to_mu_per_mm`, air 0).
No sampling, no grid: the phantom is resolution independent. The compiled kernels that do
this (and the ray culling) are :mod:`registration.sim.phantom_kernels`; the :class:`HeadPhantom`
type and its builder are :mod:`registration.sim.phantom_shapes`, the anatomy that builds it
:mod:`registration.sim.phantom_anatomy`; this module makes (and caches) the phantom and the
stand-in volume.

Anatomy (world mm; +x left, +y posterior, +z superior): scalp over a skull of outer table,
diploe and inner table whose floor is a bowl (anterior fossa ~ z -5, posterior fossa ~ z -45);
brain with ventricles; sphenoid body with sinus, sella turcica, dorsum, clinoids and greater
wings; clivus; petrous bones with inner ear and internal auditory canal; mastoids with air
cells; ear canals; frontal sinuses; the facial skeleton (orbits with fat and globes, zygoma
and arches, maxillary sinuses, ethmoid cells, nasal cavity, septum, turbinates, nasal bones,
hard palate, maxillary and mandibular arches, 28 teeth with enamel crowns); cervical spine,
spinal cord, airway and hyoid; and the arteries (internal carotids, vertebrals, basilar,
circle of Willis, ACA/MCA/PCA with branches) with a ~7 mm aneurysm at the left MCA
bifurcation. The circle of Willis lies around the origin (the ICA termini at x = +-14 mm).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from registration.core.volume import Volume, format_grid
from registration.io.cache import cached_arrays
from registration.sim.phantom_anatomy import _build_phantom
from registration.sim.phantom_shapes import PHANTOM_MODEL_VERSION, HeadPhantom

#: Label every output of :func:`registration_volume` carries.
__all__ = [
    "PHANTOM_MODEL_VERSION",
    "STAND_IN_LABEL",
    "HeadPhantom",
    "make_head_phantom",
    "registration_volume",
    "standin_params",
]

STAND_IN_LABEL = "phantom resampled to the 3DRA grid (stand-in for a reconstruction)"


def make_head_phantom(*, seed: int = 0, contrast: bool = True, facial: bool = True) -> HeadPhantom:
    """The analytic head phantom (HU), world mm, circle of Willis near the origin.

    Parameters
    ----------
    seed
        Anatomical variant: 0 is the canonical head; other seeds perturb sizes (~3 %),
        positions and vessel paths (~1.5 mm) slightly.
    contrast
        Iodine in the arteries (lumen ~ +540 HU) or plain blood (~ 40 HU).
    facial
        Include the facial skeleton: orbits, maxilla, zygoma, nasal cavity and maxillary and
        ethmoid sinuses, mandible and teeth.

    Returns
    -------
    HeadPhantom
        About 150 mm left-right, 190 mm anterior-posterior, 220 mm from vertex to chin, plus
        a neck with the cervical spine and airway.
    """
    if int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed}")
    return _cached_phantom(int(seed), bool(contrast), bool(facial))


_PHANTOMS: dict[tuple[int, bool, bool], HeadPhantom] = {}


def _cached_phantom(seed: int, contrast: bool, facial: bool) -> HeadPhantom:
    key = (seed, contrast, facial)
    if key not in _PHANTOMS:
        if len(_PHANTOMS) > 8:
            _PHANTOMS.clear()
        _PHANTOMS[key] = _build_phantom(seed, contrast, facial)
    return _PHANTOMS[key]


# --------------------------------------------------------------------------------------
# The stand-in registration volume
# --------------------------------------------------------------------------------------
#: Gaussian smoothing (voxels) and noise (HU) that make the resampled phantom look like a
#: reconstruction (a 3DRA has a soft point spread function and quantum noise).
STAND_IN_SMOOTH_VOXELS = 0.6
STAND_IN_NOISE_HU = 20.0


def standin_params(phantom: HeadPhantom, volume_format_cm: float, voxels: int, noise_seed: int) -> dict:
    """The cache parameters of :func:`registration_volume` (kind ``"standin3dra"``)."""
    return {
        **phantom.key,
        "volume_format_cm": float(volume_format_cm),
        "voxels": int(voxels),
        "noise_seed": int(noise_seed),
        "smooth": STAND_IN_SMOOTH_VOXELS,
        "noise_hu": STAND_IN_NOISE_HU,
        "n_prims": phantom.n_primitives,
    }


def registration_volume(
    phantom: HeadPhantom | int,
    volume_format_cm: float,
    *,
    voxels: int = 256,
    seed: int = 0,
    cache: bool = True,
) -> Volume:
    """The stand-in 3DRA: the phantom voxelised on the 3DRA grid, smoothed, with noise.

    Parameters
    ----------
    phantom
        A :class:`HeadPhantom`, or a phantom seed (contrast and facial structures on).
    volume_format_cm
        3DRA volume format; the cube spans ``f x SOD / SID`` at the iso-center.
    voxels
        Grid size along each axis.
    seed
        Seed of the added noise.
    cache
        Keep the result in the on-disk cache (keyed by every parameter).

    Returns
    -------
    Volume
        Axis-aligned LPS grid centered at the iso-center, labelled ``STAND_IN_LABEL``.
    """
    if not isinstance(phantom, HeadPhantom):
        phantom = make_head_phantom(seed=int(phantom))
    fmt = float(volume_format_cm)
    if not math.isfinite(fmt) or fmt <= 0:
        raise ValueError(f"volume_format_cm must be positive, got {volume_format_cm}")
    if int(voxels) != voxels or voxels < 8:
        raise ValueError(f"voxels must be an integer >= 8, got {voxels}")
    voxels = int(voxels)
    spacing, axis = format_grid(fmt, voxels=voxels)
    data_shape = (voxels, voxels, voxels)
    affine = np.diag([spacing, spacing, spacing, 1.0])
    affine[:3, 3] = axis[0]

    def build() -> dict[str, np.ndarray]:
        hu = phantom.voxelize(data_shape, affine, supersample=2)
        hu = ndimage.gaussian_filter(hu, STAND_IN_SMOOTH_VOXELS, mode="nearest")
        rng = np.random.default_rng(seed)
        hu += rng.normal(0.0, STAND_IN_NOISE_HU, hu.shape).astype(np.float32)
        return {"data": hu.astype(np.float32)}

    params = standin_params(phantom, fmt, voxels, seed)
    data = cached_arrays("standin3dra", params, build, enabled=cache)["data"]
    return Volume(data, affine, label=STAND_IN_LABEL, meta={"source": "phantom", **params})
